"""SLIC superpixels in JAX (Achanta et al. 2012), with labels carried between frames.

The low-level segmentation of M-L step 1 (the paper uses Paris 2008; "any other segmentation
algorithm could be used"). One assignment step gives each pixel the nearest of nine candidate
segments: the labels found at offsets {-S, 0, S}^2 around it in the current label map (S the
grid step). On a fresh grid this is exactly SLIC's 2S x 2S search window; on a label map
warped from the previous frame (:mod:`jaxcr.motion.propagate`) it refines the tracked
segments' boundaries to the new image while keeping their ids, so segments are tracked
through the video. Centres (mean Lab colour and mean position) come from
``jax.ops.segment_sum`` with a static number of segments. Unlike the reference SLIC there is
no connectivity post-pass (a label may be split into parts; those parts share one motion
model, which only matters for segments cut by occlusion).

Distance (SLIC eq. 3): D^2 = |lab - lab_c|^2 + (m / S)^2 |xy - xy_c|^2, m = compactness.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxcr.colour import rgb_to_lab  # noqa: F401  (re-exported for the motion pipeline)


# sRGB (D65) -> XYZ, as in IEC 61966-2-1 and OpenCV/scikit-image.
def grid_shape(height: int, width: int, step: int) -> tuple[int, int]:
    """(rows, cols) of the seed grid; the number of segments is rows * cols."""
    return -(-height // step), -(-width // step)


def grid_labels(height: int, width: int, step: int) -> Int[Array, "h w"]:
    """Initial label map: the S x S grid cells, numbered row-major."""
    _, gw = grid_shape(height, width, step)
    yy, xx = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    return ((yy // step) * gw + xx // step).astype(jnp.int32)


def segment_centres(
    lab: Float[Array, "h w 3"], labels: Int[Array, "h w"], n_segments: int
) -> tuple[Float[Array, "k 5"], Float[Array, " k"]]:
    """Mean (L, a, b, y, x) of each segment and its pixel count (0 for absent segments)."""
    h, w = labels.shape
    yy, xx = jnp.meshgrid(
        jnp.arange(h, dtype=lab.dtype), jnp.arange(w, dtype=lab.dtype), indexing="ij"
    )
    feats = jnp.concatenate([lab, yy[..., None], xx[..., None]], axis=-1).reshape(-1, 5)
    ids = labels.reshape(-1)
    count = jax.ops.segment_sum(jnp.ones_like(ids, dtype=lab.dtype), ids, n_segments)
    sums = jax.ops.segment_sum(feats, ids, n_segments)
    return sums / jnp.maximum(count, 1.0)[:, None], count


def _shift(labels: Int[Array, "h w"], dy: int, dx: int) -> Int[Array, "h w"]:
    """labels[y + dy, x + dx] with edge clamping."""
    h, w = labels.shape
    ys = jnp.clip(jnp.arange(h) + dy, 0, h - 1)
    xs = jnp.clip(jnp.arange(w) + dx, 0, w - 1)
    return labels[ys][:, xs]


def slic_step(
    lab: Float[Array, "h w 3"],
    labels: Int[Array, "h w"],
    n_segments: int,
    step: int,
    compactness: float,
) -> Int[Array, "h w"]:
    """One SLIC assignment: each pixel takes the nearest of its nine candidate segments."""
    h, w = labels.shape
    centres, count = segment_centres(lab, labels, n_segments)
    yy, xx = jnp.meshgrid(
        jnp.arange(h, dtype=lab.dtype), jnp.arange(w, dtype=lab.dtype), indexing="ij"
    )
    spatial = (compactness / step) ** 2
    best_d = jnp.full((h, w), jnp.inf, lab.dtype)
    best = labels
    for dy in (-step, 0, step):
        for dx in (-step, 0, step):
            cand = _shift(labels, dy, dx)
            c = centres[cand]  # (h, w, 5)
            d = jnp.sum((lab - c[..., :3]) ** 2, axis=-1) + spatial * (
                (yy - c[..., 3]) ** 2 + (xx - c[..., 4]) ** 2
            )
            d = jnp.where(count[cand] > 0, d, jnp.inf)
            better = d < best_d
            best = jnp.where(better, cand, best)
            best_d = jnp.where(better, d, best_d)
    return best


@functools.partial(jax.jit, static_argnames=("n_segments", "step", "n_iter"))
def slic(
    lab: Float[Array, "h w 3"],
    labels_init: Int[Array, "h w"],
    n_segments: int,
    step: int,
    compactness: float = 10.0,
    n_iter: int = 5,
) -> Int[Array, "h w"]:
    """``n_iter`` SLIC iterations from ``labels_init`` (a :func:`grid_labels` map for a fresh
    segmentation, or a warped previous label map for tracking). Returns int32 labels in
    [0, n_segments)."""

    def body(_, lbl):
        return slic_step(lab, lbl, n_segments, step, compactness)

    return jax.lax.fori_loop(0, n_iter, body, labels_init.astype(jnp.int32))
