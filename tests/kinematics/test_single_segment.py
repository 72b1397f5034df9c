"""SingleSegment (Reiter et al. eqs. 1-4): angle maps, forward kinematics, straight config."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jaxcr.kinematics.single_segment import SingleSegment, angles_to_rotation, rotation_to_angles

L = 0.04
_a2r = jax.jit(angles_to_rotation)
_r2a = jax.jit(rotation_to_angles)


@pytest.fixture(scope="module")
def robot():
    return SingleSegment.make(length=L, radius=2e-3, bending_stiffness=1e-3, n_points=33)


@pytest.fixture(scope="module")
def fwd(robot):
    return eqx.filter_jit(robot.forward)


def _reference_rotation(theta_L, delta):
    """Eq. 2 with scipy: Rz = exp(-delta [e3x]), Ry = exp((pi/2 - theta_L) [e2x])."""
    Rz = Rotation.from_rotvec([0, 0, -delta]).as_matrix()
    Ry = Rotation.from_rotvec([0, np.pi / 2 - theta_L, 0]).as_matrix()
    return Rz @ Ry @ Rz.T


@settings(derandomize=True, max_examples=60, deadline=None)
@given(
    theta_L=st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3), delta=st.floats(-np.pi + 1e-3, np.pi)
)
def test_angles_round_trip_over_workspace(theta_L, delta):
    R = np.asarray(_a2r(jnp.float32(theta_L), jnp.float32(delta)), np.float64)
    np.testing.assert_allclose(R, _reference_rotation(theta_L, delta), atol=2e-6)
    th, de = np.asarray(_r2a(jnp.asarray(R, jnp.float32)), np.float64)
    np.testing.assert_allclose(th, theta_L, atol=2e-5)
    # delta is conditioned by the bend sin(pi/2 - theta_L): compare on the circle.
    bend = np.sin(np.pi / 2 - theta_L)
    d_err = np.angle(np.exp(1j * (de - delta)))
    assert abs(d_err) * bend < 2e-5


def test_straight_configuration_is_finite_and_documented():
    R = _a2r(jnp.float32(np.pi / 2), jnp.float32(1.3))
    np.testing.assert_allclose(R, np.eye(3), atol=1e-6)
    th, de = _r2a(jnp.eye(3))
    assert float(th) == pytest.approx(np.pi / 2, abs=1e-7) and float(de) == 0.0
    # both Jacobians in one compiled program (run eagerly, ~50 operations were compiled
    # one by one)
    J, Jf = jax.jit(
        lambda R, q: (
            jax.jacrev(rotation_to_angles)(R),
            jax.jacfwd(lambda q: rotation_to_angles(angles_to_rotation(q[0], q[1])))(q),
        )
    )(jnp.eye(3), jnp.array([np.pi / 2, 0.7], jnp.float32))
    assert np.all(np.isfinite(J))
    assert np.all(np.isfinite(Jf))


def test_rotation_to_angles_gradient_matches_fd():
    with jax.enable_x64(True):
        f = jax.jit(lambda q: rotation_to_angles(angles_to_rotation(q[0], q[1])))
        q0 = jnp.array([0.4, -2.2])
        J = jax.jit(jax.jacfwd(f))(q0)
        np.testing.assert_allclose(J, np.eye(2), atol=1e-9)  # the maps are inverse
        eps = 1e-6
        fd = np.stack([(f(q0 + eps * e) - f(q0 - eps * e)) / (2 * eps) for e in jnp.eye(2)], 1)
        np.testing.assert_allclose(J, fd, atol=1e-7)


@pytest.mark.parametrize("q", [(0.3, -2.0), (np.pi / 2, 0.0), (-np.pi / 2, 1.0), (1.2, 3.0)])
def test_forward_tip_frame_and_arc(fwd, q):
    theta_L, delta = q
    res = fwd(jnp.asarray(q, jnp.float32))
    np.testing.assert_allclose(res.centreline.R[-1], _reference_rotation(theta_L, delta), atol=2e-6)
    # Circular arc of bend b in the plane spanned by e3 and d = (cos delta, -sin delta, 0).
    b = np.pi / 2 - theta_L
    s = np.asarray(res.centreline.s, np.float64)
    d = np.array([np.cos(delta), -np.sin(delta), 0.0])
    if abs(b) < 1e-9:
        ref = s[:, None] * np.array([0, 0, 1.0])
    else:
        r = L / b
        ang = s / r
        ref = r * (1 - np.cos(ang))[:, None] * d + (r * np.sin(ang))[:, None] * np.array(
            [0, 0, 1.0]
        )
    np.testing.assert_allclose(res.centreline.p, ref, atol=1e-7)
    np.testing.assert_allclose(s[-1], L, rtol=1e-7)
    assert bool(res.ok) and res.state.shape == (0,)
    np.testing.assert_allclose(res.energy, 0.5 * 1e-3 * b**2 / L, rtol=1e-5)
    np.testing.assert_allclose(res.centreline.rho, 2e-3)


def test_gradient_at_straight_is_finite_and_matches_fd():
    with jax.enable_x64(True):
        robot = SingleSegment.make(length=L, radius=2e-3, n_points=9, dtype=jnp.float64)

        def tip_fn(q):
            return robot.forward(q).centreline.p[-1]

        # the tip and its Jacobian in one compiled program (one compile instead of two)
        both = jax.jit(lambda q: (tip_fn(q), jax.jacfwd(tip_fn)(q)))

        def tip(q):
            return both(q)[0]

        def jac(q):
            return both(q)[1]

        for q0 in (jnp.array([np.pi / 2, 0.4]), jnp.array([0.2, 2.0])):
            J = jac(q0)
            assert np.all(np.isfinite(J))
            eps = 1e-6
            fd = np.stack(
                [(tip(q0 + eps * e) - tip(q0 - eps * e)) / (2 * eps) for e in jnp.eye(2)], 1
            )
            np.testing.assert_allclose(J, fd, atol=1e-9)
        # Straight: d tip / d theta_L = -(L/2) d (first-order arc sag); d/d delta = 0.
        J = jac(jnp.array([np.pi / 2, 0.4]))
        np.testing.assert_allclose(
            J[:, 0], -(L / 2) * np.array([np.cos(0.4), -np.sin(0.4), 0]), atol=1e-12
        )
        np.testing.assert_allclose(J[:, 1], 0.0, atol=1e-12)
    robot32 = SingleSegment.make(length=L, radius=2e-3, n_points=5)
    # compiled (run eagerly, its ~30 operations were compiled one by one)
    g = eqx.filter_jit(jax.grad(lambda q, m: jnp.sum(m.forward(q).centreline.p)))(
        jnp.array([np.pi / 2, 0.0]), robot32
    )
    assert np.all(np.isfinite(g))


def test_vmap_loop_jit_eager_single_trace(robot, fwd):
    qs = jnp.asarray(
        np.random.default_rng(0).uniform([-1.5, -3.1], [1.5, 3.1], size=(5, 2)), jnp.float32
    )

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def batch(model, q):
        return jax.vmap(model.forward)(q)

    out = batch(robot, qs)
    batch(robot, qs + 0.01)  # same shape: no second trace
    for i in range(5):
        eager = robot.forward(qs[i])
        np.testing.assert_allclose(out.centreline.p[i], eager.centreline.p, atol=1e-7)
        np.testing.assert_allclose(fwd(qs[i]).centreline.R, eager.centreline.R, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        robot.forward(jnp.zeros(3))
