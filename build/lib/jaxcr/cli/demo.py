"""``jaxcr demo``: kinematic-prior segmentation end to end on a small built-in synthetic set.

Generates a few frames of the ``orthogonal_occluded`` preset (a concentric-tube robot above
tissue-like texture with a laparoscopic instrument in front; :mod:`jaxcr.synth`), segments
them (``jaxcr segment``) and prints the IoU table (``jaxcr evaluate``). Everything lands in
``DIR`` (default ``./jaxcr-demo``): ``dataset/``, ``segment/`` (masks, overlays,
results.jsonl) and ``segment/table2.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from jaxcr.cli._common import seed as _seed
from jaxcr.errors import InputError

HELP = "generate a small synthetic dataset, segment it and print the IoU table"
DEFAULT_PRESET = "orthogonal_occluded"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help=HELP,
        description=__doc__.split("\n\n")[1].replace("``", "").replace(":mod:", ""),
    )
    p.add_argument(
        "-o",
        "--out",
        default="jaxcr-demo",
        metavar="DIR",
        help="output folder (default ./jaxcr-demo; reused if it exists)",
    )
    p.add_argument("--frames", type=int, default=4, metavar="N", help="frames (default 4)")
    p.add_argument("--size", default="320x240", metavar="WxH", help="image size (default 320x240)")
    p.add_argument(
        "--preset", default=DEFAULT_PRESET, help=f"synthetic preset (default {DEFAULT_PRESET})"
    )
    p.add_argument("--seed", type=_seed, default=0, help="random seed of the scene (default 0)")
    p.set_defaults(func=run)
    return p  # fmt: skip


def _sub_args(module, argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="jaxcr")
    sub = parser.add_subparsers()
    module.add_parser(sub)
    return parser.parse_args(argv)


def run(args) -> int:
    from jaxcr.cli import evaluate, segment
    from jaxcr.synth.generate import generate, parse_size

    if args.frames < 1:
        raise InputError("--frames must be >= 1", field="frames")
    from jaxcr.limits import check_frames

    check_frames(args.frames, "frames")
    size = parse_size(args.size)
    root = Path(args.out)
    from jaxcr.io import outdir

    # new, empty or an earlier demo (replaced); locked until exit
    outdir.claim(root, "demo", recognise=lambda o: (o / "segment" / "run.json").exists())
    ds_dir, seg_dir = root / "dataset", root / "segment"
    t0 = time.perf_counter()
    print(f"jaxcr demo: generating {args.frames} frames of '{args.preset}' at "
          f"{size[0]}x{size[1]} (seed {args.seed}) -> {ds_dir}")  # fmt: skip
    generate(args.preset, ds_dir, seed=args.seed, frames=args.frames, size=size)
    t1 = time.perf_counter()
    print(f"jaxcr demo: segmenting (first call compiles) -> {seg_dir}")
    seg_argv = ["segment", str(ds_dir), "-o", str(seg_dir), "--overwrite",
                "--batch-size", str(min(args.frames, 4)), "--seed", str(args.seed)]  # fmt: skip
    code = segment.run(_sub_args(segment, seg_argv))
    t2 = time.perf_counter()
    ev_args = _sub_args(evaluate, ["evaluate", str(seg_dir), "--title", "jaxcr demo"])
    ev_code = evaluate.run(ev_args)
    t3 = time.perf_counter()
    print(f"jaxcr demo: done in {t3 - t0:.0f} s (synth {t1 - t0:.0f} s, segment "
          f"{t2 - t1:.0f} s incl. compilation, evaluate {t3 - t2:.0f} s); overlays in "
          f"{seg_dir / 'overlays'}")  # fmt: skip
    return max(code, ev_code)  # 1 when some frames failed (either step), 0 when all ok
