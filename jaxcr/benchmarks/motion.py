"""Per-frame time of motion likelihood (M-L) at 640x480 in the validated setting, split into
stages, against OpenCV in the same run.

Renders one synthetic pushed video with a changing background (``jaxcr.synth``, seed ``seed``,
``frames`` frames, in a temporary folder), runs :func:`jaxcr.motion.run.run_motion` over it
once to compile, then ``repeats`` more times, and reports per used frame pair the median of
the tracker's own stage timers (:class:`jaxcr.motion.pipeline.StepRecord`: flow = grey
conversion + OpenCV LK on the grid + dense interpolation; segmentation; likelihood), measured
on the sequential path (``overlap_flow=False``). The headline ``median_s`` is the wall time per
used frame pair of the default path, which overlaps the next pair's flow with the current
pair's JAX work (:func:`~jaxcr.motion.run.run_motion`); the sequential path's wall time runs
alternately in the same run (``sequential_median_s``), and the two outputs are compared
(``overlap_outputs_identical``). In the
same run, on the same frame pairs: OpenCV ``calcOpticalFlowPyrLK`` alone on the same grid with
the same window at 3 levels (the validated setting) and at 1 and 0 levels (the floor of a
cheaper pyramid), and OpenCV DIS (fast preset, dense). The load average is recorded.

``jaxcr bench motion``; the committed table is experiments/results/motion/bench_motion.md.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace

import numpy as np


def _median_ms(fn, n: int) -> float:
    fn()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)) * 1e3


def run_motion_benchmark(
    frames: int = 8, size: tuple[int, int] = (640, 480), repeats: int = 3, seed: int = 4
) -> dict:
    """Run the benchmark (see the module docstring); ``size`` is (width, height)."""
    import cv2

    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.motion.flow import FlowConfig, grid_points, to_gray_u8
    from jaxcr.motion.pipeline import MotionConfig, resolve_steps
    from jaxcr.motion.run import run_motion
    from jaxcr.synth.motion_scenes import generate_motion_video

    load_before = os.getloadavg()
    cfg = MotionConfig()
    with tempfile.TemporaryDirectory(prefix="jaxcr_bench_motion_") as tmp:
        path = generate_motion_video(
            os.path.join(tmp, "video"), "pushed_changing", seed=seed, size=tuple(size),
            n_frames=max(6, frames),
        )  # fmt: skip
        ds = load_motion_dataset(path)
        t0 = time.perf_counter()
        run_motion(ds, cfg, overlap_flow=False)
        warmup_s = time.perf_counter() - t0
        stage = {"flow": [], "segmentation": [], "likelihood": [], "total": []}
        # wall time per used frame pair (the interval between its step's report and the
        # previous one), for the sequential path and the overlapped flow, alternated in the
        # same run (equal load); their outputs must be identical
        # "iters10": the overlapped path with LK capped at 10 iterations per level
        # (experiments/results/motion/motion_speed_r2.md), in the same loop
        cfg10 = replace(cfg, flow=replace(cfg.flow, iters=10))
        wall = {False: [], True: [], "iters10": []}
        maps = {}
        for _ in range(max(1, repeats)):
            for overlap in (False, True, "iters10"):
                stamps = []
                res = run_motion(
                    ds, cfg10 if overlap == "iters10" else cfg, overlap_flow=bool(overlap),
                    on_step=lambda r, st=stamps: st.append((r.used, time.perf_counter())),
                )  # fmt: skip
                wall[overlap] += [
                    1e3 * (t - t_prev)
                    for (_, t_prev), (used, t) in zip(stamps[:-1], stamps[1:], strict=True)
                    if used
                ]
                maps[overlap] = res.maps
                if overlap is not False:
                    continue
                for r in (r for r in res.records if r.used):
                    stage["flow"].append(r.flow_ms)
                    stage["segmentation"].append(r.segmentation_ms)
                    stage["likelihood"].append(r.likelihood_ms)
                    stage["total"].append(r.flow_ms + r.segmentation_ms + r.likelihood_ms)
        identical = all(np.array_equal(maps[False][m], maps[True][m]) for m in cfg.models)
        rgb = [rgb for _, rgb, _ in ds.frames() if rgb is not None]
    w, h = int(size[0]), int(size[1])
    _, _, flow_step = resolve_steps(cfg, w)
    fc = FlowConfig(step=flow_step)
    pts = grid_points(h, w, flow_step)[:, None, :]
    grey = [to_gray_u8(x) for x in rgb]
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)

    def lk(levels, iters=20):
        opts = dict(winSize=(fc.window, fc.window), maxLevel=levels,
                    criteria=(crit[0], iters, crit[2]), minEigThreshold=fc.min_eig)  # fmt: skip
        return lambda: [cv2.calcOpticalFlowPyrLK(a, b, pts, None, **opts)
                        for a, b in zip(grey[:-1], grey[1:], strict=True)]  # fmt: skip

    pairs = len(grey) - 1
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    n = max(3, repeats)
    ref = {
        f"OpenCV LK, {len(pts)} grid points, window {fc.window}, 3 levels (validated)": _median_ms(
            lk(3), n
        ) / pairs,
        "OpenCV LK, same points, 2 levels": _median_ms(lk(2), n) / pairs,
        "OpenCV LK, same points, 3 levels, at most 10 iterations": _median_ms(lk(3, 10), n)
        / pairs,
        "OpenCV LK, same points, 1 level": _median_ms(lk(1), n) / pairs,
        "OpenCV LK, same points, no pyramid": _median_ms(lk(0), n) / pairs,
        "OpenCV DIS (fast preset, dense)": _median_ms(
            lambda: [dis.calc(a, b, None) for a, b in zip(grey[:-1], grey[1:], strict=True)], n
        ) / pairs,
    }  # fmt: skip
    load_after = os.getloadavg()
    med = {k: float(np.median(v)) for k, v in stage.items()}
    lk3 = next(iter(ref.values()))
    rows = [{"stage": k, "median_ms": v, "share": v / med["total"]} for k, v in med.items()]
    rows += [{"stage": f"reference: {k}", "median_ms": v} for k, v in ref.items()]
    seq_ms, ovl_ms = float(np.median(wall[False])), float(np.median(wall[True]))
    rows += [
        {"stage": "wall per frame, sequential (overlap_flow=False)", "median_ms": seq_ms},
        {"stage": "wall per frame, overlapped flow (default)", "median_ms": ovl_ms,
         "share": ovl_ms / seq_ms},
        {"stage": "wall per frame, overlapped flow, LK at most 10 iterations",
         "median_ms": float(np.median(wall["iters10"])),
         "share": float(np.median(wall["iters10"])) / seq_ms},
    ]  # fmt: skip
    return {
        "name": f"motion likelihood (M-L) per frame, {w}x{h}, validated setting",
        "unit": "frame",
        "median_s": ovl_ms * 1e-3,
        "sequential_median_s": seq_ms * 1e-3,
        "overlap_speed_up": seq_ms / ovl_ms,
        "overlap_outputs_identical": identical,
        "compile_s": warmup_s,
        "reference": "OpenCV LK on the same grid (3 levels), flow only",
        "reference_median_s": lk3 * 1e-3,
        "stage_sum_median_s": med["total"] * 1e-3,
        "frame_pairs": len(stage["total"]),
        "flow_share": med["flow"] / med["total"],
        "lk_floor_ms_1_level": ref["OpenCV LK, same points, 1 level"],
        "load_avg_before": list(load_before),
        "load_avg_after": list(load_after),
        "rows": rows,
        "notes": "compile_s is the whole first run (compilation + one pass). Shared 2-core "
        "machine: absolute times are inflated by the load recorded here; the flow stage and "
        "OpenCV LK alone ran in the same process on the same frames.",
    }


__all__ = ["run_motion_benchmark"]
