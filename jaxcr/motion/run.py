"""Running M-L and the baseline over one dataset, with per-frame reporting.

:func:`run_motion` streams the frames (video or image folder) through a
:class:`~jaxcr.motion.pipeline.MotionTracker`, computes the end-effector pixels h(x) for all
frames at once (one jitted vmap), skips unreadable frames (tracking resumes from the last good
frame), and keeps the label map of the evaluation frame so that the final integrated
probabilities can be painted on it. :func:`run_baseline` runs the frame-differencing +
grabCut baseline around the first touch.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.io.motion_dataset import MotionDataset
from jaxcr.motion.baseline import fitzpatrick_segment
from jaxcr.motion.calibration import end_effector_image
from jaxcr.motion.pipeline import (
    MotionConfig,
    MotionTracker,
    StepRecord,
    pair_flow,
    resolve_steps,
)


@dataclass
class MotionResult:
    """Outcome of M-L on one video. ``maps[model]``: (H, W) probability map on the
    evaluation frame's segments; ``final_maps[model]``: on the last frame's segments;
    ``ee_uv`` (n, 2) h(x) per frame; ``records`` one per frame step; ``window_sums`` and
    ``window_counts`` (models, 2, segments) the per-window running sums (before touch,
    touching) from which any integration can be recomputed
    (:func:`jaxcr.motion.likelihood.object_probability`); ``failed`` {frame: reason} for the
    frames the reader could not use (unreadable, damaged, wrong size): the run went on without
    them."""

    eval_frame: int
    maps: dict[str, np.ndarray]
    final_maps: dict[str, np.ndarray]
    labels_eval: np.ndarray
    ee_uv: np.ndarray
    ee_visible: np.ndarray
    records: list[StepRecord]
    warnings: list[str] = field(default_factory=list)
    first_segmentation_ms: float = 0.0
    window_sums: np.ndarray | None = None
    window_counts: np.ndarray | None = None
    failed: dict[int, str] = field(default_factory=dict)


def first_touch(ds: MotionDataset) -> int | None:
    idx = np.flatnonzero(ds.touch)
    return int(idx[0]) if len(idx) else None


def eval_frame_index(ds: MotionDataset, eval_frame: int | None = None) -> int:
    """The frame :func:`run_motion` scores: ``eval_frame``, else the dataset's, else the first
    touch frame, else the last frame (known before any frame is processed, so that its
    ground-truth mask can be checked first)."""
    t_touch = first_touch(ds)
    ev = eval_frame if eval_frame is not None else ds.eval_frame
    return ev if ev is not None else (t_touch if t_touch is not None else len(ds) - 1)


# one compiled function per number of frames (the arm model is a pytree argument, not a
# closure constant: a new lambda per call recompiled for every video)
_end_effector_images = jax.jit(jax.vmap(end_effector_image, in_axes=(None, None, 0)))


def end_effector_pixels(ds: MotionDataset) -> tuple[np.ndarray, np.ndarray]:
    """h(x_i) for all frames (n, 2) and whether the tip is in front of the camera and inside
    the image."""
    uv, front = _end_effector_images(
        jnp.asarray(ds.P, jnp.float32), ds.arm, jnp.asarray(ds.x, jnp.float32)
    )
    uv, front = np.asarray(uv), np.asarray(front)
    inside = (
        (uv[:, 0] >= 0) & (uv[:, 0] <= ds.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= ds.height - 1)
    )
    return uv, front & inside


def _with_flow(frames, flow_fn, pool):
    """``(i, rgb, why, flow)`` for every item of ``frames`` (``(i, rgb, why)``; ``rgb`` None for
    an unreadable frame), in order, where ``flow`` is the future of ``flow_fn(prev_grey,
    rgb)`` from the previous readable frame (None for the first one and for unreadable
    frames). Each item is held back until the next readable frame has been read and its
    flow submitted to ``pool``, so the flow of pair k+1 runs while the caller steps pair k."""
    from jaxcr.motion.flow import to_gray_u8

    held: list = []
    prev = None
    for i, rgb, why in frames:
        if rgb is None:
            held.append((i, None, why, None))
            continue
        fut = None if prev is None else pool.submit(flow_fn, prev, rgb)
        prev = to_gray_u8(rgb)
        yield from held
        held = [(i, rgb, why, fut)]
    yield from held


def run_motion(
    ds: MotionDataset,
    cfg: MotionConfig | None = None,
    on_step: Callable[[StepRecord], None] | None = None,
    eval_frame: int | None = None,
    *,
    overlap_flow: bool = True,
) -> MotionResult:
    """M-L over the whole video. ``eval_frame`` defaults to the dataset's, else the first touch
    frame, else the last frame.

    ``overlap_flow`` (default): the OpenCV flow of the next frame pair runs in a second thread
    while the JAX likelihood and segmentation of the current pair run (they need only the
    two grey frames, not the tracker), so a frame costs about max(flow, JAX) instead of their
    sum where a second core is free. The results are identical either way (same functions on
    the same inputs; tests/motion/test_motion_pipeline.py,
    ``test_overlapped_flow_equals_sequential``); ``False`` runs them one after the other."""
    cfg = cfg or MotionConfig()
    warnings = []
    t_touch = first_touch(ds)
    if t_touch is None:
        warnings.append(
            "no frame has touch=true: arm removal only, the object cannot be told apart"
        )
    ev = eval_frame_index(ds, eval_frame)
    uv, vis = end_effector_pixels(ds)
    if not vis.any():
        warnings.append("the end-effector is out of view in every frame")
    tracker = None
    last = None  # index of the last good frame
    labels_eval = None
    failed: dict[int, str] = {}
    pool = (
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxcr-flow") if overlap_flow else None
    )
    if pool is not None:
        _, scale, step = resolve_steps(cfg, ds.width)
        flow_cfg = replace(cfg.flow, step=step)
        items = _with_flow(ds.frames(), lambda a, b: pair_flow(a, b, flow_cfg, scale), pool)
    else:
        items = ((i, rgb, why, None) for i, rgb, why in ds.frames())
    try:
        for i, rgb, why, fut in items:
            if rgb is None:
                failed[int(i)] = why
                rec = (
                    tracker.skip(i, why, ds.touch[i])
                    if tracker
                    else StepRecord(i, False, why, bool(ds.touch[i]), 0, 0, 0, 0)
                )
                if on_step:
                    on_step(rec)
                continue
            if tracker is None:
                tracker = MotionTracker(cfg, rgb)
                last = i
                rec = StepRecord(
                    i,
                    False,
                    "first frame",
                    bool(ds.touch[i]),
                    0.0,
                    tracker.first_segmentation_ms,
                    0.0,
                    0.0,
                )
                tracker.records.append(rec)
            else:
                # the touch flag of the interval [last, i]: touching at its end
                rec = tracker.step(
                    i, rgb, uv[last], uv[i], bool(ds.touch[i]), bool(vis[last]), bool(vis[i]),
                    flow=None if fut is None else fut.result(),
                )  # fmt: skip
                last = i
            if i == ev:
                labels_eval = np.asarray(tracker.labels)
            if on_step:
                on_step(rec)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    if tracker is None:
        raise RuntimeError("no readable frame in the video")
    if labels_eval is None:
        warnings.append(f"evaluation frame {ev} unreadable; using the last good frame")
        labels_eval = np.asarray(tracker.labels)
    if not any(r.used for r in tracker.records):
        warnings.append("no frame pair was usable (end-effector still or out of view)")
    maps = {m: tracker.probability_map(m, labels_eval) for m in cfg.models}
    final = {m: tracker.probability_map(m) for m in cfg.models}
    return MotionResult(
        ev,
        maps,
        final,
        labels_eval,
        uv,
        vis,
        tracker.records,
        warnings,
        tracker.first_segmentation_ms,
        np.asarray(tracker.sums),
        np.asarray(tracker.counts),
        failed,
    )


def touch_frames_u8(ds: MotionDataset, t: int) -> list[np.ndarray] | None:
    """uint8 RGB frames t-2, t-1, t (None if t < 2 or one is unreadable)."""
    if t is None or t < 2:
        return None
    want = {t - 2: None, t - 1: None, t: None}
    for i, rgb, _ in ds.frames(indices=want):
        if rgb is not None:
            want[i] = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    if any(v is None for v in want.values()):
        return None
    return [want[t - 2], want[t - 1], want[t]]


def run_baseline(ds: MotionDataset, thresholds) -> dict[float, np.ndarray] | None:
    """Baseline masks of the first touch frame for every difference threshold (grey levels),
    or None when the video has no usable touch event."""
    frames = touch_frames_u8(ds, first_touch(ds))
    if frames is None:
        return None
    return {float(th): fitzpatrick_segment(*frames, threshold=float(th)) for th in thresholds}
