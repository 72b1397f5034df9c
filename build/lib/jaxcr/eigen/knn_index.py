"""Exact batched k-nearest-neighbour search over the resampled manifold by leaf pruning
(the query step of Reiter et al. eqs. 7-8, made fast on CPU).

Brute force costs one (B, M) x k distance matrix and a top-k over M = 50k resampled points
per query; both dominate the query. Here the manifold's features are split once into
leaves of at most ``leaf_size`` points (recursive median split along the feature axis of
largest spread, as a k-d tree's leaves), each with its centre c_j and radius r_j (the
largest distance of its points to c_j). For a query x, every point in leaf j is at least
lb_j = |x - c_j| - r_j away (triangle inequality). The search takes the ``n_leaves``
leaves of smallest lb, computes exact distances to their points and keeps the b nearest.
The result is *certified* exact when the b-th distance is <= the lower bound of the best
leaf not searched; otherwise the query is searched again with 4x more leaves, and any
still uncertified query by brute force (:func:`jaxcr.eigen.manifold.knn`). So the
answer always equals brute force (up to exact distance ties); only the time depends on
the data. Distances are float32; the lower bounds subtract a rounding margin, so a
certificate is never granted by rounding.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float, Int
from jaxcr.eigen.manifold import Manifold, idw_weights, knn
from jaxcr.errors import InputError

_EPS32 = float(np.finfo(np.float32).eps)


class KnnIndex(eqx.Module):
    """Leaves of a point set (M, k): ``features`` (L, g, k) padded leaves, ``rows`` (L, g)
    the original row of each entry (-1 = padding), ``centres`` (L, k), ``radii`` (L,)."""

    features: Float[Array, "L g k"]
    rows: Int[Array, "L g"]
    centres: Float[Array, "L k"]
    radii: Float[Array, " L"]

    @property
    def n_leaves(self) -> int:
        return self.centres.shape[0]


def build_index(features: np.ndarray, leaf_size: int = 16) -> KnnIndex:
    """Split ``features`` (M, k) into leaves of at most ``leaf_size`` points (recursive
    median split along the axis of largest spread; deterministic)."""
    F = np.asarray(features, np.float64)
    if F.ndim != 2 or len(F) == 0:
        raise InputError(f"k-NN index needs points (M, k), got shape {F.shape}")
    if leaf_size < 1:
        raise InputError(f"leaf size must be >= 1, got {leaf_size}", field="leaf_size")
    leaves: list[np.ndarray] = []
    stack = [np.arange(len(F))]
    while stack:
        idx = stack.pop()
        if len(idx) <= leaf_size:
            leaves.append(idx)
            continue
        sub = F[idx]
        axis = int(np.argmax(sub.max(0) - sub.min(0)))
        half = len(idx) // 2
        order = np.argpartition(sub[:, axis], half, kind="introselect")
        stack += [idx[order[half:]], idx[order[:half]]]
    g = max(len(x) for x in leaves)
    L, k = len(leaves), F.shape[1]
    feats = np.zeros((L, g, k), np.float32)
    rows = np.full((L, g), -1, np.int32)
    centres = np.zeros((L, k))
    radii = np.zeros(L)
    for j, idx in enumerate(leaves):
        feats[j, : len(idx)] = F[idx]
        feats[j, len(idx) :] = F[idx[0]]  # padding repeats a member (never selected)
        rows[j, : len(idx)] = idx
        centres[j] = F[idx].mean(0)
        radii[j] = np.sqrt(((F[idx] - centres[j]) ** 2).sum(1).max())
    # Round the radii up so that float32 storage cannot make a bound too tight.
    radii = radii * (1 + 4 * _EPS32) + 1e-12
    return KnnIndex(
        jnp.asarray(feats),
        jnp.asarray(rows),
        jnp.asarray(centres, jnp.float32),
        jnp.asarray(radii, jnp.float32),
    )


def _search_chunk(index: KnnIndex, X, b: int, n_leaves: int):
    """Pruned search for a chunk of queries X (c, k): distances (c, b), rows (c, b),
    certified (c,)."""
    C, r = index.centres, index.radii
    x2 = jnp.sum(X * X, axis=1)
    c2 = jnp.sum(C * C, axis=1)
    dc2 = x2[:, None] - 2.0 * (X @ C.T) + c2[None, :]
    # Lower bound on |x - c| despite rounding in the expansion above: the dot product of
    # k terms errs by at most ~k eps |x||c| <= k eps (|x|^2 + |c|^2) / 2 (worst case).
    k = X.shape[1]
    slack = (k + 8) * _EPS32 * (x2[:, None] + c2[None, :])
    dc_lo = jnp.sqrt(jnp.maximum(dc2 - slack, 0.0)) * (1.0 - 4 * _EPS32)
    lb = jnp.maximum(dc_lo - r[None, :], 0.0)
    L = C.shape[0]
    take = min(n_leaves + 1, L)
    # The barriers keep XLA from rewriting "top_k then slice" into a full sort (measured
    # 30x slower on CPU).
    neg, leaf = jax.lax.optimization_barrier(jax.lax.top_k(-lb, take))
    if take > n_leaves:
        next_lb = -neg[:, n_leaves]
        leaf = leaf[:, :n_leaves]
    else:
        next_lb = jnp.full(X.shape[0], jnp.inf, X.dtype)
    cand = index.features[leaf]  # (c, n, g, k)
    rows = index.rows[leaf].reshape(X.shape[0], -1)
    d2 = jnp.sum((cand - X[:, None, None, :]) ** 2, axis=-1).reshape(X.shape[0], -1)
    d2 = jnp.where(rows >= 0, d2, jnp.inf)
    negd, j = jax.lax.optimization_barrier(jax.lax.top_k(-d2, b))
    d = jnp.sqrt(jnp.maximum(-negd, 0.0))
    sel = jnp.take_along_axis(rows, j, axis=1)
    # The b-th distance, rounded up, must not exceed what any unsearched leaf can offer.
    cert = d[:, -1] * (1 + 4 * _EPS32) <= next_lb
    return d, sel, cert


_search = jax.jit(_search_chunk, static_argnames=("b", "n_leaves"))


@partial(jax.jit, static_argnames=("b",))
def _brute(features, X, b: int):
    return jax.vmap(knn, in_axes=(None, 0, None))(features, X, b)


def _padded(X: np.ndarray, chunk: int) -> np.ndarray:
    """Pad rows to a power of two, at most ``chunk`` (few compiled shapes)."""
    n = min(chunk, 1 << max(0, len(X) - 1).bit_length())
    n = n * max(1, -(-len(X) // n))
    out = np.zeros((n, X.shape[1]), np.float32)
    out[: len(X)] = X
    if len(X):
        out[len(X) :] = X[0]
    return out


def _chunked(f, X: np.ndarray, chunk: int):
    """Apply the jitted batch function f to X in chunks of ``chunk`` rows (the last one
    padded); outputs concatenated and cut to len(X)."""
    outs = []
    for i in range(0, len(X), chunk):
        part = X[i : i + chunk]
        outs.append([np.asarray(a)[: len(part)] for a in f(_padded(part, chunk))])
    return [np.concatenate(o) for o in zip(*outs, strict=True)]


def knn_batch(
    index: KnnIndex,
    features: Float[Array, "M k"],
    X: np.ndarray,
    b: int = 3,
    n_leaves: int = 32,
    chunk: int = 256,
    stats: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact b nearest rows of ``features`` (the points ``index`` was built from) for each
    query in X (B, k): distances (B, b) ascending and row indices (B, b).

    Pass 1 searches ``n_leaves`` leaves per query; uncertified queries are searched with
    4 x ``n_leaves`` leaves, then by brute force (module docstring). ``stats`` (if given)
    receives the number of queries answered in each pass.
    """
    X = np.asarray(X, np.float32)
    if X.ndim != 2 or X.shape[1] != index.centres.shape[1]:
        raise InputError(f"queries must be (B, {index.centres.shape[1]}), got {X.shape}")
    if not 1 <= b <= int(np.sum(np.asarray(index.rows) >= 0)):
        raise InputError(f"b must be in 1..number of points, got {b}", field="b")
    B = len(X)
    D = np.zeros((B, b), np.float32)
    R = np.zeros((B, b), np.int64)
    todo = np.arange(B)
    counts = []
    g, k = index.features.shape[1:]
    for nl in (n_leaves, 4 * n_leaves):
        nl = min(nl, index.n_leaves)
        if len(todo) == 0 or nl * g < b:
            counts.append(0)
            continue
        # Chunk so that the gathered candidates stay under ~64 MB.
        ch = int(min(chunk, max(8, 2 ** int(np.log2(max(1, 2**24 // (nl * g * k)))))))
        d, r, c = _chunked(lambda x, nl=nl: _search(index, x, b, nl), X[todo], ch)
        D[todo[c]], R[todo[c]] = d[: len(todo)][c], r[: len(todo)][c]
        counts.append(int(c.sum()))
        todo = todo[~c]
    if len(todo):
        d, r = _chunked(lambda x: _brute(features, x, b), X[todo], chunk)
        D[todo], R[todo] = d, r
    counts.append(len(todo))
    if stats is not None:
        stats.update({"pass1": counts[0], "pass2": counts[1], "brute": counts[2]})
    return D, R


@jax.jit
def _idw_mean(d, rows, psi):
    return jnp.einsum("nb,nbd->nd", jax.vmap(idw_weights)(d), psi[rows])


def query_batch_indexed(
    manifold: Manifold, index: KnnIndex, X: np.ndarray, b: int = 3, **kwargs
) -> np.ndarray:
    """Reiter et al. eqs. 7-8 for a batch of eigen-features X (B, k) using the exact
    pruned search (:func:`knn_batch`; ``index`` built from ``manifold.features``). Same
    result as :func:`jaxcr.eigen.manifold.query_batch` (brute force)."""
    D, R = knn_batch(index, manifold.features, X, b, **kwargs)
    return np.asarray(_idw_mean(jnp.asarray(D), jnp.asarray(R, jnp.int32), manifold.psi))
