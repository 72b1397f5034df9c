"""Whole-backbone consistency of two views (:mod:`jaxcr.stereo.backbone_consistency`, issue 16
item 2) on a hand-built two-camera case: a 3-D arc projected exactly into both views is
consistent (zero inconsistent length, points on the arc), the same arc with a stretch
appended in one view only is inconsistent by that stretch's length (and the open-ended match
puts all of it in that view), a tube whose return hides behind its outgoing part in one view
is found with its tip, and the DLT agrees with OpenCV ``triangulatePoints``. Numpy only (no compilation); well under a second of CPU."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from jaxcr.stereo.backbone_consistency import (
    backbone_consistency,
    fold_back_tip,
    open_end_tails,
    triangulate_pixels,
)
from jaxcr.stereo.tip_consistency import trim_unexplained_tail
from jaxcr.synth.scene import look_at_pose

K = np.array([[400.0, 0.0, 160.0], [0.0, 400.0, 120.0], [0.0, 0.0, 1.0]])
T0 = look_at_pose(np.array([0.30, -0.08, 0.06]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
T1 = look_at_pose(np.array([0.06, -0.30, 0.08]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
CAMS = [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in (T0, T1)]


def _proj(T, X):
    Xc = np.atleast_2d(X) @ T[:3, :3].T + T[:3, 3]
    x = Xc @ K.T
    return x[:, :2] / x[:, 2:]


def _arc(n=200, end=1.2):
    """An arc of radius 60 mm from the origin up z, bending towards +x and rising 10 mm
    per radian along y, to the angle ``end`` (rad); (n, 3) in metres."""
    th = np.linspace(0.0, end, n)
    r = 0.06
    return np.stack([r * (1 - np.cos(th)), 0.01 * th, r * np.sin(th)], 1)


def test_dlt_matches_opencv_and_the_points():
    X = _arc(50)
    x0, x1 = _proj(T0, X), _proj(T1, X)
    P0, P1 = K @ T0[:3], K @ T1[:3]
    ours = triangulate_pixels(P0, P1, x0, x1)
    h = cv2.triangulatePoints(P0, P1, x0.T.copy(), x1.T.copy())
    ref = (h[:3] / h[3]).T
    # float64 throughout: exact projections give the points to ~1e-12 m (condition of the
    # 4x4 system ~1e4 times eps ~1e-16, times the 0.3 m scale); 1e-9 m leaves margin.
    np.testing.assert_allclose(ours, X, atol=1e-9)
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_the_views_of_one_arc_are_consistent_and_an_extra_stretch_is_not():
    X = _arc()
    b0, b1 = _proj(T0, X), _proj(T1, X)
    res = backbone_consistency(CAMS, b0, b1, step_px=1.0)
    assert res.inconsistent_px == 0.0
    # Matched samples are on the two polylines, which are exact projections: each pair
    # is within the resampling's chord error of a correspondence (step 1 px on a curve of
    # radius > 100 px: < 0.01 px off the arc; the epipolar offset along the other
    # polyline is at most one step), so the reprojection error is below one step.
    assert np.max(res.reprojection_px) < 1.0
    # Triangulated points lie on the 3-D arc within the depth of a 1 px error
    # (0.3 m / 400 px * a triangulation angle factor < 4): 3 mm is generous, 0.3 m away.
    d = np.min(np.linalg.norm(res.points[:, None] - X[None], axis=2), axis=1)
    assert np.max(d) < 3e-3
    # View 1 sees the tube go on 40 mm past the point where view 0's trace ends, across
    # the epipolar planes (along the normal of the plane through the end and the two
    # camera centres): a stretch of ~51 px that view 0 does not explain.
    c0, c1 = (-T[:3, :3].T @ T[:3, 3] for T in (T0, T1))
    n = np.cross(c1 - c0, X[-1] - c0)
    n = n / np.linalg.norm(n)
    beyond = X[-1] + np.outer(np.linspace(0.0, 0.04, 120)[1:], n)
    b1l = _proj(T1, np.vstack([X, beyond]))
    stretch = float(np.sum(np.linalg.norm(np.diff(b1l[len(X) - 1 :], axis=0), axis=1)))
    res2 = backbone_consistency(CAMS, b0, b1l, step_px=1.0)
    # The matching runs from end to end, so the unexplained stretch is paired with view
    # 0's last samples; the path takes diagonal steps through it (fewer cells of the
    # clipped cost), so the mismatch is shared between the stretch and view 0's end and
    # the inconsistent length lies between half the stretch and twice it (+1 step).
    assert 0.5 * stretch <= res2.inconsistent_px <= 2.0 * stretch + 1.0, (
        res2.inconsistent_px,
        stretch,
    )
    # The first half of view 0 is far from the stretch's epipolar lines: explained.
    assert np.all(res2.residual_px[0][: len(res2.residual_px[0]) // 2] <= 3.0)


def test_an_unexplained_tail_is_trimmed_only_without_tube_beyond_the_other_tip():
    """:func:`trim_unexplained_tail` on a hand-made matching: view 1's last 30 samples
    (1 px apart) are paired with view 0's last sample at 10 px reprojection error (its
    unexplained tail); the rest pairs one to one at 0.5 px."""
    b0 = np.stack([np.linspace(20.0, 100.0, 81), np.full(81, 60.0)], 1)
    b1 = np.stack([np.linspace(20.0, 130.0, 111), np.full(111, 80.0)], 1)
    pairs = np.r_[np.c_[np.arange(81), np.arange(81)], np.c_[np.full(30, 80), np.arange(81, 111)]]
    res1 = np.r_[np.full(81, 0.5), np.full(30, 10.0)]
    bc = SimpleNamespace(
        pairs=pairs,
        residual_px=[np.full(81, 0.5), res1],
        samples=[b0, b1],
        steps_px=np.array([1.0, 1.0]),
    )
    traces = [
        SimpleNamespace(backbone=b, width_px=8.0, score=np.zeros((160, 200))) for b in (b0, b1)
    ]
    tips = [b0[-1], b1[-1]]
    cut = trim_unexplained_tail(CAMS, traces, tips, bc)
    # View 1's tip moves back to its first sample paired with view 0's tip (index 80).
    assert cut is not None and cut.action == "trimmed" and cut.view == 1
    np.testing.assert_array_equal(cut.tips[1], b1[80])
    np.testing.assert_array_equal(cut.tips[0], b0[-1])
    # The tube seen beyond view 0's tip (score 1 on its continuation): nothing decided.
    traces[0].score = np.ones((160, 200))
    assert trim_unexplained_tail(CAMS, traces, tips, bc) is None
    # A tail shorter than the tube's width is no overshoot.
    traces[0].score = np.zeros((160, 200))
    traces[1].width_px = 40.0
    assert trim_unexplained_tail(CAMS, traces, tips, bc) is None


def _beyond(X, length=0.04, n=120):
    """X extended from its end by ``length`` m across the epipolar planes (along the
    normal of the plane through the end and the two camera centres)."""
    c0, c1 = (-T[:3, :3].T @ T[:3, 3] for T in (T0, T1))
    nrm = np.cross(c1 - c0, X[-1] - c0)
    nrm = nrm / np.linalg.norm(nrm)
    return X[-1] + np.outer(np.linspace(0.0, length, n)[1:], nrm)


def test_open_end_places_an_unseen_stretch_in_the_view_that_has_it():
    """:func:`open_end_tails`: the stretch view 1 sees past view 0's end (the case above,
    where the end-to-end match shares it between the two ends) is all in view 1's tail,
    and cutting view 0 instead is the costlier explanation."""
    X = _arc()
    b0 = _proj(T0, X)
    b1 = _proj(T1, np.vstack([X, _beyond(X)]))
    stretch = float(np.sum(np.linalg.norm(np.diff(b1[len(X) - 1 :], axis=0), axis=1)))
    tails = open_end_tails(CAMS, backbone_consistency(CAMS, b0, b1, step_px=1.0))
    # Resampled every 1 px: the cut lies within a sample or two of the end of the arc
    # (the stretch leaves the end's epipolar plane at a right angle, so its first samples
    # are 1-2 px off the plane: under 2 tol_px = 6 px they may still be matched, a few
    # px of the 51 px stretch); 6 px covers that and the step.
    assert abs(tails[1][1] - stretch) <= 6.0, (tails, stretch)
    # Cutting view 0 instead leaves the stretch in the match (each of its ~50 samples
    # costs up to the 50 px cap, at least 6 px once off the end's plane): a costlier
    # explanation than leaving it out at 6 px a sample.
    assert tails[1][2] < tails[0][2]
    # Nothing beyond either end: no tail (within the step).
    full = open_end_tails(CAMS, backbone_consistency(CAMS, b0, _proj(T1, X), step_px=1.0))
    assert full[0][1] <= 1.0 and full[1][1] <= 1.0


def test_a_tube_folding_back_over_itself_in_one_view_is_found():
    """:func:`fold_back_tip`: the tube's second half lies on camera 1's rays through its
    first half (taken backwards), deeper; view 1 sees there and back on one line, and its
    trace stops at the fold. The tip in view 1 is where the return ends, the projection
    of the tube's end, which view 0 sees whole."""
    X = _arc(120, end=1.0)
    c1 = -T1[:3, :3].T @ T1[:3, 3]
    m = 40  # the return runs back over 40 samples, to X[-41]'s image
    lam = 1.0 + 0.6 * np.linspace(0.0, 1.0, m + 1)[1:]
    back = c1 + lam[:, None] * (X[-2 : -m - 2 : -1] - c1)
    tube = np.vstack([X, back])
    b0, b1 = _proj(T0, tube), _proj(T1, X)
    bc = backbone_consistency(CAMS, b0, b1, step_px=1.0)
    fold = fold_back_tip(CAMS, bc, [8.0, 8.0])
    assert fold is not None and fold[0] == 1
    # The true tip's image is X[-41]'s: on the resampled polyline within a step of the
    # match's last sample, plus the epipolar matching's own one-sample slack: 2 px.
    truth = _proj(T1, back[-1])[0]
    assert np.linalg.norm(fold[1] - truth) <= 2.0, (fold[1], truth)
    # The views of one arc: nothing folds.
    assert fold_back_tip(CAMS, backbone_consistency(CAMS, _proj(T0, X), b1, step_px=1.0),
                         [8.0, 8.0]) is None  # fmt: skip
