"""Label propagation between frames with the optical flow (M-L step 1: segments "tracked
throughout the video").

Labels are forward-splatted: the label of pixel p of frame i lands on round(p + f(p)) in
frame i+1, f the dense forward flow of frame i. Occlusion and disocclusion are resolved by
motion layering, so that the result does not depend on the order in which a scatter writes:

* where several pixels land on one target (occlusion), the one that moves most relative to
  the dominant image motion (a robust mean of the flow, i.e. the table and camera) wins: the pushed
  object and the arm move over the table, in front of it. (XLA's scatter let the last
  written pixel win, i.e. the background whenever the object moved right or down, and those
  background ids then rode along on the object.)
* pixels that receive nothing (disoccluded, e.g. the wake of a pushed object) are filled
  from the labelled pixels up to 8 px away along the rows and columns, taking the nearest
  of those that move *least* relative to the dominant motion: a disocclusion reveals the
  layer behind the one that moved away. (The former passes of 1, 2, 2 and 3 px in a fixed
  right/left/down/up order filled the wake of an object moving right with the object's own
  ids.) Any still empty pixel falls back to the backward lookup p - f(p) (which would
  otherwise smear a moving segment into its wake).

The map then seeds :func:`jaxcr.motion.superpixels.slic`, which snaps the tracked segments
to the new frame's colours while keeping their ids.
"""

from __future__ import annotations

import functools

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


# relative motion is quantised to 1/_LEVELS px for the packed (priority, source) keys, and
# clipped at _MAX_PRIORITY px so that priority * n_pixels + source stays inside int32
_LEVELS = 4
_MAX_PRIORITY = 64
# disocclusions are filled from labelled pixels up to this many px away (the widest wake a
# frame-to-frame motion of the working image leaves; wider ones use the backward lookup)
FILL_REACH = 8


def fill_disoccluded(key: Int[Array, "h w"], n_pixels: int) -> Int[Array, "h w"]:
    """Holes (-1) of a splatted key map (priority * n_pixels + source) take the key of a
    labelled pixel 1 to :data:`FILL_REACH` px right, left, below or above: among those of
    lowest priority (within 1 px of relative motion), the nearest (first in right, left,
    down, up order at equal distance). Holes with no labelled pixel in reach stay -1. Shifts
    are static slices of an edge-padded map."""
    h, w = key.shape
    D = FILL_REACH
    big = jnp.iinfo(jnp.int32).max
    prio = jnp.where(key >= 0, key // n_pixels, big)
    pk, pp = jnp.pad(key, D, mode="edge"), jnp.pad(prio, D, mode="edge")
    offsets = [(dy, dx) for d in range(1, D + 1) for dy, dx in ((0, d), (0, -d), (d, 0), (-d, 0))]

    def at(padded, dy, dx):
        return padded[D + dy : D + dy + h, D + dx : D + dx + w]

    pmin = functools.reduce(jnp.minimum, [at(pp, dy, dx) for dy, dx in offsets])
    out = key
    for dy, dx in reversed(offsets):  # the nearest is written last
        out = jnp.where((key < 0) & (at(pp, dy, dx) <= pmin + _LEVELS), at(pk, dy, dx), out)
    return out


def dominant_motion(flow: Float[Array, "h w 2"], n_irls: int = 3) -> Float[Array, "2"]:
    """The image's dominant motion (px): the mean flow over every 4th row and column, then
    ``n_irls`` Cauchy reweightings w = 1 / (1 + |f - m|^2 / (1 px)^2), so that a pushed
    object or the arm (a minority of the pixels) does not pull it (a robust M-estimate; a
    median costs a sort, ~1 ms per frame on this CPU)."""
    sub = flow[::4, ::4].reshape(-1, 2)
    m = jnp.mean(sub, axis=0)
    for _ in range(n_irls):
        wt = 1.0 / (1.0 + jnp.sum((sub - m) ** 2, axis=1))
        m = jnp.sum(sub * wt[:, None], axis=0) / jnp.sum(wt)
    return m


def motion_priority(flow: Float[Array, "h w 2"]) -> Int[Array, "h w"]:
    """Occlusion priority of every pixel: |f(p) - dominant motion| (:func:`dominant_motion`)
    in 1/4 px, clipped at 64 px (a quarter-pixel grid is enough to order layers)."""
    rel = jnp.sqrt(jnp.sum((flow - dominant_motion(flow)) ** 2, axis=-1))
    return jnp.round(jnp.clip(rel, 0.0, _MAX_PRIORITY) * _LEVELS).astype(jnp.int32)


@jax.jit
def splat_labels(labels: Int[Array, "h w"], flow: Float[Array, "h w 2"]) -> Int[Array, "h w"]:
    """Forward-splat labels with the flow (see the module docstring); int32 ids, no holes."""
    h, w = labels.shape
    n = h * w
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    dx = jnp.round(xx + flow[..., 0]).astype(jnp.int32)
    dy = jnp.round(yy + flow[..., 1]).astype(jnp.int32)
    inside = (dx >= 0) & (dx < w) & (dy >= 0) & (dy < h)
    # out-of-image targets go to a dummy row that is cut off afterwards
    flat = jnp.where(inside, dy * w + dx, n)
    # one int32 key per source: priority first, then the source index (ties: the later
    # source, as a plain scatter would); the largest key at a target wins
    key = motion_priority(flow).reshape(-1) * n + jnp.arange(n, dtype=jnp.int32)
    out = (
        jnp.full(n + w, -1, jnp.int32)
        .at[flat.reshape(-1)]
        .max(key, mode="promise_in_bounds")[:n]
        .reshape(h, w)
    )
    out = fill_disoccluded(out, n)
    src = jnp.where(out >= 0, out % n, 0)
    splat = jnp.take(labels.astype(jnp.int32).reshape(-1), src, mode="clip")
    return jnp.where(out >= 0, splat, warp_labels(labels, flow))


def labels_at_points(labels: Int[Array, "h w"], pts: Float[Array, "n 2"]) -> Int[Array, " n"]:
    """Segment id under each (x, y) point (rounded, clamped)."""
    h, w = labels.shape
    xi = jnp.clip(jnp.round(pts[:, 0]).astype(jnp.int32), 0, w - 1)
    yi = jnp.clip(jnp.round(pts[:, 1]).astype(jnp.int32), 0, h - 1)
    return jnp.take(labels.reshape(-1), yi * w + xi, mode="clip")
