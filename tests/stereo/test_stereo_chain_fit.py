"""Joint constant-curvature chain fit (jaxcr.stereo.chain_fit) and the edge-clearance flag
of the silhouette widths (jaxcr.stereo.diameter.edge_clearance).

References: the closed-form circular arc, scipy's solve_ivp integration of the rod ODE
(dR/ds = R hat(u), dp/ds = R e3), numpy's SVD plane fit, cv2.projectPoints for the
synthetic views, finite differences for gradients."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from jaxcr.camera import Camera, project_points
from jaxcr.stereo.chain_fit import (
    _reparametrise,
    chain_points,
    chain_segment_parameters,
    drop_inconsistent_widths,
    fit_chain,
    init_chain,
)
from jaxcr.stereo.diameter import edge_clearance

# One compile per shape, shared by the tests.
_cp = jax.jit(chain_points)
_csp = jax.jit(chain_segment_parameters)
project_points_jit = jax.jit(project_points)

SEG = np.array([0.0, 0.04, 0.07])
CURV = np.array([[0.0, 10.0], [20.0, 5.0], [-15.0, 35.0]])  # body (ux, uy), 1/m
TILT = np.array([0.05, -0.08, 0.3])  # mounting rotation vector of R0


def _R0():
    return cv2.Rodrigues(TILT)[0]


def _ode_reference(s_eval: np.ndarray) -> np.ndarray:
    """Points of the chain by integrating the rod ODE with scipy (float64)."""

    def rhs(s, y):
        R = y[3:].reshape(3, 3)
        i = min(np.searchsorted(SEG, s, side="right") - 1, len(SEG) - 1)
        u = np.array([CURV[i, 0], CURV[i, 1], 0.0])
        U = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        return np.concatenate([R[:, 2], (R @ U).ravel()])

    y0 = np.concatenate([np.zeros(3), _R0().ravel()])
    sol = solve_ivp(rhs, (0.0, s_eval[-1]), y0, t_eval=s_eval, rtol=1e-10, atol=1e-12,
                    max_step=1e-3)  # fmt: skip
    return sol.y[:3].T


@pytest.fixture(scope="module")
def cams():
    c1 = Camera.look_at([0.25, 0.0, 0.12], [0.0, 0.0, 0.05], [0, 0, 1], 900.0, (640, 480))
    c2 = Camera.look_at([0.0, 0.25, 0.12], [0.0, 0.0, 0.05], [0, 0, 1], 900.0, (640, 480))
    return c1, c2


def test_single_arc_closed_form():
    k = 25.0
    s = np.linspace(0.0, 0.1, 41)
    X, t = _cp(jnp.zeros(3), jnp.eye(3), jnp.array([[0.0, k]]), jnp.zeros(1), jnp.asarray(s))
    # Rotation about body y: p = ((1 - cos ks)/k, 0, sin(ks)/k), t = (sin ks, 0, cos ks).
    ref = np.stack([(1 - np.cos(k * s)) / k, 0 * s, np.sin(k * s) / k], 1)
    np.testing.assert_allclose(np.asarray(X), ref, atol=2e-6)
    np.testing.assert_allclose(
        np.asarray(t), np.stack([np.sin(k * s), 0 * s, np.cos(k * s)], 1), atol=2e-6
    )


def test_chain_matches_ode_and_tangent_is_derivative():
    s = np.linspace(0.0, 0.09, 91)
    X, t = _cp(
        jnp.zeros(3), jnp.asarray(_R0()), jnp.asarray(CURV), jnp.asarray(SEG), jnp.asarray(s)
    )
    np.testing.assert_allclose(np.asarray(X), _ode_reference(s), atol=5e-6)  # 5 um of 90 mm
    # Tangent = dX/ds (central differences in float64 of the ODE reference), continuous
    # across the boundaries.
    h = 1e-5
    for sb in SEG[1:]:
        Xa = _ode_reference(np.array([sb - h, sb + h]))
        fd = (Xa[1] - Xa[0]) / (2 * h)
        _, tb = _cp(jnp.zeros(3), jnp.asarray(_R0()), jnp.asarray(CURV), jnp.asarray(SEG),
                             jnp.array([sb - 1e-7, sb + 1e-7]))  # fmt: skip
        np.testing.assert_allclose(np.asarray(tb[0]), fd, atol=1e-4)
        np.testing.assert_allclose(np.asarray(tb[1]), fd, atol=1e-4)


def test_segment_parameters_against_svd_plane():
    kappa, normal = _csp(jnp.zeros(3), jnp.asarray(_R0()), jnp.asarray(CURV), jnp.asarray(SEG))
    np.testing.assert_allclose(np.asarray(kappa), np.linalg.norm(CURV, axis=1), rtol=1e-6)
    ends = list(SEG[1:]) + [0.09]
    for i, (a, b) in enumerate(zip(SEG, ends, strict=True)):
        P = _ode_reference(np.linspace(a + 1e-6, b, 30))
        _, _, vt = np.linalg.svd(P - P.mean(0))
        assert abs(abs(vt[-1] @ np.asarray(normal[i])) - 1.0) < 1e-5


def test_straight_segment_finite_gradient():
    seg = jnp.array([0.0, 0.03])
    s = jnp.linspace(0, 0.06, 7)

    def f(c):
        X, _ = chain_points(jnp.zeros(3), jnp.eye(3), c, seg, s)
        k, n = chain_segment_parameters(jnp.zeros(3), jnp.eye(3), c, seg)
        return jnp.sum(X**2) + jnp.sum(k) + jnp.sum(n)

    # Away from zero, the gradient of the positions vs central differences.
    def fx(c):
        return jnp.sum(chain_points(jnp.zeros(3), jnp.eye(3), c, seg, s)[0] ** 2)

    # both gradients and the value: one compiled program (instead of two)
    grads = jax.jit(lambda c: (jax.grad(f)(c), *jax.value_and_grad(fx)(c)))
    g = grads(jnp.zeros((2, 2)))[0]
    assert np.all(np.isfinite(np.asarray(g)))

    def vg(c):
        return grads(c)[1:]

    c0 = np.array([[3.0, -2.0], [1.0, 4.0]], np.float32)
    g = np.asarray(vg(jnp.asarray(c0))[1])
    fd = np.zeros_like(c0)
    for idx in np.ndindex(c0.shape):
        e = np.zeros_like(c0)
        e[idx] = 0.05
        fd[idx] = (float(vg(jnp.asarray(c0 + e))[0]) - float(vg(jnp.asarray(c0 - e))[0])) / 0.1
    np.testing.assert_allclose(g, fd, rtol=2e-3, atol=1e-7)


def test_jit_and_vmap():
    s = jnp.linspace(0.0, 0.09, 20)
    args = (
        jnp.zeros(3),
        jnp.asarray(_R0(), jnp.float32),
        jnp.asarray(CURV, jnp.float32),
        jnp.asarray(SEG, jnp.float32),
    )
    eager = chain_points(*args, s)[0]
    np.testing.assert_allclose(
        np.asarray(jax.jit(chain_points)(*args, s)[0]), np.asarray(eager), atol=1e-7
    )
    batch = jnp.stack([args[2], 0.5 * args[2], -args[2]])
    # compiled (jit equals eager is checked above; run eagerly, the vmapped chain's ~60
    # operations were compiled one by one)
    vm = jax.jit(jax.vmap(lambda c: chain_points(args[0], args[1], c, args[3], s)[0]))(batch)
    for b in range(3):
        np.testing.assert_allclose(
            np.asarray(vm[b]),
            np.asarray(_cp(args[0], args[1], batch[b], args[3], s)[0]),
            atol=1e-7,
        )


def test_init_chain_on_exact_points():
    s = np.linspace(0.002, 0.09, 177)
    P = _ode_reference(s)
    base, R, curv = init_chain(s, P, SEG)
    np.testing.assert_allclose(base, 0.0, atol=1e-4)  # chord over the first 2 mm
    k0, n0 = _csp(jnp.asarray(base), jnp.asarray(R), jnp.asarray(curv), jnp.asarray(SEG))
    np.testing.assert_allclose(np.asarray(k0), np.linalg.norm(CURV, axis=1), rtol=0.03)


def _smooth_error(s):
    return 3e-4 * np.stack([np.sin(s / 0.013), np.cos(s / 0.021), np.sin(s / 0.017 + 1)], 1)


def _views(cams, s, rng, noise_px):
    """Silhouette-centre observations of the true chain: cv2.projectPoints of the ODE
    points, image normals from the projected curve, Gaussian noise along the normals."""
    P = _ode_reference(s)
    cs, ns = [], []
    for c in cams:
        T = np.asarray(c.T_cam_robot, np.float64)
        uv = cv2.projectPoints(P, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], np.asarray(c.K, np.float64), np.zeros(5))[0].reshape(-1, 2)  # fmt: skip
        d = np.gradient(uv, axis=0)
        n = np.stack([-d[:, 1], d[:, 0]], 1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        cs.append(uv + rng.normal(0, noise_px, len(s))[:, None] * n)
        ns.append(n)
    return P, np.stack(cs), np.stack(ns)


def test_fit_chain_recovers_parameters(cams):
    rng = np.random.default_rng(0)
    s = np.linspace(0.002, 0.09, 256)
    P, cs, ns = _views(cams, s, rng, 0.2)
    # Start from points off by up to 0.3 mm, smoothly (as the smoothed triangulation).
    base0, R0, curv0 = init_chain(s, P + _smooth_error(s), SEG)
    # two Huber passes (fit_segments_jointly's): the compiled solver of the tests below
    fit = fit_chain(
        cams[0], cams[1], s, cs, ns, np.ones((2, len(s))), SEG, base0, R0, curv0, reweight=2
    )
    assert fit["ok"]
    np.testing.assert_allclose(fit["kappa"], np.linalg.norm(CURV, axis=1), rtol=0.01)
    _, n_true = _csp(jnp.zeros(3), jnp.asarray(_R0()), jnp.asarray(CURV), jnp.asarray(SEG))
    ang = np.degrees(
        np.arccos(np.clip(np.abs(np.sum(fit["normal"] * np.asarray(n_true), 1)), 0, 1))
    )
    assert ang.max() < 0.5, ang
    assert 0.1 < fit["rms_px"] < 0.3  # the noise level


def test_fit_chain_with_one_view_dropped_on_a_segment(cams):
    """Where one view is unusable (weight 0) on the last segment, the other view plus the
    tangent continuity still fix its curvature and plane."""
    rng = np.random.default_rng(1)
    s = np.linspace(0.002, 0.09, 256)
    P, cs, ns = _views(cams, s, rng, 0.1)
    w = np.ones((2, len(s)))
    w[0, s > SEG[2]] = 0.0
    base0, R0, curv0 = init_chain(s, P + _smooth_error(s), SEG)
    fit = fit_chain(cams[0], cams[1], s, cs, ns, w, SEG, base0, R0, curv0, reweight=2)
    # One view of a 20 mm arc: its out-of-image bending is only weakly observed (3.5 %).
    np.testing.assert_allclose(fit["kappa"], np.linalg.norm(CURV, axis=1), rtol=0.05)


def test_edge_clearance_two_bars():
    """A vertical bar 6 px wide; a second bar 3 px beside it spoils the edge, 10 px does not."""
    h, w = 40, 60
    for gap, expect in [(3, 0.0), (10, 1.0)]:
        a = np.zeros((h, w), np.float32)
        a[:, 20:26] = 1.0
        a[:, 26 + gap : 30 + gap] = 1.0
        c = jnp.array([[22.5, 20.0]])
        n = jnp.array([[1.0, 0.0]])
        got = edge_clearance(jnp.asarray(a), c, n, jnp.array([6.0]), jnp.array([0.0]))
        assert float(got[0]) == expect


def test_drop_inconsistent_widths():
    s = np.linspace(0.0, 0.09, 10)
    seg = np.array([0.0, 0.05])
    d = np.where(s < 0.05, 2.4e-3, 1.8e-3) * np.ones((2, 1))
    w = np.full((2, 10), 0.9)
    d[1, 3] = 2.9e-3  # another part lying on the shaft in view 2 (+21 %)
    d[0, 8] = 1.6e-3  # partial occlusion in view 1 (-11 %: kept at 15 %)
    d[0, 9] = 2.6e-3  # foreshortened (weight 0.1): width is no diameter there, kept
    w[0, 9] = 0.1
    out = drop_inconsistent_widths(w, d, s, seg)
    expect = w.copy()
    expect[1, 3] = 0.0
    np.testing.assert_array_equal(out, expect)
    assert drop_inconsistent_widths(w, d, s, seg, max_dev=0.1)[0, 8] == 0.0


def test_reparametrise_recovers_arclength(cams):
    """Observations labelled with wrong arclengths (+2 mm on a stretch, as where the
    triangulation slid) get their arclength back from the chain (grid 0.125 mm)."""
    rng = np.random.default_rng(2)
    s = np.linspace(0.002, 0.09, 256)
    _, cs, _ = _views(cams, s, rng, 0.0)
    wrong = s + np.where((s > 0.03) & (s < 0.05), 2e-3, 0.0)
    got = _reparametrise(
        jnp.zeros(3), jnp.asarray(_R0(), jnp.float32), jnp.asarray(CURV, jnp.float32),
        jnp.asarray(SEG, jnp.float32), jnp.asarray(wrong, jnp.float32), cams[0], cams[1],
        jnp.asarray(cs, jnp.float32), jnp.ones((2, len(s)), jnp.float32), 5e-3,
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(got), s, atol=7e-5)


def test_transport_frames_vectorised_equals_loop():
    """The prefix-product frames equal the sequential rotation-minimising transport (a
    slow loop), including the fallback for a reversal between neighbouring tangents."""
    from jaxcr.stereo.chain_fit import _frame_from_tangent, _min_rotations, _transport_frames

    rng = np.random.default_rng(3)
    for reverse in (False, True):
        t = np.cumsum(rng.normal(0, 0.2, (60, 3)), axis=0) + np.array([0.0, 0.0, 1.0])
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        if reverse:
            t[30:] = -t[30:]  # nearly opposite neighbours: the identity step
        R = _frame_from_tangent(t[0] + 0.1)
        ref = [R]
        for i in range(1, len(t)):
            ref.append(_min_rotations(ref[-1][None, :, 2], t[i : i + 1])[0] @ ref[-1])
        np.testing.assert_allclose(_transport_frames(R, t), np.stack(ref), atol=1e-12)


def test_early_stopped_fit_equals_fixed_iterations(cams):
    """The early-stopped LM (default tolerances) gives the fixed-iteration fit (ftol = xtol
    = 0: all 20 iterations of every pass) to within 1e-3 relative curvature and 0.02 deg
    of bending plane (float32), in fewer iterations."""
    rng = np.random.default_rng(2)
    s = np.linspace(0.002, 0.09, 256)
    P, cs, ns = _views(cams, s, rng, 0.3)
    cs[0, 100] += 8.0 * ns[0, 100]  # an outlier, so the Huber passes matter
    base0, R0, curv0 = init_chain(s, P + _smooth_error(s), SEG)
    w = np.ones((2, len(s)))
    args = (cams[0], cams[1], s, cs, ns, w, SEG, base0, R0, curv0)
    fixed = fit_chain(*args, reweight=2, ftol=0.0, xtol=0.0)
    early = fit_chain(*args, reweight=2)
    assert fixed["num_steps"] == 40
    assert early["num_steps"] < 30, early["num_steps"]
    assert early["ok"]
    np.testing.assert_allclose(early["kappa"], fixed["kappa"], rtol=1e-3)
    # Angle between the normals by atan2(|a x b|, |a . b|) (arccos of a float32 dot
    # product cannot resolve angles below ~0.03 deg).
    a, b = early["normal"], fixed["normal"]
    ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.abs(np.sum(a * b, 1)))
    assert np.degrees(ang).max() < 0.02, np.degrees(ang)
    np.testing.assert_allclose(early["rms_px"], fixed["rms_px"], rtol=1e-3)


@jax.jit
def _observations_by_hand(c, a, kp, P, t):
    """observations_from_profiles at every sample, its inputs measured as the pipeline's
    diameter stage does (one compiled program: run eagerly, its ~60 operations were
    compiled one by one)."""
    from jaxcr.stereo.chain_fit import observations_from_profiles
    from jaxcr.stereo.diameter import profile_widths

    uv0, ok = project_points(c, P)
    uv1, _ = project_points(c, P + 1e-4 * t)
    du = uv1 - uv0
    nrm = jnp.stack([-du[:, 1], du[:, 0]], axis=1)
    nrm = nrm / jnp.linalg.norm(nrm, axis=1, keepdims=True)
    wdt, off = profile_widths(a, uv0, nrm, kp)
    clean = edge_clearance(a, uv0, nrm, wdt, off)
    return observations_from_profiles(c, P, t, uv0, ok, nrm, wdt, off, clean)


def test_joint_fit_with_precomputed_observations_equals_measuring():
    """fit_segments_jointly given observations_from_profiles at every sample (as the
    pipeline's diameter stage measures them: tangents by np.gradient over the index)
    equals measuring them itself at the subsampled observations (uniform arclength)."""
    from jaxcr.stereo.chain_fit import fit_segments_jointly

    # 640x480 views of the chain (the size of the `cams` fixture, so that the chain fit's
    # compiled solver is the one the tests above use); the silhouette drawn as a 20 px
    # polyline (float alpha): 4x the scale of the 160x120 views this test used before.
    c1 = Camera.look_at([0.35, 0.0, 0.1], [0.02, 0.0, 0.05], [0, 0, 1], 720.0, (640, 480))
    c2 = Camera.look_at([0.0, 0.35, 0.1], [0.0, 0.02, 0.05], [0, 0, 1], 720.0, (640, 480))
    s = np.linspace(0.0, 0.09, 181)  # uniform, 0.5 mm
    P = _ode_reference(s + 1e-12)
    alphas = []
    for c in (c1, c2):
        T = np.asarray(c.T_cam_robot, np.float64)
        uv = cv2.projectPoints(P, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], np.asarray(c.K, np.float64), np.zeros(5))[0].reshape(-1, 2)  # fmt: skip
        im = np.zeros((480, 640), np.uint8)
        cv2.polylines(im, [np.round(uv * 16).astype(np.int32)], False, 255, 20, cv2.LINE_AA, 4)
        alphas.append(cv2.GaussianBlur(im.astype(np.float32) / 255.0, (3, 3), 0.6))
    kps = [1.0 - a for a in alphas]
    tang = np.gradient(P, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    Pj, tj = jnp.asarray(P, jnp.float32), jnp.asarray(tang, jnp.float32)
    obs = [
        _observations_by_hand(c, jnp.asarray(a), jnp.asarray(kp), Pj, tj)
        for c, a, kp in zip((c1, c2), alphas, kps, strict=True)
    ]
    obs = tuple(np.stack([np.asarray(o[i]) for o in obs]) for i in range(4))
    assert (obs[2] > 0).mean() > 0.5  # most observations usable
    args = ((c1, c2), alphas, kps, s, P, SEG[1:])
    measured = fit_segments_jointly(*args)
    given = fit_segments_jointly(*args, observations=obs)
    np.testing.assert_allclose(given["weights"], measured["weights"], atol=1e-5)
    # The observations agree to float32 rounding (~1e-5 px, measured); the float32 LM's
    # result moves by ~2e-4 relative under such perturbations (measured 2.2e-4 on the
    # 160x120 views, 7e-6 and 3e-4 deg on these).
    np.testing.assert_allclose(given["kappa"], measured["kappa"], rtol=1e-3)
    np.testing.assert_allclose(given["angles_deg"], measured["angles_deg"], atol=0.02)
    # Sanity only: a 20 px polyline at ~7 px/mm is a coarse silhouette (measured 0.5 %;
    # 5.8 % on the 160x120 views).
    np.testing.assert_allclose(given["kappa"], np.linalg.norm(CURV, axis=1), rtol=0.1)


def test_tail_observations_extend_a_tip_lost_by_one_view(cams):
    """A tip the stereo matching lost (last segment seen by both views for 12 of its 30
    mm) but view 2 still sees: with view 2's silhouette centres beyond the last match as
    single-view observations (tails=...) the last segment's arc length comes back to
    within 0.6 mm (truncated: 12 mm) and its curvature and bending plane are closer to the
    truth (ODE chain; RMS over 6 noise seeds at 0.1 px) than the truncated fit's."""
    from jaxcr.stereo.chain_fit import fit_segments_jointly

    _, n_true = _csp(jnp.zeros(3), jnp.asarray(_R0()), jnp.asarray(CURV), jnp.asarray(SEG))
    s_all = np.arange(0.002, 0.1 + 1e-9, 1e-4)
    seen = s_all <= 0.082 + 1e-9
    err = {False: [], True: []}
    for seed in range(6):
        P, cs, ns = _views(cams, s_all, np.random.default_rng(seed), 0.1)
        sub = np.flatnonzero(seen)[::5]  # stereo samples every 0.5 mm
        s = s_all[sub]
        obs = (cs[:, sub], ns[:, sub], np.ones((2, len(s))), np.full((2, len(s)), 1.2e-3))
        for extended in (False, True):
            r = fit_segments_jointly(
                cams, (None, None), (None, None), s, P[sub] + _smooth_error(s), SEG[1:],
                observations=obs, tails=(None, cs[1][~seen]) if extended else None,
            )  # fmt: skip
            ang = np.degrees(np.arccos(min(abs(float(r["normal"][2] @ n_true[2])), 1.0)))
            kerr = abs(r["kappa"][2] / np.linalg.norm(CURV[2]) - 1.0)
            err[extended].append((r["arc_length"][2], ang, kerr))
            assert r["n_tail"][0] == 0 and (r["n_tail"][1] >= 20) == extended
    trunc, ext = np.array(err[False]), np.array(err[True])
    np.testing.assert_allclose(trunc[:, 0], 0.012, atol=2e-4)
    np.testing.assert_allclose(ext[:, 0], 0.03, atol=6e-4)
    rms_t, rms_e = (
        np.sqrt(np.mean(trunc[:, 1:] ** 2, axis=0)),
        np.sqrt(np.mean(ext[:, 1:] ** 2, axis=0)),
    )
    assert rms_e[0] < rms_t[0], (rms_e, rms_t)  # plane angle (deg)
    assert rms_e[1] < 0.6 * rms_t[1], (rms_e, rms_t)  # relative curvature
    assert ext[:, 1].max() < 1.0 and ext[:, 2].max() < 0.02, ext


def test_skeleton_tail():
    """The pipeline's tail: ordered pixels after the last sample within 3 px of the end's
    projection (a path that passes the end point twice keeps only the part after the
    second pass); none when the projection is far from the skeleton."""
    from jaxcr.stereo.pipeline import _skeleton_tail

    uv = np.stack([np.arange(50.0), np.zeros(50)], 1)
    np.testing.assert_array_equal(_skeleton_tail(uv, np.array([30.0, 1.0])), uv[33:])
    loop = np.concatenate([uv, uv[::-1][1:] + [0.0, 2.0]])  # back along the path, 2 px off
    np.testing.assert_array_equal(_skeleton_tail(loop, np.array([30.0, 1.0])), loop[71:])
    assert _skeleton_tail(uv, np.array([30.0, 10.0])) is None


def test_tail_observations_on_the_true_chain(cams):
    """Pixels of the true chain's projection beyond s = 0.08 m get their true arclength
    (grid 50 mm / 256 ~ 0.2 mm: within 0.1 mm) and view 2's sine weight
    (jaxcr.stereo.diameter.view_weights at the ODE points, numerical tangents); the image
    normals are perpendicular to the projected curve."""
    from jaxcr.stereo.chain_fit import tail_observations
    from jaxcr.stereo.diameter import view_weights

    s_all = np.arange(0.08, 0.1 + 1e-9, 1e-4)
    P, cs, ns = _views(cams, s_all, np.random.default_rng(0), 0.0)
    fit = {"base": np.zeros(3), "R0": _R0(), "curvatures": CURV}
    st, c, nr, w, _ = tail_observations(cams[1], cs[1], fit, SEG, 0.08, 0.05, spacing_px=2.0)
    assert 15 <= len(st) < len(s_all)
    idx = [int(np.argmin(np.linalg.norm(cs[1] - x, axis=1))) for x in c]
    np.testing.assert_allclose(st, s_all[idx], atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(nr * ns[1][idx], axis=1)), 1.0, atol=1e-3)
    t = np.gradient(P, s_all, axis=0)
    w_ref = np.asarray(view_weights(cams[1], jnp.asarray(P[idx]), jnp.asarray(t[idx])))
    np.testing.assert_allclose(w, w_ref, atol=2e-3)
    assert tail_observations(cams[1], cs[1][:2], fit, SEG, 0.08, 0.05)[0].shape == (0,)


def test_tail_observations_measure_the_silhouette_centre():
    """With the view's alpha, tail pixels 1 px off the tube's axis (a skeleton off-centre)
    get the silhouette centre back (within 0.25 px of the true projection along the
    normal, rendered 5 px polyline in a 160x120 view), the same arclengths as without
    alpha, usable weights and consistent diameters (spread < 5 % of the median)."""
    from jaxcr.stereo.chain_fit import tail_observations

    c2 = Camera.look_at([0.0, 0.35, 0.1], [0.0, 0.02, 0.05], [0, 0, 1], 180.0, (160, 120))
    s = np.arange(0.07, 0.1 + 1e-9, 2e-4)
    P = _ode_reference(s)
    T = np.asarray(c2.T_cam_robot, np.float64)
    uv = cv2.projectPoints(P, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], np.asarray(c2.K, np.float64), np.zeros(5))[0].reshape(-1, 2)  # fmt: skip
    im = np.zeros((120, 160), np.uint8)
    cv2.polylines(im, [np.round(uv * 16).astype(np.int32)], False, 255, 5, cv2.LINE_AA, 4)
    alpha = cv2.GaussianBlur(im.astype(np.float32) / 255.0, (3, 3), 0.6)
    d = np.gradient(uv, axis=0)
    n = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
    inner = (s > 0.08) & (s < 0.098)  # away from the polyline's end caps
    fit = {"base": np.zeros(3), "R0": _R0(), "curvatures": CURV}
    shifted = uv[inner] + n[inner]
    plain = tail_observations(c2, shifted, fit, SEG, 0.075, 0.05, spacing_px=1.0)
    st, c, nr, w, dia = tail_observations(
        c2, shifted, fit, SEG, 0.075, 0.05, spacing_px=1.0, alpha=alpha, key_proj=1.0 - alpha
    )
    np.testing.assert_allclose(st, plain[0], atol=1e-7)
    assert len(st) >= 10 and (w > 0).mean() > 0.8
    true_uv = uv[inner][[int(np.argmin(np.linalg.norm(shifted - x, axis=1))) for x in plain[1]]]
    np.testing.assert_array_less(np.abs(np.sum((c - true_uv) * nr, axis=1))[w > 0], 0.25)
    assert np.std(dia[w > 0]) < 0.05 * np.median(dia[w > 0])
