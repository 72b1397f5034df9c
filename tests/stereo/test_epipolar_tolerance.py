"""jaxcr.stereo.epipolar_tolerance: the epipolar distance's spread of two right tips under a
stated calibration uncertainty, against a Monte Carlo reference in OpenCV (cameras drawn
from the uncertainty, ``cv2.projectPoints`` with lens distortion, ``cv2.undistortPoints``
with the calibrated cameras, ``cv2.computeCorrespondEpilines`` on a fundamental matrix from
``cv2.findFundamentalMat``)."""

import cv2
import numpy as np
import pytest

from jaxcr.stereo.epipolar_tolerance import (
    REAL_LIKE_CALIBRATION,
    CalibrationUncertainty,
    epipolar_sigma_px,
    tip_epipolar_tolerance_px,
)
from tests.helpers.stereo_views import cam as _cam
from tests.helpers.stereo_views import project as _project

CAMS = [_cam([0.0, 0.0, 0.0], [0.0, -0.02, 0.35]), _cam([0.0, -0.35, 0.0], [-0.12, -0.02, 0.37])]
UNC = CalibrationUncertainty(focal_rel=0.002, principal_px=0.8, rotation_rad=6e-4,
                             translation_m=2e-4, tip_px=0.5)  # fmt: skip


def _fundamental_cv():
    """F from 60 points in a volume, undistorted projections, OpenCV's 8-point method."""
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.05, -0.05, -0.03], [0.05, 0.05, 0.05], (60, 3))
    und = [_undistort(c, _project(c, X)) for c in CAMS]
    F, _ = cv2.findFundamentalMat(und[0], und[1], cv2.FM_8POINT)
    return F


def _undistort(cam, uv):
    return cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K).reshape(-1, 2)


def _drawn(cam, rng, unc):
    """``cam`` with a calibration error drawn from ``unc`` (independent normals)."""
    K = cam.K.copy()
    K[0, 0] *= 1 + rng.normal(0, unc.focal_rel)
    K[1, 1] *= 1 + rng.normal(0, unc.focal_rel)
    K[:2, 2] += rng.normal(0, unc.principal_px, 2)
    dR = cv2.Rodrigues(rng.normal(0, unc.rotation_rad, 3))[0]
    T = cam.T_cam_robot.copy()
    T[:3, :3] = dR @ T[:3, :3]
    T[:3, 3] = dR @ T[:3, 3] + rng.normal(0, unc.translation_m, 3)
    return type(cam)(K=K, dist=cam.dist, T_cam_robot=T)


def _monte_carlo(X, unc, n=3000):
    """Standard deviation of each image's signed epipolar distance (image 2, image 1) of the
    true cameras' pixels of ``X``, read with the calibrated cameras."""
    F = _fundamental_cv()
    rng = np.random.default_rng(1)
    d = np.empty((n, 2))
    for i in range(n):
        true = [_drawn(c, rng, unc) for c in CAMS]
        uv = [_project(t, X[None])[0] + rng.normal(0, unc.tip_px, 2) for t in true]
        x = [_undistort(c, u)[0] for c, u in zip(CAMS, uv, strict=True)]
        l2 = cv2.computeCorrespondEpilines(x[0].reshape(1, 1, 2), 1, F).reshape(3)
        l1 = cv2.computeCorrespondEpilines(x[1].reshape(1, 1, 2), 2, F).reshape(3)
        d[i] = [l2 @ np.r_[x[1], 1.0], l1 @ np.r_[x[0], 1.0]]  # lines normalised by OpenCV
    return d.std(axis=0)


@pytest.mark.parametrize("X", [np.array([0.01, -0.02, 0.03]), np.array([-0.03, 0.02, -0.01])])
def test_sigma_matches_monte_carlo(X):
    # First order in errors of ~1e-3 relative; 3000 draws give the std to ~1.3 % (1 sigma):
    # 6 % covers both on any machine.
    tips = [_project(c, X[None])[0] for c in CAMS]
    sig = epipolar_sigma_px(CAMS, tips, UNC)
    ref = _monte_carlo(X, UNC)
    np.testing.assert_allclose(sig, ref, rtol=0.06)


def test_exact_calibration_leaves_the_tips_own_error():
    X = np.array([0.01, -0.02, 0.03])
    tips = [_project(c, X[None])[0] for c in CAMS]
    sig = epipolar_sigma_px(CAMS, tips, CalibrationUncertainty(0.0, 0.0, 0.0, 0.0, tip_px=0.7))
    np.testing.assert_allclose(sig, [np.sqrt(2) * 0.7] * 2, rtol=1e-9)


def test_tolerance_floor_and_undefined():
    X = np.array([0.01, -0.02, 0.03])
    tips = [_project(c, X[None])[0] for c in CAMS]
    sig = epipolar_sigma_px(CAMS, tips, REAL_LIKE_CALIBRATION)
    tol = tip_epipolar_tolerance_px(CAMS, tips, REAL_LIKE_CALIBRATION, floor_px=0.0)
    assert tol == pytest.approx(3.0 * max(sig))
    assert tip_epipolar_tolerance_px(CAMS, tips, REAL_LIKE_CALIBRATION, floor_px=50.0) == 50.0
    bad = [tips[0], np.array([np.nan, 1.0])]
    assert epipolar_sigma_px(CAMS, bad, REAL_LIKE_CALIBRATION) is None
    assert tip_epipolar_tolerance_px(CAMS, bad, REAL_LIKE_CALIBRATION) == 5.0


def _overshooting_traces(length_px):
    """The rig of tests/stereo/test_tip_consistency.py, view 1's trace run on ``length_px``
    past the tube's end (turned by -50 deg: a shadow); 5 px wide tubes."""
    from types import SimpleNamespace

    from tests.stereo.test_tip_consistency import CAMS as RIG
    from tests.stereo.test_tip_consistency import LINES, _overshoot, _score

    lines = [_overshoot(LINES[0], -50.0, length_px), LINES[1]]
    traces = [SimpleNamespace(backbone=ln, score=_score(ln), width_px=5.0, tip=ln[-1],
                              end_dir=np.zeros(2), cap_px=0.0, end_half_width_px=0.0)
              for ln in lines]  # fmt: skip
    return RIG, traces, [ln[-1] for ln in lines]


WIDE = CalibrationUncertainty(0.01, 2.0, 0.02, 2e-3)


def test_traced_stereo_tips_leaves_a_gap_within_the_calibrations_tolerance():
    """A 10 px overshoot (under two widths: no trim) leaves the tips 8 px apart: without a
    stated calibration the re-search cuts view 1 back; with an uncertainty whose tolerance
    exceeds the gap the tips are left as they are ("consistent"); with one whose tolerance
    is under it (the 5 px floor) the result is the plain one."""
    from jaxcr.stereo.pipeline import traced_stereo_tips
    from jaxcr.stereo.tip_consistency import epipolar_gap_px

    rig, traces, tips = _overshooting_traces(10.0)
    gap = epipolar_gap_px(rig, tips)
    assert gap > 5.0
    plain = traced_stereo_tips(rig, traces)
    assert plain[2].action == "cut"
    assert tip_epipolar_tolerance_px(rig, tips, WIDE) > gap
    out = traced_stereo_tips(rig, traces, calibration=WIDE)
    assert out[2].action == "consistent"
    for a, b in zip(out[0], tips, strict=True):
        np.testing.assert_array_equal(a, b)
    tight = CalibrationUncertainty(1e-4, 0.01, 1e-5, 1e-6, tip_px=0.01)
    assert tip_epipolar_tolerance_px(rig, tips, tight) == 5.0
    again = traced_stereo_tips(rig, traces, calibration=tight)
    assert again[2].action == plain[2].action
    for a, b in zip(again[0], plain[0], strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_trim_keeps_the_5px_flag_under_a_wide_calibration():
    """A 12 px overshoot leaves a tail over a tube width unexplained: the trim cuts it with
    or without a stated calibration (a tail that long is no calibration error)."""
    from jaxcr.stereo.pipeline import traced_stereo_tips

    rig, traces, tips = _overshooting_traces(12.0)
    plain = traced_stereo_tips(rig, traces)
    assert plain[2].action == "trimmed"
    out = traced_stereo_tips(rig, traces, calibration=WIDE)
    assert out[2].action == "trimmed"
    for a, b in zip(out[0], plain[0], strict=True):
        np.testing.assert_array_equal(a, b)
