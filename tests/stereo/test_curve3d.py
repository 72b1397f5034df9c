"""jaxcr.stereo.curve3d: one smooth 3-D curve fitted to two views' backbones, against a
closed-form curve projected by OpenCV and OpenCV's triangulatePoints."""

import cv2
import numpy as np
import pytest
from scipy.interpolate import BSpline

from jaxcr.stereo.curve3d import fit_spline_pair, spline_basis
from tests.helpers.stereo_views import cam as _cam
from tests.helpers.stereo_views import project as _project


def _arc(n=400):
    """A planar circular arc of 60 mm radius turned by 120 deg, its plane across the
    baseline (x) and tilted: a closed-form 3-D curve (metres) that no epipolar plane
    contains."""
    a = np.linspace(0.0, np.radians(120.0), n)
    r = 0.06
    X = np.stack([0.3 * r * np.sin(a), -r * (1 - np.cos(a)), r * np.sin(a)], 1)
    return X


CAMS = [_cam([0.0, 0.0, 0.0], [0.0, -0.02, 0.35]), _cam([0.0, -0.35, 0.0], [-0.12, -0.02, 0.37])]


def test_basis_partition_of_unity_and_derivative():
    t = np.linspace(0, 1, 37)
    _, B, dB = spline_basis(8, t)
    np.testing.assert_allclose(B.sum(1), 1.0, atol=1e-12)
    # dB against central differences of B
    h = 1e-6
    _, Bp, _ = spline_basis(8, np.clip(t + h, 0, 1))
    _, Bm, _ = spline_basis(8, np.clip(t - h, 0, 1))
    inner = (t > 2 * h) & (t < 1 - 2 * h)
    np.testing.assert_allclose(dB[inner], ((Bp - Bm) / (2 * h))[inner], atol=1e-4)


def test_fit_recovers_arc_and_ends_match_opencv_triangulation():
    X = _arc()
    bb = [_project(c, X) for c in CAMS]
    fit = fit_spline_pair(CAMS, bb[0], bb[1])
    assert fit is not None
    # Exact data: every point explained to a fraction of a pixel.
    assert fit.unexplained_px == 0.0
    assert fit.rms_px < 0.3
    # The curve lies on the true arc: each curve point within 1.5 mm of it (the arc is
    # ~130 mm long; the ordered feet are picked per cell of a 160-point grid, 0.8 mm, and
    # 1.5 mm is ~1.3 px of disparity at this depth).
    C = fit.points(np.linspace(0, 1, 200))
    d = np.min(np.linalg.norm(C[:, None] - X[None], axis=2), axis=1)
    assert d.max() < 1.5e-3
    # Its ends against OpenCV's triangulation (the same 1.5 mm) of the two views' end pixels (undistorted).
    P = [c.K @ c.T_cam_robot[:3] for c in CAMS]
    und = [cv2.undistortPoints(b[[0, -1]].reshape(-1, 1, 2), c.K, c.dist, P=c.K).reshape(-1, 2)
           for b, c in zip(bb, CAMS, strict=True)]  # fmt: skip
    Xh = cv2.triangulatePoints(P[0], P[1], und[0].T, und[1].T)
    ends_cv = (Xh[:3] / Xh[3]).T
    np.testing.assert_allclose(fit.points([0.0, 1.0]), ends_cv, atol=1.5e-3)


def test_wrong_tail_in_one_view_is_unexplained():
    X = _arc()
    bb = [_project(c, X) for c in CAMS]
    # View 2's trace runs on 120 px straight past the end (onto a cable; the epipolar lines
    # are near horizontal here and the end runs up, so view 1 cannot see it): that much of it
    # cannot be one curve with view 1: at least half of it is left unexplained (the
    # curve's end bends towards it, explaining its first part within 3 px).
    d = bb[1][-1] - bb[1][-8]
    d = d / np.linalg.norm(d)
    tail = bb[1][-1] + np.linspace(0, 120, 60)[1:, None] * d
    good = fit_spline_pair(CAMS, bb[0], bb[1], step_px=6.0)
    bad = fit_spline_pair(CAMS, bb[0], np.vstack([bb[1], tail]), step_px=6.0)
    assert bad.unexplained_px > 60.0
    assert bad.unexplained_px > good.unexplained_px + 60.0


def test_unordered_feet_also_recover_the_arc():
    X = _arc()
    bb = [_project(c, X) for c in CAMS]
    fit = fit_spline_pair(CAMS, bb[0], bb[1], ordered=False)
    C = fit.points(np.linspace(0, 1, 200))
    assert np.min(np.linalg.norm(C[:, None] - X[None], axis=2), axis=1).max() < 1.5e-3
    assert fit.unexplained_px == 0.0


def test_degenerate_inputs():
    assert fit_spline_pair(CAMS, np.zeros((1, 2)), np.zeros((5, 2))) is None


@pytest.mark.parametrize("n_ctrl", [6, 12])
def test_points_match_scipy_bspline(n_ctrl):
    X = _arc()
    bb = [_project(c, X) for c in CAMS]
    fit = fit_spline_pair(CAMS, bb[0], bb[1], n_ctrl=n_ctrl)
    t = np.linspace(0, 1, 11)
    _, B, _ = spline_basis(n_ctrl, t)
    np.testing.assert_allclose(B @ fit.ctrl, BSpline(fit.knots, fit.ctrl, 3)(t), atol=1e-12)
