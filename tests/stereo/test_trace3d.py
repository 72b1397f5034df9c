"""Stereo-coupled 3-D tracing (:mod:`jaxcr.stereo.trace3d`, issue 16 item 2,
docs/decisions.md S26) against an independent reference: a synthetic two-camera rig in
numpy whose score maps are drawn from a known 3-D arc (its projections, a tube of known
pixel width), with a distractor drawn in one view only (a straight branch leaving the
curving tube, where a 2-D tracer may go on); the projection and undistortion against
OpenCV."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from jaxcr.stereo.trace3d import finish_on_path, project, trace_backbone_3d, undistort
from jaxcr.synth.scene import look_at_pose

W, H = 256, 256
F = 750.0  # px: a 2 mm tube at 0.25 m is 6 px wide
TUBE_M = 2e-3
DIST = np.array([-0.05, 0.02, 0.0005, -0.0004, 0.0])


def _cam(eye):
    T = look_at_pose(np.asarray(eye), [0.02, 0.006, 0.03], up=(0.0, 0.0, 1.0))
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    return SimpleNamespace(K=K, dist=DIST, T_cam_robot=np.asarray(T, np.float64))


CAMS = [_cam([0.24, -0.03, 0.12]), _cam([0.04, -0.24, 0.13])]


def _arc(n=400):
    """A 60 deg arc of radius 60 mm from the base (origin) up z, bending towards +x and a
    little towards +y (its end runs across the epipolar planes of the two cameras)."""
    s = np.linspace(0.0, 1.0, n) * (np.pi / 3)
    R = 0.06
    x, z = R * (1 - np.cos(s)), R * np.sin(s)
    return np.stack([x, 0.3 * x, z], 1)


def _draw(uv, width, value=2.0):
    """A score map: ``value`` within ``width / 2`` of the polyline ``uv``, 0.1 elsewhere."""
    yy, xx = np.mgrid[0:H, 0:W]
    pix = np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float64)
    d = np.full(len(pix), np.inf)
    for a, b in zip(uv[:-1], uv[1:], strict=True):
        ab = b - a
        t = np.clip(((pix - a) @ ab) / max(ab @ ab, 1e-12), 0, 1)
        d = np.minimum(d, np.linalg.norm(pix - (a + t[:, None] * ab), axis=1))
    return np.where(d <= width / 2, value, 0.1).reshape(H, W)


def _scene():
    arc = _arc()
    scores, widths = [], []
    for cam in CAMS:
        uv = project(cam, arc[::4])
        depth = (cam.T_cam_robot[:3, :3] @ arc[len(arc) // 2] + cam.T_cam_robot[:3, 3])[2]
        w = F * TUBE_M / depth
        widths.append(w)
        scores.append(_draw(uv, w))
    # View 1 only: a straight distractor going on from the arc's middle along its tangent
    # there (where a 2-D tracer may leave the curving tube), as long as the rest of the arc.
    uv0 = project(CAMS[0], arc)
    m = len(arc) // 2
    tan = uv0[m + 5] - uv0[m - 5]
    tan /= np.linalg.norm(tan)
    line = np.stack([uv0[m], uv0[m] + 120.0 * tan])
    scores[0] = np.maximum(scores[0], _draw(line, widths[0]))
    return arc, scores, float(np.mean(widths)), line


def test_projection_and_undistortion_match_opencv():
    rng = np.random.default_rng(3)
    X = rng.uniform([-0.03, -0.03, 0.0], [0.05, 0.03, 0.07], (20, 3))
    for cam in CAMS:
        T = cam.T_cam_robot
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], cam.K, cam.dist)
        uv = project(cam, X)
        # float64 on both sides: pixels ~1e2, relative rounding ~1e-15.
        np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
        und = cv2.undistortPoints(ref, cam.K, cam.dist).reshape(-1, 2)
        # 20 fixed-point iterations: contraction ~|k1| r^2 < 0.01 per iteration here.
        np.testing.assert_allclose(undistort(cam, uv), und, atol=1e-9)


def test_traced_end_is_the_arcs_end_in_both_views():
    arc, scores, w, line = _scene()
    entries = [project(c, arc[:1])[0] for c in CAMS]
    ahead = [project(c, arc[40:41])[0] for c in CAMS]
    res = trace_backbone_3d(CAMS, scores, entries, w, ahead=ahead, high=1.0)
    assert res.reason is None
    step_px = [F * res.step_m / float((c.T_cam_robot[:3, :3] @ arc[-1] + c.T_cam_robot[:3, 3])[2])
               for c in CAMS]  # fmt: skip
    for k, cam in enumerate(CAMS):
        true_end = project(cam, arc[-1:])[0]
        err = float(np.linalg.norm(res.end_px[k] - true_end))
        # The drawn silhouette ends w/2 beyond the arc's end; the traced end is the last
        # quarter step whose (blurred, sigma w/4) evidence is at least the half level, so
        # along the tube it lies within [silhouette end - step/4, silhouette end]; across it
        # the re-centring keeps it within a grid spacing (0.15 step) of the axis; plus 1 px
        # for the blur's rounding of the disc-shaped end.
        bound = 0.5 * w + 0.25 * step_px[k] + 0.15 * step_px[k] + 1.0
        assert err <= bound, (k, err, bound)
    # The distractor (view 1 only) did not carry the path: its end is far from the path's.
    assert np.linalg.norm(res.end_px[0] - line[1]) > 10 * w


def test_finish_on_path_keeps_the_candidate_ending_at_the_path_end():
    # Three candidate traces of one view (a trace and two alternatives) ending 40 px apart;
    # the path's projected end lies 5 px from the second's tip (under 1.5 widths of 8 px):
    # that trace is kept as it is.
    line = np.stack([np.linspace(0, 100, 51), np.zeros(51)], 1)
    cands = [
        SimpleNamespace(backbone=line + [0, dy], tip=line[-1] + [0, dy], width_px=8.0)
        for dy in (0.0, 40.0, 80.0)
    ]
    chosen, how = finish_on_path(cands, np.array([97.0, 43.0]), line + [0, 40.0])
    assert how == "kept" and chosen is cands[1]
