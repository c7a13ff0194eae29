import os

# The tests check numbers, not speed: XLA:CPU's LLVM optimisation and its newer fusion emitters
# are turned off, which compiles ~3x faster (most of the suite's time is compiling) and runs the
# small test problems slower, with the same IEEE operations (no fast-math either way) rounded in
# another order in places (benchmarks/compile_time.py checks the default setting against the
# closed form). Each test process runs on one core (`pytest_configure`): at optimisation level 0,
# jaxlib 0.10.2 ran some programs with results that depend on its threads. XLA:CPU's
# concurrency-optimised schedule stays on: with it turned off as well, jaxlib 0.10.2 computed a
# vmapped batch of balls wrong on one core that the two flags alone compute right (docs: FAQ,
# "Compile time"). Set before jax creates its CPU backend; notebook kernels started by tests
# inherit both.
os.environ["XLA_FLAGS"] = " ".join(
    [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false"]
).strip()


import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_configure(config):
    """Pin this test process (each pytest-xdist worker) to one core of its own.

    Under the flags above, XLA:CPU still runs independent parts of one program concurrently on
    its thread pool, and jaxlib 0.10.2 gave a batch of 4,096 bouncing balls 206 wrong bounce
    counts with two threads (docs: FAQ, "Compile time"); with one schedulable core XLA sizes
    its pool to one thread. Two workers on a 2-core machine use the two cores as before. Called
    before jax creates its CPU backend (at the first array, after configuration), which reads
    the affinity once."""
    workerinput = getattr(config, "workerinput", None)
    if not hasattr(os, "sched_setaffinity") or (workerinput is None and getattr(config.option, "numprocesses", None)):
        return  # pytest-xdist's controller runs no test; its workers inherit its cores
    cores = sorted(os.sched_getaffinity(0))
    worker = (workerinput or {}).get("workerid", "gw0")  # "gw0", "gw1", ...
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    os.sched_setaffinity(0, {cores[index % len(cores)]})


@pytest.fixture(autouse=True)
def _seed():
    np.random.seed(0)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Free each module's compiled executables when it is done.

    Every XLA:CPU executable keeps memory mappings for its code; a whole-suite process
    compiling hundreds of executables passes Linux's default vm.max_map_count (65530) and
    LLVM aborts inside a compile (seen as a segfault in an unrelated test). Modules share
    compiled functions within themselves, not across, so clearing between them costs little.
    """
    yield
    jax.clear_caches()
