"""Each view's 2-D result: the tip pixel and the backbone polyline (OpenCV pixels).

Pixels follow OpenCV's convention: the centre of pixel (row r, column c) is at
(u, v) = (c, r), in the distorted image as recorded. The backbone polyline is the view's
ordered, smoothed skeleton of the robot (from the base to the tip); Zhang-Suen thinning
stops about half a tube width short of the tube's end, so the tip pixel is where that
skeleton, continued straight along its last 5 px, leaves the robot's mask
(:func:`tip_pixel`). Numpy at the edge (per frame).
"""

from __future__ import annotations

import numpy as np

__all__ = ["tip_pixel", "polyline_px", "view_record"]


def tip_pixel(uv: np.ndarray, mask: np.ndarray, *, search_px: int = 40, step: float = 0.25):
    """The tube's end (u, v) in one view: from the last point of the ordered skeleton ``uv``
    (n, 2) along the direction of its last 5 px, the last position (``step`` px apart, at
    most ``search_px`` px) whose nearest pixel is still in ``mask`` (H, W) bool, plus half a
    step (the mask's edge lies between that sample and the next). The skeleton's last point
    when the path is shorter than 6 samples or the direction leaves the mask at once."""
    uv = np.asarray(uv, np.float64)
    end = uv[-1]
    if len(uv) < 6 or search_px <= 0:
        return end
    d = uv[-1] - uv[-6]
    n = np.linalg.norm(d)
    if n < 1e-9:
        return end
    d = d / n
    t = np.arange(1, int(search_px / step) + 1) * step
    q = end[None] + t[:, None] * d[None]
    c = np.floor(q[:, 0] + 0.5).astype(int)
    r = np.floor(q[:, 1] + 0.5).astype(int)
    h, w = mask.shape
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    fg = np.zeros(len(t), bool)
    fg[inside] = mask[r[inside], c[inside]]
    first_out = np.flatnonzero(~fg)
    k = int(first_out[0]) if len(first_out) else len(t)
    if k == 0:
        return end
    return end + (t[k - 1] + 0.5 * step) * d


def polyline_px(uv: np.ndarray, *, spacing: float = 2.0) -> np.ndarray:
    """The ordered path ``uv`` (n, 2) decimated to samples at least ``spacing`` px apart
    along it (the first and last kept)."""
    uv = np.asarray(uv, np.float64)
    if len(uv) < 3:
        return uv
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    idx = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1], spacing)))
    idx = np.unique(np.r_[idx[idx < len(uv) - 1], len(uv) - 1])
    return uv[idx]


def view_record(uv: np.ndarray, mask: np.ndarray, *, search_px: int = 40) -> dict:
    """``{"tip_px": [u, v], "backbone_px": [[u, v], ...]}`` of one view (rounded to 0.01
    px; the polyline every 2 px, ending at the tip pixel)."""
    tip = tip_pixel(uv, mask, search_px=search_px)
    line = polyline_px(uv)
    if np.linalg.norm(tip - line[-1]) > 1e-9:
        line = np.concatenate([line, tip[None]])
    return {
        "tip_px": [round(float(x), 2) for x in tip],
        "backbone_px": np.round(line, 2).tolist(),
    }
