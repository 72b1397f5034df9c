"""Per-frame time of M-L at 640x480, split into flow, segmentation and likelihood.

  python experiments/motion_bench.py [--frames 8] [--data DIR]

Renders one pushed video with a changing background at 640x480 (not timed; kept in --data for
re-runs), then for each configuration runs the whole tracker twice over it: the first run
compiles (reported separately as "warm-up run incl. compile"), the second is timed per frame
pair. Stages, as recorded by ``MotionTracker.step``: flow (grey conversion, OpenCV LK on the
grid, dense interpolation), segmentation (Lab on the working-resolution frame, label splatting
and SLIC refinement, labels repeated to full size; JAX), likelihood (motion models, eqs. 4-16,
JAX). Medians [IQR] over the used frame pairs.

References on the same frames, what a user would otherwise run: scikit-image's ``slic`` from
scratch (same number of segments, compactness 10, its default 10 iterations) plus OpenCV's
``calcOpticalFlowPyrLK`` on the same 8-px grid (window 15, 3 levels); and OpenCV DIS (fast
preset) for a dense flow. Writes experiments/results/motion_bench.md.
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
from tqdm import tqdm  # noqa: E402

from jaxcr.motion.dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion.flow import FlowConfig, grid_flow, to_gray_u8  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig  # noqa: E402
from jaxcr.motion.run import run_motion  # noqa: E402
from jaxcr.synth.motion_scenes import generate_motion_video  # noqa: E402

W9 = FlowConfig(step=8, window=9, levels=3)
# (label, config). Superpixel step 20 px at 640x480 is 768 segments; 40 px (192 segments, 25
# flow points each at the 8-px grid) is the 320x240 experiment setting (step 20, grid 4) scaled
# to the doubled resolution, so its accuracy is the one measured in motion_report.md.
CONFIGS = (
    ("superpixels 20 px, LK grid 4 px (window 15, 3 levels), both models", MotionConfig()),
    (
        "superpixels 20 px, LK grid 8 px (window 15, 3 levels), both models",
        MotionConfig(flow=FlowConfig(step=8)),
    ),
    (
        "superpixels 40 px, LK grid 8 px (window 15, 3 levels), both models",
        MotionConfig(superpixel_step=40, flow=FlowConfig(step=8)),
    ),
    (
        "superpixels 40 px, LK grid 8 px (window 9, 3 levels), both models",
        MotionConfig(superpixel_step=40, flow=W9),
    ),
    (
        "superpixels 40 px, LK grid 8 px (window 9, 3 levels), translation only",
        MotionConfig(superpixel_step=40, flow=W9, models=("translation",)),
    ),
    (
        "superpixels 40 px, OpenCV DIS (fast preset) sampled on the 8-px grid, both models",
        MotionConfig(superpixel_step=40, flow=FlowConfig(step=8, method="dis")),
    ),
)
REF = 2  # the row compared with the user's reference (same flow)


def med(x) -> float:
    return float(np.median(np.asarray(x)))


def med_iqr(x) -> str:
    x = np.asarray(x)
    return f"{np.median(x):.1f} [{np.percentile(x, 25):.1f}, {np.percentile(x, 75):.1f}]"


def timed(fn, *args, **kw) -> float:
    t = time.perf_counter()
    fn(*args, **kw)
    return 1e3 * (time.perf_counter() - t)


def load_average() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def segmentation_parts(frames: list[np.ndarray], cfg: MotionConfig) -> dict[str, float]:
    """Median ms of the parts of one tracked segmentation step at the shapes of ``cfg`` (each
    part jitted on its own, so they need not add up to the fused step)."""
    import jax.numpy as jnp

    from jaxcr.colour import rgb_to_lab
    from jaxcr.motion.flow import dense_from_grid
    from jaxcr.motion.propagate import splat_labels
    from jaxcr.motion.superpixels import (
        auto_scale,
        grid_shape,
        segment_first,
        segment_track,
        slic,
        working_rgb,
        working_shape,
    )

    h, w = frames[0].shape[:2]
    s = auto_scale(w, cfg.superpixel_step)
    step = cfg.superpixel_step // s
    k = int(np.prod(grid_shape(*working_shape(h, w, s), step)))
    g0, g1 = to_gray_u8(frames[0]), to_gray_u8(frames[1])
    _, fl, valid = grid_flow(g0, g1, cfg.flow)
    dense = jnp.asarray(dense_from_grid(fl, valid, h, w, cfg.flow.step, s))
    small = working_rgb(frames[1], s)
    x = jnp.asarray(small)
    lbl, _ = segment_first(
        jnp.asarray(working_rgb(frames[0], s)), k, step, cfg.compactness, 6, s, h, w
    )
    lab_fn = jax.jit(rgb_to_lab)
    lab = lab_fn(x)

    def rep(fn, n=15):
        fn()  # compile
        return med([timed(fn) for _ in range(n)])

    return {
        "host area-resize": rep(lambda: working_rgb(frames[1], s)),
        "transfer": rep(lambda: jnp.asarray(small).block_until_ready()),
        "Lab (jaxcr.colour.rgb_to_lab)": rep(lambda: lab_fn(x).block_until_ready()),
        "splat": rep(lambda: splat_labels(lbl, dense).block_until_ready()),
        f"SLIC x{cfg.slic_iters_track}": rep(
            lambda: slic(
                lab, lbl, k, step, cfg.compactness, cfg.slic_iters_track
            ).block_until_ready()
        ),
        "whole step (fused)": rep(
            lambda: segment_track(
                lbl, dense, x, k, step, cfg.compactness, cfg.slic_iters_track, s, h, w
            )[1].block_until_ready()
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "jaxcr_motion_bench"))
    a = ap.parse_args()
    t_start = time.time()
    d = Path(a.data) / f"pushed_changing_640x480_{a.frames}"
    if not (d / "motion.json").exists():
        print(f"rendering the 640x480 video into {d} (not timed) ...", flush=True)
        generate_motion_video(d, "pushed_changing", seed=4, size=(640, 480), n_frames=a.frames)
    ds = load_motion_dataset(d)
    load_before = load_average()
    rows = []
    totals = {}
    for label, cfg in tqdm(CONFIGS, desc="configurations"):
        t = time.time()
        run_motion(ds, cfg)  # warm-up: compiles for this shape
        warm = time.time() - t
        res = run_motion(ds, cfg)
        recs = [r for r in res.records if r.used]
        f = np.array([r.flow_ms for r in recs])
        s = np.array([r.segmentation_ms for r in recs])
        li = np.array([r.likelihood_ms for r in recs])
        tot = f + s + li
        totals[label] = (med(f), med(s), med(tot))
        rows.append(
            [label, med_iqr(f), med_iqr(s), med_iqr(li), med_iqr(tot), f"{warm:.1f}", len(recs)]
        )
    # references on the same frames
    from skimage.segmentation import slic as sk_slic

    frames = [rgb for _, rgb, _ in ds.frames()]
    grays = [to_gray_u8(rgb) for rgb in frames]
    n_seg = (640 // 40) * (480 // 40)  # as row REF
    sk = [
        timed(sk_slic, rgb, n_segments=n_seg, compactness=10, start_label=0)
        for rgb in tqdm(frames[1:5], desc="skimage slic")
    ]
    ref_flow = FlowConfig(step=8)
    lk = [timed(grid_flow, g0, g1, ref_flow) for g0, g1 in zip(grays[:-1], grays[1:], strict=True)]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    dt = [timed(dis.calc, g0, g1, None) for g0, g1 in zip(grays[:-1], grays[1:], strict=True)]
    parts = segmentation_parts(frames, CONFIGS[REF][1])
    load_after = load_average()
    ref_total = med(sk) + med(lk)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parent,
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "jaxcr/motion", "experiments/motion_bench.py"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parent.parent,
    ).stdout.strip()
    L = [
        "# M-L per-frame time at 640x480",
        "",
        f"commit {commit}{' (motion files modified)' if dirty else ''}, jax {jax.__version__}, "
        f"opencv {cv2.__version__}, {platform.machine()}, {os.cpu_count()} cores, XLA "
        f"single-threaded; load average (1, 5, 15 min) {load_before} before and {load_after} "
        "after the timed runs (the machine is shared: timings at a load above ~2 are inflated). "
        f"{a.frames}-frame pushed_changing video (seed 4). Superpixels are computed at the "
        "working resolution 320x240 (auto scale 2: 10 or 20 working px) and repeated to full size. "
        "Median [IQR] over the used frame pairs, ms; compile excluded (separate warm-up run).",
        "",
        "| config | flow | segmentation | likelihood | total | warm-up run incl. compile (s) "
        "| frames |",
        "|---|---|---|---|---|---|---|",
    ]
    L += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    ref_label = CONFIGS[REF][0]
    seg_ours = totals[ref_label][1]
    best = min(totals.items(), key=lambda kv: kv[1][2])
    L += [
        "",
        "References on the same frames (same run):",
        "",
        f"- scikit-image `slic` from scratch ({n_seg} segments, compactness 10): {med_iqr(sk)} ms "
        f"per frame, {med(sk) / max(seg_ours, 1e-9):.0f}x our tracked segmentation "
        f"({seg_ours:.1f} ms, row {REF + 1}; ours tracks the previous frame's segments with 2 "
        "iterations, scikit-image starts from scratch).",
        f"- Our segmentation step of row {REF + 1}, by part (ms, median of 15): "
        + ", ".join(f"{k} {v:.1f}" for k, v in parts.items())
        + ".",
        f"- OpenCV `calcOpticalFlowPyrLK` on the 8-px grid (window 15, 3 levels) alone: "
        f"{med_iqr(lk)} ms; OpenCV DIS (fast preset, dense): {med_iqr(dt)} ms.",
        f"- A user's reference per frame (scikit-image SLIC + OpenCV LK on the 8-px grid, no "
        f"likelihood): {ref_total:.1f} ms; our whole M-L step (row {REF + 1}, same flow, both "
        f"models): {totals[ref_label][2]:.1f} ms ({ref_total / totals[ref_label][2]:.1f}x).",
        f"- Fastest configuration: {best[0]}, {best[1][2]:.1f} ms per frame "
        f"({'meets' if best[1][2] <= 30 else 'misses'} the 30 ms aim at this load).",
        "",
        f"Reproduce: `python experiments/motion_bench.py` ({time.time() - t_start:.0f} s for this "
        "run, including rendering the video if it was not cached).",
    ]
    out = Path(__file__).parent / "results" / "motion_bench.md"
    out.write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
