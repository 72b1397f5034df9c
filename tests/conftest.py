import atexit
import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")

# One persistent JAX compilation cache per test run, shared by the xdist workers and by every
# process the tests start. The run's first process (the xdist controller, or the only process
# without -n) creates an empty folder before any worker starts; the workers and the `jaxcr`
# subprocesses inherit these variables, so a program compiled once in the run (the refinement,
# the CTR solver, a command's glue) is loaded from disk by every later process and after
# jax.clear_caches() below, instead of being compiled again (each `jaxcr` subprocess used to
# recompile everything from scratch). The folder starts empty, so a run never depends on an
# earlier one, and the per-user cache (~/.cache/jaxcr) is never written by the tests. Set
# JAXCR_TESTS_CACHE_DIR yourself to keep a cache across runs.
RUN_CACHE_ENV = "JAXCR_TESTS_CACHE_DIR"
if not os.environ.get(RUN_CACHE_ENV):
    _run_cache = tempfile.mkdtemp(prefix="jaxcr-tests-jax-cache-")
    os.environ[RUN_CACHE_ENV] = _run_cache
    atexit.register(shutil.rmtree, _run_cache, ignore_errors=True)
RUN_CACHE = os.environ[RUN_CACHE_ENV]
# jaxcr's commands (jaxcr.io.compile_cache) ...
os.environ["JAXCR_COMPILE_CACHE"] = "1"
os.environ["JAXCR_CACHE_DIR"] = RUN_CACHE
# ... and JAX itself, in any process (a `python -c` subprocess too): every compilation is
# stored (JAX's default threshold, 1 s, would skip the many small programs a command runs)
os.environ["JAX_COMPILATION_CACHE_DIR"] = RUN_CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"

# XLA:CPU's legacy loop emitter instead of its MLIR fusion emitters, for the tests only
# (docs/decisions.md T1, experiments/results/suite_time.md "Seventh pass"). Compilation is
# most of the suite's time, and this flag cuts it by about a third (test_refine, test_ctr,
# test_kinematics_fit, test_examples: 421 -> 287 CPU-s, same run); the refinement program at
# 160x120 compiles in 6.7 instead of 11.1 CPU-s with the same refined coefficients. It is a
# code-generation choice, not a change of arithmetic (no fast math): it moves float32 results
# at the rounding level, as another x86-64 CPU's code generation does, and every tolerance in
# the suite is meant to hold under that. The library does not use it: at 640x480 the
# refinement runs 2.2x slower with it (bench_tracking). JAXCR_TESTS_XLA_DEFAULT=1 runs the
# suite with XLA's defaults (what users get); both pass. Subprocesses inherit it.
#
# And the machine code of an AVX x86-64 CPU (no FMA: --xla_cpu_max_isa=AVX) without LLVM's
# optimisation of it (--xla_backend_optimization_level=0) (docs/decisions.md T4,
# experiments/results/suite_time.md "Eleventh pass"). XLA's HLO passes are unchanged (the same
# optimised HLO, instruction for instruction); LLVM's optimisation of the emitted code, most of
# what is left of a compile after the flag above, is skipped: the 160x120 refinement program
# compiles in 1.9 instead of 5.4 CPU-s, and runs ~2x slower (0.23 vs 0.12 s for two frames).
# Level 0 alone is not enough: it gives up LLVM's fused multiply-adds in some places and not
# others, so two programs of the same arithmetic (refine_batch's lax.map and refine_frame)
# stopped agreeing bit for bit. Without FMA in the target there is none to form: every float
# operation rounds once, as IEEE says, and only the order of XLA's reductions (a choice XLA
# makes per target) can differ from another x86-64 CPU's. Measured: bit-identical to XLA's
# default level for an AVX CPU on the refinement (refine_compile_cost.py --compare, 48 of 48
# output leaves), the CTR batch solve, the LM fits and refine_batch's map; the degeneracy
# filter rounds as on an SSE4.2 CPU. So the suite checks the arithmetic of a real x86-64 CPU,
# which every tolerance must allow anyway.
#
# A flag that XLA_FLAGS already names is not added, so another CPU's code generation is one
# variable away (docs/decisions.md T5). `XLA_FLAGS=--xla_cpu_max_isa=SSE4_2 pytest ...` runs
# the suite's flags as on a CPU without AVX, the only other target these flags give (a CPU
# with AVX2 or AVX-512 still gets the AVX cap). With JAXCR_TESTS_XLA_DEFAULT=1 the cap picks
# XLA's defaults for that CPU (SSE4_2, AVX, AVX2; no cap: this CPU's own). Measured in T5: the
# whole suite passes for SSE4_2 under both; under XLA's defaults 93 of the 130 modules pass for
# AVX2 and the 30 refinement, kinematics and fit modules for this CPU.
FAST_COMPILE_FLAGS = (
    "--xla_cpu_use_fusion_emitters=false",
    "--xla_cpu_max_isa=AVX",
    "--xla_backend_optimization_level=0",
)
if os.environ.get("JAXCR_TESTS_XLA_DEFAULT", "") not in ("1", "true", "yes", "on"):
    _flags = os.environ.get("XLA_FLAGS", "")
    for _flag in FAST_COMPILE_FLAGS:
        if _flag.split("=")[0] not in _flags:
            _flags = (_flags + " " + _flag).strip()
    os.environ["XLA_FLAGS"] = _flags


def _use_run_cache():
    """Point this process's JAX at the run's cache (again: a test may have switched it off or
    elsewhere, e.g. `main(["--no-compile-cache", ...])` or enable_compile_cache(path=...))."""
    from jaxcr.io.compile_cache import enable_compile_cache

    enable_compile_cache(path=RUN_CACHE)


# Modules whose fixtures compile the refinement or run `jaxcr segment`/`demo` end to end: marked
# slow as a whole, so `pytest -m "not slow"` is a smaller subset (the whole suite is the test
# command). Individual tests are marked slow by @pytest.mark.slow or by tests/slow_tests.txt,
# the list of tests that used >= 0.8-1 s of CPU in measured runs (tests/helpers/slow_marks.py).
SLOW_MODULES = (
    "tests/segmentation/test_refine.py",
    "tests/segmentation/test_refine_multicam.py",
    "tests/segmentation/test_refine_convergence.py",
    "tests/segmentation/test_uncertainty.py",  # two compiles of the covariance (1 and 2 views)
    "tests/segmentation/test_refine_traced.py",  # five refinement programs (decisions S34)
    "tests/cli/test_cli_segment.py",
    "tests/cli/test_cli_demo.py",
    # a local Ray instance per module: mostly waiting for Ray's processes (wall, not CPU, so
    # tests/slow_tests.txt's CPU measure does not catch every test of them)
    "tests/scale/test_ray_fault.py",
    "tests/scale/test_ray_equality.py",
)


# The longest modules, longest first: summed test wall of each module in the lead's idle
# `.ci/run` of stop 34 (a968f8b, 4 December 2026 23:34-23:47 UTC; experiments/results/
# suite_time.md "Stop 34"), in brackets, with this stop's cuts (docs/decisions.md T3) noted;
# the modules that run did not list keep their earlier figures (the lead's `pytest -n 2` of 2
# December 2026 04:53-05:19 UTC, load ~4, "2 Dec") and order. Only the
# order matters. With whole modules per worker the run ends when the last module does:
# starting the longest first (LPT scheduling) keeps a long module from starting last and
# running alone while the other worker idles. A module that loads programs another one
# compiles comes after it (the first two start together).
LONGEST_FIRST = (
    "tests/cli/test_tutorial.py",  # (82) one test, the doc's commands
    # (77; one program fewer since stop 35: its camera-correction test runs
    # test_refine_traced's per-frame program)
    "tests/segmentation/test_refine.py",
    # (82) after the tutorial: its stereo notebook loads the tutorial's stereo programs
    "tests/core/test_examples.py",
    # (70 of wall for ~19 CPU-s: Ray's processes; three of its Ray runs with one worker since
    # stop 35) early, so that its waiting overlaps the other worker's compiles
    "tests/scale/test_ray_equality.py",
    "tests/kinematics/test_ctr.py",  # (58)
    "tests/kinematics/test_kinematics_fit.py",  # (57)
    "tests/cli/test_cli_segment.py",  # (54)
    # (54, four refinement programs, T2) after test_refine, which compiles its per-frame
    # program too (T3)
    "tests/segmentation/test_refine_traced.py",
    # (46) after test_refine: it loads test_refine's per-frame and vmap programs
    "tests/segmentation/test_refine_convergence.py",
    # (40) after test_refine: its unpadded program is test_refine's map program
    "tests/segmentation/test_shape_buckets.py",
    "tests/scale/test_devices.py",  # (97, 2 Dec) one test, a subprocess with 2 host devices
    "tests/stereo/test_stereo_chain_fit.py",  # (79, 2 Dec)
    "tests/scale/test_ray_fault.py",  # (64, 2 Dec)
    "tests/cli/test_cli_contract.py",  # (61, 2 Dec)
    "tests/cli/test_cli_warmup.py",  # (70 before its smaller program)
    "tests/segmentation/test_energy.py",  # (48, 2 Dec)
    "tests/segmentation/test_refine_multicam.py",  # (45, 2 Dec)
    # (38) after test_examples: its bench loads the example's CTR program
    "tests/cli/test_cli_bench_wheel.py",
    "tests/segmentation/test_uncertainty.py",  # (23, 2 Dec)
)


def pytest_collection_modifyitems(config, items):
    from tests.helpers.slow_marks import read_list

    slow_tests = read_list()  # tests/slow_tests.txt: measured, see tests/helpers/slow_marks.py
    for item in items:
        if item.nodeid.split("::")[0] in SLOW_MODULES or item.nodeid in slow_tests:
            item.add_marker(pytest.mark.slow)
    # The longest modules first (LONGEST_FIRST), then the other modules holding slow
    # (compile-heavy) tests, then the rest in their usual order: with whole modules per
    # worker (below) the long ones then overlap each other and the short ones fill in at the
    # end, instead of one long module running alone after the others.
    heavy = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    rank = {m: i for i, m in enumerate(LONGEST_FIRST)}

    def order(item):
        module = item.nodeid.split("::")[0]
        return (rank.get(module, len(rank)), module not in heavy)

    items.sort(key=order)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """`pytest -n N`: whole test modules per worker (as --dist loadfile), unless another --dist
    was asked for. xdist's default (load) splits a module's tests across workers, and each
    worker then builds the module-scoped fixtures -- most of them compile something -- again.
    """
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadFileScheduling

    # keep the order above (xdist would otherwise start the modules with the most tests first,
    # leaving the few-test, compile-heavy refinement modules for the end)
    config.option.loadscopereorder = False
    return LoadFileScheduling(config, log)


@pytest.fixture(autouse=True, scope="module")
def _run_compile_cache_module():
    """The run's cache before a module's own module-scoped fixtures (autouse fixtures come first
    in their scope), which is where the suite compiles most: without it they ran with whatever
    the previous test left (test_api points the cache at a tmp folder, test_cli_warmup and
    test_io_compile_cache switch it off), or, in a process whose JAX was imported before this
    file set JAX_COMPILATION_CACHE_DIR (a plugin importing jax), with no cache at all, so their
    programs were neither loaded nor stored. Measured: a module-scoped fixture's program
    compiled in one module and again in the next without a cache hit, in that case."""
    _use_run_cache()
    yield


@pytest.fixture(autouse=True)
def _run_compile_cache():
    _use_run_cache()
    yield


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's compiled executables after each test module.

    Every XLA:CPU executable keeps memory mappings for its machine code; one xdist worker that
    runs ~300 test modules' worth of compilations reached the kernel's per-process map limit
    (vm.max_map_count = 65530 here) near the end of the suite and crashed with "LLVM
    compilation error: Cannot allocate memory" / a segmentation fault. Module-scoped fixtures
    holding compiled functions are torn down before this runs, so their code is freed too.
    A program needed again later is loaded from the run's compilation cache (above).
    """
    yield
    import jax

    jax.clear_caches()
    gc.collect()


# ----------------------------------------------------------- optional: where compile time goes
# JAXCR_TESTS_COMPILE_LOG=<folder>: each process appends one line per test to
# <folder>/<worker>.tsv: test id, then seconds of tracing, lowering to MLIR and XLA compilation
# (or loading from the cache), cache hits and misses. Off by default.
_COMPILE_LOG = os.environ.get("JAXCR_TESTS_COMPILE_LOG")
_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_hits": "hits",
    "/jax/compilation_cache/cache_misses": "misses",
}
_tally = dict.fromkeys(_EVENTS.values(), 0.0)

if _COMPILE_LOG:
    from jax._src import monitoring

    def _on_duration(event, duration_secs, **kwargs):
        if event in _EVENTS:
            _tally[_EVENTS[event]] += duration_secs

    def _on_event(event, **kwargs):
        if event in _EVENTS:
            _tally[_EVENTS[event]] += 1

    monitoring.register_event_duration_secs_listener(_on_duration)
    monitoring.register_event_listener(_on_event)

    import resource
    import time

    def _cpu():
        # this process's CPU seconds and those of the subprocesses it has waited for (a
        # `jaxcr` command run by a test): load-independent, unlike the wall time
        own = time.process_time()
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return own, kids.ru_utime + kids.ru_stime

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        for k in _tally:
            _tally[k] = 0.0
        wall0, (own0, kids0) = time.perf_counter(), _cpu()
        yield
        wall, (own, kids) = time.perf_counter() - wall0, _cpu()
        os.makedirs(_COMPILE_LOG, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        # columns: test id, trace, lower, compile, hits, misses, wall s, own CPU s, child CPU s
        with open(os.path.join(_COMPILE_LOG, f"{worker}.tsv"), "a") as f:
            f.write("\t".join([item.nodeid, *(f"{_tally[k]:.3f}" for k in _EVENTS.values())]))
            f.write(f"\t{wall:.3f}\t{own - own0:.3f}\t{kids - kids0:.3f}\n")
