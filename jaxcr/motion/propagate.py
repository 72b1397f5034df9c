"""Label propagation between frames with the optical flow (M-L step 1: segments "tracked
throughout the video").

The label at pixel p of frame i+1 is read from frame i at p - f(p), where f is the dense
forward flow of frame i (an approximation of the backward flow that is exact for locally
constant flow). The warped map then seeds :func:`jaxcr.motion.superpixels.slic`, which snaps
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
    return labels[sy, sx]


def labels_at_points(labels: Int[Array, "h w"], pts: Float[Array, "n 2"]) -> Int[Array, " n"]:
    """Segment id under each (x, y) point (rounded, clamped)."""
    h, w = labels.shape
    xi = jnp.clip(jnp.round(pts[:, 0]).astype(jnp.int32), 0, w - 1)
    yi = jnp.clip(jnp.round(pts[:, 1]).astype(jnp.int32), 0, h - 1)
    return labels[yi, xi]
