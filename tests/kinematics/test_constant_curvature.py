"""ConstantCurvature against an independent numpy Webster & Jones (2010) transform chain."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxcr.kinematics.base import FkResult
from jaxcr.kinematics.constant_curvature import ConstantCurvature

N = 31


def wj_transform(kappa, phi, length):
    """Webster & Jones 2010 eq. 1, written out entry by entry (float64)."""
    c, s = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa * length), np.sin(kappa * length)
    if abs(kappa) < 1e-9:  # series (also avoids denormal kappa): sag kappa L^2 / 2
        p = np.array([c * kappa * length**2 / 2, s * kappa * length**2 / 2, length])
    else:
        p = np.array([c * (1 - ck) / kappa, s * (1 - ck) / kappa, sk / kappa])
    R = np.array(
        [
            [c * c * (ck - 1) + 1, s * c * (ck - 1), c * sk],
            [s * c * (ck - 1), c * c * (1 - ck) + ck, s * sk],
            [-c * sk, -s * sk, ck],
        ]
    )
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def wj_chain(kappas, phis, lengths):
    Ts, T = [np.eye(4)], np.eye(4)
    for k, f, L in zip(kappas, phis, lengths, strict=True):
        T = T @ wj_transform(k, f, L)
        Ts.append(T)
    return Ts


@pytest.fixture(scope="module")
def robot():
    return ConstantCurvature.make(
        length=[0.05, 0.04, 0.03], radius=[3e-3, 2.5e-3, 2e-3], n_points=N
    )


@pytest.fixture(scope="module")
def fwd(robot):
    return eqx.filter_jit(robot.forward)


def _q(kappas, phis, lengths):
    return jnp.asarray(np.stack([kappas, phis, lengths], 1).ravel(), jnp.float32)


@pytest.mark.parametrize(
    "kappas, phis",
    [
        ([10.0, -15.0, 30.0], [0.3, 2.0, -1.0]),
        ([0.0, 0.0, 0.0], [0.0, 1.0, 2.0]),
        ([25.0, 0.0, 1e-4], [-2.5, 0.4, 0.9]),
    ],
)
def test_matches_webster_jones_chain(fwd, robot, kappas, phis):
    lengths = [0.05, 0.04, 0.03]
    res = fwd(_q(kappas, phis, lengths))
    assert isinstance(res, FkResult)
    Ts = wj_chain(kappas, phis, lengths)
    np.testing.assert_allclose(res.centreline.p[-1], Ts[-1][:3, 3], atol=1e-6)
    np.testing.assert_allclose(res.centreline.R[-1], Ts[-1][:3, :3], atol=2e-6)
    # Section boundaries are samples: 30 steps over 3 sections -> samples 10, 20, 30.
    for i, idx in enumerate([0, 10, 20, 30]):
        np.testing.assert_allclose(res.centreline.s[idx], sum(lengths[:i]), atol=1e-8)
        np.testing.assert_allclose(res.centreline.p[idx], Ts[i][:3, 3], atol=1e-6)
    assert bool(res.ok) and float(res.residual) == 0.0 and int(res.num_steps) == 0
    assert res.state.shape == (0,)
    np.testing.assert_array_equal(
        np.asarray(res.centreline.rho)[[0, 10, 11, 21, 30]],
        np.float32([3e-3, 3e-3, 2.5e-3, 2e-3, 2e-3]),
    )


@settings(derandomize=True, max_examples=25, deadline=None)
@given(
    kappas=st.lists(st.floats(-60.0, 60.0), min_size=3, max_size=3),
    phis=st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3),
    lengths=st.lists(st.floats(0.005, 0.08), min_size=3, max_size=3),
)
def test_tip_and_frames_property(fwd, kappas, phis, lengths):
    res = fwd(_q(kappas, phis, lengths))
    T = wj_chain(kappas, phis, lengths)[-1]
    np.testing.assert_allclose(res.centreline.p[-1], T[:3, 3], atol=1e-6)
    R = np.asarray(res.centreline.R, np.float64)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=2e-6
    )


def test_straight_is_exact(fwd):
    res = fwd(_q([0.0, 0.0, 0.0], [0.4, -1.0, 3.0], [0.05, 0.04, 0.03]))
    s = np.asarray(res.centreline.s)
    np.testing.assert_array_equal(np.asarray(res.centreline.p[:, :2]), 0.0)
    np.testing.assert_allclose(res.centreline.p[:, 2], s, atol=1e-8)
    np.testing.assert_allclose(res.centreline.R, np.broadcast_to(np.eye(3), (N, 3, 3)), atol=1e-7)


def test_signed_kappa_equals_flipped_plane(fwd):
    a = fwd(_q([-12.0, 20.0, 5.0], [0.3, 1.0, -2.0], [0.05, 0.04, 0.03]))
    b = fwd(_q([12.0, 20.0, 5.0], [0.3 + np.pi, 1.0, -2.0], [0.05, 0.04, 0.03]))
    np.testing.assert_allclose(a.centreline.p, b.centreline.p, atol=1e-6)


def test_gradient_finite_at_straight_and_matches_fd():
    with jax.enable_x64(True):
        robot = ConstantCurvature.make(
            length=[0.05, 0.04], radius=[3e-3, 2e-3], n_points=9, dtype=jnp.float64
        )

        def tip_fn(q):
            return robot.forward(q).centreline.p[-1]

        # the tip and both Jacobians in one compiled program (one compile instead of three)
        both = jax.jit(lambda q: (tip_fn(q), jax.jacfwd(tip_fn)(q), jax.jacrev(tip_fn)(q)))

        def tip(q):
            return both(q)[0]

        def jac(q):
            return both(q)[1]

        for q0 in (
            jnp.array([0.0, 0.3, 0.05, 0.0, -1.0, 0.04]),
            jnp.array([12.0, 0.3, 0.05, -8.0, 1.0, 0.04]),
        ):
            _, J, J_rev = both(q0)
            assert np.all(np.isfinite(J))
            np.testing.assert_allclose(J, J_rev, atol=1e-12)
            eps = 1e-6
            fd = np.stack(
                [(tip(q0 + eps * e) - tip(q0 - eps * e)) / (2 * eps) for e in jnp.eye(6)], 1
            )
            np.testing.assert_allclose(J, fd, atol=1e-8)
        # At straight: d tip / d kappa_1 = (L1^2/2 + L1 L2) along the bending direction, exact.
        J = jac(jnp.array([0.0, 0.3, 0.05, 0.0, -1.0, 0.04]))
        lever = 0.05**2 / 2 + 0.05 * 0.04
        np.testing.assert_allclose(
            J[:, 0], lever * np.array([np.cos(0.3), np.sin(0.3), 0.0]), atol=1e-12
        )
    # float32 gradient at straight also finite.
    robot32 = ConstantCurvature.make(length=[0.05], radius=[1e-3], n_points=5)
    g = jax.jit(jax.grad(lambda q: robot32.forward(q).centreline.p[-1, 0]))(jnp.zeros(3))
    assert np.all(np.isfinite(g))


def test_joint_subset_and_energy():
    robot = ConstantCurvature.make(
        length=[0.05, 0.03], radius=[2e-3, 2e-3], kappa=[0.0, 0.0], phi=[0.5, -0.5],
        bending_stiffness=[2e-3, 1e-3], joints=("kappa",), n_points=11,
    )  # fmt: skip
    assert robot.n_joints == 2
    res = robot.forward(jnp.array([10.0, -20.0]))
    T = wj_chain([10.0, -20.0], [0.5, -0.5], [0.05, 0.03])[-1]
    np.testing.assert_allclose(res.centreline.p[-1], T[:3, 3], atol=1e-6)
    np.testing.assert_allclose(res.energy, 0.5 * (2e-3 * 100 * 0.05 + 1e-3 * 400 * 0.03), rtol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        robot.forward(jnp.zeros(3))


def test_ok_flags_bad_lengths_and_nan(fwd):
    assert not bool(fwd(_q([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [0.05, -0.01, 0.03])).ok)
    assert not bool(fwd(_q([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [0.05, 0.0, 0.03])).ok)
    assert not bool(fwd(_q([1.0, np.nan, 3.0], [0.0, 0.0, 0.0], [0.05, 0.04, 0.03])).ok)
    assert bool(fwd(_q([1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [0.05, 0.04, 0.03])).ok)


def test_invalid_construction():
    with pytest.raises(ValueError, match="joints"):
        ConstantCurvature.make(length=[0.05], radius=[1e-3], joints=("kappa", "twist"))
    with pytest.raises(ValueError, match="too few"):
        ConstantCurvature.make(length=[0.05, 0.04, 0.03], radius=[1e-3] * 3, n_points=3)


def test_vmap_equals_loop_jit_equals_eager_and_single_trace(robot, fwd):
    rng = np.random.default_rng(0)
    qs = np.stack(
        [
            _q(rng.uniform(-30, 30, 3), rng.uniform(-3, 3, 3), rng.uniform(0.01, 0.06, 3))
            for _ in range(4)
        ]
    )

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def batch(model, q):
        return jax.vmap(model.forward)(q)

    out = batch(robot, jnp.asarray(qs))
    out2 = batch(robot, jnp.asarray(qs[::-1].copy()))  # second batch of the same shape: no retrace
    for i in range(4):
        eager = robot.forward(jnp.asarray(qs[i]))
        np.testing.assert_allclose(out.centreline.p[i], eager.centreline.p, atol=1e-7)
        np.testing.assert_allclose(out2.centreline.p[3 - i], eager.centreline.p, atol=1e-7)
        np.testing.assert_allclose(
            fwd(jnp.asarray(qs[i])).centreline.R, eager.centreline.R, atol=1e-6
        )
