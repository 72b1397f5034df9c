"""Exact pruned k-NN over the resampled manifold (jaxcr.eigen.knn_index) vs
scipy.spatial.cKDTree and the brute-force query of jaxcr.eigen.manifold."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxcr.eigen.knn_index import build_index, knn_batch, query_batch_indexed
from jaxcr.eigen.manifold import Manifold, query_batch
from jaxcr.errors import InputError


@pytest.fixture(scope="module")
def cloud():
    """A smooth 2-D manifold in 8-D (like the resampled eigen-features) plus queries near
    it and far from it."""
    rng = np.random.default_rng(3)
    u = rng.uniform(0, 1, (4000, 2))
    F = np.concatenate([np.sin(3 * u), np.cos(2 * u), u**2, u[:, :1] * u[:, 1:], u], 1)
    F = F[:, :8].astype(np.float32)
    near = F[rng.integers(0, len(F), 150)] + 0.01 * rng.normal(size=(150, 8))
    far = F[rng.integers(0, len(F), 50)] + 0.3 * rng.normal(size=(50, 8))
    X = np.concatenate([near, far]).astype(np.float32)
    return Manifold(jnp.asarray(u, jnp.float32), jnp.asarray(F)), X


def test_index_partitions_points_and_bounds_radii(cloud):
    m, _ = cloud
    F = np.asarray(m.features)
    idx = build_index(F, leaf_size=16)
    rows = np.asarray(idx.rows)
    got = np.sort(rows[rows >= 0])
    np.testing.assert_array_equal(got, np.arange(len(F)))  # every point exactly once
    assert idx.features.shape[1] <= 16
    feats = np.asarray(idx.features)
    for j in range(0, idx.n_leaves, 37):
        v = rows[j] >= 0
        np.testing.assert_array_equal(feats[j][v], F[rows[j][v]])
        d = np.linalg.norm(F[rows[j][v]] - np.asarray(idx.centres[j]), axis=1)
        assert d.max() <= float(idx.radii[j])


@pytest.mark.parametrize("n_leaves", [1, 4, 32])
def test_knn_batch_matches_ckdtree(cloud, n_leaves):
    """Exact at every pruning level: few leaves force the second pass and brute force."""
    m, X = cloud
    idx = build_index(np.asarray(m.features), leaf_size=16)
    stats: dict = {}
    D, R = knn_batch(idx, m.features, X, 3, n_leaves=n_leaves, chunk=64, stats=stats)
    d_ref, i_ref = cKDTree(np.asarray(m.features, np.float64)).query(X.astype(np.float64), 3)
    np.testing.assert_array_equal(R, i_ref)
    np.testing.assert_allclose(D, d_ref, rtol=1e-5, atol=1e-6)
    assert sum(stats.values()) == len(X)
    if n_leaves == 1:
        assert stats["brute"] > 0 and stats["pass2"] > 0  # fallbacks exercised
    if n_leaves == 32:
        assert stats["pass1"] > len(X) // 2


def test_query_batch_indexed_equals_brute_force(cloud):
    m, X = cloud
    idx = build_index(np.asarray(m.features), leaf_size=16)
    got = query_batch_indexed(m, idx, X, 3)
    ref = np.asarray(query_batch(m, jnp.asarray(X), 3))
    np.testing.assert_allclose(got, ref, atol=1e-6)
    # An exact match takes the point's parameters (eq. 7 special case).
    one = query_batch_indexed(m, idx, np.asarray(m.features[5:6]), 3)
    np.testing.assert_allclose(one[0], np.asarray(m.psi[5]), atol=1e-6)


def test_knn_index_bad_input(cloud):
    m, X = cloud
    idx = build_index(np.asarray(m.features))
    with pytest.raises(InputError, match="queries"):
        knn_batch(idx, m.features, X[:, :5], 3)
    with pytest.raises(InputError, match="b must"):
        knn_batch(idx, m.features, X, 0)
    with pytest.raises(InputError, match="points"):
        build_index(np.zeros((0, 3)))
    with pytest.raises(InputError, match="leaf size"):
        build_index(np.zeros((5, 3)), leaf_size=0)
