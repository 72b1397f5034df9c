"""PCA vs numpy SVD (Reiter et al. eq. 5) and the thin-plate smoothing spline vs
scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline", smoothing=...)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from jaxcr.eigen.pca import components_for_variance, fit_pca, project
from jaxcr.eigen.tps import evaluate_tps, fit_tps, tps_kernel
from jaxcr.errors import InputError


def _data(n=200, m=40, seed=0):
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(n, 5)) * np.array([5.0, 3.0, 2.0, 1.0, 0.5])
    A = rng.normal(size=(5, m))
    return (Z @ A + 0.05 * rng.normal(size=(n, m)) + 1.0).astype(np.float32)


def test_pca_matches_numpy_svd():
    X = _data()
    p = fit_pca(jnp.asarray(X))
    Xc = X.astype(np.float64) - X.mean(0)
    _, s, vt = np.linalg.svd(Xc, full_matrices=False)
    np.testing.assert_allclose(np.asarray(p.variance), s**2 / (len(X) - 1), rtol=2e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(p.mean), X.mean(0), atol=1e-5)
    # Directions equal up to sign (sign fixed by our convention) for the separated ones.
    for j in range(5):
        ours, ref = np.asarray(p.components[:, j]), vt[j]
        assert min(np.abs(ours - ref).max(), np.abs(ours + ref).max()) < 1e-3
        assert ours[np.argmax(np.abs(ours))] > 0
    # eq. 5 and orthonormality.
    k = components_for_variance(p, 0.9)
    E = p.truncate(k)
    L = np.asarray(jax.vmap(project, in_axes=(None, 0))(E, jnp.asarray(X)))
    np.testing.assert_allclose(L, (X - X.mean(0)) @ np.asarray(E.components), atol=1e-3)
    np.testing.assert_allclose(np.asarray(p.components.T @ p.components), np.eye(40), atol=1e-5)


def test_components_for_variance_closed_form():
    X = _data()
    p = fit_pca(jnp.asarray(X))
    v = np.asarray(p.variance, np.float64)
    c = np.cumsum(v) / v.sum()
    for f in (0.65, 0.85, 0.9, 0.95, 1.0):
        k = components_for_variance(p, f)
        assert c[k - 1] >= f - 1e-6 and (k == 1 or c[k - 2] < f)
    with pytest.raises(InputError):
        components_for_variance(p, 1.5)
    with pytest.raises(InputError):
        fit_pca(jnp.ones((1, 4)))


def _spline_data(n=150, k=3, seed=1):
    rng = np.random.default_rng(seed)
    x = np.stack([rng.uniform(0.1, 1.4, n), rng.uniform(0, np.pi, n)], 1)
    y = np.stack([np.sin(2 * x[:, 0]) * np.cos(x[:, 1]), x[:, 0] * x[:, 1], np.exp(-x[:, 1])], 1)[
        :, :k
    ]
    return x, y + 0.01 * rng.normal(size=y.shape)


@pytest.mark.parametrize("smoothing", [0.0, 1e-3, 0.1])
def test_tps_matches_scipy_rbf(smoothing):
    x, y = _spline_data()
    rng = np.random.default_rng(2)
    xq = np.stack([rng.uniform(0.1, 1.4, 300), rng.uniform(0, np.pi, 300)], 1)
    ref = RBFInterpolator(x, y, kernel="thin_plate_spline", smoothing=smoothing)(xq)
    # float64 solve: agrees to solver precision.
    with jax.enable_x64(True):
        s64 = fit_tps(jnp.asarray(x), jnp.asarray(y), smoothing)
        got64 = np.asarray(evaluate_tps(s64, jnp.asarray(xq), chunk=128))
    np.testing.assert_allclose(got64, ref, atol=1e-8)
    # float32 (the default) with iterative refinement: within 2e-3 of the data range (~2).
    s32 = fit_tps(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32), smoothing)
    got32 = np.asarray(evaluate_tps(s32, jnp.asarray(xq, jnp.float32), chunk=128))
    np.testing.assert_allclose(got32, ref, atol=2e-3)


def test_tps_3d_matches_scipy():
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.03, 0.03, (120, 3))
    y = np.stack([np.sin(60 * x[:, 0]) + x[:, 2] * 20, x[:, 1] * 30], 1)
    ref = RBFInterpolator(x, y, kernel="thin_plate_spline", smoothing=1e-6)(x[:20] + 1e-3)
    with jax.enable_x64(True):
        s = fit_tps(jnp.asarray(x), jnp.asarray(y), 1e-6)
        got = np.asarray(evaluate_tps(s, jnp.asarray(x[:20] + 1e-3)))
    np.testing.assert_allclose(got, ref, atol=1e-6)


def test_tps_interpolates_and_vmap_jit():
    x, y = _spline_data(60)
    s = fit_tps(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32), 0.0)
    loop = np.stack([np.asarray(s(jnp.asarray(xi, jnp.float32))) for xi in x[:10]])
    np.testing.assert_allclose(loop, y[:10], atol=2e-3)
    batch = np.asarray(evaluate_tps(s, jnp.asarray(x[:10], jnp.float32), chunk=4))
    np.testing.assert_allclose(batch, loop, atol=2e-5)  # float32 summation order
    jitted = np.asarray(eqx.filter_jit(lambda sp, z: sp(z))(s, jnp.asarray(x[3], jnp.float32)))
    np.testing.assert_allclose(jitted, loop[3], atol=2e-5)
    f = eqx.filter_jit(eqx.debug.assert_max_traces(lambda sp, z: sp(z), max_traces=1))
    for xi in x[:5]:
        f(s, jnp.asarray(xi, jnp.float32))


def test_tps_gradient_vs_finite_differences_and_at_centre():
    x, y = _spline_data(40)
    with jax.enable_x64(True):
        s = fit_tps(jnp.asarray(x), jnp.asarray(y), 1e-3)
        p_np = np.array([0.7, 1.3])
        p = jnp.asarray(p_np)
        # compiled (eagerly, the Jacobians and the spline compiled their operations one by one)
        J = np.asarray(eqx.filter_jit(lambda s, p: jax.jacfwd(s)(p))(s, p))
        value = eqx.filter_jit(lambda s, p: s(p))
        eps = 1e-6
        fd = np.stack(
            [
                (np.asarray(value(s, p_np + eps * e)) - np.asarray(value(s, p_np - eps * e)))
                / (2 * eps)
                for e in np.eye(2)
            ],
            axis=1,
        )
        np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-7)
        # Exactly at a centre (r = 0): finite gradient (double where in the kernel).
        Jc = np.asarray(eqx.filter_jit(lambda s, p: jax.jacrev(s)(p))(s, jnp.asarray(x[0])))
        assert np.all(np.isfinite(Jc))
    g = jax.jit(jax.grad(tps_kernel))(0.0)
    assert np.isfinite(g) and float(tps_kernel(jnp.asarray(0.0))) == 0.0


def test_tps_bad_input():
    with pytest.raises(InputError):
        fit_tps(jnp.zeros((3, 2)), jnp.zeros((3, 1)))
    with pytest.raises(InputError):
        fit_tps(jnp.zeros((10, 2)), jnp.zeros((9, 1)))
    with pytest.raises(InputError):
        fit_tps(jnp.ones((10, 2)) * jnp.arange(10)[:, None], jnp.zeros((10, 1)), -1.0)
