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

Shadow removal in the pipeline (:func:`shadow_cut`): a loose key (or a background plate
difference) segments the tube's shadow on the cloth together with the tube. The shadow
starts where the tube meets the base, so the flood-filled region is the tube plus a
branch along the floor, and the skeleton's longest path starts at the far end of the
shadow, runs to the base and turns up the tube: the "convexity defect". The slope-angle
segments of the ordered path put a segment start at that turn; the robot's backbone is
the path from the start of the slope segment that contains the base point (the seed of
the base localisation). Without a shadow branch that segment is the first one, and
nothing is cut.
"""

from __future__ import annotations

import numpy as np

__all__ = ["slope_angle_segments", "shadow_cut"]


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


def shadow_cut(
    path: np.ndarray, base_point: np.ndarray, tolerance_deg: float = 20.0, j: int = 3
) -> int:
    """Index where the robot's backbone starts on an ordered path ``path`` (n, d) (pixels
    or metres, base end first) that may begin with the tube's shadow (module docstring).

    ``base_point`` (d,): a point on the robot near its base (the base localisation's seed).
    The base index is the path point nearest ``base_point`` in the first half of the path
    (a curled tip may pass the base later on); the cut is the start of the slope-angle
    segment (``tolerance_deg``, look-ahead ``j``) that contains it. Returns 0 when that is
    the first segment (no shadow branch)."""
    path = np.asarray(path, np.float64)
    n = len(path)
    if n < 2 * j + 4:
        return 0
    half = max(n // 2, 1)
    i_base = int(np.argmin(np.linalg.norm(path[:half] - np.asarray(base_point), axis=1)))
    segs = slope_angle_segments(path, tolerance_deg, j)
    starts = [int(s[0]) for s in segs]
    # The segment containing the base point: the last start at or before it.
    return max(st for st in starts if st <= i_base)
