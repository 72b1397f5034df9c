"""The tip step after the branch choice (:func:`jaxcr.stereo.pipeline._tip_step`, issue 16
item 2, docs/decisions.md S50): where two tips are over the 5 px flag apart but within the
rig's calibration tolerance and their backbones explain each other, the fold and the trim
do not act (``mend_within_tolerance=False``); the tips' re-search still runs, over the
tolerance. A 3-D arc projected by ``cv2.projectPoints`` into two pinhole cameras; the
epipolar distances are the closed form of the two poses' fundamental matrix."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.branch_choice import CONSISTENT_PX
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses
from jaxcr.synth.scene import look_at_pose

K = np.array([[220.0, 0.0, 80.0], [0.0, 220.0, 60.0], [0.0, 0.0, 1.0]])
T0 = look_at_pose(np.array([0.30, -0.08, 0.06]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
T1 = look_at_pose(np.array([0.06, -0.30, 0.08]), [0.0, 0.0, 0.04], up=(0.0, 0.0, 1.0))
CAMS = [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in (T0, T1)]
F = fundamental_from_poses(K, T0, K, T1)
TOLERANCE_PX = 8.0  # the re-search's level (what the calibration tolerance gives on a rig)


def _proj(T, X):
    rvec, _ = cv2.Rodrigues(np.asarray(T[:3, :3], np.float64))
    uv, _ = cv2.projectPoints(np.atleast_2d(X).astype(np.float64), rvec, T[:3, 3], K, None)
    return uv.reshape(-1, 2)


def _tube():
    """A planar arc (radius 6 cm, 70 deg) from the base up, in both views (px)."""
    s = np.linspace(0.0, np.deg2rad(70.0), 60)
    arc = np.stack([0.06 * (1 - np.cos(s)), 0.0 * s, 0.06 * np.sin(s)], 1)
    return [_proj(T, arc) for T in (T0, T1)]


def _off_epiline(bb1, x0, off_px):
    """View 1's backbone with its tip moved ``off_px`` across the epipolar line of view 0's
    tip ``x0`` (the calibration error of a rig moves right tips so)."""
    ln = F @ np.r_[x0, 1.0]
    ln = ln / np.hypot(ln[0], ln[1])
    out = bb1.copy()
    out[-1] = out[-1] + off_px * ln[:2]
    return out


def _trace(bb):
    return SimpleNamespace(tip=bb[-1].copy(), backbone=bb, width_px=4.0)


def _spy(monkeypatch):
    calls = {"fold": 0, "trim": 0, "research_px": None}

    def fold(cams, bc, widths):
        calls["fold"] += 1

    def trim(cams, traces, tips, bc, tails):
        calls["trim"] += 1

    def research(cams, traces, tips, flag_px):
        calls["research_px"] = flag_px
        return SimpleNamespace(tips=tips, action="consistent")

    monkeypatch.setattr(pipeline, "fold_back_tip", fold)
    monkeypatch.setattr(pipeline, "trim_unexplained_tail", trim)
    monkeypatch.setattr(pipeline, "reconcile_tips", research)
    return calls


def _step(views, mend):
    tips = [v.tip for v in views]
    return pipeline._tip_step(CAMS, views, tips, "trace_stereo", 5.0, research_px=TOLERANCE_PX,
                              mend_within_tolerance=mend)  # fmt: skip


@pytest.mark.parametrize("mend", [True, False])
def test_a_consistent_pair_within_the_tolerance_is_not_mended(monkeypatch, mend):
    """Tips 6 px apart (over the 5 px flag, under the 8 px tolerance), backbones that
    explain each other but for the last few px: the fold and the trim run only with
    ``mend_within_tolerance`` (as before S50); the re-search runs over the tolerance
    either way."""
    tube = _tube()
    views = [_trace(tube[0]), _trace(_off_epiline(tube[1], tube[0][-1], 6.0))]
    gap = max(epipolar_distances(F, views[0].tip, views[1].tip))
    assert 5.0 < gap < TOLERANCE_PX
    bad = backbone_consistency(CAMS, views[0].backbone, views[1].backbone).inconsistent_px
    assert bad <= CONSISTENT_PX
    calls = _spy(monkeypatch)
    _step(views, mend)
    assert (calls["fold"], calls["trim"]) == ((1, 1) if mend else (0, 0))
    assert calls["research_px"] == TOLERANCE_PX


def test_a_pair_over_the_tolerance_or_inconsistent_is_still_mended(monkeypatch):
    """Over the tolerance (12 px apart), or within it but with a backbone that leaves the
    other view over ``CONSISTENT_PX`` unexplained (view 0 runs off the tube half way, out
    across the epipolar lines and back to a tip 6 px from view 1's line), the fold and the
    trim run with ``mend_within_tolerance=False`` too."""
    tube = _tube()
    calls = _spy(monkeypatch)
    far = [_trace(tube[0]), _trace(_off_epiline(tube[1], tube[0][-1], 12.0))]
    assert max(epipolar_distances(F, far[0].tip, far[1].tip)) > TOLERANCE_PX
    _step(far, False)
    assert (calls["fold"], calls["trim"]) == (1, 1)

    half = tube[0][:30]
    ln = F.T @ np.r_[tube[1][-1], 1.0]  # view 0's epipolar line of view 1's tip
    ln = ln / np.hypot(ln[0], ln[1])
    out = half[-1] + 40.0 * ln[:2]
    end = tube[0][-1] + 6.0 * ln[:2]
    t = np.linspace(0.0, 1.0, 20)[1:, None]
    wrong = [_trace(np.vstack([half, half[-1] + t * (out - half[-1]), out + t * (end - out)])),
             _trace(tube[1])]  # fmt: skip
    gap = max(epipolar_distances(F, wrong[0].tip, wrong[1].tip))
    assert 5.0 < gap < TOLERANCE_PX
    bad = backbone_consistency(CAMS, wrong[0].backbone, wrong[1].backbone).inconsistent_px
    assert bad > CONSISTENT_PX
    _step(wrong, False)
    assert (calls["fold"], calls["trim"]) == (2, 2)
