"""Principal component analysis of stereo descriptors (Reiter et al. Sec. III-D.1, eq. 5).

``L = E^T (H~ - c)``: E holds the top-k principal directions (columns), c the mean
descriptor. k is chosen as the smallest number of components whose cumulative explained
variance reaches a given fraction (65/85/90/95 % in the paper's Table I).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float
from jaxcr.errors import InputError


class PCA(eqx.Module):
    """Mean ``mean`` (m,), directions ``components`` (m, r) as orthonormal columns sorted by
    decreasing variance, ``variance`` (r,) the variance along each (ddof = 1)."""

    mean: Float[Array, " m"]
    components: Float[Array, "m r"]
    variance: Float[Array, " r"]

    @property
    def n_components(self) -> int:
        return self.components.shape[1]

    def truncate(self, k: int) -> PCA:
        """The first ``k`` components (the projection matrix E of eq. 5)."""
        return PCA(self.mean, self.components[:, :k], self.variance[:k])


def fit_pca(X: Float[Array, "n m"]) -> PCA:
    """PCA of the rows of X via the SVD of the centred data (all min(n, m) components).

    Signs are fixed so that the largest-magnitude entry of each direction is positive
    (deterministic, comparable with other SVDs).
    """
    X = jnp.asarray(X)
    n = X.shape[0]
    if n < 2:
        raise InputError(f"PCA needs at least 2 samples, got {n}")
    mean = X.mean(axis=0)
    _, s, vt = jnp.linalg.svd(X - mean, full_matrices=False)
    V = vt.T
    sign = jnp.sign(V[jnp.argmax(jnp.abs(V), axis=0), jnp.arange(V.shape[1])])
    V = V * jnp.where(sign == 0, 1.0, sign)
    return PCA(mean=mean, components=V, variance=s**2 / (n - 1))


def components_for_variance(pca: PCA, fraction: float) -> int:
    """Smallest k with sum(variance[:k]) >= fraction * sum(variance) (Table I)."""
    if not 0.0 < fraction <= 1.0:
        raise InputError(f"variance fraction must be in (0, 1], got {fraction}", field="variance")
    v = np.asarray(pca.variance, np.float64)
    c = np.cumsum(v) / max(v.sum(), 1e-300)
    return int(min(np.searchsorted(c, fraction - 1e-12) + 1, len(v)))


def project(pca: PCA, h: Float[Array, " m"]) -> Float[Array, " k"]:
    """Eigen-feature of one descriptor, L = E^T (H~ - c) (Reiter et al. eq. 5)."""
    return pca.components.T @ (h - pca.mean)
