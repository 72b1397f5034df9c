"""Choosing the branch each view's tracer took at a crossing with both views
(:mod:`jaxcr.stereo.branch_choice`, issue 16 item 2): the ranking rules on hand-made
candidates whose tips are projections of known 3-D points (closed form), and the whole chain
(:func:`jaxcr.segmentation.foreground.trace_alternatives` on an X-junction mask, then
:func:`jaxcr.stereo.pipeline.traced_stereo_tips`) on a rectified pair, where the epipolar
lines are the image rows."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from jaxcr.segmentation.foreground import (
    PlateForegroundConfig,
    plate_foreground,
    start_alternatives,
    trace_alternatives,
)
from jaxcr.stereo.branch_choice import choose_branches
from jaxcr.stereo.pipeline import traced_stereo_tips
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses
from jaxcr.synth.scene import look_at_pose

K = np.array([[220.0, 0.0, 80.0], [0.0, 220.0, 60.0], [0.0, 0.0, 1.0]])
T0 = look_at_pose(np.array([0.30, -0.08, 0.06]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
T1 = look_at_pose(np.array([0.06, -0.30, 0.08]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
CAMS = [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in (T0, T1)]
F = fundamental_from_poses(K, T0, K, T1)


def _proj(T, X):
    Xc = np.atleast_2d(X) @ T[:3, :3].T + T[:3, 3]
    x = Xc @ K.T
    return x[:, :2] / x[:, 2:]


TIP = np.array([0.02, 0.0, 0.08])  # the tube's end (base frame, m)
CABLE_END = np.array([0.0, 0.03, 0.05])  # where a cable crossing the tube ends


def _cand(tip, followed=0, turn=0.0):
    return SimpleNamespace(tip=np.asarray(tip, np.float64), crossings_followed=followed,
                           crossing_turn_deg=turn)  # fmt: skip


def _on_epiline_of(x0, offset_px):
    """A point of view 1 on the epipolar line of view-0 pixel ``x0``, ``offset_px`` along it
    from the line's foot nearest the true tip (exactly consistent with ``x0``)."""
    ln = F @ np.r_[x0, 1.0]
    ln = ln / np.hypot(ln[0], ln[1])
    t1 = _proj(T1, TIP)[0]
    foot = t1 - (ln[:2] @ t1 + ln[2]) * ln[:2]
    return foot + offset_px * np.array([-ln[1], ln[0]])


def test_the_consistent_smoother_branch_is_chosen():
    """View 0 traced the tube to its end; view 1's tracer followed a cable to its end (one
    crossing followed, 40 deg turn). View 1's alternatives: the tube's end (consistent,
    smooth), a decoy exactly on view 0's tip's epipolar line 40 px from the end (consistent,
    smoother than the trace but turning more than the tube's end) and one off the line.
    View 0's alternative along the cable to its end is consistent with view 1's trace (both
    see the cable's end, one 3-D point) but not smoother than view 0's own trace, so it is
    not a candidate. Expected: view 0's trace and view 1's tube end, exactly (no
    arithmetic on the tips)."""
    t0, t1 = _proj(T0, TIP)[0], _proj(T1, TIP)[0]
    c0, c1 = _proj(T0, CABLE_END)[0], _proj(T1, CABLE_END)[0]
    assert max(epipolar_distances(F, t0, c1)) > 15.0  # flagged, and beyond match_px
    assert max(epipolar_distances(F, c0, c1)) < 1e-6  # the cable's end: consistent
    decoy = _on_epiline_of(t0, 40.0)
    cands = [
        [_cand(t0, 0, 5.0), _cand(c0, 1, 30.0)],
        [_cand(c1, 1, 40.0), _cand(decoy, 0, 25.0), _cand(t1, 0, 10.0), _cand(t1 + [0, 30], 0, 0.0)],
    ]  # fmt: skip
    res = choose_branches(CAMS, cands)
    assert res.indices == (0, 2), res
    np.testing.assert_array_equal(res.tips[1], t1)
    assert res.epipolar_px < 1e-6
    # Without the tube's end, the decoy is the best consistent smoother branch: the rules
    # rank, they cannot know a decoy (what the frame's images then decide is not here).
    res = choose_branches(CAMS, [cands[0], cands[1][:2] + cands[1][3:]])
    assert res.indices == (0, 1)
    # The cable pair is consistent but needs view 0 to leave a smoother trace: with view 0's
    # cable branch as smooth as its trace it still loses to (trace, tube end) on crossings.
    cands[0][1] = _cand(c0, 0, 5.0)
    assert choose_branches(CAMS, cands).indices == (0, 2)


def test_no_consistent_pair_chooses_nothing_and_both_views_never_change():
    """Alternatives consistent only with each other (both views leave their traces) are
    not considered; with no other consistent pair the result is None."""
    t0, t1 = _proj(T0, TIP)[0], _proj(T1, TIP)[0]
    c1 = _proj(T1, CABLE_END)[0]
    far0 = t0 + np.array([0.0, -40.0])
    assert max(epipolar_distances(F, far0, c1)) > 15.0
    assert max(epipolar_distances(F, far0, t1)) > 15.0
    assert max(epipolar_distances(F, t0, c1)) > 15.0
    cands = [[_cand(far0, 1, 40.0), _cand(t0, 0, 1.0)], [_cand(c1, 1, 40.0), _cand(t1, 0, 1.0)]]
    assert choose_branches(CAMS, cands) is None


def _x_junction(cable_deg=20.0, bend_deg=30.0):
    """160x120 mask: a tube 7 px wide up from (60, 119) to (60, 60), bending ``bend_deg``
    left there and ending 30 px on; a cable as wide and as dark crossing it at (60, 60),
    ``cable_deg`` right of its heading, from 60 px behind the crossing to 50 px beyond it
    (inside the image). Returns the mask, the tube's drawn end (cv2.line's round cap: 3.5
    px beyond the end point) and the cable's far end."""
    m = np.zeros((120, 160), np.uint8)
    cv2.line(m, (60, 119), (60, 60), 1, 7)
    a = np.radians(bend_deg)
    end = np.array([60 - 30 * np.sin(a), 60 - 30 * np.cos(a)])
    cv2.line(m, (60, 60), tuple(int(round(x)) for x in end), 1, 7)
    b = np.radians(cable_deg)
    c0 = (int(round(60 - 60 * np.sin(b))), int(round(60 + 60 * np.cos(b))))
    c1 = (int(round(60 + 50 * np.sin(b))), int(round(60 - 50 * np.cos(b))))
    cv2.line(m, c0, c1, 1, 7)
    return m > 0, end + 3.5 * np.array([-np.sin(a), -np.cos(a)]), np.array(c1, np.float64)


def _traced(mask):
    plate = np.broadcast_to(np.array([0.16, 0.50, 0.20]), mask.shape + (3,)).copy()
    frame = plate.copy()
    frame[mask] = 0.1
    cfg = PlateForegroundConfig(align=False, start_spread_deg=0.0, close_px=0.0, refine=False)
    return plate_foreground(frame, plate, (60.0, 119.0), (0.0, -1.0), cfg=cfg)


def test_x_junction_the_other_view_picks_the_tube_not_the_cable():
    """View 1 is the X-junction mask (the tracer follows the straighter cable to its end,
    inside the image, where the off-border re-trace does not act); view 0 a straight tube
    whose end is on the row of view 1's tube end. The cameras are a rectified pair (camera
    1 moved 0.1 m along x: the epipolar lines are the rows). The junction's alternatives
    include the tube's end; it is the one on view 0's tip's row and it follows no crossing
    (the cable is on the mask behind the crossing too, the tube's branch is not).
    Expected: view 1's tip at the tube's drawn end within 2 px (the bound of
    test_foreground_plate's tracing tests: nearest-pixel sampling 0.5 + 0.25 px march +
    the pixel half-diagonal 0.71, rounded up), view 0's tip unchanged."""
    mask1, end1, cable_end = _x_junction()
    tr1 = _traced(mask1)
    assert np.linalg.norm(tr1.tip - cable_end) < 6.0  # the tracer alone follows the cable
    assert tr1.crossings_followed == 1
    alts = trace_alternatives(tr1)
    good = [a for a in alts if np.linalg.norm(a.tip - end1) < 2.0]
    assert len(good) == 1 and good[0].crossings_followed == 0
    mask0 = np.zeros((120, 160), bool)
    cv2.line(mask0.view(np.uint8), (60, 119), (60, int(round(end1[1] + 3.5))), 1, 7)
    tr0 = _traced(mask0)
    assert abs(tr0.tip[1] - end1[1]) < 2.0
    Ts = [np.eye(4), np.eye(4)]
    Ts[1][0, 3] = -0.1  # camera 1 at x = +0.1 m
    cams = [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in Ts]
    tips, src, _, chosen = traced_stereo_tips(cams, [tr0, tr1])
    assert "+branch" in src and chosen[0] is tr0 and chosen[1] is not tr1
    assert np.linalg.norm(tips[1] - end1) < 2.0, (tips[1], end1)
    np.testing.assert_array_equal(tips[0], tr0.tip)


def test_an_alternative_that_comes_back_holds_the_hook():
    """A tube 7 px wide up from (60, 119) to (60, 25) that hooks round (a half circle of
    radius 3.5 px: the way back touches the way out) and comes back down, diverging slowly,
    to (74, 110). The tracer stops at the hook's apex; the re-trace from a junction of the
    merged run that reaches the way back's end must hold the apex too (the path out and
    back, :func:`jaxcr.segmentation.foreground.trace_alternatives`; a re-trace alone runs
    from the junction straight onto the way back, 37 px below the apex, and the other view,
    which sees the hook, cannot explain that path). Expected, against the drawn geometry:
    two alternatives ending within 2 px of the way back's drawn end (the bound of the X-
    junction test; both stories are offered: a bend seen end-on, a hook), one of them
    with a path that passes within 4.5 px of the hook's apex on the centre line
    (60 + 3.5, 25 - 3.5): the half width 3.5 px (the tracer re-centres on the merged run
    of the two tubes, and marches on to the mask's end) plus 1 px for the nearest-pixel
    sampling and the 2 px steps."""
    m = np.zeros((120, 160), np.uint8)
    cv2.line(m, (60, 119), (60, 25), 1, 7)
    cv2.ellipse(m, (63, 25), (3, 3), 0, 180, 360, 1, 7)
    cv2.line(m, (67, 25), (74, 110), 1, 7)
    tr = _traced(m > 0)
    apex = np.array([63.5, 21.5])
    assert np.linalg.norm(tr.tip - apex) < 6.0  # the tracer alone stops at the hook
    d = np.array([7.0, 85.0]) / np.hypot(7.0, 85.0)
    end = np.array([74.0, 110.0]) + 3.5 * d  # cv2.line's round cap
    good = [a for a in trace_alternatives(tr) if np.linalg.norm(a.tip - end) < 2.0]
    assert len(good) == 2  # the re-trace as it is, and out to the apex and back

    def apex_px(bb):
        t = np.linspace(0.0, 1.0, 11)[:, None]
        dense = np.concatenate([a + t * (b - a) for a, b in zip(bb[:-1], bb[1:], strict=True)])
        return float(np.min(np.linalg.norm(dense - apex, axis=1)))

    assert sorted(apex_px(a.backbone) for a in good)[0] < 4.5


def test_any_pair_lets_both_views_leave_their_traces():
    """Both views' tracers followed a cable to its end (a consistent pair of wrong ends,
    but their whole backbones, the ``inconsistency_of`` here, leave 60 px unexplained);
    each view's alternative is the tube's end, which only together explain everything.
    One view kept (the default): no pair gains, nothing is chosen. ``any_pair``: the two
    alternatives together, exactly."""
    t0, t1 = _proj(T0, TIP)[0], _proj(T1, TIP)[0]
    c0, c1 = _proj(T0, CABLE_END)[0], _proj(T1, CABLE_END)[0]
    cands = [[_cand(c0, 0, 5.0), _cand(t0, 0, 5.0)], [_cand(c1, 0, 5.0), _cand(t1, 0, 5.0)]]
    bad = {(0, 0): 60.0, (0, 1): 300.0, (1, 0): 300.0, (1, 1): 0.0}

    def inconsistency(a, b, tips):
        i0 = next(i for i, x in enumerate(cands[0]) if x is a)
        i1 = next(i for i, x in enumerate(cands[1]) if x is b)
        return bad[(i0, i1)]

    res = choose_branches(CAMS, cands, inconsistency_of=inconsistency)
    assert res is None or res.indices == (0, 0)
    res = choose_branches(CAMS, cands, inconsistency_of=inconsistency, any_pair=True)
    assert res.indices == (1, 1), res
    np.testing.assert_array_equal(res.tips[0], t0)
    np.testing.assert_array_equal(res.tips[1], t1)
    # An alternative that follows more crossing objects than its view's trace is gated out.
    cands[1][1] = _cand(t1, 1, 5.0)
    res = choose_branches(CAMS, cands, inconsistency_of=inconsistency, any_pair=True)
    assert res is None or res.indices == (0, 0)


def test_more_crossings_allowed_only_for_a_pair_that_explains_itself():
    """View 0 traced a cable (its tip the cable's end, no crossing followed); its
    alternative is the tube's end but "follows" one crossing object (a tube crossing its
    own silhouette is an X as a cable is). View 1 traced the tube. By default the
    alternative is gated out; with ``more_crossings_if_consistent`` it is chosen because
    the pair explains itself (0 px), and it is not chosen when the pair leaves more than
    ``consistent_px`` unexplained, or when a pair that follows fewer crossings also
    explains itself."""
    t0, t1 = _proj(T0, TIP)[0], _proj(T1, TIP)[0]
    c0 = _proj(T0, CABLE_END)[0]
    cands = [[_cand(c0, 0, 5.0), _cand(t0, 1, 30.0)], [_cand(t1, 0, 5.0)]]
    bad = {(0, 0): 300.0, (1, 0): 0.0}

    def inconsistency(a, b, tips):
        return bad[(next(i for i, x in enumerate(cands[0]) if x is a), 0)]

    res = choose_branches(CAMS, cands, inconsistency_of=inconsistency)
    assert res is None or res.indices == (0, 0)
    res = choose_branches(
        CAMS, cands, inconsistency_of=inconsistency, more_crossings_if_consistent=True
    )
    assert res.indices == (1, 0) and res.inconsistent_px == 0.0
    bad[(1, 0)] = 41.0  # over CONSISTENT_PX (40): gated as before
    res = choose_branches(
        CAMS, cands, inconsistency_of=inconsistency, more_crossings_if_consistent=True
    )
    assert res is None or res.indices == (0, 0)
    # A second alternative, also the tube's end (1 px off) with no crossing followed and
    # also explaining itself, outranks it (crossings followed come first).
    bad[(1, 0)], bad[(2, 0)] = 0.0, 10.0
    cands[0].append(_cand(t0 + [1.0, 0.0], 0, 30.0))
    res = choose_branches(
        CAMS, cands, inconsistency_of=inconsistency, more_crossings_if_consistent=True
    )
    assert res.indices == (2, 0)


def _cv2_proj(T, X):
    """``X`` (n, 3) projected by OpenCV (the reference camera model; no distortion)."""
    rvec, _ = cv2.Rodrigues(np.asarray(T[:3, :3], np.float64))
    uv, _ = cv2.projectPoints(np.atleast_2d(X).astype(np.float64), rvec, T[:3, 3], K, None)
    return uv.reshape(-1, 2)


def _arc(n=60):
    """A closed-form planar arc (radius 6 cm, 70 deg) from the base up: the tube (m)."""
    s = np.linspace(0.0, np.deg2rad(70.0), n)
    return np.stack([0.06 * (1 - np.cos(s)), 0.0 * s, 0.06 * np.sin(s)], 1)


def _turned_onto(T, arc, cable):
    """One view's trace that turned onto the cable where its image crosses the tube's:
    the arc's projection up to its point nearest the cable's image, then the cable's
    projection from its own point nearest there to its far end."""
    a, c = _cv2_proj(T, arc), _cv2_proj(T, cable)
    d = np.linalg.norm(a[:, None] - c[None], axis=2)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    return np.vstack([a[: i + 1], c[j:]])


def test_both_traces_on_a_cable_offer_a_pair_of_two_re_traces():
    """A 3-D arc (the tube) and a straight 3-D cable passing 2 cm in front of it, both
    projected with ``cv2.projectPoints``. Each view's trace turned onto the cable where
    the cable's image crosses the tube's (at a different point of the tube in each view,
    so the traces' pair leaves most of its backbones unexplained, by
    ``backbone_consistency``) and follows one crossing object; each view's re-trace is
    the whole arc (no crossing followed). One view kept (the default): no pair with one
    trace explains itself, nothing is chosen. ``both_if_traces_cross``: the two re-traces,
    which explain each other (under 1 px of backbone unexplained; the traces' pair over
    15 px), with the arc's
    projected end as tips. Not offered where one trace follows no crossing object, nor
    where an alternative follows as many as its trace."""
    from jaxcr.stereo.backbone_consistency import backbone_consistency

    arc = _arc()
    # Through a point in front of the arc's middle (towards both cameras), across it.
    mid = arc[30] + np.array([0.02, -0.02, 0.0])
    cable = mid[None] + np.linspace(-0.08, 0.08, 80)[:, None] * np.array([0.3, 0.8, -0.5])
    views = []
    for T in (T0, T1):
        tube = _cv2_proj(T, arc)
        trace = _turned_onto(T, arc, cable)
        views.append([
            SimpleNamespace(tip=trace[-1], backbone=trace, crossings_followed=1,
                            crossing_turn_deg=40.0),
            SimpleNamespace(tip=tube[-1], backbone=tube, crossings_followed=0,
                            crossing_turn_deg=0.0),
        ])  # fmt: skip

    def inconsistency(a, b, tips):
        return backbone_consistency(CAMS, a.backbone, b.backbone).inconsistent_px

    assert inconsistency(views[0][0], views[1][0], None) > 15.0
    assert inconsistency(views[0][1], views[1][1], None) < 1.0
    # margin_px: 1.25 widths of a 4 px tube at this image's scale (160 x 120 px).
    kw = dict(inconsistency_of=inconsistency, more_crossings_if_consistent=True, margin_px=5.0)
    res = choose_branches(CAMS, views, **kw)
    assert res is None or res.indices == (0, 0)
    res = choose_branches(CAMS, views, both_if_traces_cross=True, **kw)
    assert res.indices == (1, 1), res
    for k, T in enumerate((T0, T1)):
        np.testing.assert_allclose(res.tips[k], _cv2_proj(T, arc[-1:])[0], atol=1e-9)
    # One trace follows no crossing object: that view's trace is evidence, no pair of two.
    views[1][0].crossings_followed = 0
    res = choose_branches(CAMS, views, both_if_traces_cross=True, **kw)
    assert res is None or 0 in res.indices
    # An alternative that follows as many crossing objects as its trace: not offered.
    views[1][0].crossings_followed, views[1][1].crossings_followed = 1, 1
    res = choose_branches(CAMS, views, both_if_traces_cross=True, **kw)
    assert res is None or 0 in res.indices


def test_the_entrys_other_starts_are_alternatives():
    """A rod 7 px wide runs from the entry (60, 119) 20 deg right of the given direction
    (up) for 90 px, longer than the tube, which goes straight up 56 px and ends inside the
    image. The tracer starts along the given direction and turned 20 deg either way and
    keeps the longest trace: the rod's. The start along the given direction, which reached
    the tube's end, is offered back by :func:`jaxcr.segmentation.foreground.
    start_alternatives` (``departure`` 0; docs/decisions.md S45), and the tube's end is
    among :func:`trace_alternatives`. Expected against the drawn geometry: the kept trace within 6 px of
    the rod's drawn end (as the X-junction test's cable end), one start alternative within
    2 px of the tube's drawn end (cv2.line's round cap 3.5 px beyond (60, 63); the bound of
    the X-junction test)."""
    m = np.zeros((120, 160), np.uint8)
    cv2.line(m, (60, 119), (60, 63), 1, 7)
    b = np.radians(20.0)
    rod_end = np.array([60 + 90 * np.sin(b), 119 - 90 * np.cos(b)])
    cv2.line(m, (60, 119), tuple(int(round(x)) for x in rod_end), 1, 7)
    plate = np.broadcast_to(np.array([0.16, 0.50, 0.20]), m.shape + (3,)).copy()
    frame = plate.copy()
    frame[m > 0] = 0.1
    cfg = PlateForegroundConfig(align=False, start_spread_deg=20.0, close_px=0.0, refine=False)
    tr = plate_foreground(frame, plate, (60.0, 119.0), (0.0, -1.0), cfg=cfg)
    rod_tip = rod_end + 3.5 * np.array([np.sin(b), -np.cos(b)])
    assert np.linalg.norm(tr.tip - rod_tip) < 6.0, tr.tip  # the longest start: the rod
    tube_end = np.array([60.0, 63.0 - 3.5])
    starts = start_alternatives(tr)
    assert [np.linalg.norm(a.tip - tube_end) < 2.0 for a in starts].count(True) == 1
    # trace_alternatives offers it (here a re-trace from the junction where the tube leaves
    # the rod reaches the same end first, and the start's copy is not repeated).
    good = [a for a in trace_alternatives(tr) if np.linalg.norm(a.tip - tube_end) < 2.0]
    assert len(good) >= 1


def _off_epiline(x0, along_px, off_px):
    """A point of view 1 ``off_px`` across the epipolar line of view-0 pixel ``x0``, at the
    line's point ``along_px`` from its foot nearest the true tip's image."""
    ln = F @ np.r_[x0, 1.0]
    ln = ln / np.hypot(ln[0], ln[1])
    return _on_epiline_of(x0, along_px) + off_px * ln[:2]


def test_tips_that_agree_replace_a_flagged_pair_whose_backbones_look_consistent():
    """View 0 traced the tube to its end; view 1's tracer followed a cable that runs along
    the epipolar lines, so its backbone pair with view 0 explains itself (10 px, under the
    1.25-width margin of 20 px) while its tip is 10 px off view 0's tip's epipolar line
    (flagged at 5 px). View 1's alternative ends at the tube's end (exactly consistent, 10
    px unexplained too, a larger turn than the trace). By default no alternative passes the
    gate (it must leave 20 px less unexplained). With ``tip_flag_px=5`` (S49) it does: its
    tips agree, its backbones are no less consistent and its tip is over the margin from
    the trace's (another branch). Not when it leaves more unexplained than the traces,
    follows more crossing objects, ends within the margin of the trace's tip, or when the
    traces' own tips agree."""
    t0, t1 = _proj(T0, TIP)[0], _proj(T1, TIP)[0]
    c1 = _off_epiline(t0, 60.0, 10.0)
    e = max(epipolar_distances(F, t0, c1))
    assert 5.0 < e < 15.0, e  # flagged, within match_px
    assert max(epipolar_distances(F, t0, t1)) < 1e-6
    cands = [[_cand(t0, 0, 5.0)], [_cand(c1, 0, 20.0), _cand(t1, 0, 30.0)]]
    bad = {0: 10.0, 1: 10.0}

    def inconsistency(a, b, tips):
        return bad[next(i for i, x in enumerate(cands[1]) if x is b)]

    kw = dict(inconsistency_of=inconsistency, margin_px=20.0)
    res = choose_branches(CAMS, cands, **kw)
    assert res.indices == (0, 0)
    res = choose_branches(CAMS, cands, tip_flag_px=5.0, **kw)
    assert res.indices == (0, 1) and res.epipolar_px < 1e-6
    # The ranking alone: without it the traces' pair (smaller turn) would still win.
    res = choose_branches(CAMS, cands, tip_flag_px=5.0, tip_rank=False, **kw)
    assert res.indices == (0, 0)
    bad[1] = 10.5  # leaves more unexplained than the traces' pair: gated out
    assert choose_branches(CAMS, cands, tip_flag_px=5.0, **kw).indices == (0, 0)
    bad[1] = 10.0
    cands[1][1].crossings_followed = 1  # follows more crossing objects: gated out
    assert choose_branches(CAMS, cands, tip_flag_px=5.0, **kw).indices == (0, 0)
    cands[1][1].crossings_followed = 0
    # The trace's tip 12 px from the alternative's (10 px off the line): the same path's
    # end, for the tip step to mend, not another branch.
    cands[1][0] = _cand(_off_epiline(t0, 7.0, 10.0), 0, 20.0)
    assert np.linalg.norm(cands[1][0].tip - t1) < 20.0
    assert 5.0 < max(epipolar_distances(F, t0, cands[1][0].tip)) < 15.0
    assert choose_branches(CAMS, cands, tip_flag_px=5.0, **kw).indices == (0, 0)
    # The traces' tips agree (3 px): the rule does not act (the alternative's pair is not
    # 20 px more consistent).
    cands[1][0] = _cand(_off_epiline(t0, 60.0, 3.0), 0, 20.0)
    assert max(epipolar_distances(F, t0, cands[1][0].tip)) <= 5.0
    assert choose_branches(CAMS, cands, tip_flag_px=5.0, **kw).indices == (0, 0)


def test_tips_that_agree_by_chance_over_inconsistent_backbones_are_flagged(monkeypatch):
    """The tube is a 3-D arc (``cv2.projectPoints``). View 1 traced it. View 0's trace left
    it half way along a straight image path that ends on the epipolar line of view 1's
    tip, 40 px from the tube's end: the tips agree (under 1e-6 px), so by default the
    branch choice does not run and the wrong trace stays. Its backbone pair with view 1
    leaves over 40 px unexplained (``backbone_consistency``); with ``backbones_flag``
    (S49) the choice runs and view 0's re-trace, the whole arc, is chosen (its tip exactly
    the arc's projected end). The pipeline's guided candidates are switched off here:
    only the views' own re-traces are offered."""
    from jaxcr.stereo import pipeline
    from jaxcr.stereo.backbone_consistency import backbone_consistency

    arc = _arc()
    tube = [_cv2_proj(T, arc) for T in (T0, T1)]
    ln = F.T @ np.r_[tube[1][-1], 1.0]  # view 0's epipolar line of view 1's tip
    ln = ln / np.hypot(ln[0], ln[1])
    wrong_end = tube[0][-1] + 40.0 * np.array([-ln[1], ln[0]])
    half = tube[0][: len(arc) // 2]
    # Out across the epipolar lines and back: no monotone matching explains it.
    out = half[-1] + 40.0 * ln[:2]
    t = np.linspace(0.0, 1.0, 20)[1:, None]
    wrong = np.vstack([half, half[-1] + t * (out - half[-1]), out + t * (wrong_end - out)])

    def tr(bb, alts=()):
        return SimpleNamespace(tip=bb[-1].copy(), backbone=bb, cap_px=0.0, end_dir=np.zeros(2),
                               end_half_width_px=0.0, retrace=object(), width_px=4.0,
                               crossings_followed=0, crossing_turn_deg=0.0, alts=list(alts))  # fmt: skip

    views = [tr(wrong, [tr(tube[0])]), tr(tube[1])]
    assert max(epipolar_distances(F, views[0].tip, views[1].tip)) < 1e-6
    assert backbone_consistency(CAMS, wrong, tube[1]).inconsistent_px > 40.0
    assert backbone_consistency(CAMS, tube[0], tube[1]).inconsistent_px < 1.0
    monkeypatch.setattr(pipeline, "trace_alternatives", lambda t: t.alts)
    monkeypatch.setattr(pipeline, "guided_candidates", lambda cams, traces, cut_back: [[], []])
    traces, tips, src = pipeline._branch_step(CAMS, views, 5.0)
    assert traces[0] is views[0] and traces[1] is views[1] and "+branch" not in src
    traces, tips, src = pipeline._branch_step(CAMS, views, 5.0, backbones_flag=True)
    assert traces[0] is views[0].alts[0] and traces[1] is views[1] and "+branch" in src
    np.testing.assert_array_equal(tips[0], tube[0][-1])
