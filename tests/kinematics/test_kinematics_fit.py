"""jaxcr.kinematics.fit: point-to-polyline geometry, the reparametrised joint limits, agreement
with scipy.optimize.least_squares on the same residual, and recovery of known q from noisy
synthetic backbones for every robot kind."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from jaxcr.io.exported import cached_call
from jaxcr.kinematics import ConstantCurvature, SingleSegment
from jaxcr.kinematics.ctr import TEST_CTR, ConcentricTubeRobot
from jaxcr.kinematics.ctr_mechanics import telescoping_ok
from jaxcr.kinematics.fit import (
    _cold_forward,
    canonical_joints,
    closest_points_on_polyline,
    fit_backbone,
    free_from_joints,
    joints_from_free,
)


def _closest_loop(points, poly):
    """Slow reference: every segment, clamped projection, keep the least distance."""
    out = []
    for p in points:
        best, bd = None, np.inf
        for a, b in zip(poly[:-1], poly[1:], strict=True):
            ab = b - a
            t = 0.0 if ab @ ab == 0 else np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
            c = a + t * ab
            d = np.sum((p - c) ** 2)
            if d < bd:
                best, bd = c, d
        out.append(best)
    return np.asarray(out)


def test_closest_points_match_loop():
    rng = np.random.default_rng(0)
    poly = np.cumsum(rng.normal(size=(9, 3)), axis=0)
    poly[4] = poly[3]  # a zero-length segment
    pts = rng.normal(size=(40, 3)) * 3
    # compiled (run eagerly, its ~25 operations were compiled one by one)
    got = np.asarray(jax.jit(closest_points_on_polyline)(jnp.asarray(pts), jnp.asarray(poly)))
    # float32 arithmetic on coordinates of size ~10: a few eps32 x 10 (1e-5 with margin)
    np.testing.assert_allclose(got, _closest_loop(pts, poly), atol=1e-4)


def test_closest_points_gradient_finite_on_polyline():
    poly = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 1.0]])
    pts = jnp.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0]])  # on a segment and on a vertex
    # compiled: the eager gradient compiled ~60 operations one by one
    g = jax.jit(jax.grad(lambda P: jnp.sum((pts - closest_points_on_polyline(pts, P)) ** 2)))(poly)
    assert np.all(np.isfinite(np.asarray(g)))


def _ctr(**kw):
    # Small grid and scan for test speed; the fit code does not depend on them.
    return ConcentricTubeRobot.from_dict(
        dict(TEST_CTR, n_points=13), scan_points=8, n_starts=2, cold_steps=15, **kw
    )


def test_ctr_reparametrisation_covers_the_joint_limits():
    model = _ctr()
    rng = np.random.default_rng(1)
    z = jnp.asarray(rng.normal(scale=3.0, size=(200, 6)), jnp.float32)

    @eqx.filter_jit  # one program (run eagerly, its ~80 operations compiled one by one)
    def maps(model, z):
        q = jax.vmap(lambda zz: joints_from_free(model, zz))(z)
        tubes = model.mechanics()
        ok = jax.vmap(lambda qq: telescoping_ok(tubes, qq[:3]))(q)
        back = jax.vmap(lambda qq: joints_from_free(model, free_from_joints(model, qq)))(q)
        return q, ok, back

    q, ok, back = (np.asarray(x) for x in maps(model, z))
    assert np.all(ok)
    # round trip inside the limits: float32 logit/sigmoid, |d beta| <= eps32 x L / (f (1-f))
    # with f >= 0.05 for |z| <= 3: ~1e-7 x 0.4 / 0.05 -> 1e-5 with margin
    inside = np.all(np.abs(np.asarray(z)) < 3.0, axis=1)
    np.testing.assert_allclose(back[inside], q[inside], atol=1e-5)


def _noisy_backbone(model, q, sigma, seed, stride=2):
    p = np.asarray(_cold_forward(model, jnp.asarray(q, _model_dtype(model))).centreline.p)
    return _noisy_points(p.astype(np.float64), sigma, seed, stride)


def _model_dtype(model):
    return jax.tree_util.tree_leaves(model)[0].dtype


def _noisy_points(p, sigma, seed, stride=2):
    idx = np.unique(np.r_[np.arange(0, len(p), stride), len(p) - 1])  # every stride-th + tip
    rng = np.random.default_rng(seed)
    return p[idx] + rng.normal(scale=sigma, size=(len(idx), 3))


# compiled (run eagerly, its ~15 operations were compiled one by one)
_canonical_joints = eqx.filter_jit(canonical_joints)


def _same_shape_joints(model, q):
    """Canonical joints with CC's signed kappa made positive ((k, phi) == (-k, phi + pi))."""
    q = np.array(_canonical_joints(model, jnp.asarray(q)), np.float64)
    if model.kind == "constant_curvature":
        qs = q.reshape(model.n_sections, len(model.joints))
        k, f = model.joints.index("kappa"), model.joints.index("phi")
        neg = qs[:, k] < 0
        qs[neg, k] *= -1
        qs[neg, f] = np.arctan2(np.sin(qs[neg, f] + np.pi), np.cos(qs[neg, f] + np.pi))
        q = qs.reshape(-1)
    return q


@pytest.mark.parametrize(
    "case",
    [
        ("single_segment", [0.6, 0.7]),
        ("constant_curvature", [8.0, 0.5, 6.0, -1.0]),
    ],
)
def test_recovers_q_from_noisy_backbone(case):
    kind, q_true = case
    if kind == "single_segment":
        # The problem `jaxcr fit` solves in tests/cli (test_cli_fit, test_cli_fit_rig: 24
        # samples, 9 points, base term on, the defaults), called as the command calls it
        # (jit_call=cached_call: the stored traced programs), so that it is one program in the
        # run for all three (a Levenberg-Marquardt solve compiles for ~2.5 s of CPU). The
        # direct call (jit_call=None) is the constant-curvature case's and the other tests'.
        model, stride, base_weight = SingleSegment.make(0.1, 0.003, n_points=24), 3, 1.0
        jit_call = cached_call
    else:
        model = ConstantCurvature.make(
            [0.05, 0.05], [0.003] * 2, joints=("kappa", "phi"), n_points=33
        )
        stride, base_weight, jit_call = 2, 0.0, None
    sigma = 2e-4  # 0.2 mm tracker noise

    def centreline(q):  # the compiled FK of the noisy backbones (fit._cold_forward)
        p = _cold_forward(model, jnp.asarray(q, jnp.float32)).centreline.p
        return np.asarray(p, np.float64)

    for seed in (11, 12):  # fresh seeds (the configurations were chosen on seed 0)
        pts = _noisy_backbone(model, q_true, sigma, seed, stride)
        res = fit_backbone(
            model, jnp.asarray(pts, jnp.float32), base_weight=base_weight, jit_call=jit_call
        )
        assert bool(res.ok), res.result
        # J by central differences of the slow reference residual (_cov_tolerance_fd; no
        # Jacobian program of its own). Against the jacfwd J of the fit's residual that this
        # used before (2.5 s of compilation per model): tolerance ratio 0.998-1.001 per joint
        # on both seeds at h = 3e-4, 1e-3 and 3e-3 (3 December 2026)
        tol = _cov_tolerance_fd(
            centreline, np.asarray(q_true, np.float64), pts, sigma, h=1e-3,
            base_weight=base_weight,
        )  # fmt: skip
        err = np.abs(_same_shape_joints(model, res.q) - _same_shape_joints(model, q_true))
        err = np.minimum(err, 2 * np.pi - err) if kind == "single_segment" else err
        assert np.all(err <= tol), (err, tol)
        # point-to-polyline keeps the normal part of the noise: rms ~ sigma sqrt(2); a fit
        # within 3x of that (9x the expected sum of squares: chi-square with >= 16 dof, 9 or
        # 17 points with 2 normal components each less the fitted joints, stays well inside)
        assert float(res.rms) < 3 * sigma * np.sqrt(2)


def _backbone_residual_loop(points, p, tip_weight=1.0, base_weight=0.0):
    """Slow float64 reference of backbone_residual (identity base pose): each point minus its
    closest point on the polyline ``p`` (:func:`_closest_loop`), the tip term, and with
    ``base_weight`` the base term."""
    c = _closest_loop(points, p)
    parts = [(points - c).reshape(-1), tip_weight * (points[-1] - p[-1])]
    if base_weight:
        parts.append(base_weight * (points[0] - p[0]))
    return np.concatenate(parts)


def _cov_tolerance_fd(
    centreline, q_true, points, sigma, h, k=5.0, solver_rtol=1e-6, base_weight=0.0
):
    """k-sigma per joint from the Gauss-Newton covariance sigma^2 (J^T J)^-1 of the fit's
    residual at the truth (with its ``base_weight``), plus the float32 solver's resolution
    (its rtol on ~unit-scale parameters, x100 margin). J = d residual / d q by central
    differences (step ``h``) of the slow reference residual around ``centreline``, a
    compiled q -> (N, 3) FK.

    Why: a Jacobian program of the fit's residual cost ~2.5 s of compilation per model (and
    jacfwd executed eagerly through the CTR's equilibrium solve ~48 s of CPU); the compiled
    FK used instead is the one the noisy backbone needs anyway. Error of J: truncation
    h^2 |d3r/dq3| / 6 (negligible at h = 1e-3 m, rad or 1/m on these smooth shapes) plus
    the FK's noise delta / h: closed-form models in float32 give delta ~ eps32 x 0.1 m ~
    1e-8 m, so ~1e-5 m per unit of q against columns of >= ~1e-3 m per unit (a section's
    kappa); a CTR's float32 equilibrium tolerance (tip angles to ~1e-5 rad over ~0.1 m)
    gives delta ~1e-6 m, so ~1e-3 m per unit of q against columns of ~0.03-1 m per unit.
    Measured against the jacfwd tolerance: on the CTR case below (its three-tube robot then,
    2 December 2026) ratio 0.92-1.01 per joint at h = 1e-3, the same within 0.03 at h = 3e-4
    and 3e-3 (so not
    noise: the kinks of the closest-point map, which jacfwd takes one-sided), k = 5 sigma
    stays >= 4.6 sigma; on the single-segment and constant-curvature cases (3 December
    2026) 0.998-1.001."""
    q_true = np.asarray(q_true, np.float64)
    cols = []
    for i in range(len(q_true)):
        dq = np.zeros_like(q_true)
        dq[i] = h
        rp = _backbone_residual_loop(points, centreline(q_true + dq), base_weight=base_weight)
        rm = _backbone_residual_loop(points, centreline(q_true - dq), base_weight=base_weight)
        cols.append((rp - rm) / (2 * h))
    J = np.stack(cols, axis=1)
    cov = sigma**2 * np.linalg.pinv(J.T @ J)
    return k * np.sqrt(np.diag(cov)) + 100 * solver_rtol * (1.0 + np.abs(q_true))


@pytest.mark.slow
def test_recovers_ctr_q_from_noisy_backbone():
    """A two-tube CTR (TEST_CTR's outer two tubes): the CTR path of the fit (the telescoping
    reparametrisation of the translations, warm-started rounds from the cold equilibrium) is
    the same code for any number of tubes, and its programs are a third smaller than the
    three-tube robot's (fit + FK 17.5 vs 26.5 CPU-s, same loaded run, 3 December 2026); the
    three-tube reparametrisation is test_ctr_reparametrisation_covers_the_joint_limits'."""
    model = ConcentricTubeRobot.from_dict(
        dict(TEST_CTR, tubes=TEST_CTR["tubes"][:2], n_points=13), scan_points=8, n_starts=2,
        cold_steps=15,
    )  # fmt: skip
    q_true = np.array([-0.22, -0.15, 0.2, -0.8])
    sigma = 1e-4

    # one compiled FK (the cold equilibrium solve) for the truth, the 12 difference points
    # and the fit's own warm starts (the same compiled function)
    def centreline(q):
        p = _cold_forward(model, jnp.asarray(q, jnp.float32)).centreline.p
        return np.asarray(p, np.float64)

    pts = _noisy_points(centreline(q_true), sigma, seed=21)
    res = fit_backbone(model, jnp.asarray(pts, jnp.float32), max_steps=60, rounds=2)
    assert bool(res.ok), res.result
    # solver_rtol: the CTR default rtol
    tol = _cov_tolerance_fd(centreline, q_true, pts, sigma, h=1e-3, solver_rtol=1e-4)
    err = np.abs(np.asarray(res.q) - q_true)
    err[2:] = np.minimum(err[2:], 2 * np.pi - err[2:])
    assert np.all(err <= tol), (err, tol)


def test_same_optimum_as_scipy_least_squares():
    """Same residual (float64), minimised by optimistix LM and by scipy's trust-region
    reflective least squares from the same start: same cost and same q. scipy minimises the
    slow reference residual (:func:`_backbone_residual_loop`) of the compiled float64 FK
    that made the points, with its own 3-point difference Jacobian (no program of ours
    but that FK: a compiled residual + jacfwd program cost ~3 s of compilation). One
    section (the float64 copy of the fit is the smallest program that shows the agreement:
    the float32 recovery of two sections is test_recovers_q_from_noisy_backbone's)."""
    with jax.enable_x64(True):
        model = ConstantCurvature.make(
            [0.05], [0.003], joints=("kappa", "phi"), n_points=17, dtype=jnp.float64
        )
        pts = _noisy_backbone(model, [7.0, 0.3], 3e-4, seed=5)
        q0 = np.array([1.0, 0.0])
        res = fit_backbone(model, jnp.asarray(pts), q0=q0)

        def fun(q):
            p = _cold_forward(model, jnp.asarray(q, jnp.float64)).centreline.p
            return _backbone_residual_loop(pts, np.asarray(p, np.float64))

        def jac(q):  # central differences (h = 1e-6: error ~1e-12 + eps64 |r| / h ~1e-12)
            h = 1e-6
            return np.stack([(fun(q + h * e) - fun(q - h * e)) / (2 * h) for e in np.eye(2)], 1)

        # 3-point differences: relative error ~eps64^(2/3) ~ 1e-11 in J, which moves the
        # stopping point by far less than the 1e-8 relative cost tolerance below
        ref = scipy.optimize.least_squares(
            fun, q0, jac="3-point", method="trf", xtol=1e-14, ftol=1e-14, gtol=1e-14
        )
        assert bool(res.ok)
        # Both stop where the relative cost decrease is ~1e-10: costs agree to that.
        assert abs(float(res.cost) - ref.cost) <= 1e-8 * ref.cost
        # q: a cost gap dC bounds |dq| by sqrt(2 dC / lambda_min(J^T J)) near the optimum
        J = jac(ref.x)
        lam = np.linalg.eigvalsh(J.T @ J)[0]
        qtol = np.sqrt(2 * 1e-8 * ref.cost / lam)
        dq = _same_shape_joints(model, res.q) - _same_shape_joints(model, ref.x)
        assert np.max(np.abs(dq)) <= qtol, (dq, qtol)


def test_fit_pose_recovers_a_shifted_base():
    """Points measured in a frame shifted by 2 cm and turned about x: the fitted base pose maps
    the model back onto them (residual at noise level) and its translation is the shift.
    Its own program: no test of `jaxcr fit --fit-pose` runs this single-segment problem any
    more (test_cli_fit_rig's pose fit is the tutorial rig's, to load the tutorial's program)."""
    model = SingleSegment.make(0.1, 0.003, n_points=24)
    q_true = jnp.array([0.5, 0.4])
    p = np.asarray(_cold_forward(model, q_true).centreline.p, np.float64)
    p = p[np.r_[0 : len(p) : 3, len(p) - 1]]
    a = 0.1
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    t = np.array([0.02, -0.01, 0.005])
    pts = p @ R.T + t
    res = fit_backbone(model, jnp.asarray(pts, jnp.float32), fit_pose=True, base_weight=1.0)
    assert bool(res.ok)
    # noiseless: float32 residual resolution ~ eps32 x 0.1 m, x1000 margin for LM stopping
    assert float(res.max) < 1e-5
    # the base point p(0) = 0 lands on t
    np.testing.assert_allclose(np.asarray(res.T_ref_robot)[:3, 3], t, atol=1e-4)


def test_tip_pixels_two_views_with_pose_and_prior():
    """Two views of the tip (4 equations) with q and the base pose free (8 unknowns): the prior
    makes it well posed; the fit must reproject onto both tip pixels and stay finite."""
    from jaxcr.camera import Camera, project_points
    from jaxcr.kinematics.fit import fit_tip_pixels

    model = SingleSegment.make(0.1, 0.003, n_points=24)  # the other tests' FK program
    cams = (
        Camera.look_at([0.0, -0.3, 0.05], [0.0, 0.0, 0.05], [0.0, 0.0, 1.0], 300.0, (320, 240)),
        Camera.look_at([0.3, 0.0, 0.05], [0.0, 0.0, 0.05], [0.0, 0.0, 1.0], 300.0, (320, 240)),
    )
    tip = _cold_forward(model, jnp.array([0.7, 0.3])).centreline.p[-1:]
    project = jax.jit(project_points)  # one program for both views
    uv = jnp.stack([project(c, tip)[0][0] for c in cams])
    res = fit_tip_pixels(model, cams, uv, fit_pose=True, prior_weight=1.0)
    assert bool(res.ok), res.result
    # linearised, the prior leaves r = w^2 (J J^T + w^2)^-1 r0: with w = 1 and J's singular
    # values ~300 px/rad (f = 300 px at 0.3 m, 0.1 m lever), |r| ~ |r0| / 9e4 ~ 1e-3 px for a
    # start ~100 px off; 0.05 px leaves room for the nonlinearity
    assert float(res.max) < 0.05
    assert np.all(np.isfinite(np.asarray(res.T_ref_robot)))
