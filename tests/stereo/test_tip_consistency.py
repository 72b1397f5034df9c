"""Epipolar re-search of the two views' tips (:mod:`jaxcr.stereo.tip_consistency`, issue 16
item 2, open item a) on a small synthetic rig: a 3-D arc seen by two 160x120 pinhole
cameras, each view's "trace" the projected centre line (closed form), one of them spoiled
as a tracer spoils it on a real rig. The reference is the true tip's projection."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from jaxcr.stereo.tip_consistency import reconcile_tips
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses
from jaxcr.synth.scene import look_at_pose

W, H = 160, 120
K = np.array([[220.0, 0.0, 80.0], [0.0, 220.0, 60.0], [0.0, 0.0, 1.0]])
T0 = look_at_pose(np.array([0.30, -0.08, 0.06]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
T1 = look_at_pose(np.array([0.06, -0.30, 0.08]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))


def _cam(T):
    return SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T)


CAMS = [_cam(T0), _cam(T1)]

# The tube: an arc of radius 0.1 m in the x-z plane, 0.08 m long, from the base upwards.
S = np.linspace(0.0, 0.08, 161)
P = np.stack([0.1 * (1 - np.cos(S / 0.1)), np.zeros_like(S), 0.1 * np.sin(S / 0.1)], 1)


def _proj(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    x = Xc @ K.T
    return x[:, :2] / x[:, 2:]


def _score(line: np.ndarray, value: float = 1.0) -> np.ndarray:
    img = np.zeros((H, W), np.float32)
    cv2.polylines(img, [np.round(line * 16).astype(np.int32)], False, value, 5, cv2.LINE_AA, 4)
    return img


def _epi(tips):
    F = fundamental_from_poses(K, T0, K, T1)
    return max(epipolar_distances(F, tips[0], tips[1]))


LINES = [_proj(T, P) for T in (T0, T1)]
TRUE_TIPS = [ln[-1] for ln in LINES]


def _overshoot(line: np.ndarray, turn_deg: float, length: float) -> np.ndarray:
    """The line continued past its end by ``length`` px, turned by ``turn_deg`` (a trace
    that ran on onto a shadow or a cable touching the tip)."""
    d = line[-1] - line[-3]
    d /= np.linalg.norm(d)
    a = np.radians(turn_deg)
    d = np.array([np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1]])
    extra = line[-1] + np.arange(1.0, length + 0.5, 1.0)[:, None] * d
    return np.vstack([line, extra])


def test_the_synthetic_rig_sees_the_tube_in_both_views():
    for ln in LINES:
        assert np.all((ln >= 0) & (ln <= [W - 1, H - 1]))
    # The true tips are consistent (pinhole, exact poses): below 1e-6 px.
    assert _epi(TRUE_TIPS) < 1e-6


@pytest.mark.parametrize("view", [0, 1])
def test_an_overshooting_view_is_cut_back_to_the_other_views_epipolar_line(view):
    """View ``view``'s trace ran 20 px past the tube's end, turned by -50 deg (its score is
    foreground there too: a shadow); the other view ends at the true tip and its score has
    nothing beyond (evidence 0). The tip moves back to the crossing of its backbone with
    the other tip's epipolar line: the true tip up to the 0.5 px resampling of the
    backbone and the antialiased line (0.5 px)."""
    lines = list(LINES)
    lines[view] = _overshoot(LINES[view], -50.0, 20.0)
    traces = [SimpleNamespace(backbone=ln, score=_score(ln), width_px=5.0) for ln in lines]
    tips = [ln[-1] for ln in lines]
    assert _epi(tips) > 5.0  # flagged (the old pipeline kept these tips)
    res = reconcile_tips(CAMS, traces, tips)
    assert res.action == "cut" and res.view == view, res
    assert np.linalg.norm(res.tips[view] - TRUE_TIPS[view]) < 0.5
    np.testing.assert_array_equal(res.tips[1 - view], tips[1 - view])
    assert res.epipolar_after_px < 0.5


def test_a_short_view_with_tube_ahead_is_extended_to_the_epipolar_line():
    """View 0's trace stopped 15 px short of the tube's end although its score shows the
    tube there (at 0.5, above ``low``: e.g. the tracer's support test failed in a dark
    crease). It moves on along its last stretch's arc to the epipolar line of view 1's tip:
    within 1.5 px of the true tip (the constant-curvature extrapolation of a projected arc
    over 15 px; measured 0.2 px)."""
    s = np.cumsum(np.r_[0.0, np.linalg.norm(np.diff(LINES[0], axis=0), axis=1)])
    short = LINES[0][s <= s[-1] - 15.0]
    score0 = np.maximum(_score(short), _score(LINES[0], 0.5))
    traces = [SimpleNamespace(backbone=short, score=score0),
              SimpleNamespace(backbone=LINES[1], score=_score(LINES[1]))]  # fmt: skip
    tips = [short[-1], LINES[1][-1]]
    assert _epi(tips) > 5.0
    res = reconcile_tips(CAMS, traces, tips)
    assert res.action == "extended" and res.view == 0, res
    assert np.linalg.norm(res.tips[0] - TRUE_TIPS[0]) < 1.5


def test_consistent_tips_are_left_alone_and_undecidable_ones_kept():
    traces = [SimpleNamespace(backbone=ln, score=_score(ln)) for ln in LINES]
    res = reconcile_tips(CAMS, traces, TRUE_TIPS)
    assert res.action == "consistent"
    # Short view whose score beyond its tip is half tube, half background (evidence
    # between absent and present): no decision, the tips are kept.
    s = np.cumsum(np.r_[0.0, np.linalg.norm(np.diff(LINES[0], axis=0), axis=1)])
    short = LINES[0][s <= s[-1] - 16.0]
    mid = LINES[0][(s > s[-1] - 16.0) & (s <= s[-1] - 8.0)]
    score0 = np.maximum(_score(short), _score(np.vstack([short[-1:], mid]), 0.5))
    traces = [SimpleNamespace(backbone=short, score=score0),
              SimpleNamespace(backbone=LINES[1], score=_score(LINES[1]))]  # fmt: skip
    res = reconcile_tips(CAMS, traces, [short[-1], LINES[1][-1]])
    assert res.action == "kept", res
    np.testing.assert_array_equal(res.tips[0], short[-1])
