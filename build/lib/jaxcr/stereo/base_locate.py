"""Rough localisation of the robot and of its base in one view (stereo report sec. 3.1):

1. rough location by flood fill: ``cv2.floodFill`` on the keyed mask, seeded at the
   projected base point, keeps the connected robot and drops noise and marker squares;
   (the report: ~100x faster than keying the whole image pixel by pixel);
2. Canny edges of the mask in a region of interest (ROI) around the projected base;
3. Hough lines (``cv2.HoughLinesP``) in the ROI: the tube's two sides near the base are
   nearly straight; the base mask is the mask inside the ROI between the detected side
   lines; its centroid is the seed of the flood fill (so the robot need not sit exactly
   at the projected base point).

cv2 at the edge: numpy uint8 masks in, numpy out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BaseLocation", "locate_base", "flood_component"]


@dataclass
class BaseLocation:
    """``seed`` (row, col) the flood-fill seed (centroid of the base mask); ``roi`` (r0, r1,
    c0, c1); ``lines`` (k, 4) Hough segments x1 y1 x2 y2 in image pixels; ``base_mask``
    (H, W) bool; ``found`` whether any robot pixel lies in the ROI."""

    seed: tuple[float, float]
    roi: tuple[int, int, int, int]
    lines: np.ndarray
    base_mask: np.ndarray
    found: bool


def flood_component(mask: np.ndarray, seed_rc: tuple[float, float]) -> np.ndarray:
    """The 8-connected component of ``mask`` (H, W) bool containing the foreground pixel
    nearest ``seed_rc`` (``cv2.floodFill``). Empty if the mask is empty."""
    m = np.ascontiguousarray(mask.astype(np.uint8))
    h, w = m.shape
    r, c = int(np.floor(seed_rc[0] + 0.5)), int(np.floor(seed_rc[1] + 0.5))
    if 0 <= r < h and 0 <= c < w and m[r, c]:
        # The pixel nearest the seed is foreground: no search over the image (a tie with
        # another pixel at the same distance is an 8-neighbour: same component).
        start = (c, r)
    else:
        rr, cc = np.nonzero(m)
        if len(rr) == 0:
            return np.zeros_like(mask, bool)
        k = int(np.argmin((rr - seed_rc[0]) ** 2 + (cc - seed_rc[1]) ** 2))
        start = (int(cc[k]), int(rr[k]))
    ff = np.zeros((h + 2, w + 2), np.uint8)
    cv2.floodFill(m, ff, start, 2, flags=8 | cv2.FLOODFILL_MASK_ONLY | (1 << 8))
    return ff[1:-1, 1:-1].view(bool)


def locate_base(mask: np.ndarray, base_uv: tuple[float, float], roi_half: int = 24) -> BaseLocation:
    """Find the tube's base near the projected base point ``base_uv`` (u, v) pixels."""
    h, w = mask.shape
    u, v = base_uv
    r0, r1 = int(max(0, v - roi_half)), int(min(h, v + roi_half + 1))
    c0, c1 = int(max(0, u - roi_half)), int(min(w, u + roi_half + 1))
    roi = mask[r0:r1, c0:c1].astype(np.uint8) * 255
    found = bool(roi.any())
    base_mask = np.zeros((h, w), bool)
    lines = np.zeros((0, 4), np.int32)
    if not found:
        return BaseLocation((float(v), float(u)), (r0, r1, c0, c1), lines, base_mask, False)
    edges = cv2.Canny(roi, 50, 150)
    hl = cv2.HoughLinesP(edges, 1, np.pi / 180, threshold=8, minLineLength=6, maxLineGap=2)
    if hl is not None:
        lines = hl.reshape(-1, 4) + np.array([c0, r0, c0, r0])
    # Base mask: foreground in the ROI, restricted to the band between the two outermost
    # parallel Hough lines when there are such lines (side lines of the tube).
    band = mask[r0:r1, c0:c1].astype(bool)
    if len(lines) >= 2:
        d = lines[:, 2:] - lines[:, :2]
        ang = np.arctan2(d[:, 1], d[:, 0]) % np.pi
        a0 = np.median(ang)
        par = lines[np.abs(((ang - a0 + np.pi / 2) % np.pi) - np.pi / 2) < np.radians(10)]
        if len(par) >= 2:
            nrm = np.array([-np.sin(a0), np.cos(a0)])
            off = ((par[:, :2] + par[:, 2:]) / 2) @ nrm
            lo, hi = off.min() - 1.0, off.max() + 1.0
            yy, xx = np.mgrid[r0:r1, c0:c1]
            o = xx * nrm[0] + yy * nrm[1]
            band = band & (o >= lo) & (o <= hi)
    if not band.any():
        band = mask[r0:r1, c0:c1].astype(bool)
    base_mask[r0:r1, c0:c1] = band
    rr, cc = np.nonzero(band)  # the ROI only
    seed = (float(rr.mean() + r0), float(cc.mean() + c0))
    return BaseLocation(seed, (r0, r1, c0, c1), lines, base_mask, True)
