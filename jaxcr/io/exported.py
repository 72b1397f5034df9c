"""Traced programs kept on disk beside the persistent compilation cache (``jax.export``).

JAX's persistent compilation cache (:mod:`jaxcr.io.compile_cache`) stores XLA's output, but
finds it by hashing the lowered program, so every new process still traces the Python code to
a jaxpr and lowers it to StableHLO before it can look the executable up. For the refinement of
``jaxcr segment`` that was most of a second process's compile time (measured in
``experiments/results/segmentation/compile_split.md``). :func:`cached_call` stores the lowered
program itself (``jax.export`` serialisation) under a key made of the arguments' shapes,
dtypes and static values, the function's name, the versions of JAX and the solver libraries,
and a hash of jaxcr's own source files (any change of the code makes new keys); a later process
deserialises it and calls it, which lowers only a thin wrapper and finds the executable in the
persistent cache.

Only functions whose result depends on nothing but their arguments may go through it (no
closures over values that are not arguments): module-level ``eqx.filter_jit`` functions such as
``refine._refine_batch_jit``. The entries live in ``<cache folder>/exported/``; the cache's
switches (``JAXCR_COMPILE_CACHE``, ``JAXCR_CACHE_DIR``) turn them off with it. A file that cannot
be read or written is not an error: the function is then traced as usual.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import os
import pickle
import tempfile
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import equinox as eqx
import jax

FORMAT = b"jaxcr.exported/2\n"
#: XLA:CPU options that compile a program with about a third less CPU (0.64-0.68x for segment's
#: programs) into code that runs up to ~2x slower (the legacy loop emitter instead of the MLIR
#: fusion emitters; docs/decisions.md T1 and S22): for programs that run rarely per process.
FAST_COMPILE = {"xla_cpu_use_fusion_emitters": False}
#: LAPACK kernels of jaxlib that ``jax.export`` refuses by default because their calling
#: convention is not promised stable *across jaxlib versions* (QR's "apply Q", which lineax's
#: QR solve inside Optimistix's Levenberg-Marquardt uses: ``jaxcr fit``'s solve). A stored
#: program is keyed by the exact jaxlib version that wrote it (:func:`_versions`), so it is only
#: ever loaded by that jaxlib, where the kernel is the one it was traced against. Host callbacks
#: stay unexportable (JAX refuses them regardless): such a function is traced as usual.
_SAME_VERSION_CUSTOM_CALLS = tuple(
    f"lapack_{t}_ffi" for t in ("sormqr", "dormqr", "cunmqr", "zunmqr")
)
_memo: dict[tuple, tuple[Callable, object, list, list]] = {}
_source_hash: str | None = None
#: XLA compilations started by :func:`compile_ahead`, by memo key; a call waits for its own
_compiling: dict[tuple, Future] = {}
_ahead = threading.local()  # .pool: the compile_ahead pool of this thread, if inside one


def _jaxcr_source_hash() -> str:
    """SHA-256 over every ``.py`` file of the installed jaxcr package (path and content)."""
    global _source_hash
    if _source_hash is None:
        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _source_hash = h.hexdigest()
    return _source_hash


def _versions() -> str:
    import importlib.metadata as md

    out = []
    for name in ("jax", "jaxlib", "equinox", "optimistix", "lineax"):
        try:
            out.append(f"{name}={md.version(name)}")
        except md.PackageNotFoundError:
            out.append(f"{name}=?")
    return ",".join(out)


def _folder() -> str | None:
    """``<cache folder>/exported``, or None when the cache is off or JAX cannot serialise
    (``jax.export`` needs the ``flatbuffers`` package, a dependency of jaxcr)."""
    base = jax.config.jax_compilation_cache_dir
    if not base or importlib.util.find_spec("flatbuffers") is None:
        return None
    return os.path.join(base, "exported")


def _key(name: str, leaves, static) -> str:
    h = hashlib.sha256()
    h.update(FORMAT + name.encode() + _versions().encode() + _jaxcr_source_hash().encode())
    h.update(str(jax.tree_util.tree_structure(static)).encode())
    h.update(repr(jax.tree_util.tree_leaves(static)).encode())
    for x in leaves:
        h.update(f"{x.shape}{x.dtype}{getattr(x, 'weak_type', False)};".encode())
    return h.hexdigest()[:40]


def _load(path: str):
    with open(path, "rb") as fh:
        blob = fh.read()
    if not blob.startswith(FORMAT):
        raise ValueError("not a jaxcr exported program")
    n = int.from_bytes(blob[len(FORMAT) : len(FORMAT) + 8], "little")
    body = blob[len(FORMAT) + 8 :]
    # the output's structure is rebuilt here from a pickled example (leaves numbered
    # 0..k-1), not unpickled as a treedef: a pickled treedef of equinox modules carries
    # copies of equinox's sentinel objects and cannot unflatten them in a new process
    template = pickle.loads(body[n:])
    return jax.export.deserialize(bytearray(body[:n])), jax.tree_util.tree_structure(template)


def _store(path: str, exported, out_tree) -> None:
    body = exported.serialize()
    template = jax.tree_util.tree_unflatten(out_tree, list(range(out_tree.num_leaves)))
    blob = FORMAT + len(body).to_bytes(8, "little") + bytes(body) + pickle.dumps(template)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=os.path.dirname(path))
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _named(fn: Callable, name: str) -> Callable:
    def named(*a):
        return fn(*a)

    named.__name__ = named.__qualname__ = name
    return named


def cached_call(fn: Callable, *args, compiler_options: dict | None = None):
    """``fn(*args)`` through a stored traced program when the compilation cache is on.

    ``fn``: a module-level function (typically ``eqx.filter_jit``) whose result is a pytree of
    arrays determined by ``args`` alone; non-array arguments (configs, strings, static fields
    of modules) are part of the key. Falls back to ``fn(*args)`` when the cache is off or an
    entry cannot be made. ``compiler_options``: XLA options of this program's compilation
    (``jax.jit(..., compiler_options=)``, e.g. :data:`FAST_COMPILE` for a program that runs
    once per process); they are part of the persistent cache's key, not of the stored traced
    program (the same program serves every set of options).
    """
    opts = tuple(sorted((compiler_options or {}).items()))
    folder = _folder()
    if folder is None and not opts:
        return fn(*args)
    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, in_tree = jax.tree_util.tree_flatten(dyn)
    name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"
    key = _key(name, leaves, static)
    memo_key = (key, opts, folder is not None)
    if memo_key not in _memo:
        out_box = []

        def flat(*lv):
            a = eqx.combine(jax.tree_util.tree_unflatten(in_tree, lv), static)
            out_leaves, out_tree_ = jax.tree_util.tree_flatten(fn(*a))
            out_box.append(out_tree_)
            return out_leaves

        # the program's own name in JAX's logs and monitoring events (not "flat"/"call")
        short = name.rsplit(".", 1)[-1]
        flat.__name__ = flat.__qualname__ = short
        if folder is None:  # cache off: traced in this process, compiled with the options
            call = jax.jit(flat, compiler_options=dict(opts))
            _memo[memo_key] = (call, None, out_box, [])
        else:
            path = os.path.join(folder, f"{name.rsplit('.', 1)[-1]}-{key}.jaxexport")
            try:
                exported, out_tree = _load(path)
            except (OSError, ValueError, EOFError, pickle.UnpicklingError):
                try:
                    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
                    checks = [jax.export.DisabledSafetyCheck.custom_call(t)
                              for t in _SAME_VERSION_CUSTOM_CALLS]  # fmt: skip
                    exported = jax.export.export(jax.jit(flat), disabled_checks=checks)(*shapes)
                except Exception:  # not exportable (e.g. a host callback): trace as usual
                    return fn(*args)
                out_tree = out_box[0]
                try:
                    _store(path, exported, out_tree)
                except OSError:
                    pass
            call = jax.jit(_named(exported.call, f"{short}_stored"),
                           compiler_options=dict(opts) or None)  # fmt: skip
            _memo[memo_key] = (call, out_tree, out_box, [])
    call, out_tree, out_box, ran = _memo[memo_key]
    pool = getattr(_ahead, "pool", None)
    if pool is not None:
        if ran:  # compiled and run in this process already: only the outputs' shapes
            tree = out_tree if out_tree is not None else out_box[-1]
            return jax.tree_util.tree_unflatten(tree, [_zeros(*a) for a in ran])
        return _start_compile(pool, memo_key, call, leaves, out_tree, out_box)
    pending = _compiling.pop(memo_key, None)
    if pending is not None:
        # started ahead: wait for it (a failed compilation is compiled, and raises, again here)
        with contextlib.suppress(Exception):
            pending.result()
    out = call(*leaves)
    if not ran:
        ran.extend((x.shape, x.dtype, x.sharding) for x in out)
    return jax.tree_util.tree_unflatten(out_tree if out_tree is not None else out_box[-1], out)


def _zeros(shape, dtype, sharding):
    import numpy as np

    return jax.device_put(np.zeros(shape, dtype), sharding)


def _start_compile(pool, memo_key, call, leaves, out_tree, out_box):
    """Lower ``call`` for ``leaves`` here (a thin wrapper of a stored program; with the cache off
    this traces), start its XLA compilation in ``pool`` and return zeros shaped as its outputs."""
    lowered = call.lower(*leaves)
    if memo_key not in _compiling:
        _compiling[memo_key] = pool.submit(lowered.compile)
    # placed as the program's real outputs (committed to their device): a later program that
    # takes them lowers, and is keyed in the persistent cache, as in the real run
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    zeros = [_zeros(a.shape, a.dtype, a.sharding or device)
             for a in jax.tree_util.tree_leaves(lowered.out_info)]  # fmt: skip
    return jax.tree_util.tree_unflatten(out_tree if out_tree is not None else out_box[-1], zeros)


@contextlib.contextmanager
def compile_ahead(max_workers: int = 2) -> Iterator[None]:
    """Inside this context (in this thread) :func:`cached_call` does not run its program: it
    loads or traces the program and lowers it as usual, starts XLA's compilation in a pool of
    ``max_workers`` threads and returns zeros of the program's output shapes, so code run
    inside (a dry run of the real work on any inputs of the right shapes) queues every program
    it would compile. XLA compiles without Python's lock, so the programs compile side by side
    (on a machine with several cores the first process waits for about the largest program, not
    the sum). On exit the context waits for the compilations it started; a later
    :func:`cached_call` of the same program and shapes then runs the compiled executable
    (nothing is compiled or loaded again), and the persistent cache is written and read as
    without this context. Only the programs' compilation depends on the dry run, never a
    result. A program already run in this process answers with zeros at once.
    (docs/decisions.md S30)"""
    pool = ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix="jaxcr-compile")
    _ahead.pool = pool
    try:
        yield
    except BaseException:  # e.g. Ctrl-C: drop what has not started
        _ahead.pool = None
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    _ahead.pool = None
    # every queued compilation finishes before the real run starts: its compile and run times
    # (jaxcr._timing.CompileTimer, process-wide events) are then not mixed up with a program
    # still compiling in the pool
    pool.shutdown(wait=True)


def programs_stored() -> bool:
    """True when :func:`cached_call` keeps traced programs (the compilation cache is on): the
    condition for :func:`compile_ahead` to queue anything (else a call runs its program)."""
    return _folder() is not None


def in_compile_ahead() -> bool:
    """True inside :func:`compile_ahead` in this thread (a dry run: results are zeros)."""
    return getattr(_ahead, "pool", None) is not None
