"""Contour of the segmented marker region (Reiter et al. Sec. III-B.2).

Steps (per binary image): convex hull of the labelled pixels; the hull densified by linear
interpolation into control points; each control point moved to the nearest labelled pixel
(this pulls the contour into the concave side of the bent segment); consecutive points
joined by Bresenham lines; plus the Sobel edge points of the binary image (marker borders
inside the polygon, which help under partial occlusion).

Pixel coordinates are (x, y) = (column, row), integers. The per-frame geometry (hull,
snapping, Bresenham) has a data-dependent size and runs in numpy; the Sobel edge map is a
JAX function for one image (batch it with ``jax.vmap``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Convex hull (Andrew's monotone chain) of 2-D points (n, 2): vertices (h, 2) in
    counter-clockwise order (for y up; clockwise on screen), collinear points dropped."""
    p = np.unique(np.asarray(points, np.int64), axis=0)  # sorted by x, then y
    if len(p) < 3:
        return p
    p = [tuple(q) for q in p.tolist()]  # python ints: the scan below is scalar work

    def half(seq):
        out: list = []
        for q in seq:
            while len(out) >= 2:
                o, a = out[-2], out[-1]
                cross = (a[0] - o[0]) * (q[1] - o[1]) - (a[1] - o[1]) * (q[0] - o[0])
                if cross > 0:
                    break
                out.pop()
            out.append(q)
        return out

    lower = half(p)
    upper = half(p[::-1])
    return np.array(lower[:-1] + upper[:-1], np.int64)


def densify_polygon(vertices: np.ndarray, spacing: float) -> np.ndarray:
    """Points (m, 2) float along the closed polygon ``vertices`` (h, 2), at most ``spacing``
    pixels apart: each edge is cut into ceil(len / spacing) equal pieces (linear
    interpolation); every vertex is kept."""
    v = np.asarray(vertices, np.float64)
    if len(v) < 2:
        return v.copy()
    nxt = np.roll(v, -1, axis=0)
    out = []
    for a, b in zip(v, nxt, strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        t = np.arange(n)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out, axis=0)


def snap_to_nearest(points: np.ndarray, targets: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """For each point (m, 2), the nearest of ``targets`` (t, 2) (Euclidean; exact ties may
    go to either). Brute force via |p|^2 - 2 p.t + |t|^2 (one small matmul per chunk): both
    sets are small (hundreds to thousands) and the coordinates are pixel-sized, so float64
    rounding cannot reorder distinct squared integer-ish distances."""
    p = np.asarray(points, np.float64)
    t = np.asarray(targets, np.float64)
    t2 = (t * t).sum(1)
    idx = np.empty(len(p), np.int64)
    for i in range(0, len(p), chunk):
        q = p[i : i + chunk]
        d2 = t2[None, :] - 2.0 * (q @ t.T)  # |q|^2 is constant per row
        idx[i : i + chunk] = np.argmin(d2, axis=1)
    return np.asarray(targets)[idx]


def bresenham(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Integer pixels (n, 2) of the 8-connected Bresenham line from ``p0`` to ``p1``
    (inclusive, integer (x, y))."""
    x0, y0 = (int(v) for v in p0)
    x1, y1 = (int(v) for v in p1)
    dx, dy = abs(x1 - x0), -abs(y1 - y0)
    sx = 1 if x0 < x1 else -1
    sy = 1 if y0 < y1 else -1
    err = dx + dy
    out = []
    while True:
        out.append((x0, y0))
        if x0 == x1 and y0 == y1:
            break
        e2 = 2 * err
        if e2 >= dy:
            err += dy
            x0 += sx
        if e2 <= dx:
            err += dx
            y0 += sy
    return np.array(out, np.int64)


def polyline_pixels(points: np.ndarray, closed: bool = True) -> np.ndarray:
    """Bresenham pixels joining consecutive integer points (closing the loop if ``closed``);
    duplicates removed (order not kept)."""
    p = np.asarray(points, np.int64)
    if len(p) == 0:
        return np.zeros((0, 2), np.int64)
    if len(p) == 1:
        return p.copy()
    pairs = zip(p, np.roll(p, -1, axis=0) if closed else p[1:], strict=False)
    segs = [bresenham(a, b) for a, b in pairs]
    return np.unique(np.concatenate(segs, axis=0), axis=0)


def sobel(image: Float[Array, "h w"]) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """3x3 Sobel derivatives (d/dx along columns, d/dy along rows) of one image, with the
    border mirrored without repeating the edge pixel (OpenCV's default BORDER_REFLECT_101,
    ``cv2.Sobel(img, CV_32F, 1, 0)`` / ``(0, 1)``)."""
    x = jnp.pad(jnp.asarray(image, jnp.float32), 1, mode="reflect")
    smooth_r = x[:-2, :] + 2.0 * x[1:-1, :] + x[2:, :]  # along rows
    gx = smooth_r[:, 2:] - smooth_r[:, :-2]
    smooth_c = x[:, :-2] + 2.0 * x[:, 1:-1] + x[:, 2:]  # along columns
    gy = smooth_c[2:, :] - smooth_c[:-2, :]
    return gx, gy


def sobel_edges(mask: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """Binary edge map of a binary image: pixels where the Sobel gradient is non-zero and
    which are themselves labelled (the inner border of every marker)."""
    gx, gy = sobel(mask.astype(jnp.float32))
    return mask & ((jnp.abs(gx) + jnp.abs(gy)) > 0)


#: Edge maps of a batch of masks (B, H, W), one compile per shape.
sobel_edges_batch = jax.jit(jax.vmap(sobel_edges))


def contour_points(
    mask: np.ndarray, spacing: float = 2.0, edges: np.ndarray | None = None
) -> np.ndarray:
    """All contour points (n, 2) int (x, y) of one binary marker image (H, W):
    hull -> densify (``spacing`` px) -> snap to nearest labelled pixel -> Bresenham, plus
    the Sobel edge points (``edges``, computed here if not given). Empty for an empty mask.
    """
    m = np.asarray(mask, bool)
    ys, xs = np.nonzero(m)
    if len(xs) == 0:
        return np.zeros((0, 2), np.int64)
    pix = np.stack([xs, ys], axis=1)
    # Only boundary pixels can be nearest to a point outside the region.
    e = np.asarray(sobel_edges(jnp.asarray(m))) if edges is None else np.asarray(edges, bool)
    ey, ex = np.nonzero(e)
    border = np.stack([ex, ey], axis=1) if len(ex) else pix
    # The hull of a region is the hull of its boundary pixels (far fewer).
    hull = convex_hull(border)
    ctrl = densify_polygon(hull, spacing)
    snapped = snap_to_nearest(ctrl, border)
    # Consecutive duplicates add nothing to the Bresenham chain.
    keep = np.ones(len(snapped), bool)
    keep[1:] = np.any(snapped[1:] != snapped[:-1], axis=1)
    line = polyline_pixels(snapped[keep], closed=True)
    if len(ex):
        line = np.unique(np.concatenate([line, np.stack([ex, ey], axis=1)], axis=0), axis=0)
    return line
