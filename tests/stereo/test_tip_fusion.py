"""jaxcr.stereo.tip_fusion: the Mahalanobis triangulation against OpenCV's optimal
triangulation in the isotropic case (``cv2.correctMatches``, Hartley-Sturm, then
``cv2.triangulatePoints``) and against a brute-force minimisation (scipy Nelder-Mead on a
cost projected by ``cv2.projectPoints``) in the anisotropic one; the fused tips on a rig
without calibration error; the end's fall-off against a closed-form erf step.

Tolerances (float64 throughout): the optimal points agree to 1e-6 px (Hartley-Sturm roots
of a degree-6 polynomial, Gauss-Newton to a relative cost change of 1e-12); the brute force
to 1e-4 px (Nelder-Mead's own tolerance); the fall-off to 0.15 px (bilinear sampling of a
1-px grid and 0.5-px linear interpolation of the 20/80 % crossings)."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.special import erf

from jaxcr.stereo.epipolar_tolerance import CalibrationUncertainty
from jaxcr.stereo.tip_fusion import (
    end_covariance,
    end_falloff_px,
    fuse_tips,
    fuse_traced_tips,
    mahalanobis_triangulate,
)
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses
from tests.helpers.stereo_views import cam as _cam
from tests.helpers.stereo_views import project as _project

CAMS = [_cam([0.0, 0.0, 0.0], [0.0, -0.02, 0.35]), _cam([0.0, -0.35, 0.0], [-0.12, -0.02, 0.37])]
PINHOLE = [SimpleNamespace(K=c.K, dist=np.zeros(5), T_cam_robot=c.T_cam_robot) for c in CAMS]
EXACT = CalibrationUncertainty(0.0, 0.0, 0.0, 0.0, tip_px=0.0)


def _KT():
    return [c.K for c in CAMS], [c.T_cam_robot for c in CAMS]


def _noisy_pixels(rng, X):
    Ks, Ts = _KT()
    return [_project(SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T), X[None])[0]
            + rng.normal(0, 2.0, 2) for K, T in zip(Ks, Ts, strict=True)]  # fmt: skip


def _reproject(K, T, X):
    return _project(SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T), X[None])[0]


@pytest.mark.parametrize("seed", range(5))
def test_isotropic_equals_opencv_optimal_triangulation(seed):
    rng = np.random.default_rng(seed)
    X_true = rng.uniform([-0.04, -0.04, -0.02], [0.04, 0.04, 0.04])
    Ks, Ts = _KT()
    xs = _noisy_pixels(rng, X_true)
    X, _ = mahalanobis_triangulate(Ks, Ts, xs, [np.eye(2), np.eye(2)])
    # In normalised coordinates (both focal lengths 900 px: the same minimiser; OpenCV's
    # polynomial is ill-scaled with a pixel F).
    E = Ks[1].T @ fundamental_from_poses(Ks[0], Ts[0], Ks[1], Ts[1]) @ Ks[0]
    n = [np.linalg.solve(K, np.r_[x, 1.0])[:2] for K, x in zip(Ks, xs, strict=True)]
    c1, c2 = cv2.correctMatches(E / np.linalg.norm(E), n[0].reshape(1, 1, 2), n[1].reshape(1, 1, 2))
    Xh = cv2.triangulatePoints(Ts[0][:3], Ts[1][:3], c1.reshape(2, 1), c2.reshape(2, 1)).ravel()
    X_cv = Xh[:3] / Xh[3]
    for K, T, c in zip(Ks, Ts, (c1, c2), strict=True):
        np.testing.assert_allclose(_reproject(K, T, X), (K @ np.r_[c.ravel(), 1.0])[:2], atol=1e-6)
    np.testing.assert_allclose(X, X_cv, atol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_anisotropic_equals_brute_force(seed):
    rng = np.random.default_rng(10 + seed)
    X_true = rng.uniform([-0.04, -0.04, -0.02], [0.04, 0.04, 0.04])
    Ks, Ts = _KT()
    xs = _noisy_pixels(rng, X_true)
    covs = [end_covariance(rng.normal(size=2), 6.0, 0.4, 0.3),
            end_covariance(rng.normal(size=2), 1.5, 0.5)]  # fmt: skip
    X, cost = mahalanobis_triangulate(Ks, Ts, xs, covs)
    W = [np.linalg.inv(C) for C in covs]

    def brute_cost(Xmm):
        c = 0.0
        for K, T, x, w in zip(Ks, Ts, xs, W, strict=True):
            r = _reproject(K, T, Xmm * 1e-3) - x
            c += r @ w @ r
        return c

    res = minimize(brute_cost, X_true * 1e3, method="Nelder-Mead",
                   options={"xatol": 1e-9, "fatol": 1e-14, "maxiter": 20000})  # fmt: skip
    assert cost <= res.fun + 1e-9
    for K, T in zip(Ks, Ts, strict=True):
        np.testing.assert_allclose(_reproject(K, T, X), _reproject(K, T, res.x * 1e-3), atol=1e-4)


def test_covariance_axes():
    d = np.array([3.0, 4.0])
    C = end_covariance(d, 5.0, 0.5, 0.2)
    u = d / 5.0
    n = np.array([-u[1], u[0]])
    assert u @ C @ u == pytest.approx(25.04)
    assert n @ C @ n == pytest.approx(0.29)
    assert u @ C @ n == pytest.approx(0.0, abs=1e-12)


def _tube_tips(offset_px):
    """True tip X, its pixels in both (pinhole) views, view 0's pixel moved ``offset_px``
    along its image direction of a 3-D tube axis, and the two image directions."""
    X = np.array([0.01, -0.005, 0.01])
    axis = np.array([0.6, 0.7, 0.39])
    axis /= np.linalg.norm(axis)
    tips, dirs = [], []
    for c in PINHOLE:
        a, b = _project(c, np.stack([X, X + 1e-3 * axis]))
        d = (b - a) / np.linalg.norm(b - a)
        tips.append(a)
        dirs.append(d)
    moved = [tips[0] + offset_px * dirs[0], tips[1].copy()]
    return X, tips, moved, dirs


def test_fused_tips_recover_an_end_off_along_the_tube():
    """View 0 placed 8 px long, its along variance large, view 1 precise, no calibration
    error: the fused end is the true one (the other view's along evidence carried)."""
    X, truth, moved, dirs = _tube_tips(8.0)
    f = fuse_tips(PINHOLE, moved, dirs, sigma_along=[100.0, 0.01], calibration=EXACT,
                  sigma_across=0.01)  # fmt: skip
    assert f.applied and f.reason == "fused"
    assert f.sin.min() > 0.3
    for a, b in zip(f.tips, truth, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-3)
    np.testing.assert_allclose(f.point, X, atol=1e-7)
    assert f.moved_px[0] == pytest.approx(8.0, abs=1e-3)


def test_equal_weights_share_the_along_error_and_fused_tips_are_epipolar_consistent():
    _, truth, moved, dirs = _tube_tips(6.0)
    f = fuse_tips(CAMS, moved, dirs, sigma_along=[3.0, 3.0], calibration=EXACT, sigma_across=0.5)
    assert 0.5 < f.moved_px[0] < 6.0 and f.moved_px[1] > 0.5
    Ks, Ts = _KT()
    und = [cv2.undistortPoints(t.reshape(1, 1, 2), c.K, c.dist, P=c.K).reshape(2)
           for t, c in zip(f.tips, CAMS, strict=True)]  # fmt: skip
    d = epipolar_distances(fundamental_from_poses(Ks[0], Ts[0], Ks[1], Ts[1]), *und)
    assert max(d) < 1e-4


def test_gates_keep_the_tips():
    _, _, moved, dirs = _tube_tips(6.0)
    f = fuse_tips(PINHOLE, moved, dirs, sigma_along=[3.0, 3.0], calibration=EXACT, min_sin=0.999)
    assert not f.applied and f.reason == "along_epipolar"
    assert all(np.array_equal(a, b) for a, b in zip(f.tips, moved, strict=True))
    f = fuse_tips(PINHOLE, moved, dirs, sigma_along=[0.1, 0.1], calibration=EXACT,
                  sigma_across=0.1, max_chi2=9.0)  # fmt: skip
    assert not f.applied and f.reason == "disagree" and f.chi2 > 9.0
    assert fuse_tips(PINHOLE, [moved[0], np.array([np.nan, 1.0])], dirs,
                     sigma_along=[3.0, 3.0], calibration=EXACT) is None  # fmt: skip


@pytest.mark.parametrize("angle_deg", [0.0, 37.0, 120.0])
def test_falloff_of_an_erf_step(angle_deg):
    """A tube end blurred by a Gaussian of sigma 2 px: its 20-80 % distance is
    2 * 0.8416 * 2 px (the normal quantiles), whatever the direction."""
    s, R = 2.0, 4.0
    a = np.radians(angle_deg)
    d = np.array([np.cos(a), np.sin(a)])
    tip = np.array([40.3, 41.7])
    v, u = np.mgrid[0:84, 0:84].astype(np.float64)
    tau = (u - tip[0]) * d[0] + (v - tip[1]) * d[1]
    score = 0.2 + 0.6 * 0.5 * (1.0 - erf(tau / (np.sqrt(2.0) * s)))
    assert end_falloff_px(score, tip, d, R) == pytest.approx(2 * 0.8416 * s, abs=0.15)
    assert np.isnan(end_falloff_px(np.full((84, 84), 0.5), tip, d, R))


def test_noise_removed_leaves_the_calibration_offset():
    """Right tips on a miscalibrated rig (view 1's true camera turned 0.1 deg about its x axis): the
    residual is the calibration's; with a placement error far smaller than the calibration
    term the tips stay nearly put, while the reprojections move by the epipolar offset."""
    X, _, _, dirs = _tube_tips(0.0)
    T = PINHOLE[1].T_cam_robot.copy()
    T[:3] = cv2.Rodrigues(np.array([np.radians(0.1), 0.0, 0.0]))[0] @ T[:3]  # about its centre
    true1 = _project(SimpleNamespace(K=PINHOLE[1].K, dist=np.zeros(5), T_cam_robot=T), X[None])[0]
    tips = [_project(PINHOLE[0], X[None])[0], true1]
    unc = CalibrationUncertainty(0.0, 1.0, 0.0, 0.0, tip_px=0.0)  # ~1.1 px per view
    kw = dict(sigma_along=[0.05, 0.05], calibration=unc, sigma_across=0.05)
    rep = fuse_tips(PINHOLE, tips, dirs, output="reprojected", **kw)
    rem = fuse_tips(PINHOLE, tips, dirs, output="noise_removed", **kw)
    assert rep.moved_px.max() > 0.3
    assert rem.tips[0] == pytest.approx(tips[0], abs=0.01)
    assert rem.tips[1] == pytest.approx(tips[1], abs=0.01)
    with pytest.raises(ValueError, match="output must be"):
        fuse_tips(PINHOLE, tips, dirs, output="both", **kw)


def test_fuse_traced_tips_reads_the_traces():
    """The traced views' end directions and a constant along sigma, as fuse_tips; with
    ``sigma_along_px=None`` the fall-off of the traces' scores decides the weights (here
    view 0's end is blurred 3 px, view 1's sharp, so view 0 takes the along correction)."""
    _, _, moved, dirs = _tube_tips(6.0)
    v, u = np.mgrid[0:720, 0:1280].astype(np.float64)

    def trace(tip, d, blur):
        tau = (u - tip[0]) * d[0] + (v - tip[1]) * d[1]
        score = 0.8 * 0.5 * (1.0 - erf(tau / (np.sqrt(2.0) * blur)))
        return SimpleNamespace(end_dir=d, score=score, end_half_width_px=4.0)

    traces = [trace(moved[0], dirs[0], 3.0), trace(moved[1], dirs[1], 0.3)]
    a = fuse_traced_tips(PINHOLE, traces, moved, EXACT, sigma_along_px=8.0)
    b = fuse_tips(PINHOLE, moved, dirs, sigma_along=[8.0, 8.0], calibration=EXACT,
                  sigma_across=1.0, min_sin=0.1)  # fmt: skip
    for x, y in zip(a.tips, b.tips, strict=True):
        np.testing.assert_array_equal(x, y)
    c = fuse_traced_tips(PINHOLE, traces, moved, EXACT, sigma_along_px=None)
    assert c.sigma_along[0] > 2.0 * c.sigma_along[1]
    assert c.moved_px[0] > 2.0 * c.moved_px[1]
