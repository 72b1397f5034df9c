"""Label propagation between frames with the optical flow (M-L step 1: segments "tracked
throughout the video").

Labels are forward-splatted: the label of pixel p of frame i lands on round(p + f(p)) in
frame i+1, f the dense forward flow of frame i. Pixels that receive nothing (disoccluded, e.g.
the wake of a pushed object) are filled from their nearest labelled neighbours by a few
passes of 2-px neighbour propagation, and any still empty pixel falls back to the backward
lookup p - f(p) (which would otherwise smear a moving segment into its wake). The map then
seeds :func:`jaxcr.motion.superpixels.slic`, which snaps
the tracked segments to the new frame's colours while keeping their ids.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


@jax.jit
def warp_labels(labels: Int[Array, "h w"], flow: Float[Array, "h w 2"]) -> Int[Array, "h w"]:
    """labels_{i+1}(p) = labels_i(round(p - flow(p))), flow (x, y) in pixels, clamped at the
    image border (nearest neighbour: labels are ids, not values)."""
    h, w = labels.shape
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    sx = jnp.clip(jnp.round(xx - flow[..., 0]).astype(jnp.int32), 0, w - 1)
    sy = jnp.clip(jnp.round(yy - flow[..., 1]).astype(jnp.int32), 0, h - 1)
    return jnp.take(labels.reshape(-1), sy * w + sx, mode="clip")  # flat 1-D gather (fast on CPU)


def _fill_step(lbl: Int[Array, "h w"], d: int) -> Int[Array, "h w"]:
    """Holes (-1) take the label found ``d`` px right, left, below or above (first found in
    that order; edge clamped). Shifts are static slices of an edge-padded map."""
    h, w = lbl.shape
    padded = jnp.pad(lbl, d, mode="edge")
    out = lbl
    for dy, dx in ((0, d), (0, -d), (d, 0), (-d, 0)):
        nb = padded[d + dy : d + dy + h, d + dx : d + dx + w]
        out = jnp.where((out < 0) & (nb >= 0), nb, out)
    return out


@jax.jit
def splat_labels(labels: Int[Array, "h w"], flow: Float[Array, "h w 2"]) -> Int[Array, "h w"]:
    """Forward-splat labels with the flow (see the module docstring); int32 ids, no holes."""
    h, w = labels.shape
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    dx = jnp.round(xx + flow[..., 0]).astype(jnp.int32)
    dy = jnp.round(yy + flow[..., 1]).astype(jnp.int32)
    inside = (dx >= 0) & (dx < w) & (dy >= 0) & (dy < h)
    # out-of-image targets go to a dummy row that is cut off afterwards
    flat = jnp.where(inside, dy * w + dx, h * w)
    out = (
        jnp.full((h + 1) * w, -1, jnp.int32)
        .at[flat.reshape(-1)]
        .set(labels.astype(jnp.int32).reshape(-1), mode="promise_in_bounds")
    )
    out = out[: h * w].reshape(h, w)
    for d in (1, 2, 2, 3):
        out = _fill_step(out, d)
    return jnp.where(out >= 0, out, warp_labels(labels, flow))


def labels_at_points(labels: Int[Array, "h w"], pts: Float[Array, "n 2"]) -> Int[Array, " n"]:
    """Segment id under each (x, y) point (rounded, clamped)."""
    h, w = labels.shape
    xi = jnp.clip(jnp.round(pts[:, 0]).astype(jnp.int32), 0, w - 1)
    yi = jnp.clip(jnp.round(pts[:, 1]).astype(jnp.int32), 0, h - 1)
    return jnp.take(labels.reshape(-1), yi * w + xi, mode="clip")
