"""Per-frame time of M-L at 640x480, split into flow, segmentation and likelihood.

  python experiments/motion_bench.py [--frames 10] [--flow-step 4]

Renders one pushed video at 640x480 (not timed), warms up (compiles) on the first frame pair,
then times every tracker step: flow (OpenCV LK on the grid + dense interpolation),
segmentation (label splatting + SLIC refinement, JAX), likelihood (motion models, eqs. 4-16,
both models, JAX). Reference in the same run: scikit-image's SLIC on the same frame (what a
user would otherwise call) and OpenCV DIS flow. Writes experiments/results/motion_bench.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import cv2  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

from jaxcr.motion.dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion.flow import FlowConfig, to_gray_u8  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig  # noqa: E402
from jaxcr.motion.run import run_motion  # noqa: E402
from jaxcr.synth.motion_scenes import generate_motion_video  # noqa: E402


def med_iqr(x):
    x = np.asarray(x)
    return f"{np.median(x):.1f} [{np.percentile(x, 25):.1f}, {np.percentile(x, 75):.1f}]"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--data", default=None)
    a = ap.parse_args()
    d = Path(a.data or tempfile.mkdtemp()) / "bench640"
    if not (d / "motion.json").exists():
        generate_motion_video(d, "pushed_changing", seed=4, size=(640, 480), n_frames=a.frames)
    ds = load_motion_dataset(d)
    rows = []
    for label, cfg in (
        ("LK grid 4 px, both models", MotionConfig()),
        ("LK grid 8 px, both models", MotionConfig(flow=FlowConfig(step=8))),
        (
            "LK grid 8 px, translation only",
            MotionConfig(flow=FlowConfig(step=8), models=("translation",)),
        ),
    ):
        t = time.time()
        run_motion(ds, cfg)  # warm-up: compiles for this shape
        compile_and_first = time.time() - t
        res = run_motion(ds, cfg)
        recs = [r for r in res.records if r.used]
        f = [r.flow_ms for r in recs]
        s = [r.segmentation_ms for r in recs]
        li = [r.likelihood_ms for r in recs]
        tot = np.array(f) + np.array(s) + np.array(li)
        rows.append(
            (
                label,
                med_iqr(f),
                med_iqr(s),
                med_iqr(li),
                med_iqr(tot),
                f"{compile_and_first:.1f}",
                len(recs),
            )
        )
    # references on the same frames
    frames = [rgb for _, rgb, _ in ds.frames()]
    from skimage.segmentation import slic as sk_slic

    sk = []
    for rgb in frames[:4]:
        t = time.perf_counter()
        sk_slic(rgb, n_segments=(640 // 20) * (480 // 20), compactness=10, start_label=0)
        sk.append(1e3 * (time.perf_counter() - t))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    dt = []
    for a_, b_ in zip(frames[:-1], frames[1:], strict=True):
        g0, g1 = to_gray_u8(a_), to_gray_u8(b_)
        t = time.perf_counter()
        dis.calc(g0, g1, None)
        dt.append(1e3 * (time.perf_counter() - t))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    L = [
        "# M-L per-frame time at 640x480",
        "",
        f"commit {commit}, jax {jax.__version__}, opencv {cv2.__version__}, {platform.machine()}, XLA single-threaded, "
        f"machine shared with other developers (load varies); {a.frames}-frame pushed_changing video, superpixel step 20 px "
        "(768 segments). Median [IQR] over the used frame pairs, ms; compile time excluded (separate warm-up run).",
        "",
        "| config | flow | segmentation | likelihood | total | warm-up run incl. compile (s) | frames |",
        "|---|---|---|---|---|---|---|",
    ]
    L += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    L += [
        "",
        f"References on the same frames: scikit-image `slic` (from scratch, same number of segments) {med_iqr(sk)} ms; "
        f"OpenCV DIS (fast preset, dense) {med_iqr(dt)} ms.",
        "",
        "Reproduce: `python experiments/motion_bench.py`.",
    ]
    out = Path(__file__).parent / "results" / "motion_bench.md"
    out.write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
