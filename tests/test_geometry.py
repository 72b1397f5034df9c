"""Geometry helpers against closed forms and scipy's Rotation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.geometry import hat, kabsch, so3_exp, so3_left_jacobian, so3_log, umeyama, vee


def test_hat_vee_roundtrip_and_cross():
    w = jnp.array([0.3, -1.2, 2.0])
    v = jnp.array([1.0, 0.5, -0.7])
    np.testing.assert_allclose(hat(w) @ v, np.cross(w, v), atol=1e-6)
    np.testing.assert_allclose(vee(hat(w)), w, atol=1e-7)


@pytest.mark.parametrize("w", [[0.0, 0.0, 0.0], [1e-6, 0, 0], [0.3, -0.2, 0.1], [2.0, 1.0, -0.5]])
def test_exp_log_against_scipy(w):
    w = np.array(w)
    R_ref = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(so3_exp(jnp.array(w)), R_ref, atol=1e-6)
    np.testing.assert_allclose(so3_log(jnp.array(R_ref, jnp.float32)), w, atol=1e-5)


def test_log_near_pi():
    w = np.array([0.0, 3.1, 0.2])
    R = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(so3_log(jnp.array(R, jnp.float32)), w, atol=1e-4)


def test_gradients_finite_at_zero():
    for f in (so3_exp, so3_left_jacobian):
        g = jax.jacfwd(f)(jnp.zeros(3))
        assert np.all(np.isfinite(g))
        g = jax.jacrev(f)(jnp.zeros(3))
        assert np.all(np.isfinite(g))
    g = jax.grad(lambda w: so3_log(so3_exp(w)).sum())(jnp.zeros(3))
    np.testing.assert_allclose(g, np.ones(3), atol=1e-5)


def test_left_jacobian_is_integral_of_exp():
    w = np.array([0.4, -0.9, 0.3])
    ts = np.linspace(0.0, 1.0, 2001)
    ref = np.trapezoid([Rotation.from_rotvec(t * w).as_matrix() for t in ts], ts, axis=0)
    np.testing.assert_allclose(so3_left_jacobian(jnp.array(w)), ref, atol=1e-6)


def test_kabsch_and_umeyama_recover_transform():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.2, -0.5, 1.0]).as_matrix()
    t = np.array([0.1, -0.2, 0.3])
    Q = P @ R.T + t
    T = kabsch(jnp.array(P), jnp.array(Q))
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-5)
    np.testing.assert_allclose(T[:3, 3], t, atol=1e-5)
    R2, t2, c = umeyama(jnp.array(P), jnp.array(2.5 * Q), with_scale=True)
    np.testing.assert_allclose(c, 2.5, rtol=1e-5)
    np.testing.assert_allclose(R2, R, atol=1e-5)
