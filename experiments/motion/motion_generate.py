"""Generate the synthetic video set for the M-L experiments (not committed: ~100 MB).

  python experiments/motion/motion_generate.py --out /tmp/motion_data [--frames 24 --size 320x240]

pushed_static / pushed_changing: seeds 0..9 each (object = OBJECTS[seed % 5], so two videos
per object and background type; changing backgrounds cycle distractor / shake / lighting /
all three with seed % 4). held_static / held_changing: seeds 0..3 each (book and spirit
level, the 3-D motion set). ``--first-seed 10 --presets pushed_changing`` writes an unseen
changing-background test set (seeds 10..19) with the same generator defaults.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

from jaxcr.synth.motion_scenes import generate_motion_video  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/motion_data")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--pushed", type=int, default=10)
    ap.add_argument("--held", type=int, default=4)
    ap.add_argument(
        "--first-seed", type=int, default=0, help="seeds first..first+n-1 (a fresh test set)"
    )
    ap.add_argument(
        "--presets",
        default="pushed_static,pushed_changing,held_static,held_changing",
        help="comma-separated subset of the presets",
    )
    a = ap.parse_args()
    presets = a.presets.split(",")
    w, h = (int(v) for v in a.size.split("x"))
    s0 = a.first_seed
    jobs = [
        (p, s)
        for p in ("pushed_static", "pushed_changing")
        if p in presets
        for s in range(s0, s0 + a.pushed)
    ]
    jobs += [
        (p, s)
        for p in ("held_static", "held_changing")
        if p in presets
        for s in range(s0, s0 + a.held)
    ]
    for preset, seed in jobs:
        d = Path(a.out) / f"{preset}_{seed:02d}"
        if (d / "motion.json").exists():
            continue
        t = time.time()
        generate_motion_video(d, preset, seed=seed, size=(w, h), n_frames=a.frames)
        print(f"{d} {time.time() - t:.1f} s", flush=True)


if __name__ == "__main__":
    main()
