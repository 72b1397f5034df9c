"""Segment (tube) identification from the diameter profile along the backbone.

A concentric-tube robot's outer diameter is piecewise constant along the backbone and steps
down at each tube's end. The boundaries are the optimal least-squares piecewise-constant
fit with ``k`` pieces (dynamic programming, Bellman 1961 / optimal segmentation), which is
exact for noise-free steps and robust to outliers when the profile is median-filtered
first. With ``k`` unknown, the fit with the smallest penalised cost
``SSE + penalty * k`` is kept. The report (sec. 5.2) separated segments by thresholding the
filtered radius profile; the DP fit needs no thresholds.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import median_filter

__all__ = ["piecewise_constant", "segment_backbone"]


def piecewise_constant(values: np.ndarray, k: int, min_len: int = 3) -> tuple[np.ndarray, float]:
    """Optimal k-piece constant fit of ``values`` (n,). Returns ``(starts, sse)``: the index
    where each piece starts (k,) (``starts[0] = 0``) and the residual sum of squares."""
    y = np.asarray(values, np.float64)
    n = len(y)
    if n < k * min_len:
        raise ValueError(f"{n} samples cannot make {k} segments of >= {min_len}")
    c1 = np.concatenate([[0.0], np.cumsum(y)])
    c2 = np.concatenate([[0.0], np.cumsum(y * y)])

    def sse(i, j):  # [i, j), broadcast over i (column) and j (row)
        m = j - i
        s = c1[j] - c1[i]
        return c2[j] - c2[i] - s * s / np.maximum(m, 1)

    cost = np.full((k + 1, n + 1), np.inf)
    arg = np.zeros((k + 1, n + 1), np.int64)
    cost[0, 0] = 0.0
    ii = np.arange(n + 1)[:, None]
    for p in range(1, k + 1):
        # All end points j of this row at once (in column chunks to bound memory): the
        # candidate starts i are rows, invalid ones inf; argmin takes the first minimum
        # in increasing i, as a loop over i would.
        for j0 in range(p * min_len, n + 1, 512):
            j = np.arange(j0, min(j0 + 512, n + 1))[None, :]
            valid = (ii >= (p - 1) * min_len) & (ii <= j - min_len)
            c = np.where(valid, cost[p - 1, :, None] + sse(ii, j), np.inf)
            b = np.argmin(c, axis=0)
            cost[p, j[0]] = c[b, np.arange(j.shape[1])]
            arg[p, j[0]] = b
    starts = []
    j = n
    for p in range(k, 0, -1):
        i = arg[p, j]
        starts.append(i)
        j = i
    return np.array(starts[::-1], np.int64), float(cost[k, n])


def segment_backbone(
    s: np.ndarray,
    diameters: np.ndarray,
    n_segments: int | None = None,
    max_segments: int = 4,
    filter_len: int = 5,
    penalty: float | None = None,
) -> dict:
    """Split the backbone into tubes from diameters (n,) sampled at arclengths ``s`` (n,).

    Returns ``{"starts": indices (k,), "boundaries_s": (k-1,) arclength of each change
    (midway between samples), "diameters": (k,) median diameter per segment}``. With
    ``n_segments=None`` the number is chosen by ``SSE + penalty * k`` (default penalty:
    ``n * (0.08 * median diameter)^2 / 4``, i.e. a step must explain more than about an
    8 % diameter change over a quarter of the samples), and then reduced while a step is
    not a clear decrease (telescoping tubes only get thinner towards the tip)."""
    d = median_filter(np.asarray(diameters, np.float64), size=filter_len, mode="nearest")
    n = len(d)
    if n_segments is None:
        pen = penalty if penalty is not None else n * (0.08 * np.median(d)) ** 2 / 4
        best = None
        for k in range(1, max_segments + 1):
            if n < 3 * k:
                break
            st, e = piecewise_constant(d, k)
            score = e + pen * k
            if best is None or score < best[0]:
                best = (score, st)
        starts = best[1]
        # A concentric-tube robot's diameter only steps down from base to tip: fewer
        # pieces while some step is not a clear decrease (> 4 %).
        while len(starts) > 1:
            ends = list(starts[1:]) + [n]
            lv = np.array([np.median(d[a:b]) for a, b in zip(starts, ends, strict=True)])
            if np.all(lv[1:] < 0.96 * lv[:-1]):
                break
            starts, _ = piecewise_constant(d, len(starts) - 1)
    else:
        starts, _ = piecewise_constant(d, n_segments)
    bounds = np.array([(s[i - 1] + s[i]) / 2 for i in starts[1:]])
    ends = list(starts[1:]) + [n]
    diam = np.array([np.median(diameters[a:b]) for a, b in zip(starts, ends, strict=True)])
    return {"starts": starts, "boundaries_s": bounds, "diameters": diam}
