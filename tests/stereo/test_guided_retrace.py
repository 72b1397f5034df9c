"""jaxcr.stereo.guided_retrace: one view's tube found again along the other view's
backbone, against a closed-form 3-D curve projected by OpenCV (``cv2.projectPoints``, with
lens distortion) and OpenCV's epipolar lines (``cv2.computeCorrespondEpilines`` on a
fundamental matrix from ``cv2.findFundamentalMat``)."""

from types import SimpleNamespace

import cv2
import numpy as np

from jaxcr.stereo.guided_retrace import (
    epipolar_lines,
    evidence_map,
    guided_candidate,
    guided_candidates,
    guided_retrace,
)
from jaxcr.stereo.tip_consistency import undistort_pixels
from tests.helpers.stereo_views import cam as _cam
from tests.helpers.stereo_views import project as _project

H, W = 720, 1280
WIDTH = 9.0  # drawn tube width, px


def _arc(n=400):
    """A circular arc of 60 mm radius turned by 120 deg in a tilted plane (metres)."""
    a = np.linspace(0.0, np.radians(120.0), n)
    r = 0.06
    return np.stack([0.3 * r * np.sin(a), -r * (1 - np.cos(a)), r * np.sin(a)], 1)


CAMS = [_cam([0.0, 0.0, 0.0], [0.0, -0.02, 0.35]), _cam([0.0, -0.35, 0.0], [-0.12, -0.02, 0.37])]


def _draw(lines, width=WIDTH):
    img = np.zeros((H, W), np.uint8)
    for ln in lines:
        pts = np.round(np.asarray(ln) * 16).astype(np.int32)
        cv2.polylines(img, [pts], False, 255, int(width), cv2.LINE_AA, shift=4)
    return img.astype(np.float64) / 255.0


def _dist_to(points, line):
    """Distance (px) of each point to the polyline ``line``."""
    seg = np.asarray(line, np.float64)
    a, b = seg[:-1], seg[1:]
    ab = b - a
    out = []
    for p in np.asarray(points, np.float64):
        t = np.clip(np.sum((p - a) * ab, 1) / np.maximum(np.sum(ab * ab, 1), 1e-12), 0, 1)
        out.append(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))
    return np.asarray(out)


def _scene():
    """The arc in both views; in view 2 a distractor (a cable) leaves the tube at 40 % of
    its length straight along the tube's tangent there, to the image border."""
    X = _arc()
    bb = [_project(c, X) for c in CAMS]
    i = int(0.4 * len(X))
    t = bb[1][i + 5] - bb[1][i - 5]
    t /= np.linalg.norm(t)
    cable = np.stack([bb[1][i], bb[1][i] + 2000.0 * t])
    scores = [_draw([bb[0]]), _draw([bb[1], cable])]
    return X, bb, scores


def test_epipolar_lines_match_opencv():
    # Points in a volume (a planar curve leaves the 8-point F undetermined).
    X = np.random.default_rng(0).uniform([-0.05, -0.06, -0.03], [0.05, 0.02, 0.07], (60, 3))
    uv = [_project(c, X) for c in CAMS]
    und = [undistort_pixels(c, u) for c, u in zip(CAMS, uv, strict=True)]
    F_cv, _ = cv2.findFundamentalMat(und[0], und[1], cv2.FM_8POINT)
    for view in (0, 1):
        ours = epipolar_lines(CAMS, uv[view][::7], view)
        ref = cv2.computeCorrespondEpilines(
            und[view][::7].reshape(-1, 1, 2), view + 1, F_cv
        ).reshape(-1, 3)
        # Same lines up to sign (both normalised to a^2 + b^2 = 1); the 8-point F from exact
        # (float64, undistorted) correspondences is exact to rounding.
        sign = np.sign(np.sum(ours * ref, axis=1))[:, None]
        np.testing.assert_allclose(ours, sign * ref, atol=2e-4 * np.abs(ref).max())
        # And each line passes through the other view's undistorted image of the point.
        other = und[1 - view][::7]
        d = np.abs(np.sum(ours[:, :2] * other, axis=1) + ours[:, 2])
        assert d.max() < 1e-6


def test_guided_retrace_follows_the_tube_not_the_cable():
    X, bb, scores = _scene()
    E = evidence_map(scores[1], width_px=WIDTH)
    gp = guided_retrace(CAMS, 0, bb[0], E, bb[1][0], WIDTH)
    assert gp is not None
    # Every point of the path on the tube (within half a width plus 1.5 px of its axis),
    # none on the cable beyond the junction, and the end on the tube's end.
    assert _dist_to(gp.backbone, bb[1]).max() < 0.5 * WIDTH + 1.5
    assert np.linalg.norm(gp.backbone[-1] - bb[1][-1]) < 0.5 * WIDTH + 1.0
    assert gp.tail_px < WIDTH and gp.off_px < WIDTH and gp.beyond == 0.0


def _trace(score, bb):
    """The attributes of a TubeTrace that guided_candidate(s) read, for a synthetic view."""
    return SimpleNamespace(
        score=score, seed_mask=score > 0.4, entry=bb[0], width_px=WIDTH, backbone=bb,
        tip=bb[-1], shift=np.zeros(2), scale=1, measured_width_px=WIDTH,
        crossing_turn_deg=0.0, crossings_followed=0, retrace=None,
    )  # fmt: skip


def test_guided_candidate_tip_on_the_projected_end():
    X, bb, scores = _scene()
    cable_trace = np.vstack([bb[1][: int(0.4 * len(X))], bb[1][int(0.4 * len(X))] + [0, 0]])
    other = _trace(scores[1], cable_trace)
    cand = guided_candidate(CAMS, 0, _trace(scores[0], bb[0]), other)
    assert cand is not None and cand.departure == -1
    # The refined tip (the silhouette's end less the end face's length) within 2.5 px of
    # the projected end point (the drawn line's round cap is a half disc, not the
    # foreshortened end face refine_tip_details models: up to w/4 of model error).
    assert np.linalg.norm(cand.tip - bb[1][-1]) < 2.5
    assert _dist_to(cand.backbone, bb[1]).max() < 2.0  # moved onto the tube's axis


def test_guided_candidates_gate_an_anchor_that_stops_on_a_going_tube():
    X, bb, scores = _scene()
    half = len(X) // 2
    # View 1's trace stopped half way along the tube (its tube goes on): as an anchor it
    # is refused; view 0 guides view 1 to the whole tube.
    traces = [_trace(scores[0], bb[0]), _trace(scores[1], bb[1][:half])]
    out = guided_candidates(CAMS, traces)
    assert out[0] == []
    assert len(out[1]) == 1
    assert np.linalg.norm(out[1][0].tip - bb[1][-1]) < 2.5


def test_traced_stereo_tips_takes_the_guided_candidate():
    """View 1's trace followed the cable from the junction (and noted no junction, so it has
    no re-traces of its own); view 0 traced the tube. The branch choice of
    :func:`jaxcr.stereo.pipeline.traced_stereo_tips` is offered view 1 re-traced along
    view 0 and takes it: view 1's tip on the projected end (the bound of
    test_guided_candidate_tip_on_the_projected_end), view 0's trace kept."""
    from jaxcr.segmentation.foreground import PlateForegroundConfig, TubeTrace
    from jaxcr.stereo.pipeline import traced_stereo_tips

    X, bb, scores = _scene()
    i = int(0.4 * len(X))
    t = bb[1][i + 5] - bb[1][i - 5]
    cable_path = np.vstack(
        [bb[1][: i + 1], bb[1][i] + np.outer(np.arange(4, 240, 4), t / np.linalg.norm(t))]
    )
    assert np.all((cable_path >= 0) & (cable_path < [W, H]))
    ctx = SimpleNamespace(low=SimpleNamespace(junctions=[]), cfg=PlateForegroundConfig(), k=1)

    def trace(score, path):
        tr = TubeTrace(score > 0.4, path, path[-1].copy(), path[0].copy(), score=score,
                       seed_mask=score > 0.4, width_px=WIDTH)  # fmt: skip
        tr.retrace = ctx
        return tr

    traces = [trace(scores[0], bb[0]), trace(scores[1], cable_path)]
    tips, src, _, chosen = traced_stereo_tips(CAMS, traces)
    assert "+branch" in src and chosen[0] is traces[0] and chosen[1].departure == -1
    assert np.linalg.norm(tips[1] - bb[1][-1]) < 2.5, (tips[1], bb[1][-1])
