"""SLIC superpixels in JAX (Achanta et al. 2012), with labels carried between frames.

The low-level segmentation of M-L step 1 (the paper uses Paris 2008; "any other segmentation
algorithm could be used"). One assignment step gives each pixel the nearest of nine candidate
segments: the labels found at offsets {-S, 0, S}^2 around it in the current label map (S the
grid step). On a fresh grid this is exactly SLIC's 2S x 2S search window (the centre of grid
cell k can only be reached from the 3 x 3 cells around it, as in gSLICr), so no pixel is ever
compared with all centres; on a label map warped from the previous frame
(:mod:`jaxcr.motion.propagate`) it refines the tracked segments' boundaries to the new image
while keeping their ids, so segments are tracked through the video. Centres (mean Lab colour
and mean position) come from ``jax.ops.segment_sum`` with a static number of segments. Unlike
the reference SLIC there is no connectivity post-pass (a label may be split into parts; those
parts share one motion model, which only matters for segments cut by occlusion).

Tracking uses a *local* refinement (:data:`TRACK_REACH`): after the flow has carried the
labels, the candidates are the labels at offsets {-r, 0, r}^2 with r = 3 working px instead
of the grid step. With the grid-step candidates a pixel could take a label found S px away
whenever that segment's mean colour was nearer, which on textured surfaces scatters stray
pixels of a segment far from its body; strays that land on the arm or the pushed object then
ride along with it, so background ids were carried by the moving object and the object's ids
left behind (experiments/motion/motion_label_leakage.py on the synthetic videos, this change
alone: mean over the touching frames of the object ids' area on the background 0.16 / 0.25
-> 0.10 / 0.10 on the static / changing pushed videos, of the object's area under background
ids 0.30 / 0.38 -> 0.17 / 0.16; with the layered splat of :mod:`~jaxcr.motion.propagate`
see experiments/results/motion/motion_label_leakage.md). With r px per step a label moves at most r px per iteration beyond where the
flow put it, enough to snap the splatted boundaries to the new image (the flow is smooth
across boundaries over a few px) without jumping across a gap.

Distance (SLIC eq. 3): D^2 = |lab - lab_c|^2 + (m / S)^2 |xy - xy_c|^2, m = compactness.

Speed (measured in ``experiments/results/motion/motion_bench.md``): the segmentation runs at a
*working resolution*, the frame shrunk by an integer ``scale`` with area averaging
(:func:`working_rgb`), and the labels are repeated back to full size
(:func:`upsample_labels`). Superpixels are about 20 px wide, so halving a 640 x 480 frame
keeps them 10 px wide at a quarter of the pixels. Shifted label maps are static slices of an
edge-padded map (no gathers), and each centre column is gathered on its own (1-D gathers).
"""

from __future__ import annotations

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxcr.colour import rgb_to_lab
from jaxcr.motion.propagate import splat_labels

_FAR = 1e30  # distance added for candidates whose segment is empty (never chosen)


def grid_shape(height: int, width: int, step: int) -> tuple[int, int]:
    """(rows, cols) of the seed grid; the number of segments is rows * cols."""
    return -(-height // step), -(-width // step)


def grid_labels(height: int, width: int, step: int) -> Int[Array, "h w"]:
    """Initial label map: the S x S grid cells, numbered row-major."""
    _, gw = grid_shape(height, width, step)
    yy, xx = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    return jnp.asarray((yy // step) * gw + xx // step, jnp.int32)


def working_shape(height: int, width: int, scale: int) -> tuple[int, int]:
    """(rows, cols) of the working image: the frame shrunk by ``scale`` (rounded up)."""
    if scale < 1:
        raise ValueError(f"working scale must be a positive integer, got {scale}")
    return -(-height // scale), -(-width // scale)


def working_rgb(rgb: np.ndarray, scale: int = 1) -> np.ndarray:
    """A frame at the working resolution, float32 RGB in [0, 1], (ceil(H / s), ceil(W / s), 3).

    ``rgb`` is float RGB in [0, 1] or uint8, (H, W, 3). The frame is shrunk by ``scale`` with
    area averaging (``cv2.INTER_AREA``: the mean of each s x s block when s divides the size),
    on the host before the transfer to JAX; the Lab conversion (:func:`jaxcr.colour.rgb_to_lab`)
    then runs on the small image inside :func:`segment_first` / :func:`segment_track`.
    """
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB frame, got shape {a.shape}")
    a = a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32, copy=False)
    if scale != 1:
        h, w = working_shape(a.shape[0], a.shape[1], scale)
        a = cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(a)


def upsample_labels(
    labels: Int[Array, "h w"], height: int, width: int, scale: int
) -> Int[Array, "H W"]:
    """Full-size label map from a working-resolution one: each working pixel covers a
    ``scale`` x ``scale`` block (nearest neighbour), cropped to (height, width)."""
    if scale == 1:
        return labels[:height, :width]
    up = jnp.repeat(jnp.repeat(labels, scale, axis=0), scale, axis=1)
    return up[:height, :width]


def _coords(h: int, w: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return yy.astype(dtype), xx.astype(dtype)


def segment_centres(
    lab: Float[Array, "h w 3"], labels: Int[Array, "h w"], n_segments: int
) -> tuple[Float[Array, "k 5"], Float[Array, " k"]]:
    """Mean (L, a, b, y, x) of each segment and its pixel count (0 for absent segments)."""
    h, w = labels.shape
    yy, xx = _coords(h, w, np.dtype(lab.dtype))
    feats = jnp.concatenate(
        [lab, yy[..., None], xx[..., None], jnp.ones((h, w, 1), lab.dtype)], axis=-1
    ).reshape(-1, 6)
    sums = jax.ops.segment_sum(feats, labels.reshape(-1), n_segments)
    count = sums[:, 5]
    return sums[:, :5] / jnp.maximum(count, 1.0)[:, None], count


def shifted(labels: Int[Array, "h w"], pad: int, dy: int, dx: int) -> Int[Array, "h w"]:
    """labels[y + dy, x + dx] with edge clamping, from a map edge-padded by ``pad`` >= |d|."""
    h, w = labels.shape[0] - 2 * pad, labels.shape[1] - 2 * pad
    return labels[pad + dy : pad + dy + h, pad + dx : pad + dx + w]


def slic_step(
    lab: Float[Array, "h w 3"],
    labels: Int[Array, "h w"],
    n_segments: int,
    step: int,
    compactness: float,
    reach: int = 0,
) -> Int[Array, "h w"]:
    """One SLIC assignment: each pixel takes the nearest of its nine candidate segments, the
    labels at offsets {-r, 0, r}^2 with r = ``reach`` px (0: the grid ``step``, SLIC's
    search window on a fresh grid; small values refine tracked boundaries locally, see the
    module docstring). Ties go to the first candidate in row-major offset order."""
    h, w = labels.shape
    centres, count = segment_centres(lab, labels, n_segments)
    spatial = (compactness / step) ** 2
    # one gathered value per column and candidate: (L, a, b, y, x, empty penalty). Separate
    # 1-D gathers with clip mode: XLA's CPU row gather from a (k, 6) table is ~80x slower.
    cols = [centres[:, i] for i in range(5)] + [jnp.where(count > 0, 0.0, _FAR).astype(lab.dtype)]
    r = reach or step
    yy, xx = _coords(h, w, np.dtype(lab.dtype))
    padded = jnp.pad(labels, r, mode="edge")
    best_d = jnp.full((h, w), jnp.inf, lab.dtype)
    best = labels
    for dy in (-r, 0, r):
        for dx in (-r, 0, r):
            cand = shifted(padded, r, dy, dx)
            c = [jnp.take(col, cand, mode="clip") for col in cols]
            d = (
                (lab[..., 0] - c[0]) ** 2
                + (lab[..., 1] - c[1]) ** 2
                + (lab[..., 2] - c[2]) ** 2
                + spatial * ((yy - c[3]) ** 2 + (xx - c[4]) ** 2)
                + c[5]
            )
            better = d < best_d
            best = jnp.where(better, cand, best)
            best_d = jnp.where(better, d, best_d)
    return best


@functools.partial(jax.jit, static_argnames=("n_segments", "step", "n_iter", "reach"))
def slic(
    lab: Float[Array, "h w 3"],
    labels_init: Int[Array, "h w"],
    n_segments: int,
    step: int,
    compactness: float = 10.0,
    n_iter: int = 5,
    reach: int = 0,
) -> Int[Array, "h w"]:
    """``n_iter`` SLIC iterations from ``labels_init`` (a :func:`grid_labels` map for a fresh
    segmentation, or a warped previous label map for tracking, then with a small ``reach``:
    :func:`slic_step`). Returns int32 labels in [0, n_segments)."""

    def body(_, lbl):
        return slic_step(lab, lbl, n_segments, step, compactness, reach)

    return jax.lax.fori_loop(0, n_iter, body, labels_init.astype(jnp.int32))


# candidate offset (working px) of the tracking refinement; at most step // 2 so that the
# candidates stay inside the segment scale on tiny grids
TRACK_REACH = 3


def track_reach(step: int) -> int:
    """Candidate offset of :func:`segment_track`'s refinement for a grid ``step``: 3 working
    px, at most ``step // 2`` (at least 1)."""
    return max(1, min(TRACK_REACH, step // 2))


def auto_scale(width: int, step: int) -> int:
    """Default working-resolution factor: shrink while the working frame stays at least 320 px
    wide and the superpixels at least 8 working px wide (1 for frames up to 639 px wide or
    superpixel steps under 16 px)."""
    return max(1, min(width // 320, step // 8))


@functools.partial(
    jax.jit, static_argnames=("n_segments", "step", "n_iter", "scale", "height", "width")
)
def segment_first(
    rgb: Float[Array, "h w 3"],
    n_segments: int,
    step: int,
    compactness: float,
    n_iter: int,
    scale: int,
    height: int,
    width: int,
) -> tuple[Int[Array, "h w"], Int[Array, "H W"]]:
    """Fresh SLIC on the working-resolution frame (:func:`working_rgb`; ``step`` in working
    px) from the seed grid. Returns the working label map and the full-size (height, width)
    one."""
    h, w = rgb.shape[:2]
    lbl = slic(rgb_to_lab(rgb), grid_labels(h, w, step), n_segments, step, compactness, n_iter)
    return lbl, upsample_labels(lbl, height, width, scale)


@functools.partial(
    jax.jit, static_argnames=("n_segments", "step", "n_iter", "scale", "height", "width")
)
def segment_track(
    labels: Int[Array, "h w"],
    flow: Float[Array, "h w 2"],
    rgb: Float[Array, "h w 3"],
    n_segments: int,
    step: int,
    compactness: float,
    n_iter: int,
    scale: int,
    height: int,
    width: int,
) -> tuple[Int[Array, "h w"], Int[Array, "H W"]]:
    """Carry the working label map to the next frame: forward-splat with the dense flow (in
    working px, :func:`jaxcr.motion.propagate.splat_labels`), then ``n_iter`` local SLIC
    steps (candidate offset :func:`track_reach`, see the module docstring) on the new
    working-resolution frame (:func:`working_rgb`; ids kept). Returns working and full-size
    label maps."""
    lbl = slic(
        rgb_to_lab(rgb),
        splat_labels(labels, flow),
        n_segments,
        step,
        compactness,
        n_iter,
        track_reach(step),
    )
    return lbl, upsample_labels(lbl, height, width, scale)
