"""``jaxcr warmup DATASET [segment options]``: compile ahead what ``jaxcr segment`` will run.

Runs ``jaxcr segment``'s own code (the same option parsing, :class:`RefineConfig` and batch
loop) on the dataset's first usable frames, one chunk of ``--batch-size`` frames (two with
``--warm-start``: the first chunk starts cold, later ones from the previous result), into a
temporary folder that is deleted afterwards. Every program segment compiles for these image
shapes and settings (nominal kinematics, background subtraction, refinement, overlays) is then
in the persistent compilation cache, so a later ``jaxcr segment`` with the same options in a new
process loads them instead of compiling. Options that change compiled shapes: --camera,
--batch-size, --basis, --levels, --max-steps, --background, --camera-correction(-mode),
--mu-out, --warm-start, --shape-buckets; give ``warmup`` the ones you will give ``segment``.
With shape buckets (the default) the programs serve every image size of the same bucket.

Prints each program with its XLA compile seconds (or load seconds, when it was already in the
cache), then the totals.
Exit code 0, 2 on bad input or when the compilation cache is off (nothing would be kept).
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
import tempfile
import time
from contextlib import contextmanager

from jaxcr.errors import InputError

HELP = "pre-compile `jaxcr segment` for a dataset into the persistent compilation cache"
# segment's options that only concern its output folder
_NOT_FOR_WARMUP = {"help", "out", "resume", "retry_failed", "overwrite", "limit"}

_FINISHED = re.compile(r"Finished XLA compilation of (.+?) in ([0-9.eE+-]+) sec")
_HIT = re.compile(r"Persistent compilation cache hit for '(.+?)'")


def add_parser(subparsers) -> argparse.ArgumentParser:
    from jaxcr.cli import segment

    p = subparsers.add_parser(
        "warmup",
        help=HELP,
        description=__doc__.split("\n\n")[1].replace("``", ""),
    )
    # the segment parser's own actions (same names, defaults and checks)
    seg = segment.add_parser(argparse.ArgumentParser().add_subparsers())
    for action in seg._actions:
        if action.dest not in _NOT_FOR_WARMUP:
            p._add_action(action)
    p.set_defaults(func=run)
    return p


class _CompileLog(logging.Handler):
    """Collects JAX's compile log lines (jax_log_compiles) as (name, seconds, cache hit):
    JAX logs a persistent-cache hit, then "Finished XLA compilation" (compile or load time)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.programs: list[tuple[str, float, bool]] = []
        self._hit: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        msg = record.getMessage()
        if m := _HIT.search(msg):
            self._hit = m.group(1)
        elif m := _FINISHED.search(msg):
            name = m.group(1)
            self.programs.append((name, float(m.group(2)), self._hit == name))
            self._hit = None


@contextmanager
def _compile_log():
    import jax

    handler = _CompileLog()
    logger = logging.getLogger("jax")
    old = (logger.level, logger.propagate, jax.config.jax_log_compiles)
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False  # keep the lines off stderr; they are summarised instead
    jax.config.update("jax_log_compiles", True)
    try:
        yield handler
    finally:
        jax.config.update("jax_log_compiles", old[2])
        logger.removeHandler(handler)
        logger.setLevel(old[0])
        logger.propagate = old[1]


def run(args) -> int:
    import jax

    from jaxcr.cli import segment
    from jaxcr.segmentation.batch import Segmenter

    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        raise InputError(
            "the compilation cache is off (--no-compile-cache, JAXCR_COMPILE_CACHE=0 or an "
            "unwritable JAXCR_CACHE_DIR): nothing would be kept",
            field="compile-cache",
        )
    ds = segment.load(args.dataset)
    cams = segment.select_cameras(ds, args.camera)
    if args.batch_size < 1:
        raise InputError("--batch-size must be >= 1", field="batch-size")
    cfg = segment.refine_config(args)
    ranges = segment.robot_hsv_ranges(args)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="jaxcr-warmup-") as tmp:
        seg = Segmenter(
            ds,
            cams,
            cfg,
            args.background,
            tmp,
            overlays=not args.no_overlays,
            warm_start=args.warm_start,
            batch_size=args.batch_size,
            colour_ranges=ranges,
            shape_buckets=(args.shape_buckets or "on") == "on",
        )
        usable = [f for f in seg.frame_ids if f not in ds.bad_frames]
        if not usable:
            raise InputError("the dataset has no usable frame to compile with", field="frames")
        chunk = usable[: args.batch_size]
        frames = chunk * (2 if args.warm_start else 1)
        sizes = ", ".join(
            f"{c} {ds.cameras[c].width}x{ds.cameras[c].height}"
            + (f" (bucket {w}x{h})" if seg.shape_buckets and (h, w) != (
                ds.cameras[c].height, ds.cameras[c].width) else "")
            for c in cams
            for h, w in [seg._array_shape(ds.cameras[c])]
        )  # fmt: skip
        print(
            f"jaxcr warmup: compiling segment for {sizes}, batch {args.batch_size}"
            + (", warm start" if args.warm_start else "")
            + f" -> cache {folder}",
            flush=True,
        )
        with _compile_log() as log:
            records = seg.run(frames, progress=not args.quiet).records
    bad = [r for r in records if not r.get("ok")]
    for name, secs, hit in log.programs:
        print(f"  {name}: {secs:.2f} s" + (" (loaded from the cache)" if hit else ""))
    n_hit = sum(1 for *_, hit in log.programs if hit)
    xla = sum(s for _, s, hit in log.programs if not hit)
    print(
        f"jaxcr warmup: {len(log.programs) - n_hit} programs compiled ({xla:.1f} s of XLA "
        f"compilation), {n_hit} loaded from the cache; compile (trace + lower + XLA) "
        f"{seg.compile_s:.1f} s, total {time.perf_counter() - t0:.1f} s"
    )
    if bad:  # the programs ran and are cached all the same; say so rather than fail
        print(
            f"jaxcr warmup: note: {len(bad)} warm-up frame(s) failed ({bad[0].get('reason')})",
            file=sys.stderr,
        )
    return 0
