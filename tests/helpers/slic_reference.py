"""Slow per-pixel reference of one SLIC assignment step (Achanta et al.), shared by the
motion superpixel tests."""

import numpy as np


def slic_step_loop(lab, labels, k, step, m, reach=None):
    """One SLIC step by loops: centres from ``labels``, then each pixel takes the nearest of
    the centres of the labels at its 3x3 neighbours ``reach`` px apart (default: the grid
    step) (colour + (m/step)^2 space)."""
    r = reach or step
    h, w = labels.shape
    cen = np.zeros((k, 5))
    cnt = np.zeros(k)
    for y in range(h):
        for x in range(w):
            j = labels[y, x]
            cen[j] += [*lab[y, x], y, x]
            cnt[j] += 1
    cen /= np.maximum(cnt, 1)[:, None]
    out = labels.copy()
    for y in range(h):
        for x in range(w):
            best, bd = labels[y, x], np.inf
            for dy in (-r, 0, r):
                for dx in (-r, 0, r):
                    j = labels[min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)]
                    if cnt[j] == 0:
                        continue
                    c = cen[j]
                    d = np.sum((lab[y, x] - c[:3]) ** 2) + (m / step) ** 2 * (
                        (y - c[3]) ** 2 + (x - c[4]) ** 2
                    )
                    if d < bd:
                        best, bd = j, d
            out[y, x] = best
    return out
