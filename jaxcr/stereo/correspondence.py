"""Stereo correspondence of two ordered backbones by monotone epipolar matching.

Both backbones run from the base to the tip, so corresponding points keep their order.
The matching is a dynamic-time-warping path through the cost matrix ``C[i, j]`` = Sampson
epipolar distance of (view-1 point i, view-2 point j), clipped at ``cap``: the path starts
at (0, 0) and moves right, down or diagonally. Where the backbone runs along an epipolar
line (ambiguous), the order constraint still places the match. Each view-1 point keeps its
cheapest view-2 partner on the path; then the partner is refined to sub-sample precision by
intersecting the epipolar line with the view-2 polyline near it (when they cross at an
angle larger than ``min_angle``), which is the report's epipolar-geometry correspondence.

The DTW recursion ``D[i, j] = c[i, j] + min(D[i-1, j-1], D[i-1, j], D[i, j-1])`` is
evaluated row by row with a ``lax.scan``; inside a row the horizontal moves become a
cumulative minimum: ``D[i, j] = S[j] + min_{k <= j} (M[k] - S[k-1])`` with ``S`` the
cumulative sum of row i's costs and ``M[k] = min(D[i-1, k-1], D[i-1, k])``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float, Int
from jaxcr.stereo.triangulation import sampson_distance_np

__all__ = [
    "dtw_path",
    "dtw_path_costs",
    "dtw_path_costs_np",
    "match_backbones",
    "refine_on_epilines",
]


def _cum_argmin(v: Float[Array, " m"]) -> tuple[Float[Array, " m"], Int[Array, " m"]]:
    idx = jnp.arange(v.shape[0])

    def comb(a, b):
        va, ia = a
        vb, ib = b
        take_b = vb < va
        return jnp.where(take_b, vb, va), jnp.where(take_b, ib, ia)

    return jax.lax.associative_scan(comb, (v, idx))


@jax.jit
def dtw_path_costs(cost: Float[Array, "n m"]) -> tuple[Float[Array, "n m"], Int[Array, "n m"]]:
    """Accumulated DTW cost ``D`` (n, m) and, per cell, the column ``k`` where the current
    row's horizontal run started (for backtracking; the run was entered from row i-1 at
    column k-1 (diagonal) or k (vertical))."""
    inf = jnp.asarray(jnp.inf, cost.dtype)
    s0 = jnp.cumsum(cost[0])
    k0 = jnp.zeros(cost.shape[1], jnp.int32)

    def row(prev, c):
        M = jnp.minimum(prev, jnp.concatenate([jnp.array([inf], cost.dtype), prev[:-1]]))
        S = jnp.cumsum(c)
        Sm1 = jnp.concatenate([jnp.zeros(1, cost.dtype), S[:-1]])
        best, k = _cum_argmin(M - Sm1)
        D = S + best
        return D, (D, k.astype(jnp.int32))

    _, (Ds, ks) = jax.lax.scan(row, s0, cost[1:])
    return jnp.concatenate([s0[None], Ds]), jnp.concatenate([k0[None], ks])


def dtw_path_costs_np(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same recursion as :func:`dtw_path_costs` in numpy (float64), one vectorised
    row at a time; faster than the JAX scan for the varying shapes of single frames (no
    compilation per shape). Ties pick the smallest run start, as the JAX version does."""
    n, m = cost.shape
    D = np.empty((n, m))
    K = np.zeros((n, m), np.int64)
    S = np.cumsum(cost, axis=1)  # all rows' cumulative sums at once
    Sm1 = np.zeros_like(S)
    Sm1[:, 1:] = S[:, :-1]
    D[0] = S[0]
    idx = np.arange(m)
    # Row buffers reused with ``out=`` (the loop is over rows; each row is vectorised).
    M, v, cm = np.empty(m), np.empty(m), np.empty(m)
    le, kk = np.empty(m, bool), np.empty(m, np.int64)
    for i in range(1, n):
        prev = D[i - 1]
        M[0] = prev[0]
        np.minimum(prev[1:], prev[:-1], out=M[1:])
        np.subtract(M, Sm1[i], out=v)
        np.minimum.accumulate(v, out=cm)
        np.less_equal(v, cm, out=le)
        np.multiply(idx, le, out=kk)
        np.maximum.accumulate(kk, out=K[i])
        np.add(S[i], cm, out=D[i])
    return D, K


def _backtrack(D: np.ndarray, K: np.ndarray) -> np.ndarray:
    """All cells (i, j) of the optimal path, from (0, 0) to (n-1, m-1) in order (p, 2)."""
    n, m = D.shape
    cells = []
    j = m - 1
    for i in range(n - 1, -1, -1):
        k = int(K[i, j]) if i > 0 else 0
        cells.extend((i, c) for c in range(j, k - 1, -1))
        if i == 0:
            break
        # Entered row i at column k from (i-1, k-1) or (i-1, k).
        j = k - 1 if (k > 0 and D[i - 1, k - 1] <= D[i - 1, k]) else k
    return np.array(cells[::-1], np.int64)


def dtw_path(cost: np.ndarray) -> np.ndarray:
    """The cells (p, 2) of the cheapest monotone path through ``cost`` (n, m) from (0, 0)
    to (n - 1, m - 1), in order (:func:`dtw_path_costs_np`, then backtracking)."""
    D, K = dtw_path_costs_np(np.asarray(cost, np.float64))
    return _backtrack(D, K)


def refine_on_epilines(
    F: np.ndarray, x_from: np.ndarray, x_to: np.ndarray, j: np.ndarray, window: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Where the epipolar line ``F x_from[i]`` (in the other image) crosses the polyline
    ``x_to`` within ``window`` samples of ``j[i]``: the crossing point (linear
    interpolation) and the sine of the crossing angle (quality, 0 where there is no
    crossing; the point is then ``x_to[j[i]]``). Returns ``(points (n, 2), quality (n,),
    fractional sample position along x_to (n,))``.
    """
    n, m = len(x_from), len(x_to)
    j = np.asarray(j, np.int64)
    h = np.concatenate([x_from, np.ones((n, 1))], 1)
    lines = h @ F.T  # (n, 3) in the other image
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-300)
    offs = np.arange(-window, window + 1)
    idx = np.clip(j[:, None] + offs[None], 0, m - 1)
    pts = x_to[idx]  # (n, W, 2)
    sd = np.einsum("nwk,nk->nw", pts, lines[:, :2]) + lines[:, 2:3]
    a, b = sd[:, :-1], sd[:, 1:]
    seg = pts[:, 1:] - pts[:, :-1]
    seg_len = np.linalg.norm(seg, axis=2)
    cross = (a * b <= 0) & (seg_len > 0)
    # |cos| between the segment and the line's normal = |sin| of the crossing angle.
    quality = np.abs(np.einsum("nwk,nk->nw", seg, lines[:, :2])) / np.maximum(seg_len, 1e-300)
    centre = window - 0.5
    dist_c = np.abs(np.arange(2 * window) - centre)[None].repeat(n, 0)
    dist_c = np.where(cross, dist_c, np.inf)
    w = np.argmin(dist_c, axis=1)
    r = np.arange(n)
    has = np.isfinite(dist_c[r, w])
    aa, bb = a[r, w], b[r, w]
    den = aa - bb
    t = np.clip(np.where(np.abs(den) > 1e-300, aa / np.where(den == 0, 1.0, den), 0.5), 0, 1)
    p0, p1 = pts[r, w], pts[r, w + 1]
    refined = p0 + t[:, None] * (p1 - p0)
    out = np.where(has[:, None], refined, x_to[j])
    frac = np.where(has, idx[r, w] + t * (idx[r, w + 1] - idx[r, w]), j.astype(float))
    return out, np.where(has, quality[r, w], 0.0), frac


def _point_at(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points of the polyline ``x`` (m, 2) at fractional sample positions ``u``."""
    u = np.clip(u, 0, len(x) - 1)
    k = np.minimum(np.floor(u).astype(np.int64), len(x) - 2)
    t = (u - k)[:, None]
    return x[k] * (1 - t) + x[k + 1] * t


def match_backbones(
    E: np.ndarray,
    x1: np.ndarray,
    x2: np.ndarray,
    cap: float,
    n_real1: int | None = None,
    n_real2: int | None = None,
    min_quality: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match two ordered backbones (normalised coordinates, base first): ``x1`` (n, 2) in
    view 1, ``x2`` (m, 2) in view 2, with ``x2^T E x1 = 0``.

    Every cell of the optimal monotone path becomes one correspondence (so a backbone part
    foreshortened in one view, e.g. a tip pointing at that camera, still gets as many
    matches as the other view has samples). Each is refined on the epipolar line in the
    view where the line crosses the polyline more steeply. Returns ``(y1 (p, 2), y2 (p, 2),
    quality (p,))`` in path order; quality = sine of the crossing angle used.

    Tip extension: the first ``n_real1``/``n_real2`` samples are the observed backbone; any
    samples after them extrapolate the tip in the image. A tip pointing at one camera is
    foreshortened in that view, and its observed skeleton ends early; extrapolating it lets
    the other view's tip samples find their epipolar crossing. Cells where both samples are
    extrapolated are dropped, and an extrapolated sample is never kept fixed.

    Optional arclength matching where epipolar matching is ill-posed: matches whose
    crossing angle has a sine below ``min_quality`` (default 0: off; on the synthetic set
    it did not reduce errors) take their positions along both polylines from linear
    interpolation between the neighbouring good matches.
    """
    cost = np.minimum(sampson_distance_np(E, x1, x2), cap)
    D, K = dtw_path_costs_np(cost)
    path = _backtrack(D, K)
    n1 = len(x1) if n_real1 is None else n_real1
    n2 = len(x2) if n_real2 is None else n_real2
    path = path[(path[:, 0] < n1) | (path[:, 1] < n2)]
    i, j = path[:, 0], path[:, 1]
    a2, qa, fa = refine_on_epilines(E, x1[i], x2, j)  # keep x1, move along view 2
    a1, qb, fb = refine_on_epilines(E.T, x2[j], x1, i)  # keep x2, move along view 1
    use_a = np.where(i >= n1, False, np.where(j >= n2, True, qa >= qb))
    q = np.where(use_a, qa, qb)
    # Positions along both polylines (fractional sample indices) of every match.
    u1 = np.where(use_a, i.astype(float), fb)
    u2 = np.where(use_a, fa, j.astype(float))
    good = q >= min_quality
    if good.sum() >= 2 and not good.all():
        # Where the backbone runs along the epipolar lines in both views, the crossing is
        # ill-defined: match by arclength instead, interpolating the position along the
        # other polyline linearly between the well-conditioned matches on either side.
        k = np.arange(len(q))
        u1 = np.where(good, u1, np.interp(k, k[good], u1[good]))
        u2 = np.where(good, u2, np.interp(k, k[good], u2[good]))
    y1 = _point_at(x1, u1)
    y2 = _point_at(x2, u2)
    # Past the end of one view's observed backbone (a tip foreshortened in that view, e.g.
    # pointing at the camera, collapses onto its last samples), the other view's samples
    # are paired with that view's last observed sample unrefined: the DLT point is then the
    # point of the other view's ray closest to the last ray, i.e. along the collapsed tip.
    end1 = i >= n1 - 1
    end2 = j >= n2 - 1
    tail1 = end1 & ~end2
    tail2 = end2 & ~end1
    y1 = np.where(tail1[:, None], x1[n1 - 1], y1)
    y2 = np.where(tail1[:, None], x2[np.minimum(j, len(x2) - 1)], y2)
    y2 = np.where(tail2[:, None], x2[n2 - 1], y2)
    y1 = np.where(tail2[:, None], x1[np.minimum(i, len(x1) - 1)], y1)
    return y1, y2, q
