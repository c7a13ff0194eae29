import os

# The tests check numbers, not speed: XLA:CPU's LLVM optimisation and its newer fusion emitters
# are turned off, which compiles ~3x faster (most of the suite's time is compiling) and runs the
# small test problems slower, with the same IEEE operations (no fast-math either way) rounded in
# another order in places (benchmarks/compile_time.py checks the default setting against the
# closed form). XLA:CPU's concurrency-optimised thunk schedule is turned off too: with the first
# two flags alone, jaxlib 0.10.2 ran some programs with results that depend on its threads
# (docs: FAQ, "Compile time"). Set before jax creates its CPU backend; notebook kernels started
# by tests inherit it.
os.environ["XLA_FLAGS"] = " ".join(
    [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false",
     "--xla_cpu_enable_concurrency_optimized_scheduler=false"]
).strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
