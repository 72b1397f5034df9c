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


# --- S19: the view that disagrees re-decides its end by the other view's tip -------------
# The tube is drawn 5 px wide (its mask, cv2.LINE_8 at 1/16 px); a view's wrong trace left
# the tube at a point before its end onto a spur (a cable touching it) and ended there.


def _mask(*lines) -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    for ln in lines:
        cv2.polylines(m, [np.round(ln * 16).astype(np.int32)], False, 1, 5, cv2.LINE_8, 4)
    return m.astype(bool)


def _short(line: np.ndarray, back_px: float) -> np.ndarray:
    s = np.cumsum(np.r_[0.0, np.linalg.norm(np.diff(line, axis=0), axis=1)])
    return line[s <= s[-1] - back_px]


def _tube_trace(line, mask, **kw):
    from jaxcr.segmentation.foreground import TubeTrace

    return TubeTrace(mask=mask, backbone=line, tip=line[-1], entry=line[0],
                     score=mask.astype(np.float32), seed_mask=mask, width_px=5.0, **kw)  # fmt: skip


def _spurred(j: int, turn_deg: float, back_px: float, spur_px: float):
    """View ``j`` traced onto a spur leaving the tube ``back_px`` before its end (turned by
    ``turn_deg``, ``spur_px`` long; the tube's end is in its mask too); the other view
    traced right."""
    spur = _overshoot(_short(LINES[j], back_px), turn_deg, spur_px)
    traces = [None, None]
    traces[j] = _tube_trace(spur, _mask(LINES[j], spur))
    traces[1 - j] = _tube_trace(LINES[1 - j], _mask(LINES[1 - j]))
    return traces


@pytest.mark.parametrize(("j", "turn", "back", "spur"),
                         [(1, 60.0, 10.0, 20.0), (0, 60.0, 10.0, 20.0), (0, -60.0, 12.0, 25.0),
                          (1, 70.0, 15.0, 30.0)])  # fmt: skip
def test_the_disagreeing_view_takes_the_branch_that_ends_on_the_epipolar_line(j, turn, back, spur):
    """The re-decided tip is where the geodesic path inside the mask to the tube's end
    crosses the epipolar line of the other (true) tip. Reference: the true tip's
    projection. Tolerance: the path lies inside the 5 px band, so up to half a width
    (2.5 px) plus the rasterisation (0.5 px) off the axis, which moves the crossing along
    the epipolar line by that over the sine of the angle between line and tube (0.74 in
    view 1, 0.98 in view 0: closed form here): 3 / 0.74 = 4.1 px."""
    from jaxcr.stereo.tip_consistency import _end_on_epiline, _epiline

    traces = _spurred(j, turn, back, spur)
    tips = [t.tip for t in traces]
    F = fundamental_from_poses(K, T0, K, T1)
    line = _epiline(F, TRUE_TIPS[1 - j], to_second=(j == 1))
    d = LINES[j][-1] - LINES[j][-6]
    sin_angle = abs(d @ line[:2]) / np.linalg.norm(d)
    assert _epi(tips) > 2.0 and np.linalg.norm(tips[j] - TRUE_TIPS[j]) > 10.0
    res = _end_on_epiline(CAMS, traces, tips, j)
    assert res is not None
    assert np.linalg.norm(res - TRUE_TIPS[j]) < 3.0 / sin_angle
    assert _epi([res, tips[1]] if j == 0 else [tips[0], res]) < 0.5


def test_no_branch_ends_on_the_epipolar_line_no_decision():
    """View 1's mask is cut 15 px before the tube's end (the tube matched the background
    there): no extremity of it lies on the epipolar line of the true tip of view 0."""
    from jaxcr.stereo.tip_consistency import _end_on_epiline

    short = _short(LINES[1], 15.0)
    traces = [_tube_trace(LINES[0], _mask(LINES[0])), _tube_trace(short, _mask(short))]
    assert _end_on_epiline(CAMS, traces, [t.tip for t in traces], 1) is None


def test_a_trim_that_would_cut_the_right_view_rebranches_the_other():
    """The open-ended match places the unexplained stretch in view 0 (right, its path
    passes no junction or gap), so the round-10 trim cut it; now view 1 (its spur) moves
    to the end of its tube instead (same tolerance as above)."""
    from jaxcr.stereo.backbone_consistency import backbone_consistency, open_end_tails
    from jaxcr.stereo.tip_consistency import trim_unexplained_tail

    traces = _spurred(1, 70.0, 15.0, 30.0)
    tips = [t.tip for t in traces]
    bc = backbone_consistency(CAMS, traces[0].backbone, traces[1].backbone)
    tails = open_end_tails(CAMS, bc)
    res = trim_unexplained_tail(CAMS, traces, tips, bc, tails=tails)
    assert res.action == "rebranched" and res.view == 1, res
    np.testing.assert_array_equal(res.tips[0], tips[0])
    assert np.linalg.norm(res.tips[1] - TRUE_TIPS[1]) < 3.0 / 0.74
    # A gap bridged on view 0's cut tail (its last 10 px; the tracer may have left the tube
    # across it): the trim stands (round 10).
    n = len(LINES[0])
    traces[0] = _tube_trace(LINES[0], traces[0].seed_mask, gaps=[(n - 12, n - 8)])
    res = trim_unexplained_tail(CAMS, traces, tips, bc, tails=tails)
    assert res.action == "trimmed" and res.view == 0, res


def test_tail_is_clean_reads_junctions_gaps_and_the_ends_jitter():
    from jaxcr.stereo.tip_consistency import _tail_is_clean

    line = np.c_[np.arange(0.0, 101.0), np.full(101, 50.0)]  # 1 px per sample, 100 px
    tr = _tube_trace(line, _mask(line))
    cut = line[60]
    assert _tail_is_clean(tr, cut)
    tr.junctions = [(70, line[70], None)]  # on the tail
    assert not _tail_is_clean(tr, cut)
    tr.junctions = [(55, line[55], None)]  # within two widths (10 px) behind the cut
    assert not _tail_is_clean(tr, cut)
    tr.junctions = [(45, line[45], None)]  # farther behind
    assert _tail_is_clean(tr, cut)
    tr.junctions = [(85, line[85], None)]  # under two look lengths (20 px) before the end
    assert _tail_is_clean(tr, cut)
    tr.junctions, tr.gaps = [], [(62, 66)]  # a bridged gap on the tail
    assert not _tail_is_clean(tr, cut)


def test_mask_geodesics_match_skimage():
    """Geodesic distances inside a mask (8-neighbour steps 1 and sqrt 2) against
    ``skimage.graph.MCP_Geometric`` on unit costs (the same metric; float64 sums of at
    most a few hundred steps: 1e-9)."""
    from skimage.graph import MCP_Geometric

    from jaxcr.stereo.tip_consistency import _mask_paths_from

    rng = np.random.default_rng(5)
    mask = np.ones((40, 50), bool)
    mask[rng.random(mask.shape) < 0.25] = False
    src = np.array([[20, 25], [3, 4]])
    mask[tuple(src.T)] = True
    dist, pred = _mask_paths_from(mask, src, np.inf)
    ref, _ = MCP_Geometric(np.where(mask, 1.0, np.inf), fully_connected=True).find_costs(
        [tuple(p) for p in src]
    )
    fin = np.isfinite(ref) & mask
    np.testing.assert_allclose(dist[fin], ref[fin], atol=1e-9)
    assert np.all(~np.isfinite(dist[~fin]))
