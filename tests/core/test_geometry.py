"""Geometry helpers against closed forms and scipy's Rotation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from jaxcr.geometry import (
    hat,
    invert_transform,
    kabsch,
    make_transform,
    orthonormalize,
    rot_x,
    rot_y,
    rot_z,
    se3_exp,
    so3_exp,
    so3_left_jacobian,
    so3_log,
    transform_points,
    umeyama,
    vee,
)


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
        assert np.all(np.isfinite(jax.jit(jax.jacfwd(f))(jnp.zeros(3))))
        assert np.all(np.isfinite(jax.jit(jax.jacrev(f))(jnp.zeros(3))))
    g = jax.jit(jax.grad(lambda w: so3_log(so3_exp(w)).sum()))(jnp.zeros(3))
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


# ---------------------------------------------------------------------------------------------
# Property tests and the standard kit (jit, vmap, gradients) — added by the kinematics owner.
# ---------------------------------------------------------------------------------------------

_exp_jit = jax.jit(so3_exp)
_log_jit = jax.jit(so3_log)
_rotvec = arrays(np.float64, (3,), elements=st.floats(-4.0, 4.0))


@settings(derandomize=True, max_examples=60, deadline=None)
@given(w=_rotvec)
def test_exp_is_orthonormal_and_matches_scipy_property(w):
    R = np.asarray(_exp_jit(jnp.asarray(w, jnp.float32)), np.float64)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=2e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=2e-6)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=2e-6)


@settings(derandomize=True, max_examples=60, deadline=None)
@given(w=_rotvec)
def test_log_exp_round_trip_property(w):
    # Canonical rotation vector (angle in [0, pi)); skip the measure-zero band right at pi.
    theta = np.linalg.norm(w)
    if theta > np.pi:
        w = w * (1.0 - 2.0 * np.pi / theta)
        theta = np.linalg.norm(w)
    if abs(theta - np.pi) < 1e-3:
        return
    R = Rotation.from_rotvec(w).as_matrix()
    w_back = np.asarray(_log_jit(jnp.asarray(R, jnp.float32)), np.float64)
    np.testing.assert_allclose(w_back, w, atol=1e-5)
    np.testing.assert_allclose(Rotation.from_rotvec(w_back).as_matrix(), R, atol=2e-5)


@pytest.mark.parametrize("axis, fn", [(0, rot_x), (1, rot_y), (2, rot_z)])
def test_elementary_rotations_match_scipy(axis, fn):
    for a in (-2.5, 0.0, 0.7):
        e = np.zeros(3)
        e[axis] = a
        np.testing.assert_allclose(
            fn(jnp.float32(a)), Rotation.from_rotvec(e).as_matrix(), atol=1e-6
        )


def test_se3_exp_matches_matrix_exponential():
    xi = np.array([0.1, -0.3, 0.2, 0.5, -1.1, 0.7])
    X = np.zeros((4, 4))
    X[:3, :3] = np.asarray(hat(jnp.asarray(xi[3:])))
    X[:3, 3] = xi[:3]
    np.testing.assert_allclose(se3_exp(jnp.asarray(xi, jnp.float32)), expm(X), atol=1e-6)


def test_transforms_invert_and_apply():
    R = Rotation.from_rotvec([0.3, 0.2, -0.9]).as_matrix()
    t = np.array([0.5, -0.1, 2.0])
    T = make_transform(jnp.asarray(R, jnp.float32), jnp.asarray(t, jnp.float32))
    np.testing.assert_allclose(T @ invert_transform(T), np.eye(4), atol=1e-6)
    P = np.random.default_rng(3).normal(size=(7, 3))
    np.testing.assert_allclose(
        transform_points(T, jnp.asarray(P, jnp.float32)), P @ R.T + t, atol=1e-5
    )


def test_orthonormalize_returns_rotation_near_input():
    R = Rotation.from_rotvec([0.4, -0.2, 0.1]).as_matrix()
    noisy = R + 1e-3 * np.random.default_rng(4).normal(size=(3, 3))
    Q = np.asarray(orthonormalize(jnp.asarray(noisy, jnp.float32)), np.float64)
    np.testing.assert_allclose(Q.T @ Q, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-6)
    np.testing.assert_allclose(Q, R, atol=5e-3)


def test_jit_equals_eager_and_vmap_equals_loop():
    W = np.random.default_rng(5).normal(size=(6, 3)).astype(np.float32)
    for f in (so3_exp, so3_left_jacobian, hat):
        batched = jax.jit(jax.vmap(f))(jnp.asarray(W))
        for i in range(len(W)):
            np.testing.assert_allclose(batched[i], f(jnp.asarray(W[i])), atol=1e-6)
    Rs = jax.vmap(so3_exp)(jnp.asarray(W))
    logs = jax.vmap(so3_log)(Rs)
    for i in range(len(W)):
        np.testing.assert_allclose(logs[i], so3_log(Rs[i]), atol=1e-6)


def test_gradients_match_finite_differences():
    with jax.enable_x64(True):
        w0 = jnp.array([0.3, -0.7, 0.4])
        v = jnp.array([0.2, 0.5, -1.0])
        for f in (
            lambda w: so3_exp(w) @ v,
            lambda w: so3_left_jacobian(w) @ v,
            lambda w: so3_log(so3_exp(w) @ so3_exp(v / 4)),
        ):
            f = jax.jit(f)
            J = jax.jit(jax.jacfwd(f))(w0)
            np.testing.assert_allclose(J, jax.jit(jax.jacrev(f))(w0), atol=1e-10)
            eps = 1e-6
            fd = np.stack(
                [(f(w0 + eps * e) - f(w0 - eps * e)) / (2 * eps) for e in jnp.eye(3)], axis=1
            )
            np.testing.assert_allclose(J, fd, atol=1e-8)


def test_exp_derivative_is_left_jacobian():
    # d/dt exp(w + t d) at t=0 equals hat(J_l(w) d) exp(w) (left-trivialised derivative).
    with jax.enable_x64(True):
        w = jnp.array([0.5, 0.2, -0.8])
        d = jnp.array([0.1, -0.3, 0.6])
        dR = jax.jvp(so3_exp, (w,), (d,))[1]
        np.testing.assert_allclose(dR, hat(so3_left_jacobian(w) @ d) @ so3_exp(w), atol=1e-12)


@pytest.mark.parametrize(
    "theta", [1e-5, 1e-4, 1.2e-4, 1e-3, 1.6e-3, 1e-2, 0.1, 0.49, 0.51, 1.0, 2.5]
)
def test_float32_accuracy_across_small_angles(theta):
    # Regression: (1 - cos t)/t^2 and (t - sin t)/t^3 evaluated directly lose ~5% in float32 at
    # t ~ 1e-3 (a 1e-6 m tip error on a 0.19 m constant-curvature robot). Reference: float64.
    a = np.array([0.3, -0.5, 0.8])
    w = a / np.linalg.norm(a) * theta
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    J = np.eye(3) + (1 - np.cos(theta)) / theta**2 * W + (theta - np.sin(theta)) / theta**3 * W @ W
    w32 = jnp.asarray(w, jnp.float32)
    np.testing.assert_allclose(so3_left_jacobian(w32), J, atol=1e-7)
    np.testing.assert_allclose(so3_exp(w32), Rotation.from_rotvec(w).as_matrix(), atol=3e-7)


@pytest.mark.parametrize("gap", [1e-4, 5e-4, 1.4e-3, 1e-2])
def test_log_float32_close_to_pi(gap):
    # Regression: angles within 1.4e-3 rad of pi used to come back as exactly pi.
    axis = np.array([0.48, -0.6, 0.64])
    w = axis / np.linalg.norm(axis) * (np.pi - gap)
    R = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(so3_log(jnp.asarray(R, jnp.float32)), w, atol=2e-6)
