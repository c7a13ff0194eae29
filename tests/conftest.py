import jax
import numpy as np
import pytest

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
