import gc
import os

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's compiled executables after each test module.

    Every XLA:CPU executable keeps memory mappings for its machine code; one xdist worker that
    runs ~300 test modules' worth of compilations reached the kernel's per-process map limit
    (vm.max_map_count = 65530 here) near the end of the suite and crashed with "LLVM
    compilation error: Cannot allocate memory" / a segmentation fault. Module-scoped fixtures
    holding compiled functions are torn down before this runs, so their code is freed too.
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()
