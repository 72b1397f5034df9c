"""Segmentation and shape metrics: IoU (Watson et al. eq. 8), adjusted IoU, 3-D shape errors.

All functions act on one frame (vmap for batches), are pure JAX and jit-able.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float


def iou(pred: Bool[Array, "h w"], truth: Bool[Array, "h w"]) -> Float[Array, ""]:
    """Intersection over union |A n B| / |A u B| (eq. 8). Both empty gives 1."""
    pred, truth = pred.astype(bool), truth.astype(bool)
    inter = jnp.sum(pred & truth)
    union = jnp.sum(pred | truth)
    return jnp.where(union > 0, inter / jnp.maximum(union, 1), 1.0).astype(jnp.float32)


def adjusted_iou(
    pred: Bool[Array, "h w"], truth: Bool[Array, "h w"], occluded: Bool[Array, "h w"]
) -> Float[Array, ""]:
    """IoU after removing predicted pixels in occluded regions (Watson et al. Sec. III-B).

    ``truth`` holds the *visible* robot pixels; the full projection predicts occluded robot
    parts too, which the visible labels cannot confirm, so those pixels are excluded.
    """
    return iou(pred.astype(bool) & ~occluded.astype(bool), truth)


def _arclength(p: Float[Array, "n 3"]) -> Float[Array, " n"]:
    seg = jnp.linalg.norm(jnp.diff(p, axis=0), axis=-1)
    return jnp.concatenate([jnp.zeros(1, p.dtype), jnp.cumsum(seg)])


def resample_by_arclength(p: Float[Array, "n 3"], s_new: Float[Array, " m"]) -> Float[Array, "m 3"]:
    """Linear interpolation of a polyline at arclengths ``s_new`` (metres from p[0]; clamped
    to the polyline's length)."""
    s = _arclength(p)
    return jnp.stack([jnp.interp(s_new, s, p[:, i]) for i in range(3)], axis=-1)


def tip_error(p_est: Float[Array, "n 3"], p_true: Float[Array, "m 3"]) -> Float[Array, ""]:
    """Distance between the last points (tips) of two centrelines (metres)."""
    return jnp.linalg.norm(p_est[-1] - p_true[-1])


def tip_error_components(
    p_est: Float[Array, "n 3"], p_true: Float[Array, "m 3"], R_cam: Float[Array, "3 3"]
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Tip error split in a camera's frame (metres): ``(lateral, depth)``.

    ``R_cam`` rotates robot-frame vectors into the camera frame (x right, y down, z along the
    optical axis). ``lateral`` is the error's length in the image plane (x, y), what one view
    observes; ``depth`` is the absolute component along the optical axis, which a single view
    sees only through perspective scale. ``lateral**2 + depth**2 == tip_error**2``.
    """
    d = R_cam @ (p_est[-1] - p_true[-1])
    return jnp.sqrt(d[0] * d[0] + d[1] * d[1]), jnp.abs(d[2])


def mean_centreline_error(
    p_est: Float[Array, "n 3"], p_true: Float[Array, "m 3"], n_samples: int = 100
) -> Float[Array, ""]:
    """Mean distance (metres) between two centrelines compared at equal arclength from the base.

    Both polylines are resampled at ``n_samples`` arclengths evenly spread over [0, L], L the
    shorter of the two lengths.
    """
    length = jnp.minimum(_arclength(p_est)[-1], _arclength(p_true)[-1])
    s = jnp.linspace(0.0, 1.0, n_samples, dtype=p_est.dtype) * length
    a = resample_by_arclength(p_est, s)
    b = resample_by_arclength(p_true, s)
    return jnp.mean(jnp.linalg.norm(a - b, axis=-1))
