import gc
import os

import pytest

# Modules whose fixtures compile the refinement (145-205 s each on the loaded 2-core machine,
# issue 15) or run `jaxcr segment`/`demo` end to end: marked slow as a whole, so
# `pytest -m "not slow"` is the fast subset. Individual tests elsewhere use @pytest.mark.slow.
SLOW_MODULES = (
    "tests/segmentation/test_refine.py",
    "tests/segmentation/test_refine_multicam.py",
    "tests/segmentation/test_refine_convergence.py",
    "tests/segmentation/test_uncertainty.py",  # two compiles of the covariance (1 and 2 views)
    "tests/cli/test_cli_segment.py",
    "tests/cli/test_cli_demo.py",
)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid.split("::")[0] in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Commands run in-process by the tests would otherwise turn on the per-user persistent
# compilation cache (on by default in every command) for the rest of the worker, writing
# thousands of entries to ~/.cache; the cache has its own tests (tests/io/test_io_compile_cache.py,
# tests/cli/test_cli_warmup.py), which set these variables themselves.
os.environ.setdefault("JAXCR_COMPILE_CACHE", "0")


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
