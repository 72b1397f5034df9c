"""Time ratio of cheaper OpenCV LK settings to the validated one (window 15, 3 levels, 20
iterations) on the same 640x480 frame pairs, interleaved round by round so that the shared
machine's load hits every setting alike; prints the median per-pair times and the median of
the per-round ratios (issue 18, motion row; experiments/results/motion/motion_speed_r2.md).

    python experiments/motion/motion_lk_ratio.py [--rounds 15] [--video DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import cv2
import numpy as np

from jaxcr.io.motion_dataset import load_motion_dataset
from jaxcr.motion.flow import grid_points, to_gray_u8

SETTINGS = {
    "validated (3 levels, 20 iterations)": (3, 20),
    "3 levels, 10 iterations": (3, 10),
    "2 levels, 20 iterations": (2, 20),
    "1 level, 20 iterations": (1, 20),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--video", default=None, help="a jaxcr.motion/1 folder (default: rendered)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.video
        if path is None:
            from jaxcr.synth.motion_scenes import generate_motion_video

            path = generate_motion_video(os.path.join(tmp, "v"), "pushed_changing", seed=4,
                                         size=(640, 480), n_frames=8)  # fmt: skip
        ds = load_motion_dataset(path)
        grey = [to_gray_u8(x) for _, x, _ in ds.frames() if x is not None]
    h, w = grey[0].shape
    pts = grid_points(h, w, 8)[:, None, :]
    pairs = list(zip(grey[:-1], grey[1:], strict=True))

    def run(levels, iters):
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, iters, 0.03)
        t0 = time.perf_counter()
        for a, b in pairs:
            cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=(15, 15), maxLevel=levels,
                                     criteria=crit, minEigThreshold=1e-3)  # fmt: skip
        return 1e3 * (time.perf_counter() - t0) / len(pairs)

    load = os.getloadavg()
    times = {k: [] for k in SETTINGS}
    for s in SETTINGS.values():
        run(*s)  # warm
    for _ in range(args.rounds):
        for k, s in SETTINGS.items():
            times[k].append(run(*s))
    ref = np.array(times[next(iter(SETTINGS))])
    print(f"{len(pts)} points, {len(pairs)} pairs, {args.rounds} rounds; load average "
          f"{load[0]:.1f} before, {os.getloadavg()[0]:.1f} after; cv2 threads "
          f"{cv2.getNumThreads()}")  # fmt: skip
    print("| LK setting | median ms per pair | median per-round ratio to validated |")
    print("|---|---|---|")
    for k, v in times.items():
        r = np.median(np.array(v) / ref)
        print(f"| {k} | {np.median(v):.1f} | {r:.3f} |")


if __name__ == "__main__":
    main()
