"""Centreline integrator (Watson et al. eq. 1) against solve_ivp, closed-form arcs, invariants."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.integrate import solve_ivp

from jaxcr.geometry import hat
from jaxcr.kinematics.cosserat import (
    Centreline,
    integrate_centreline,
    integrate_steps,
    integrate_steps_doubling,
    perturb_centreline,
)

M = 16  # steps in the fixed-shape tests (one compile for the hypothesis tests)


@pytest.fixture(scope="module")
def steps_jit():
    return jax.jit(integrate_steps)


def _ode_reference(u_fn, L):
    """p' = R e3, R' = R hat(u(s)) from the origin with scipy's DOP853, tight tolerances (f64)."""
    R0, p0 = np.eye(3), np.zeros(3)

    def rhs(s, y):
        R = y[3:].reshape(3, 3)
        u = u_fn(s)
        U = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        return np.concatenate([R[:, 2], (R @ U).ravel()])

    y0 = np.concatenate([p0, R0.ravel()])
    sol = solve_ivp(rhs, (0.0, L), y0, method="DOP853", rtol=1e-12, atol=1e-14)
    return sol.y[:3, -1], sol.y[3:, -1].reshape(3, 3)


def test_varying_curvature_matches_solve_ivp(steps_jit):
    # u(s) = (a sin(b s), c, d s): torsion-free but non-planar and varying along s.
    a, b, c, d, L = 12.0, 40.0, -8.0, 300.0, 0.1
    u_fn = lambda s: np.array([a * np.sin(b * s), c, d * s])  # noqa: E731
    p_ref, R_ref = _ode_reference(u_fn, L)
    with jax.enable_x64(True):
        n = 2001
        s = np.linspace(0.0, L, n)
        mid = 0.5 * (s[1:] + s[:-1])
        u_steps = np.stack([u_fn(x) for x in mid])
        p, R = steps_jit(jnp.asarray(u_steps), jnp.asarray(np.diff(s)))
        # Midpoint curvature per exact SO(3) step: global error O(h^2), h = 5e-5 m.
        np.testing.assert_allclose(p[-1], p_ref, atol=1e-8)
        np.testing.assert_allclose(R[-1], R_ref, atol=1e-7)
        # Convergence order: 4x fewer steps -> about 16x larger error.
        n2 = 501
        s2 = np.linspace(0.0, L, n2)
        u2 = np.stack([u_fn(x) for x in 0.5 * (s2[1:] + s2[:-1])])
        # padded with zero-length steps to the shape above (one compiled program): a step
        # of length 0 is the identity motion, exactly (exp(0) = I, J(0) 0 e3 = 0)
        pad = n - n2
        u2 = np.concatenate([u2, np.zeros((pad, 3))])
        p2, _ = steps_jit(jnp.asarray(u2), jnp.asarray(np.r_[np.diff(s2), np.zeros(pad)]))
        e1 = np.linalg.norm(np.asarray(p[-1]) - p_ref)
        e2 = np.linalg.norm(np.asarray(p2[-1]) - p_ref)
        assert 8.0 < e2 / e1 < 32.0
    # And in float32 it is still accurate to micrometres.
    p32, R32 = steps_jit(jnp.asarray(u_steps, jnp.float32), jnp.asarray(np.diff(s), jnp.float32))
    np.testing.assert_allclose(p32[-1], p_ref, atol=2e-6)


@pytest.mark.parametrize("k", [0.0, 1e-5, 5.0, 60.0])
def test_constant_curvature_is_closed_form_arc(k):
    L, n = 0.08, 9
    s = jnp.linspace(0.0, L, n)
    cl = integrate_centreline(s, jnp.tile(jnp.array([0.0, k, 0.0]), (n - 1, 1)), jnp.full(n, 1e-3))
    s_np = np.asarray(s, np.float64)
    if k == 0.0:
        ref = np.stack([0 * s_np, 0 * s_np, s_np], 1)
    else:
        ref = np.stack([(1 - np.cos(k * s_np)) / k, 0 * s_np, np.sin(k * s_np) / k], 1)
    np.testing.assert_allclose(cl.p, ref, atol=1e-7)
    ang = k * s_np
    Rref = np.stack(
        [np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]]) for t in ang]
    )
    np.testing.assert_allclose(cl.R, Rref, atol=1e-6)
    assert cl.p.shape == (n, 3) and cl.R.shape == (n, 3, 3) and cl.u.shape == (n, 3)
    np.testing.assert_allclose(cl.tip_position, cl.p[-1])
    np.testing.assert_allclose(cl.tip_rotation, cl.R[-1])


@settings(derandomize=True, max_examples=30, deadline=None)
@given(
    u=arrays(np.float64, (M, 3), elements=st.floats(-200.0, 200.0)),
    h=arrays(np.float64, (M,), elements=st.floats(0.0, 0.02)),
)
def test_frames_orthonormal_property(steps_jit, u, h):
    p, R = steps_jit(jnp.asarray(u, jnp.float32), jnp.asarray(h, jnp.float32))
    RtR = np.einsum("nji,njk->nik", np.asarray(R, np.float64), np.asarray(R, np.float64))
    np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(3), RtR.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(np.asarray(R, np.float64)), 1.0, atol=1e-5)
    # Unit-speed curve: chord of each step never exceeds its arclength.
    chord = np.linalg.norm(np.diff(np.asarray(p, np.float64), axis=0), axis=1)
    assert np.all(chord <= h * (1 + 1e-5) + 1e-7)  # float32 positions: ~1e-8 m rounding


@settings(derandomize=True, max_examples=20, deadline=None)
@given(
    h=arrays(np.float64, (M,), elements=st.floats(0.0, 0.02)),
    w=arrays(np.float64, (3,), elements=st.floats(-3.0, 3.0)),
    p0=arrays(np.float64, (3,), elements=st.floats(-1.0, 1.0)),
)
def test_zero_curvature_is_straight_property(steps_jit, h, w, p0):
    from scipy.spatial.transform import Rotation

    R0 = Rotation.from_rotvec(w).as_matrix()
    p, R = steps_jit(
        jnp.zeros((M, 3), jnp.float32),
        jnp.asarray(h, jnp.float32),
        jnp.asarray(p0, jnp.float32),
        jnp.asarray(R0, jnp.float32),
    )
    s = np.concatenate([[0.0], np.cumsum(h)])
    np.testing.assert_allclose(p, p0 + s[:, None] * R0[:, 2], atol=1e-5)
    np.testing.assert_allclose(R, np.broadcast_to(R0, (M + 1, 3, 3)), atol=1e-6)


def test_jit_equals_eager_and_vmap_equals_loop():
    # 6 steps, not M: the eager reference compiles every primitive of the associative scan
    # on its own, once per operand shape, and the scan's levels (their slice shapes) grow
    # with log2 of the steps (16 steps: 10.1 CPU-s, 6: 6.8, in two loaded runs). 6, not
    # a power of two, also takes the scan's odd-length path, which 16 did not.
    m = 6
    rng = np.random.default_rng(0)
    u = jnp.asarray(rng.normal(scale=20.0, size=(5, m, 3)), jnp.float32)
    h = jnp.full((m,), 0.005, jnp.float32)
    with jax.disable_jit():  # integrate_steps is jitted: the eager path, op by op
        eager = [integrate_steps(u[i], h) for i in range(2)]
    eager += [integrate_steps(u[i], h) for i in range(2, 5)]
    p_v, R_v = jax.vmap(integrate_steps, in_axes=(0, None))(u, h)
    p_j, R_j = jax.jit(jax.vmap(integrate_steps, in_axes=(0, None)))(u, h)
    for i in range(5):
        np.testing.assert_allclose(p_v[i], eager[i][0], atol=1e-7)
        np.testing.assert_allclose(R_v[i], eager[i][1], atol=1e-6)
        np.testing.assert_allclose(p_j[i], eager[i][0], atol=1e-7)
        np.testing.assert_allclose(R_j[i], eager[i][1], atol=1e-6)


def test_vmapped_integration_compiles_once():
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def batch(u, h):
        return jax.vmap(integrate_steps, in_axes=(0, None))(u, h)

    h = jnp.full((M,), 0.005, jnp.float32)
    batch(jnp.zeros((4, M, 3), jnp.float32), h)
    batch(jnp.ones((4, M, 3), jnp.float32), h)  # second batch, same shape: no retrace


# Steps of the gradient tests: the programs differentiate the associative scan, whose size
# grows with its levels (log2 of the steps); 6 steps (3 levels, not a power of two: the odd-
# length path too) instead of M = 16 (4 levels) for the same checks.
M_GRAD = 6


def test_gradient_matches_finite_differences():
    with jax.enable_x64(True):
        rng = np.random.default_rng(1)
        u0 = jnp.asarray(rng.normal(scale=10.0, size=(M_GRAD, 3)))
        h = jnp.full((M_GRAD,), 0.004)

        def tip(u):
            return integrate_steps(u, h)[0][-1]

        # the tip and both Jacobians in one compiled program (one compile instead of three)
        both = jax.jit(lambda u: (tip(u), jax.jacfwd(tip)(u), jax.jacrev(tip)(u)))
        _, J, Jr = both(u0)
        np.testing.assert_allclose(J, Jr, atol=1e-12)
        eps = 1e-6
        for idx in [(0, 0), (2, 1), (4, 2), (M_GRAD - 1, 0)]:
            e = jnp.zeros_like(u0).at[idx].set(eps)
            fd = (both(u0 + e)[0] - both(u0 - e)[0]) / (2 * eps)
            np.testing.assert_allclose(J[:, idx[0], idx[1]], fd, atol=1e-9)


def test_gradient_finite_at_zero_curvature_and_matches_small_bend():
    h = jnp.full((M_GRAD,), 0.005, jnp.float32)
    f = lambda u: integrate_steps(u, h)[0][-1]  # noqa: E731
    J = jax.jit(jax.jacrev(f))(jnp.zeros((M_GRAD, 3), jnp.float32))
    assert np.all(np.isfinite(J))
    # d tip_x / d u_y of step k at a straight rod: h * (L - s_mid_k) (lever arm), exact.
    s = np.arange(M_GRAD + 1) * 0.005
    lever = 0.005 * (s[-1] - 0.5 * (s[1:] + s[:-1]))
    np.testing.assert_allclose(J[0, :, 1], lever, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(J[1, :, 0], -lever, rtol=1e-5, atol=1e-9)


def test_perturb_centreline():
    # compiled (run eagerly, their operations were compiled one by one)
    integrate, perturb = jax.jit(integrate_centreline), jax.jit(perturb_centreline)
    n = 11
    s = jnp.linspace(0.0, 0.1, n)
    u = jnp.tile(jnp.array([0.0, 10.0, 0.0]), (n - 1, 1))
    base = integrate(s, u, jnp.full(n, 1e-3))
    assert isinstance(base, Centreline)
    same = perturb(base, jnp.zeros((n - 1, 3)))
    np.testing.assert_allclose(same.p, base.p, atol=1e-7)
    du = jnp.tile(jnp.array([0.0, 5.0, 0.0]), (n - 1, 1))
    pert = perturb(base, du)
    ref = integrate(s, u + du, base.rho)
    np.testing.assert_allclose(pert.p, ref.p, atol=1e-7)
    np.testing.assert_allclose(pert.u[1:], u + du)
    # Perturbation starts from the base pose even when that pose is not the origin.
    moved = Centreline(s=s, p=base.p + 1.0, R=base.R, u=base.u, rho=base.rho)
    np.testing.assert_allclose(perturb(moved, du).p, ref.p + 1.0, atol=1e-6)


def test_hat_used_consistently_with_ode_reference():
    # The reference ODE's skew matrix equals jaxcr's hat (guards a sign slip in the test).
    u = np.array([0.3, -1.0, 2.0])
    U = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    np.testing.assert_allclose(hat(jnp.asarray(u)), U, atol=1e-7)


def test_doubling_integration_matches_associative_scan():
    # integrate_steps_doubling (the refinement's integrator) forms the same prefix products
    # as integrate_steps (validated against scipy's ODE solution above) in another order:
    # both are products of the same unit-norm factors, so in float32 they differ by
    # rounding only, ~ (log2 m + 1) * eps32 * |p| per product chain, < 1e-6 m here.
    # 12 steps (not a power of two: both integrators' uneven last round and level), not 40:
    # the program holds both integrations and both gradients, whose size grows with the
    # rounds/levels (log2 m), and the rounding argument does not depend on m.
    a, b, c, d, L = 12.0, 40.0, -8.0, 300.0, 0.1
    n = 13
    s = np.linspace(0.0, L, n)
    mid = 0.5 * (s[1:] + s[:-1])
    u = jnp.asarray(np.stack([a * np.sin(b * mid), np.full_like(mid, c), d * mid], -1), jnp.float32)
    ds = jnp.asarray(np.diff(s), jnp.float32)
    p0 = jnp.array([0.01, -0.02, 0.03], jnp.float32)
    R0 = jnp.asarray(np.linalg.qr(np.ones((3, 3)) + np.eye(3))[0], jnp.float32)
    # both integrations and both tip gradients (what the refinement differentiates) in one
    # compiled program (instead of three)
    (p_d, R_d), (p_a, R_a), tip_d, tip_a = jax.jit(
        lambda u: (
            integrate_steps_doubling(u, ds, p0, R0),
            integrate_steps(u, ds, p0, R0),
            jax.jacrev(lambda v: integrate_steps_doubling(v, ds, p0, R0)[0][-1])(u),
            jax.jacrev(lambda v: integrate_steps(v, ds, p0, R0)[0][-1])(u),
        )
    )(u)
    np.testing.assert_allclose(p_d, p_a, atol=1e-6)
    np.testing.assert_allclose(R_d, R_a, atol=2e-6)
    # the gradients: same rounding argument
    np.testing.assert_allclose(tip_d, tip_a, atol=1e-7)
