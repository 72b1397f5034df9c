"""Per-frame time of motion likelihood (M-L) at 640x480 in the validated setting, split into
stages, against OpenCV in the same run.

Renders one synthetic pushed video with a changing background (``jaxcr.synth``, seed ``seed``,
``frames`` frames, in a temporary folder), runs :func:`jaxcr.motion.run.run_motion` over it
once to compile, then ``repeats`` more times, and reports per used frame pair the median of
the tracker's own stage timers (:class:`jaxcr.motion.pipeline.StepRecord`: flow = grey
conversion + OpenCV LK on the grid + dense interpolation; segmentation; likelihood). In the
same run, on the same frame pairs: OpenCV ``calcOpticalFlowPyrLK`` alone on the same grid with
the same window at 3 levels (the validated setting) and at 1 and 0 levels (the floor of a
cheaper pyramid), and OpenCV DIS (fast preset, dense). The load average is recorded.

``jaxcr bench motion``; the committed table is experiments/results/motion/bench_motion.md.
"""

from __future__ import annotations

import os
import tempfile
import time

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
        run_motion(ds, cfg)
        warmup_s = time.perf_counter() - t0
        stage = {"flow": [], "segmentation": [], "likelihood": [], "total": []}
        for _ in range(max(1, repeats)):
            res = run_motion(ds, cfg)
            for r in (r for r in res.records if r.used):
                stage["flow"].append(r.flow_ms)
                stage["segmentation"].append(r.segmentation_ms)
                stage["likelihood"].append(r.likelihood_ms)
                stage["total"].append(r.flow_ms + r.segmentation_ms + r.likelihood_ms)
        rgb = [rgb for _, rgb, _ in ds.frames() if rgb is not None]
    w, h = int(size[0]), int(size[1])
    _, _, flow_step = resolve_steps(cfg, w)
    fc = FlowConfig(step=flow_step)
    pts = grid_points(h, w, flow_step)[:, None, :]
    grey = [to_gray_u8(x) for x in rgb]
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)

    def lk(levels):
        opts = dict(winSize=(fc.window, fc.window), maxLevel=levels, criteria=crit,
                    minEigThreshold=fc.min_eig)  # fmt: skip
        return lambda: [cv2.calcOpticalFlowPyrLK(a, b, pts, None, **opts)
                        for a, b in zip(grey[:-1], grey[1:], strict=True)]  # fmt: skip

    pairs = len(grey) - 1
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    n = max(3, repeats)
    ref = {
        f"OpenCV LK, {len(pts)} grid points, window {fc.window}, 3 levels (validated)": _median_ms(
            lk(3), n
        ) / pairs,
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
    return {
        "name": f"motion likelihood (M-L) per frame, {w}x{h}, validated setting",
        "unit": "frame",
        "median_s": med["total"] * 1e-3,
        "compile_s": warmup_s,
        "reference": "OpenCV LK on the same grid (3 levels), flow only",
        "reference_median_s": lk3 * 1e-3,
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
