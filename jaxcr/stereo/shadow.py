"""Slope-angle segmentation of an ordered point sequence (stereo report sec. 5.3,
Algorithm 1), used to cut off the shadow that a loose chroma or plate key segments along
with the tube (a "convexity defect" at the base).

Faithful to the report: with look-ahead ``j`` the reference slope is ``data[1+j] -
data[1]``; walking ``a = 2 .. n-j-1``, the current slope ``data[a+j] - data[a]`` is
compared with the reference; when the angle exceeds ``tolerance`` for both the current and
the next slope (``data[a+1+j] - data[a]``, a guard against a single noisy point), a new
segment starts at ``a`` and the reference becomes ``data[a+j] - data[a]``. (The report's
``acosd(dot(...))`` needs unit slopes; they are normalised here.) Larger tolerances give
fewer segments (report Fig. 18). Works for 2-D pixel or 3-D points.
"""

from __future__ import annotations

import numpy as np

__all__ = ["slope_angle_segments"]


def _unit(v):
    return v / max(np.linalg.norm(v), 1e-12)


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(_unit(a) @ _unit(b), -1.0, 1.0))))


def slope_angle_segments(
    data: np.ndarray, tolerance_deg: float = 20.0, j: int = 3
) -> list[np.ndarray]:
    """Split ordered points ``data`` (n, d) into segments of nearly constant slope.

    Returns a list of index arrays (0-based, consecutive, covering ``0 .. n-j-2`` as the
    report's loop does, plus the last ``j + 1`` points appended to the final segment)."""
    data = np.asarray(data, np.float64)
    n = len(data)
    if n < j + 2:
        return [np.arange(n)]
    segs: list[list[int]] = [[0]]
    ref = data[j] - data[0]
    for a in range(1, n - j - 1):
        cur = data[a + j] - data[a]
        if _angle(cur, ref) > tolerance_deg:
            dump = data[a + 1 + j] - data[a]
            if _angle(dump, ref) > tolerance_deg:
                segs.append([a])
                ref = data[a + j] - data[a]
                continue
        segs[-1].append(a)
    segs[-1].extend(range(n - j - 1, n))
    return [np.array(s, np.int64) for s in segs]
