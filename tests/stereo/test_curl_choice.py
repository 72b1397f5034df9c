"""``choose_curled_end`` (docs/decisions.md S46) on a pinhole rig: a tube whose end hooks
round in 3-D, drawn in each view round its projected axis (tests.helpers.drawn_tube, noise
5 % of the contrast). View 1's path and tip stop at the hook's apex, as the tracer's do;
view 2's tip is right. The curled fit must replace view 1's tip and put it within 2.5 px of
the projected tip (test_curl_end's bound); with view 1's path and tip right (a tube that
does not curl at its end) nothing is replaced.
"""

from types import SimpleNamespace

import numpy as np

from jaxcr.segmentation.foreground import TubeTrace
from jaxcr.stereo.curl_choice import choose_curled_end, curled_trace
from tests.helpers.drawn_tube import drawn_tube

K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
SHAPE = (480, 640)


def _rig():
    T1 = np.eye(4)
    a = np.radians(15.0)
    T2 = np.eye(4)
    T2[:3, :3] = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    T2[:3, 3] = [0.08, 0.0, 0.01]
    return [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in (T1, T2)]


def _project(T, P):
    x = P @ T[:3, :3].T + T[:3, 3]
    return (x / x[:, 2:]) @ K.T[:, :2]


def _hooked_tube(turn_deg: float) -> np.ndarray:
    """3-D axis (n, 3), metres: 40 mm straight along +x at depth 0.3 m, then an arc of
    radius 5 mm in the image plane turning towards -y (up in view 1) by ``turn_deg``."""
    s = np.linspace(0.0, 0.04, 200)
    straight = np.stack([-0.02 + s, np.full_like(s, 0.01), np.full_like(s, 0.3)], 1)
    R, a = 0.005, np.radians(np.linspace(0.0, turn_deg, 300))
    arc = np.stack([0.02 + R * np.sin(a), 0.01 - R * (1 - np.cos(a)), np.full_like(a, 0.3)], 1)
    return np.vstack([straight, arc])


def _views(turn_deg: float, apex_in_view1: bool, seed: int = 0):
    cams = _rig()
    axis3 = _hooked_tube(turn_deg)
    rng = np.random.default_rng(seed)
    traces, truth = [], []
    for k, c in enumerate(cams):
        uv = _project(c.T_cam_robot, axis3)
        score = 0.1 + 0.9 * drawn_tube(SHAPE, uv, 6.0) + rng.normal(0.0, 0.05, SHAPE)
        # View 1's path stops at the apex (the straight part and the arc's first 20 deg).
        n = 200 + 20 if (k == 0 and apex_in_view1) else len(uv)
        path = uv[:n:4] if (n - 1) % 4 == 0 else np.vstack([uv[:n:4], uv[n - 1]])
        traces.append(TubeTrace(mask=score > 0.5, backbone=path, tip=path[-1], entry=path[0],
                                score=score, width_px=12.0))  # fmt: skip
        truth.append(uv[-1])
    return cams, traces, truth


def test_a_hook_seen_to_its_apex_gets_its_curled_tip():
    cams, traces, truth = _views(150.0, apex_in_view1=True)
    tips = [traces[0].tip, truth[1]]
    assert np.linalg.norm(tips[0] - truth[0]) > 15.0  # the apex is far from the tip
    cc = choose_curled_end(cams, traces, tips)
    assert cc is not None and cc.view == 0
    assert np.linalg.norm(cc.tips[0] - truth[0]) <= 2.5
    np.testing.assert_array_equal(cc.tips[1], tips[1])
    assert cc.epipolar_after_px < cc.epipolar_before_px - 1.0
    t = curled_trace(traces[0], cc.fit)
    assert t.curl_of is traces[0]
    np.testing.assert_array_equal(t.backbone[-1], cc.fit.tip)


def test_an_end_traced_whole_is_left_alone():
    cams, traces, truth = _views(150.0, apex_in_view1=False, seed=1)
    assert choose_curled_end(cams, traces, truth) is None


def test_an_end_whose_cue_fades_is_refitted():
    """S47: view 1's tube fades to 60 % contrast over its last 18 px (a grey tube over a
    white board) and its path stops where the fade starts; the gentle fit finds the end
    (1.4 px off when measured; at 40 % over 30 px it stays where the fade starts: a cue
    under half the tube's contrast is background to the fit)."""
    cams = _rig()
    s = np.linspace(0.0, 0.05, 300)
    axis3 = np.stack([-0.02 + s, 0.01 + 0.2 * s, np.full_like(s, 0.3)], 1)
    rng = np.random.default_rng(3)
    traces, truth = [], []
    for k, c in enumerate(cams):
        uv = _project(c.T_cam_robot, axis3)
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))]
        cover = drawn_tube(SHAPE, uv, 6.0)
        n = len(uv)
        if k == 0:
            n = int(np.searchsorted(arc, arc[-1] - 18.0))
            faded = drawn_tube(SHAPE, uv[n - 1 :], 6.0)
            cover = np.maximum(drawn_tube(SHAPE, uv[:n], 6.0), 0.6 * faded)
        score = 0.1 + 0.9 * cover + rng.normal(0.0, 0.05, SHAPE)
        path = np.vstack([uv[: n - 1 : 4], uv[n - 1]])
        traces.append(TubeTrace(mask=score > 0.5, backbone=path, tip=path[-1], entry=path[0],
                                score=score, width_px=12.0))  # fmt: skip
        truth.append(uv[-1])
    tips = [traces[0].tip, truth[1]]
    assert np.linalg.norm(tips[0] - truth[0]) > 15.0
    cc = choose_curled_end(cams, traces, tips)
    assert cc is not None and cc.view == 0 and cc.action == "refitted"
    assert np.linalg.norm(cc.tips[0] - truth[0]) <= 2.5
    assert choose_curled_end(cams, traces, tips, refit=False) is None
    # The pipeline's default (curl=False) fits the gentle model alone: the same end.
    cc2 = choose_curled_end(cams, traces, tips, curl=False)
    assert cc2 is not None and cc2.action == "refitted"
    np.testing.assert_array_equal(cc2.tips[0], cc.tips[0])
    t = curled_trace(traces[0], cc.fit, cc.action)
    np.testing.assert_array_equal(t.tip, cc.tips[0])
    np.testing.assert_array_equal(t.backbone[-1], cc.tips[0])


def test_a_refitted_view_is_recorded_as_refitted_not_as_a_branch():
    """``_traced_tips`` (what ``jaxcr stereo --segmentation trace`` records): the view whose
    trace is a refitted copy gets ``+refitted`` (not ``+branch``) and the copy's path."""
    from jaxcr.stereo.pipeline import _traced_tips
    from jaxcr.stereo.tip_consistency import TipConsistency

    cams, traces, truth = _views(150.0, apex_in_view1=True)
    cc = choose_curled_end(cams, traces, [traces[0].tip, truth[1]])
    assert cc is not None
    chosen = [curled_trace(traces[0], cc.fit, "refitted"), traces[1]]
    tips = [chosen[0].tip, cc.tips[1]]
    res = TipConsistency(tips, "refitted", 0, float("nan"), 1.0, 0.5)
    vrec = [{"tip_px": [0.0, 0.0], "backbone_px": t.backbone.tolist()} for t in traces]
    _traced_tips(vrec, traces, (tips, "trace_stereo", res, chosen))
    assert vrec[0]["tip_source"] == "trace_stereo+refitted"
    assert vrec[1]["tip_source"] == "trace_stereo"
    np.testing.assert_allclose(vrec[0]["tip_px"], chosen[0].tip, atol=0.006)
    np.testing.assert_allclose(vrec[0]["backbone_px"][-1], chosen[0].tip, atol=0.006)
    assert len(vrec[0]["backbone_px"]) > len(traces[0].backbone)  # the fitted axis appended
