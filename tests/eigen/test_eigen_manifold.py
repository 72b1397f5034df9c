"""Manifold resampling and the k-NN inverse-distance query (Reiter et al. eqs. 6-8) vs
scipy.spatial.cKDTree and a numpy implementation; model training/estimation on a
synthetic smooth manifold; model files (round trip, corrupt/incompatible -> InputError)."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxcr.eigen.colour import ColourModel
from jaxcr.eigen.manifold import (
    Manifold,
    build_manifold,
    grid_points,
    idw_weights,
    knn,
    query,
    query_batch,
)
from jaxcr.eigen.model import TrainConfig, estimate, train
from jaxcr.errors import InputError
from jaxcr.io.eigen_model import FORMAT, load_model, save_model


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(0)
    F = rng.normal(size=(3000, 6)).astype(np.float32)
    P = rng.uniform(0, 1, (3000, 2)).astype(np.float32)
    X = rng.normal(size=(50, 6)).astype(np.float32)
    return Manifold(jnp.asarray(P), jnp.asarray(F)), X


def test_knn_matches_ckdtree(cloud):
    m, X = cloud
    tree = cKDTree(np.asarray(m.features, np.float64))
    d_ref, i_ref = tree.query(X.astype(np.float64), k=3)
    for x, dr, ir in zip(X, d_ref, i_ref, strict=True):
        d, i = knn(m.features, jnp.asarray(x), 3)
        np.testing.assert_array_equal(np.asarray(i), ir)
        np.testing.assert_allclose(np.asarray(d), dr, rtol=1e-5, atol=1e-5)


def test_query_matches_numpy_idw(cloud):
    m, X = cloud
    tree = cKDTree(np.asarray(m.features, np.float64))
    d, i = tree.query(X.astype(np.float64), k=3)
    w = (1 / d) / (1 / d).sum(1, keepdims=True)  # eq. 7
    ref = np.einsum("nb,nbd->nd", w, np.asarray(m.psi)[i])  # eq. 8
    got = np.asarray(query_batch(m, jnp.asarray(X), 3))
    np.testing.assert_allclose(got, ref, atol=1e-5)
    loop = np.stack([np.asarray(query(m, jnp.asarray(x), b=3)) for x in X[:5]])
    np.testing.assert_allclose(got[:5], loop, atol=1e-6)
    f = eqx.filter_jit(eqx.debug.assert_max_traces(query, max_traces=1))
    for x in X[:4]:
        f(m, jnp.asarray(x), b=3)


def test_exact_match_and_weight_gradients(cloud):
    m, _ = cloud
    x = m.features[17]
    np.testing.assert_allclose(np.asarray(query(m, x, b=3)), np.asarray(m.psi[17]), atol=1e-6)
    w = idw_weights(jnp.asarray([0.0, 1.0, 2.0]))
    np.testing.assert_array_equal(np.asarray(w), [1.0, 0.0, 0.0])
    w2 = idw_weights(jnp.asarray([0.0, 0.0, 2.0]))
    np.testing.assert_array_equal(np.asarray(w2), [0.5, 0.5, 0.0])
    # Gradients: finite at an exact match; finite differences elsewhere.
    g0 = jax.jacfwd(idw_weights)(jnp.asarray([0.0, 1.0, 2.0]))
    assert np.all(np.isfinite(np.asarray(g0)))
    with jax.enable_x64(True):
        d = jnp.asarray([0.3, 0.5, 0.9])
        J = np.asarray(jax.jacfwd(idw_weights)(d))
        eps = 1e-7
        fd = np.stack(
            [
                (np.asarray(idw_weights(d + eps * e)) - np.asarray(idw_weights(d - eps * e)))
                / (2 * eps)
                for e in np.eye(3)
            ],
            1,
        )
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-8)


def test_grid_points_cover_box():
    g = grid_points(np.array([0.0, -1.0]), np.array([1.0, 1.0]), np.array([0.3, 0.5]))
    assert g.min(0).tolist() == [0.0, -1.0] and g.max(0).tolist() == [1.0, 1.0]
    assert len(np.unique(g[:, 0])) == 5 and len(np.unique(g[:, 1])) == 5


def _toy_training(n=400, seed=0, nb=16):
    """Descriptors as a smooth nonlinear function of psi over the IREP-like workspace."""
    rng = np.random.default_rng(seed)
    psi = np.stack([rng.uniform(0.1, 1.3, n), rng.uniform(0.0, np.pi, n)], 1)
    ang = np.linspace(0, 2 * np.pi, nb, endpoint=False)

    def desc(p):
        a = np.exp(2 * np.cos(ang[None, :] - p[:, 1:2]) * (1.5 - p[:, :1]))
        b = np.exp(1.5 * np.cos(ang[None, :] - 0.5 * p[:, 1:2] - p[:, :1]))
        h = np.concatenate([a, b], 1)
        return h / h.sum(1, keepdims=True)

    return psi, desc


def test_train_estimate_recovers_psi_on_toy_manifold():
    psi, desc = _toy_training()
    colour = ColourModel(jnp.zeros((5, 2)), jnp.asarray(0, jnp.int32))
    cfg = TrainConfig(
        n_bins=16, variance=0.999, smoothing=1e-6, step=np.deg2rad(0.5), centre="region"
    )
    model = train(desc(psi), psi, colour, cfg)
    rng = np.random.default_rng(9)
    test = np.stack([rng.uniform(0.15, 1.25, 100), rng.uniform(0.1, np.pi - 0.1, 100)], 1)
    est = estimate(model, desc(test))
    err = np.rad2deg(np.abs(est - test))
    assert np.median(err) < 0.5, np.median(err, 0)
    # Resampled points stay inside the sampled region (no extrapolated features).
    assert np.asarray(model.manifold.psi).min(0)[0] >= psi[:, 0].min() - 1e-6


def test_build_manifold_position_3d():
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.01, 0.01, (200, 3))
    f = np.stack([np.sin(300 * x[:, 0]), x[:, 1] * 100 + x[:, 2] * 50], 1)
    m, spline = build_manifold(x, f, 1e-3, smoothing=1e-8)
    assert m.psi.shape[1] == 3 and m.features.shape[1] == 2
    np.testing.assert_allclose(np.asarray(spline(jnp.asarray(x[0], jnp.float32))), f[0], atol=2e-2)


@pytest.fixture(scope="module")
def small_model():
    psi, desc = _toy_training(120)
    colour = ColourModel(
        jnp.asarray(np.arange(10, dtype=np.float32).reshape(5, 2)), jnp.asarray(2, jnp.int32)
    )
    cfg = TrainConfig(n_bins=16, variance=0.99, step=np.deg2rad(2.0))
    centres = np.array([[100.5, 80.25], [90.0, 81.0]])
    return train(desc(psi), psi, colour, cfg, view_centres=centres), desc


def test_model_file_round_trip(tmp_path, small_model):
    model, desc = small_model
    path = save_model(model, tmp_path / "m.npz", meta={"dataset": "toy"})
    back = load_model(path)
    assert back.config == model.config
    np.testing.assert_array_equal(
        np.asarray(back.manifold.features), np.asarray(model.manifold.features)
    )
    np.testing.assert_array_equal(np.asarray(back.colour.centres), np.asarray(model.colour.centres))
    assert int(back.colour.marker) == 2
    np.testing.assert_array_equal(back.view_centres, model.view_centres)
    psi = np.array([[0.5, 1.0], [1.0, 2.0]])
    np.testing.assert_allclose(estimate(back, desc(psi)), estimate(model, desc(psi)), atol=1e-7)
    with np.load(path) as z:
        assert str(z["format"]) == FORMAT
        cfg = json.loads(str(z["config"]))
        assert cfg["param_names"] == ["theta_L", "delta"] and cfg["param_units"] == "rad"


def _rewrite(path, out, **changes):
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    np.savez(out, **d)
    return out


def test_model_file_errors(tmp_path, small_model):
    model, _ = small_model
    good = save_model(model, tmp_path / "good.npz")
    with pytest.raises(InputError, match="not found"):
        load_model(tmp_path / "nope.npz")
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(b"this is not a zip file")
    with pytest.raises(InputError, match="readable"):
        load_model(bad)
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(good.read_bytes()[:200])
    with pytest.raises(InputError):
        load_model(trunc)
    with pytest.raises(InputError, match="unsupported model format"):
        load_model(_rewrite(good, tmp_path / "v9.npz", format=np.array("jaxcr.manifold/9")))
    with pytest.raises(InputError, match="no 'format'"):
        load_model(_rewrite(good, tmp_path / "nofmt.npz", format=None))
    with pytest.raises(InputError, match="pca_mean"):
        load_model(_rewrite(good, tmp_path / "shape.npz", pca_mean=np.zeros(7, np.float32)))
    with pytest.raises(InputError, match="manifold_features"):
        load_model(_rewrite(good, tmp_path / "nofeat.npz", manifold_features=None))
    with pytest.raises(InputError, match="config"):
        load_model(_rewrite(good, tmp_path / "cfg.npz", config=np.array("{not json")))
    with pytest.raises(InputError, match="view_centres"):
        load_model(_rewrite(good, tmp_path / "noc.npz", view_centres=None))
    with pytest.raises(InputError, match="view_centres"):
        load_model(_rewrite(good, tmp_path / "nanc.npz", view_centres=np.full((2, 2), np.nan)))
    with pytest.raises(InputError, match="finite"):
        f = np.asarray(model.manifold.features).copy()
        f[0, 0] = np.nan
        load_model(_rewrite(good, tmp_path / "nan.npz", manifold_features=f))


def test_model_file_version1_reads_as_region_centre(tmp_path, small_model):
    """A version-1 file (no view centres; per-frame centroids) still loads, as centre
    'region', and estimates the same."""
    model, desc = small_model
    good = save_model(model, tmp_path / "good.npz")
    with np.load(good) as z:
        cfg = json.loads(str(z["config"]))
    cfg.pop("centre")
    v1 = _rewrite(
        good,
        tmp_path / "v1.npz",
        format=np.array("jaxcr.manifold/1"),
        config=np.array(json.dumps(cfg)),
        view_centres=None,
    )
    back = load_model(v1)
    assert back.config.centre == "region" and back.view_centres is None
    psi = np.array([[0.5, 1.0]])
    np.testing.assert_allclose(estimate(back, desc(psi)), estimate(model, desc(psi)), atol=1e-7)


def test_train_bad_input():
    colour = ColourModel(jnp.zeros((5, 2)), jnp.asarray(0, jnp.int32))
    with pytest.raises(InputError, match="variance"):
        train(np.zeros((10, 4)), np.zeros((10, 2)), colour, TrainConfig(n_bins=2 * 4, variance=2.0))
    with pytest.raises(InputError, match="disagree"):
        train(np.zeros((10, 16)), np.zeros((9, 2)), colour, TrainConfig(n_bins=8))
    with pytest.raises(InputError, match="2 x n_bins"):
        train(np.zeros((10, 12)), np.zeros((10, 2)), colour, TrainConfig(n_bins=8))
    with pytest.raises(InputError, match="columns"):
        train(np.zeros((10, 16)), np.zeros((10, 3)), colour, TrainConfig(n_bins=8))
    with pytest.raises(InputError, match="view centres"):
        train(np.zeros((10, 16)), np.zeros((10, 2)), colour, TrainConfig(n_bins=8))
    with pytest.raises(InputError, match="centre"):
        TrainConfig(n_bins=8, centre="middle").check()
