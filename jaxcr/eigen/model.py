"""The trained eigen-feature estimator: colour model + PCA projection + resampled manifold,
and the two entry points :func:`train` (descriptors + parameters -> model) and
:func:`estimate` (descriptors -> parameters).

``params`` names what the manifold is parametrised by: ``"angles"`` = psi = (theta_L,
delta) in radians (Reiter et al. eq. 1) or ``"position"`` = the tip (x, y, z) in metres,
robot frame (Reiter et al. Sec. V, "Generalizing the method").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxcr.eigen.colour import ColourModel
from jaxcr.eigen.knn_index import KnnIndex, build_index, query_batch_indexed
from jaxcr.eigen.manifold import Manifold, build_manifold
from jaxcr.eigen.pca import PCA, components_for_variance, fit_pca
from jaxcr.errors import InputError

CENTRES = ("fixed", "region")
PARAM_KINDS = {"angles": ("theta_L", "delta"), "position": ("x", "y", "z")}
#: Default grid spacing of the resampled manifold per parameter kind (radians / metres).
DEFAULT_STEP = {"angles": float(np.deg2rad(0.5)), "position": 0.5e-3}


@dataclass
class TrainConfig:
    """Training options (stored in the model file).

    n_bins: histogram bins per image (72, 120, 360). variance: PCA variance fraction kept.
    smoothing: thin-plate smoothing lambda. step: resampling grid spacing (radians or metres;
    None = :data:`DEFAULT_STEP`). b: neighbours in the query (eq. 7-8). params: "angles" or
    "position". spacing: contour control-point spacing (pixels). normalise: histograms sum
    to 1. cameras: the two views, left then right.
    """

    n_bins: int = 120
    variance: float = 0.90
    smoothing: float = 1e-4
    step: float | None = None
    b: int = 3
    params: str = "angles"
    spacing: float = 2.0
    normalise: bool = True
    centre: str = "fixed"
    cameras: tuple[str, str] = ("left", "right")
    max_gap: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def check(self) -> None:
        if self.n_bins < 4 or self.n_bins > 3600:
            raise InputError(f"n_bins must be in 4..3600, got {self.n_bins}", field="n_bins")
        if not 0 < self.variance <= 1:
            raise InputError(f"variance must be in (0, 1], got {self.variance}", field="variance")
        if self.params not in PARAM_KINDS:
            raise InputError(f"params must be one of {sorted(PARAM_KINDS)}", field="params")
        if self.b < 1:
            raise InputError(f"b must be >= 1, got {self.b}", field="b")
        if not 0 <= self.smoothing < float("inf"):  # NaN was accepted
            raise InputError(f"smoothing must be finite and >= 0, got {self.smoothing}",
                             field="smoothing")  # fmt: skip
        if self.step is not None and not 0 < self.step < float("inf"):
            raise InputError(f"step must be finite and > 0, got {self.step}", field="step")
        if self.centre not in CENTRES:
            raise InputError(
                f"centre must be one of {CENTRES}, got {self.centre!r}", field="centre"
            )


@dataclass
class EigenModel:
    config: TrainConfig
    colour: ColourModel
    pca: PCA  # truncated to the kept components
    manifold: Manifold
    n_train: int
    timings: dict[str, float] = field(default_factory=dict)
    #: Fixed histogram reference points (2, 2) (x, y pixels per view) if config.centre is
    #: "fixed", else None.
    view_centres: np.ndarray | None = None
    #: Leaf index of the manifold features for the exact pruned query (built on first use;
    #: not stored in model files, it is a deterministic function of the manifold).
    index: KnnIndex | None = None

    def knn_index(self) -> KnnIndex:
        if self.index is None:
            self.index = build_index(np.asarray(self.manifold.features))
        return self.index

    @property
    def n_components(self) -> int:
        return self.pca.n_components


def train(
    descriptors: np.ndarray,
    params: np.ndarray,
    colour: ColourModel,
    config: TrainConfig,
    *,
    view_centres: np.ndarray | None = None,
) -> EigenModel:
    """Train an eigen-feature pose estimator (``jcr.eigen.train``; Reiter et al. Sec. III).

    PCA of the stereo descriptors keeps ``config.variance`` of their variance (eq. 5: the
    eigen-features L = E^T (H - c)); a thin-plate spline maps the parameters to the
    eigen-features and is resampled on a grid of spacing ``config.step`` (Sec. III-D), the
    manifold that :func:`estimate` and :func:`jaxcr.eigen.query` search.

    Parameters
    ----------
    descriptors : (n, 2 * n_bins) array
        Stereo descriptors of the n training views: the left and right angular histograms
        side by side (:func:`jaxcr.eigen.pipeline.stereo_histograms`), float32.
    params : (n, d) array
        What each view shows: psi = (theta_L, delta) in radians (d = 2,
        ``config.params="angles"``) or the tip (x, y, z) in metres, robot frame (d = 3,
        ``"position"``). At least d + 3 views.
    colour : ColourModel
        The colour model the views were segmented with
        (:func:`jaxcr.eigen.colour.fit_colour_model`); stored in the model for queries.
    config : TrainConfig
        Bins, PCA variance kept, spline smoothing, grid step, neighbours b, ...
    view_centres : (2, 2) array, optional
        The fixed histogram centres (x, y pixels per view) the descriptors were computed with
        (:func:`jaxcr.eigen.pipeline.view_centres`); required iff ``config.centre`` is
        ``"fixed"``, stored so that queries use the same points.

    Returns
    -------
    EigenModel
        ``pca`` (truncated to the kept components), ``manifold`` (``features`` (m, k)
        eigen-features on the grid, ``psi`` (m, d) their parameters), ``colour``,
        ``config``, ``n_train`` and ``timings`` (seconds per stage). Save it with
        :func:`jaxcr.io.eigen_model.save_model`.

    Raises
    ------
    InputError
        Shapes that disagree with each other or with ``config``, too few views, a bad
        config value (the field is named).

    Examples
    --------
    A toy appearance: 25 views on a 5 x 5 grid of psi, with 8-bin histograms per view that
    move smoothly with psi (real descriptors come from images,
    :func:`jaxcr.eigen.pipeline.stereo_histograms`):

    >>> import jax.numpy as jnp
    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> t, d = np.meshgrid(np.linspace(0.2, 1.0, 5), np.linspace(-0.4, 0.4, 5))
    >>> psi = np.stack([t.ravel(), d.ravel()], 1)  # (25, 2): theta_L, delta (rad)
    >>> def histograms(psi):
    ...     bins = np.arange(8)
    ...     left = np.exp(-((bins - 2 - 4 * psi[:, :1]) ** 2) / 2)
    ...     right = np.exp(-((bins - 3.5 - 6 * psi[:, 1:]) ** 2) / 2)
    ...     return np.concatenate([left, right], 1)  # (n, 2 * 8)
    >>> colour = jcr.eigen.ColourModel(jnp.zeros((2, 2)), jnp.int32(0))
    >>> config = jcr.eigen.TrainConfig(n_bins=8, centre="region", step=0.05)
    >>> model = jcr.eigen.train(histograms(psi), psi, colour, config)
    >>> model.n_train, model.manifold.psi.shape
    (25, (289, 2))

    An unseen configuration is recovered (:func:`estimate`):

    >>> np.round(jcr.eigen.estimate(model, histograms(np.array([[0.5, 0.1]]))), 2)
    array([[0.5, 0.1]], dtype=float32)
    """
    config.check()
    H = np.asarray(descriptors, np.float32)
    P = np.asarray(params, np.float64)
    if H.ndim != 2 or P.ndim != 2 or len(H) != len(P):
        raise InputError(f"descriptors (n, m) and params (n, d) disagree: {H.shape}, {P.shape}")
    if H.shape[1] != 2 * config.n_bins:
        raise InputError(
            f"descriptors must have 2 x n_bins = {2 * config.n_bins} columns, got {H.shape[1]}"
        )
    d = len(PARAM_KINDS[config.params])
    if P.shape[1] != d:
        raise InputError(f"params {config.params!r} need {d} columns, got {P.shape[1]}")
    if len(H) < d + 3:
        raise InputError(f"need at least {d + 3} training frames, got {len(H)}")
    if config.centre == "fixed":
        if view_centres is None or np.shape(view_centres) != (2, 2):
            raise InputError("centre 'fixed' needs the (2, 2) view centres", field="centre")
        view_centres = np.asarray(view_centres, np.float64)
    else:
        view_centres = None
    t0 = time.perf_counter()
    full = fit_pca(jnp.asarray(H))
    k = components_for_variance(full, config.variance)
    pca = full.truncate(k)
    L = (jnp.asarray(H) - pca.mean) @ pca.components
    L.block_until_ready()
    t1 = time.perf_counter()
    step = DEFAULT_STEP[config.params] if config.step is None else config.step
    manifold, _ = build_manifold(P, L, step, config.smoothing, config.max_gap)
    manifold.features.block_until_ready()
    t2 = time.perf_counter()
    index = build_index(np.asarray(manifold.features))
    t3 = time.perf_counter()
    return EigenModel(
        config,
        colour,
        pca,
        manifold,
        len(H),
        {
            "pca_s": t1 - t0,
            "manifold_s": t2 - t1,
            "index_s": t3 - t2,
            "variance_total": float(full.variance.sum()),
        },
        view_centres,
        index,
    )


def eigen_features(model: EigenModel, descriptors: np.ndarray) -> np.ndarray:
    """L = E^T (H~ - c) for a batch (n, m) -> (n, k) (eq. 5)."""
    H = jnp.asarray(descriptors, jnp.float32)
    m = model.pca.mean.shape[0]
    if H.ndim != 2 or H.shape[1] != m:
        raise InputError(f"descriptors must be (n, {m}), got {tuple(H.shape)}")
    return (H - model.pca.mean) @ model.pca.components


def estimate(model: EigenModel, descriptors: np.ndarray) -> np.ndarray:
    """Estimate the parameters of new views (Reiter et al. eqs. 5, 7, 8).

    Projects the descriptors on the model's principal components (eq. 5) and takes the
    inverse-distance weighted mean of the ``model.config.b`` nearest manifold points
    (eqs. 7-8; exact pruned k-NN search, :mod:`jaxcr.eigen.knn_index`): the batch form of
    :func:`jaxcr.eigen.query`.

    Parameters
    ----------
    model : EigenModel
        A trained model (:func:`train`, or :func:`jaxcr.io.eigen_model.load_model`).
    descriptors : (n, 2 * n_bins) array
        Stereo descriptors of the n views, computed as the training ones were.

    Returns
    -------
    (n, d) array
        psi = (theta_L, delta) in radians, or the tip (x, y, z) in metres (robot frame), as
        the model was trained (``model.config.params``).

    Raises
    ------
    InputError
        Descriptors whose width is not the model's.

    Examples
    --------
    With the toy model of :func:`train`'s example, the training views themselves:

    >>> import jax.numpy as jnp
    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> t, d = np.meshgrid(np.linspace(0.2, 1.0, 5), np.linspace(-0.4, 0.4, 5))
    >>> psi = np.stack([t.ravel(), d.ravel()], 1)
    >>> bins = np.arange(8)
    >>> H = np.concatenate([np.exp(-((bins - 2 - 4 * psi[:, :1]) ** 2) / 2),
    ...                     np.exp(-((bins - 3.5 - 6 * psi[:, 1:]) ** 2) / 2)], 1)
    >>> colour = jcr.eigen.ColourModel(jnp.zeros((2, 2)), jnp.int32(0))
    >>> model = jcr.eigen.train(H, psi, colour,
    ...                         jcr.eigen.TrainConfig(n_bins=8, centre="region", step=0.05))
    >>> np.round(jcr.eigen.estimate(model, H[[6, 18]]), 2), psi[[6, 18]]
    (array([[ 0.4, -0.2],
           [ 0.8,  0.2]], dtype=float32), array([[ 0.4, -0.2],
           [ 0.8,  0.2]]))
    """
    L = eigen_features(model, descriptors)
    return query_batch_indexed(model.manifold, model.knn_index(), np.asarray(L), model.config.b)
