"""Whether a stereo pair's two images were given in the wrong camera order (issue 16, audit
round 31 case S19: ``"cameras": ["R", "L"]`` with an L->R calibration).

The entry check (the two ``entry_px`` triangulated must reproject within 10 px) misses a
swapped order when the two entry pixels lie near each other (7 px apart in S19); the frame
then ran with one view's tip 240 px off and no flag. Here the two views' whole 2-D
backbones are compared under the calibration as given and with the two cameras exchanged
(view 1's image paired with camera 2's calibration and the reverse): the length of
backbone that does not triangulate consistently
(:func:`jaxcr.stereo.backbone_consistency.backbone_consistency`'s ``inconsistent_px``),
where a pair triangulated behind either camera counts as inconsistent too (a rig whose
cameras are parallel, its baseline along the image rows, has the same epipolar lines in
both orders: only the sign of the disparity, that is the depth, tells the orders apart).

A wrong order is *suspected* when the backbones are long enough to tell (the shorter at
least ``min_length_px``) and the exchanged order explains them much better: its
inconsistent length is at most ``1 / ratio`` of the given order's, and the given order
leaves at least ``min_fraction`` of the two backbones' summed length unexplained, and the
exchanged order also explains the two backbones' *ends* (each skeleton's last sample has a
pair reprojecting within ``tip_tol_px``, 10 px). The last condition is the S33 fix (issue
16, real_like development seed 4005, docs/decisions.md S33): there the cameras were in the
right order but one view's trace followed an occluding cable beyond the tube's crossing;
on that rig (two cameras at about one height) a wrong curve in one view pairs with the
other view's tube almost everywhere in the exchanged order (60 of 852 px unexplained
against 526 given), but not at its end (the ends' pairs reproject 33-38 px off exchanged,
190 px given). A genuinely swapped order explains the whole of two right backbones,
their ends included. Host numpy float64 and cv2 (undistortion), per frame, outside jit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.backbone_consistency import backbone_consistency

__all__ = ["CameraOrderCheck", "camera_order_check"]


@dataclass
class CameraOrderCheck:
    """Result of :func:`camera_order_check`. ``inconsistent_px``: the length (px, both views
    summed) of backbone that does not triangulate consistently in front of both cameras with
    the calibration as given; ``exchanged_px``: the same with the two cameras exchanged;
    ``length_px``: the two backbones' summed length (px, undistorted); ``tip_px``: [given,
    exchanged], the larger of the two backbone ends' residuals (each end sample's smallest
    reprojection error over its pairs, px, undistorted) in either order; ``suspect``: the
    exchanged order explains the backbones much better, their ends included (module
    docstring)."""

    inconsistent_px: float
    exchanged_px: float
    length_px: float
    suspect: bool
    tip_px: tuple[float, float] = (0.0, 0.0)


def _unexplained_px(cams, backbone1, backbone2, tol_px: float) -> tuple[float, float, float, float]:
    """(inconsistent length, summed length, shorter length, end residual) of the two
    backbones under ``cams``: a sample is explained by a pair of the monotone match that
    reprojects within ``tol_px`` and lies in front of both cameras; the end residual is the
    larger of the two backbones' last samples' smallest pair reprojection (px, inf when a
    last sample's pairs all lie behind a camera)."""
    bc = backbone_consistency(cams, backbone1, backbone2, tol_px=tol_px)
    X = bc.points
    front = np.isfinite(bc.reprojection_px)
    with np.errstate(invalid="ignore"):
        for cam in cams:
            T = np.asarray(cam.T_cam_robot, np.float64)
            front &= X @ T[2, :3] + T[2, 3] > 0  # depth along the optical axis (NaN: False)
    ok = front & (bc.reprojection_px <= tol_px)
    err = np.where(front, bc.reprojection_px, np.inf)
    bad = 0.0
    end = 0.0
    for k in range(2):
        explained = np.zeros(len(bc.samples[k]), bool)
        explained[bc.pairs[ok, k]] = True
        bad += float(np.sum(~explained)) * float(bc.steps_px[k])
        last = bc.pairs[:, k] == len(bc.samples[k]) - 1
        end = max(end, float(np.min(err[last])) if np.any(last) else np.inf)
    return bad, float(np.sum(bc.length_px)), float(np.min(bc.length_px)), end


def camera_order_check(
    cams, backbone1, backbone2, *, ratio: float = 4.0, min_fraction: float = 0.1,
    min_length_px: float = 60.0, tol_px: float = 3.0, tip_tol_px: float = 10.0,
) -> CameraOrderCheck:  # fmt: skip
    """Compare the two views' backbones under the given and the exchanged camera order.

    ``cams``: the two calibrated cameras (``K``, ``dist``, ``T_cam_robot`` in one shared
    frame) in the dataset's order; ``backbone1``, ``backbone2``: (n, 2) distorted (u, v)
    pixels of views 1 and 2, each from the robot's entry to its tip (the whole skeleton:
    a tip decision made under a wrong order must not shorten what is compared).
    ``ratio`` (4), ``min_fraction`` (0.1), ``min_length_px`` (60 px): the thresholds of
    ``suspect`` (module docstring). Measured: the round-31 audit frame (1280x720, entry
    pixels 7 px apart) leaves 0 of ~1165 px unexplained in the correct order and ~306 px
    (26 %) exchanged; the stereo synth at 320x240 (entry pixels ~6 px apart) 0 of 293 px /
    174 px (59 %, seed 0) and 0 of 180 px / 38 px (21 %, seed 4, a short robot); 0.1 keeps a
    factor 2 below the smallest, and the ratio 4 keeps a frame whose one view took a wrong
    branch (unexplained in both orders) unflagged. 60 px is about four tube widths at
    1280x720, below which a short stub is explained by almost any geometry. ``tol_px`` as
    in :func:`backbone_consistency`. ``tip_tol_px`` (10 px, the CLI's tip-epipolar WARNING
    level): how close the exchanged order must explain the two backbones' ends (S33, module
    docstring: 0.6 and 6.5 px on the two genuinely swapped real_like frames flagged, 33-38
    px on the false flags of seed 4005; experiments/results/stereo/warnings_s33.md)."""
    given, total, shorter, tip_given = _unexplained_px(cams, backbone1, backbone2, tol_px)
    swapped, _, _, tip_swapped = _unexplained_px((cams[1], cams[0]), backbone1, backbone2, tol_px)
    suspect = bool(
        shorter >= min_length_px
        and given >= min_fraction * total
        and given >= ratio * swapped
        and tip_swapped <= tip_tol_px
    )
    return CameraOrderCheck(
        round(given, 1), round(swapped, 1), round(total, 1), suspect,
        (round(tip_given, 1), round(tip_swapped, 1)),
    )  # fmt: skip
