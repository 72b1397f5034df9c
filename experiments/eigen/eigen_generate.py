"""Generate the IREP stereo datasets of the eigen-feature experiments (Reiter et al.):
train (2296 frames), test (806) and occluded test (806), and record the generation time.

    taskset -c 1 python experiments/eigen/eigen_generate.py --out /tmp/irep --size 512x384

Writes ``<out>/{train,test,test_occluded}`` and ``experiments/results/eigen/eigen_generate.json``.
Use ``--frames-train/--frames-test`` for smaller sets and ``--tag`` for other timing runs;
``--sets val,val_occluded`` writes the validation sets of eigen_accuracy.py.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path

from jaxcr.synth.irep import generate_irep

RESULTS = Path(__file__).resolve().parent.parent / "results" / "eigen"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="/tmp/irep")
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames-train", type=int, default=2296)
    ap.add_argument("--frames-test", type=int, default=806)
    ap.add_argument(
        "--frames-val", type=int, default=300, help="validation sets (training random stream)"
    )
    ap.add_argument("--sets", default="train,test,test_occluded")
    ap.add_argument("--tag", default="")
    a = ap.parse_args()
    w, h = (int(x) for x in a.size.split("x"))
    out = Path(a.out)
    spec = {
        "train": ("train", a.frames_train, False),
        "test": ("test", a.frames_test, False),
        "test_occluded": ("test", a.frames_test, True),
        # New configurations from the training stream (the stratified sampling depends on
        # the frame count), for design choices that must not look at the test sets.
        "val": ("train", a.frames_val, False),
        "val_occluded": ("train", a.frames_val, True),
    }
    rec = {}
    for name in a.sets.split(","):
        split, n, occ = spec[name]
        t0 = time.perf_counter()
        info = generate_irep(out / name, n, split, a.seed, (w, h), occluded=occ, overwrite=True)
        info["wall_s"] = time.perf_counter() - t0
        info["per_frame_s"] = info["wall_s"] / n
        rec[name] = info
        print(name, json.dumps(info))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    meta = {
        "commit": commit,
        "machine": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "size": [w, h],
        "seed": a.seed,
    }
    path = RESULTS / f"eigen_generate{a.tag}.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps({"meta": meta, "sets": rec}, indent=1) + "\n")


if __name__ == "__main__":
    main()
