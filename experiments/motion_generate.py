"""Generate the synthetic video set for the M-L experiments (not committed: ~100 MB).

  python experiments/motion_generate.py --out /tmp/motion_data [--frames 24 --size 320x240]

pushed_static / pushed_changing: seeds 0..9 each (object = OBJECTS[seed % 5], so two videos
per object and background type; changing backgrounds cycle distractor / shake / lighting /
all three with seed % 4). held_static / held_changing: seeds 0..3 each (book and spirit
level, the 3-D motion set).
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
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    jobs = [(p, s) for p in ("pushed_static", "pushed_changing") for s in range(a.pushed)]
    jobs += [(p, s) for p in ("held_static", "held_changing") for s in range(a.held)]
    for preset, seed in jobs:
        d = Path(a.out) / f"{preset}_{seed:02d}"
        if (d / "motion.json").exists():
            continue
        t = time.time()
        generate_motion_video(d, preset, seed=seed, size=(w, h), n_frames=a.frames)
        print(f"{d} {time.time() - t:.1f} s", flush=True)


if __name__ == "__main__":
    main()
