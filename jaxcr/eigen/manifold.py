"""The parametric eigen-feature manifold G(psi) = L (Reiter et al. eq. 6), its dense
resampling, and the k-NN inverse-distance query (eqs. 7-8).

Training (:func:`build_manifold`): one thin-plate smoothing spline per eigen-feature
dimension maps the parameters psi (2-DOF angles (theta_L, delta) in radians, or a 3-DOF tip
position (x, y, z) in metres) to the eigen-feature; the spline is then evaluated on a dense
regular grid over the training parameters' bounding box. Grid points farther than
``max_gap`` (in parameter units) from every training sample are dropped: there the spline
extrapolates and its features are not supported by data.

Query (:func:`query`, batched by :func:`query_batch`): the b nearest resampled points in
eigen-feature space (Euclidean), weights w_l = (1/d_l) / sum_p (1/d_p) (eq. 7), estimate
psi = sum_l w_l psi_l (eq. 8). An exact match (d_l = 0) gets all the weight. This is
the brute-force reference; trained models query through the exact pruned search of
:mod:`jaxcr.eigen.knn_index` (same neighbours, several times faster on CPU).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float, Int
from jaxcr.eigen.tps import ThinPlateSpline, evaluate_tps, fit_tps
from jaxcr.errors import InputError

#: Distances below this (eigen-feature units) count as exact matches in eq. 7.
EXACT_EPS = 1e-12


class Manifold(eqx.Module):
    """Resampled manifold: parameters ``psi`` (M, d) and eigen-features ``features`` (M, k)."""

    psi: Float[Array, "M d"]
    features: Float[Array, "M k"]


def grid_points(lo: np.ndarray, hi: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Regular grid (M, d) covering the box [lo, hi] with spacing at most ``step`` per axis
    (both ends included)."""
    axes = [
        np.linspace(a, b, max(2, int(np.ceil((b - a) / s)) + 1))
        for a, b, s in zip(lo, hi, step, strict=True)
    ]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=1)


def _min_dist(grid: np.ndarray, samples: np.ndarray, chunk: int = 8192) -> np.ndarray:
    s = jnp.asarray(samples, jnp.float32)
    s2 = jnp.sum(s**2, 1)

    @jax.jit
    def f(g):
        d2 = jnp.sum(g**2, 1)[:, None] - 2.0 * g @ s.T + s2[None, :]
        return jnp.sqrt(jnp.maximum(jnp.min(d2, axis=1), 0.0))

    out = []
    for i in range(0, len(grid), chunk):
        g = grid[i : i + chunk]
        pad = chunk - len(g)
        gp = np.concatenate([g, np.repeat(g[:1], pad, 0)]) if pad else g
        out.append(np.asarray(f(jnp.asarray(gp, jnp.float32)))[: len(g)])
    return np.concatenate(out)


def resample(
    spline: ThinPlateSpline, psi_train: np.ndarray, step: np.ndarray, max_gap: float
) -> Manifold:
    """Evaluate ``spline`` densely (grid of spacing ``step`` over the training box),
    keeping grid points within ``max_gap`` of a training sample."""
    psi_train = np.asarray(psi_train, np.float64)
    grid = grid_points(psi_train.min(0), psi_train.max(0), np.asarray(step, np.float64))
    keep = _min_dist(grid, psi_train) <= max_gap
    grid = grid[keep]
    if len(grid) == 0:
        raise InputError("no resampled manifold points: max_gap too small for the samples")
    feats = evaluate_tps(spline, jnp.asarray(grid, spline.centres.dtype))
    return Manifold(psi=jnp.asarray(grid, jnp.float32), features=jnp.asarray(feats, jnp.float32))


def check_grid(psi, step) -> float:
    """Refuse (InputError, field ``step``) a resampling ``step`` whose grid over the box of the
    parameters ``psi`` (n, d) would exceed :data:`jaxcr.limits.MAX_MANIFOLD_POINTS` points.
    Returns the grid's number of points (an upper bound of the resampled manifold's)."""
    from jaxcr.limits import MAX_MANIFOLD_POINTS

    psi = np.asarray(psi, np.float64)
    step = np.broadcast_to(np.asarray(step, np.float64), (psi.shape[1],))
    n_grid = float(np.prod(np.floor(np.ptp(psi, axis=0) / step) + 1))
    if n_grid > MAX_MANIFOLD_POINTS:
        raise InputError(
            f"step {step.tolist()} makes a grid of {n_grid:.3g} points over the training "
            f"parameters, over the limit of {MAX_MANIFOLD_POINTS}",
            field="step",
        )
    return n_grid


def build_manifold(
    psi: Float[Array, "n d"],
    features: Float[Array, "n k"],
    step,
    smoothing: float = 0.0,
    max_gap: float | None = None,
) -> tuple[Manifold, ThinPlateSpline]:
    """Fit the spline psi -> features (eq. 6) and resample it (see module docstring).

    ``step``: grid spacing per parameter (scalar or (d,)); ``max_gap`` defaults to 3 x the
    median nearest-neighbour spacing of the training parameters.
    """
    psi = np.asarray(psi, np.float64)
    d = psi.shape[1]
    step = np.broadcast_to(np.asarray(step, np.float64), (d,))
    if not np.all(np.isfinite(step) & (step > 0)):
        raise InputError(f"resampling step must be a finite number > 0, got {step}", field="step")
    check_grid(psi, step)  # before any spline work (jaxcr.limits)
    spline = fit_tps(jnp.asarray(psi, jnp.float32), jnp.asarray(features, jnp.float32), smoothing)
    if max_gap is None:
        nn = _nearest_other(psi)
        max_gap = 3.0 * float(np.median(nn))
    return resample(spline, psi, step, max_gap), spline


def _nearest_other(x: np.ndarray, chunk: int = 2048) -> np.ndarray:
    out = []
    for i in range(0, len(x), chunk):
        d2 = ((x[i : i + chunk, None, :] - x[None, :, :]) ** 2).sum(-1)
        d2[np.arange(len(d2)), np.arange(i, i + len(d2))] = np.inf
        out.append(np.sqrt(d2.min(1)))
    return np.concatenate(out)


def knn(
    features: Float[Array, "M k"], x: Float[Array, " k"], b: int
) -> tuple[Float[Array, " b"], Int[Array, " b"]]:
    """Distances (ascending) and indices of the ``b`` nearest rows of ``features`` to x
    (brute force: |f|^2 - 2 f.x + |x|^2, clipped at 0)."""
    d2 = jnp.sum(features**2, axis=1) - 2.0 * features @ x + jnp.sum(x**2)
    neg, idx = jax.lax.top_k(-d2, b)
    # Recompute the few selected distances exactly (the expansion cancels for near matches).
    dsel = jnp.sum((features[idx] - x) ** 2, axis=1)
    return jnp.sqrt(jnp.maximum(dsel, 0.0)), idx


def idw_weights(d: Float[Array, " b"]) -> Float[Array, " b"]:
    """w_l = (1/d_l) / sum_p 1/d_p (Reiter et al. eq. 7); exact matches (d < EXACT_EPS)
    share all the weight. Finite gradients everywhere (double where)."""
    exact = d < EXACT_EPS
    any_exact = jnp.any(exact)
    inv = 1.0 / jnp.where(exact, 1.0, d)
    w_far = inv / jnp.sum(inv)
    w_exact = exact / jnp.maximum(jnp.sum(exact), 1)
    return jnp.where(any_exact, w_exact.astype(d.dtype), w_far)


def query(manifold: Manifold, x: Float[Array, " k"], *, b: int = 3) -> Float[Array, " d"]:
    """Parameters of one eigen-feature vector (``jcr.eigen.query``; Reiter et al. eqs. 7-8).

    The inverse-distance weighted mean of the parameters of the ``b`` manifold points
    nearest to ``x`` (brute force; jit- and vmap-able, :func:`query_batch` for many).

    Parameters
    ----------
    manifold : Manifold
        The resampled manifold: ``features`` (m, k) eigen-features on the grid and ``psi``
        (m, d) their parameters (``EigenModel.manifold``, :func:`build_manifold`).
    x : (k,) array
        One eigen-feature vector, L = E^T (H - c) (eq. 5) of a view's descriptor H.
    b : int, optional
        Neighbours averaged (default 3, as the paper).

    Returns
    -------
    (d,) array
        psi = (theta_L, delta) in radians, or the tip (x, y, z) in metres, as the manifold
        is parametrised.

    Examples
    --------
    A manifold of three points on a line, parametrised by one angle:

    >>> import jax.numpy as jnp
    >>> import jaxcr as jcr
    >>> manifold = jcr.eigen.Manifold(psi=jnp.array([[0.0], [0.1], [0.2]]),
    ...                               features=jnp.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))
    >>> print(f"{float(jcr.eigen.query(manifold, jnp.array([1.0, 0.0]), b=1)[0]):.3f}")
    0.100

    Two neighbours at distances 0.25 and 0.75 weigh 3 : 1:

    >>> print(f"{float(jcr.eigen.query(manifold, jnp.array([0.25, 0.0]), b=2)[0]):.4f}")
    0.0250
    """
    d, idx = knn(manifold.features, x, b)
    return idw_weights(d) @ manifold.psi[idx]


@eqx.filter_jit
def _query_rows(X: Float[Array, "B k"], manifold: Manifold, b: int) -> Float[Array, "B d"]:
    return jax.vmap(lambda m, x: query(m, x, b=b), in_axes=(None, 0))(manifold, X)


def query_batch(
    manifold: Manifold, X: Float[Array, "B k"], b: int = 3, *, devices: int | None = None
) -> Float[Array, "B d"]:
    """:func:`query` for a batch of eigen-features (one compile per batch shape), the rows
    spread over ``devices`` local devices (None: all, one on a usual machine;
    :func:`jaxcr.scale.devices.map_frames`, bit-identical per row)."""
    from jaxcr.scale.devices import map_frames

    return map_frames(_query_rows, X, manifold, b, devices=devices)
