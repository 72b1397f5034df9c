"""The Motion-Likelihood pipeline, frame by frame (M-L Fig. 3).

:class:`MotionTracker` keeps the tracked label map and, per motion model, the running
average of every segment's probability. Each :meth:`MotionTracker.step` takes the next image
and the end-effector pixels of the two frames, and

1. computes the LK grid flow (:mod:`~jaxcr.motion.flow`, OpenCV),
2. evaluates the motion models, the likelihood and arm removal for all segments and
   updates the running averages (:func:`frame_probabilities`, one jitted JAX call),
3. warps the labels with the flow and refines them with SLIC on the new frame (JAX), at the
   superpixels' working resolution (:func:`~jaxcr.motion.superpixels.working_rgb`).

The per-frame times of the three parts are recorded separately. A frame pair is *used* only
if the end-effector is in view in both frames and moved at least ``min_motion`` px; otherwise
the step is recorded with the reason and only the tracking advances.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, replace

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxcr.motion import flow as flowmod
from jaxcr.motion.likelihood import (
    gaussian_likelihood,
    object_probability,
    remove_arm,
    window_update,
)
from jaxcr.motion.motion_models import (
    homography_error,
    robust_translation,
    segment_homography,
    stabilise_flow,
    translation_error,
)
from jaxcr.motion.propagate import labels_at_points
from jaxcr.motion.superpixels import (
    auto_scale,
    grid_shape,
    segment_first,
    segment_track,
    working_rgb,
    working_shape,
)

MODELS = ("translation", "homography")


@dataclass(frozen=True)
class MotionConfig:
    """Settings of M-L. Lengths in pixels, lambda in px^2 (Sigma = lambda I, eq. 10).

    Defaults are the validated setting and scale with the frame: superpixel step W / 16
    (``superpixel_step`` = 0, :func:`auto_superpixel_step`) and LK grid step W / 80
    (``flow.step`` = 0), LK window 15 px and 3 pyramid levels: 20 px and 4 px on the 320x240
    videos of the accuracy experiments (experiments/results/motion/motion_report.md), 40 px and 8 px
    at 640x480 (experiments/results/motion/motion_bench.md), i.e. 16 x 12 superpixels with 25 flow
    points each. The resolved values are :attr:`MotionTracker.sp_step` (working px),
    :attr:`MotionTracker.scale` and :attr:`MotionTracker.flow_cfg`."""

    superpixel_step: int = 0  # 0: auto_superpixel_step(frame width)
    compactness: float = 10.0
    slic_iters_first: int = 6
    slic_iters_track: int = 2
    flow: flowmod.FlowConfig = field(default_factory=flowmod.FlowConfig)
    models: tuple[str, ...] = MODELS
    # lambda and threshold chosen on the static synthetic videos (P-R point closest to (1, 1),
    # experiments/results/motion/motion_report.md); the paper found 0.75 for the threshold
    lam: float = 5.0
    kappa: float = 1.0
    min_motion: float = 0.5
    threshold: float = 0.85
    homography_irls: int = 3
    perspective_penalty: float = 1.0
    select_sigma: float = 0.5
    translation_irls: int = 5  # Cauchy reweightings of the mean flow b_j (0: plain mean)
    stabilise: bool = True  # flow relative to the background homography (camera shake)
    integration: str = "product"  # likelihood.object_probability: "product" | "mixture"
    prior_frames: float = 1.0  # Beta prior per window, pseudo-frames at 1/2
    superpixel_scale: int = 0  # superpixels on the frame shrunk by this factor (0: auto_scale)
    # A tracked segment whose area falls below this fraction of its area in the previous
    # frame has been lost by the tracking (overrun by a neighbour, occluded, or left behind
    # when the object moved): its id stops collecting evidence from then on, so the id's
    # later pixels (often background it was re-assigned to) cannot dilute or fake the
    # evidence of the segment it named at the evaluation frame. 0 disables.
    retire_fraction: float = 0.5


def auto_superpixel_step(width: int) -> int:
    """Default superpixel step for a frame ``width`` px wide: W / 16 rounded, at least 4 px
    (16 superpixels across the frame: 20 px at 320 px, 40 px at 640 px)."""
    return max(4, round(width / 16))


def resolve_steps(cfg: MotionConfig, width: int) -> tuple[int, int, int]:
    """(superpixel step in full-size px, working scale, flow grid step in px) for a frame
    ``width`` px wide: the config's values, or the defaults (:func:`auto_superpixel_step`,
    :func:`~jaxcr.motion.superpixels.auto_scale`, :func:`~jaxcr.motion.flow.auto_step`) where
    they are 0. An automatic flow step is rounded to a multiple of the working scale; an
    explicit one that is not a multiple makes the superpixels run at full size (scale 1),
    since the dense flow must stay aligned with the working pixels."""
    sp = cfg.superpixel_step or auto_superpixel_step(width)
    scale = cfg.superpixel_scale or auto_scale(width, sp)
    step = cfg.flow.step
    if not step:
        step = scale * max(1, round(flowmod.auto_step(width) / scale))
    if step % scale:
        scale = 1
    return sp, scale, step


#: the static (shape- or branch-deciding) arguments of the two jitted per-frame functions below
_FRAME_STATIC = (
    "n_segments",
    "models",
    "n_irls",
    "penalty",
    "select_sigma",
    "stabilise",
    "translation_irls",
)


@functools.partial(jax.jit, static_argnames=_FRAME_STATIC)
def frame_probabilities(
    pts: Float[Array, "n 2"],
    flow: Float[Array, "n 2"],
    valid: Bool[Array, " n"],
    labels: Int[Array, "h w"],
    x_now: Float[Array, "2"],
    x_next: Float[Array, "2"],
    touch: Bool[Array, ""],
    lam: float,
    kappa: float,
    n_segments: int,
    models: tuple[str, ...] = MODELS,
    n_irls: int = 3,
    penalty: float = 0.0,
    select_sigma: float = 0.0,
    stabilise: bool = False,
    translation_irls: int = 0,
) -> tuple[Float[Array, "m k"], Bool[Array, " k"]]:
    """Arm-removed membership probability of every segment for one frame pair, one row per
    model in ``models`` (eqs. 4-13), and which segments had valid flow (``present``). With
    ``stabilise`` the flow is first taken relative to the background
    (:func:`~jaxcr.motion.motion_models.stabilise_flow`)."""
    seg = labels_at_points(labels, pts)
    if stabilise:
        flow, _ = stabilise_flow(pts, flow, valid)
    w = valid.astype(flow.dtype)
    b, count = robust_translation(flow, seg, w, n_segments, translation_irls)
    rows = []
    for m in models:
        if m == "translation":
            rho = translation_error(b, x_now, x_next)
        elif m == "homography":
            H = segment_homography(
                pts,
                flow,
                seg,
                valid,
                n_segments,
                n_irls=n_irls,
                perspective_penalty=penalty,
                select_sigma=select_sigma,
                translation_irls=translation_irls,
                translation=(b, count),
            )
            rho = homography_error(H, x_now, x_next)
        else:
            raise ValueError(f"unknown motion model {m!r}")
        rows.append(remove_arm(gaussian_likelihood(rho, lam), touch, kappa))
    return jnp.stack(rows), count > 0


_window_update = jax.vmap(window_update, in_axes=(0, 0, 0, None, None))


@functools.partial(jax.jit, static_argnames=_FRAME_STATIC)
def frame_update(
    sums: Float[Array, "m 2 k"],
    counts: Float[Array, "m 2 k"],
    pts: Float[Array, "n 2"],
    flow: Float[Array, "n 2"],
    valid: Bool[Array, " n"],
    labels: Int[Array, "h w"],
    x_now: Float[Array, "2"],
    x_next: Float[Array, "2"],
    touch: Bool[Array, ""],
    lam: float,
    kappa: float,
    n_segments: int,
    models: tuple[str, ...] = MODELS,
    n_irls: int = 3,
    penalty: float = 0.0,
    select_sigma: float = 0.0,
    stabilise: bool = False,
    translation_irls: int = 0,
) -> tuple[Float[Array, "m 2 k"], Float[Array, "m 2 k"]]:
    """One frame pair of M-L in one jitted call: :func:`frame_probabilities` and the
    per-window running sums of every model (:func:`~jaxcr.motion.likelihood.window_update`).
    Returns the new (sums, counts)."""
    p, present = frame_probabilities(
        pts,
        flow,
        valid,
        labels,
        x_now,
        x_next,
        touch,
        lam,
        kappa,
        n_segments,
        models,
        n_irls,
        penalty,
        select_sigma,
        stabilise,
        translation_irls,
    )
    return _window_update(sums, counts, p, present, touch)


@functools.partial(jax.jit, static_argnames=("n_segments",))
def _label_areas(labels: Int[Array, "h w"], n_segments: int) -> Float[Array, " k"]:
    return jnp.bincount(labels.reshape(-1), length=n_segments).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames=("n_segments",))
def _retire_lost(
    alive: Bool[Array, " k"],
    area: Float[Array, " k"],
    labels: Int[Array, "h w"],
    n_segments: int,
    fraction: float,
) -> tuple[Bool[Array, " k"], Float[Array, " k"]]:
    """Ids still tracked after a step (``alive`` and area >= ``fraction`` x the previous
    area; MotionConfig.retire_fraction) and the new areas (px of ``labels``)."""
    new = _label_areas(labels, n_segments)
    return alive & (new >= fraction * area), new


@dataclass(frozen=True)
class PairFlow:
    """M-L step 2 for one frame pair (host arrays): the next frame's grey image, the LK grid
    points, flow and validity (:func:`~jaxcr.motion.flow.grid_flow`), the dense flow at the
    superpixels' working resolution (:func:`~jaxcr.motion.flow.dense_from_grid`) and the
    wall time it took (ms)."""

    gray: np.ndarray
    pts: np.ndarray
    flow: np.ndarray
    valid: np.ndarray
    dense: np.ndarray
    ms: float


def pair_flow(
    prev_gray: np.ndarray, next_frame: np.ndarray, flow_cfg: flowmod.FlowConfig, scale: int
) -> PairFlow:
    """Grid flow from ``prev_gray`` (uint8, (H, W)) to ``next_frame`` (RGB as
    :func:`~jaxcr.motion.flow.to_gray_u8` takes it, or uint8 grey) with a resolved
    ``flow_cfg`` (its ``step`` set) and its dense field at working ``scale``. OpenCV and
    NumPy only (no JAX; OpenCV releases the GIL): safe and useful in a second thread."""
    t0 = time.perf_counter()
    next_gray = flowmod.to_gray_u8(next_frame)
    h, w = next_gray.shape
    pts, fl, valid = flowmod.grid_flow(prev_gray, next_gray, flow_cfg)
    dense = flowmod.dense_from_grid(fl, valid, h, w, flow_cfg.step, scale)
    return PairFlow(next_gray, pts, fl, valid, dense, 1e3 * (time.perf_counter() - t0))


@dataclass
class StepRecord:
    """What happened between frames ``index - 1`` and ``index``."""

    index: int
    used: bool
    reason: str
    touch: bool
    flow_ms: float
    segmentation_ms: float
    likelihood_ms: float
    valid_flow: float


class MotionTracker:
    """Incremental M-L over a video (see the module docstring).

    Args:
        cfg: settings.
        first_rgb: the first frame, float32 RGB in [0, 1], (H, W, 3).
    """

    def __init__(self, cfg: MotionConfig, first_rgb: np.ndarray):
        self.cfg = cfg
        h, w = first_rgb.shape[:2]
        self.height, self.width = h, w
        sp, s, flow_step = resolve_steps(cfg, w)
        self.scale = s
        self.sp_step = max(1, round(sp / s))
        self.flow_cfg = replace(cfg.flow, step=flow_step)
        gh, gw = grid_shape(*working_shape(h, w, s), self.sp_step)
        self.n_segments = gh * gw
        t0 = time.perf_counter()
        self.work_labels, self.labels = segment_first(
            jnp.asarray(working_rgb(first_rgb, s)),
            self.n_segments,
            self.sp_step,
            cfg.compactness,
            cfg.slic_iters_first,
            s,
            h,
            w,
        )
        self.labels.block_until_ready()
        self.first_segmentation_ms = 1e3 * (time.perf_counter() - t0)
        self.gray = flowmod.to_gray_u8(first_rgb)
        m = len(cfg.models)
        # per model, window (before touch, touching) and segment: eq. 16 running sums
        self.sums = jnp.zeros((m, 2, self.n_segments), jnp.float32)
        self.counts = jnp.zeros((m, 2, self.n_segments), jnp.float32)
        self.records: list[StepRecord] = []
        self._pts = None
        # per id: still the segment it was (MotionConfig.retire_fraction) and its last area
        self.area = _label_areas(self.work_labels, self.n_segments)
        self.alive = jnp.ones(self.n_segments, bool)

    def in_view(self, uv) -> bool:
        return bool(
            np.all(np.isfinite(uv))
            and 0 <= uv[0] <= self.width - 1
            and 0 <= uv[1] <= self.height - 1
        )

    def pair_flow(self, prev_gray: np.ndarray, next_frame: np.ndarray) -> PairFlow:
        """The flow of one frame pair as :meth:`step` uses it (:func:`pair_flow` with this
        tracker's settings). Touches no tracker state, so it may run in another thread while
        the tracker steps (:func:`jaxcr.motion.run.run_motion` overlaps it with the JAX work
        of the previous pair)."""
        return pair_flow(prev_gray, next_frame, self.flow_cfg, self.scale)

    def step(
        self,
        index: int,
        next_rgb: np.ndarray,
        x_now,
        x_next,
        touch: bool,
        now_visible: bool = True,
        next_visible: bool = True,
        *,
        flow: PairFlow | None = None,
    ) -> StepRecord:
        """Advance to ``next_rgb``; ``x_now``/``x_next`` are h(x) at the two frames (px).
        ``flow``: the pair's flow already computed by :meth:`pair_flow` from the tracker's
        last frame to ``next_rgb`` (its time is then the recorded ``flow_ms``); default:
        computed here."""
        cfg = self.cfg
        if flow is None:
            flow = self.pair_flow(self.gray, next_rgb)
        gray, pts, fl, valid, dense = flow.gray, flow.pts, flow.flow, flow.valid, flow.dense
        t1 = time.perf_counter()
        reason = ""
        x_now = np.asarray(x_now, np.float32)
        x_next = np.asarray(x_next, np.float32)
        if not (now_visible and next_visible and self.in_view(x_now) and self.in_view(x_next)):
            reason = "end-effector out of view"
        elif np.linalg.norm(x_next - x_now) < cfg.min_motion:
            reason = f"end-effector still (< {cfg.min_motion:g} px)"
        elif not valid.any():
            reason = "no valid flow"
        if not reason:
            if self._pts is None or self._pts.shape != pts.shape:
                self._pts = jnp.asarray(pts)  # the grid is fixed: transferred once
            sums, counts = frame_update(
                self.sums,
                self.counts,
                self._pts,
                jnp.asarray(fl),
                jnp.asarray(valid),
                self.labels,
                jnp.asarray(x_now),
                jnp.asarray(x_next),
                jnp.asarray(bool(touch)),
                cfg.lam,
                cfg.kappa,
                self.n_segments,
                cfg.models,
                cfg.homography_irls,
                cfg.perspective_penalty,
                cfg.select_sigma,
                cfg.stabilise,
                cfg.translation_irls,
            )
            # lost ids keep the evidence they collected while they were the segment
            self.sums = jnp.where(self.alive, sums, self.sums)
            self.counts = jnp.where(self.alive, counts, self.counts)
            self.sums.block_until_ready()
        t2 = time.perf_counter()
        self.work_labels, self.labels = segment_track(
            self.work_labels,
            jnp.asarray(dense),
            jnp.asarray(working_rgb(next_rgb, self.scale)),
            self.n_segments,
            self.sp_step,
            cfg.compactness,
            cfg.slic_iters_track,
            self.scale,
            self.height,
            self.width,
        )
        if cfg.retire_fraction > 0:
            self.alive, self.area = _retire_lost(
                self.alive, self.area, self.work_labels, self.n_segments, cfg.retire_fraction
            )
        self.labels.block_until_ready()
        t3 = time.perf_counter()
        self.gray = gray
        rec = StepRecord(
            index,
            not reason,
            reason,
            bool(touch),
            flow.ms,
            1e3 * (t3 - t2),
            1e3 * (t2 - t1),
            float(valid.mean()),
        )
        self.records.append(rec)
        return rec

    def skip(self, index: int, reason: str, touch: bool = False) -> StepRecord:
        """Record an unreadable frame (tracking continues from the last good frame)."""
        rec = StepRecord(index, False, reason, bool(touch), 0.0, 0.0, 0.0, 0.0)
        self.records.append(rec)
        return rec

    def segment_probability(self, model: str) -> np.ndarray:
        """Integrated probability of every segment (eq. 16 per window, combined by
        ``cfg.integration``) for one model, (n_segments,)."""
        i = self.cfg.models.index(model)
        return np.asarray(
            object_probability(
                self.sums[i], self.counts[i], self.cfg.integration, self.cfg.prior_frames
            )
        )

    def probability_map(self, model: str, labels=None) -> np.ndarray:
        """(H, W) float32 map of the integrated probability on ``labels`` (default: current)."""
        lbl = self.labels if labels is None else labels
        return np.asarray(jnp.asarray(self.segment_probability(model))[lbl])
