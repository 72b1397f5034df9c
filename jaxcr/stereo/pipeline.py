"""The stereo shape-sensing pipeline for one stereo pair (issue 4, method steps 2-7).

``reconstruct_pair(image1, image2, cam1, cam2, config)`` runs, per view and then jointly:

1. base frame from the ArUco markers (:mod:`jaxcr.stereo.aruco`), both views combined, or
   without markers from a given ``T_cam_base`` or the entry pixels
   (:mod:`jaxcr.stereo.base_frame`; with entry pixels the z axis is set after step 6);
2. foreground alpha from the chroma key and/or the background plate
   (:mod:`jaxcr.stereo.chroma`); marker squares (projected from the base pose) removed;
3. base localisation (Hough in a ROI at the projected robot base) and flood fill of the
   robot (:mod:`jaxcr.stereo.base_locate`);
4. Zhang-Suen thinning in JAX (:mod:`jaxcr.stereo.thinning`);
5. ordering of the skeleton from the base (:mod:`jaxcr.stereo.ordering`);
6. monotone epipolar correspondence and DLT triangulation in the base frame
   (:mod:`jaxcr.stereo.correspondence`, :mod:`jaxcr.stereo.triangulation`), then
   smoothing and resampling along the arclength, then sub-pixel refinement: the backbone's
   projections are moved to the silhouette centres measured across the tube and
   re-triangulated;
7. diameters along the backbone (:mod:`jaxcr.stereo.diameter`), segments from diameter
   steps (:mod:`jaxcr.stereo.segments`), and per segment a plane fit (angles with the X-Y,
   Z-X, Y-Z planes) and a circular-arc fit (curvature, arc length) (:mod:`jaxcr.stereo.fits`);
   the joint chain fit's continuation over the part one view alone sees extends the stored
   backbone (flagged ``single_view``); each view's tip pixel and 2-D backbone
   (:mod:`jaxcr.stereo.view2d`).

Speed (``experiments/stereo/stereo_bench.py``): both views go through each JAX stage in one jitted
call (alpha/key projection/mask from the uint8 images; thinning of the robots' bounding-box
crops, padded to one square window and vmapped; refinement profiles and diameters, one
program); arrays whose length varies per frame are padded to buckets (thinning windows
64 px times a power of two; backbone points 256; the joint chain fit's observations 256
times a power of two and its segments padded to four,
:func:`jaxcr.stereo.chain_fit.pad_chain`), so a new frame of a seen size compiles nothing
and a first run compiles each program about once (docs/decisions.md S23); the two marker
detections run in two threads (OpenCV releases the GIL); ordering, DTW and the arclength
smoothing are vectorised numpy/scipy without per-pixel Python loops.

Per-frame problems raise :class:`StereoFailure` with a short ``reason`` code
(``calibration_size``, ``markers``, ``base``, ``robot_not_found``, ``correspondence``) for the batch
driver to record; nothing else is expected to raise. Stage timings (seconds, wall clock,
JAX results blocked) are returned in ``result["timings"]``, the process CPU time of each
stage (all threads) in ``result["timings"]["cpu"]``.
"""

from __future__ import annotations

import functools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter1d

from jaxcr.camera import Camera, project_points
from jaxcr.segmentation.capsule_end import with_capsule_end
from jaxcr.segmentation.foreground import (
    PlateForegroundConfig,
    plate_foreground,
    trace_alternatives,
)
from jaxcr.stereo.aruco import MarkerLayout, detect_markers, stereo_base_pose
from jaxcr.stereo.backbone_consistency import backbone_consistency, fold_back_tip, open_end_tails
from jaxcr.stereo.base_frame import (
    BaseSpec,
    frame_from_direction,
    initial_direction,
    relative_pose,
    triangulate_entry,
)
from jaxcr.stereo.base_locate import flood_component, locate_base
from jaxcr.stereo.branch_choice import CONSISTENT_PX, choose_branches
from jaxcr.stereo.camera_order import camera_order_check
from jaxcr.stereo.chain_fit import (
    _direct,  # the default jit_call: fn(*args)
    chain_points,
    fit_segments_jointly,
    observations_from_profiles,
    pad_chain,
)
from jaxcr.stereo.chroma import (
    KEY_COLOURS,
    chroma_alpha_and_projection,
    plate_alpha,
    plate_alpha_shadow_invariant,
)
from jaxcr.stereo.correspondence import match_backbones
from jaxcr.stereo.curl_choice import choose_curled_end, curled_trace
from jaxcr.stereo.diameter import (
    cylinder_diameters,
    edge_clearance,
    profile_widths,
    report_interpolation_diameters,
    view_weights,
)
from jaxcr.stereo.epipolar_tolerance import CalibrationUncertainty, tip_epipolar_tolerance_px
from jaxcr.stereo.fits import fit_arc, fit_plane, plane_angles
from jaxcr.stereo.guided_ranking import offered_guided, with_own_turns
from jaxcr.stereo.guided_retrace import guided_candidates
from jaxcr.stereo.ordering import order_skeleton
from jaxcr.stereo.run_on import with_run_on
from jaxcr.stereo.segments import segment_backbone
from jaxcr.stereo.shadow import shadow_cut
from jaxcr.stereo.thinning import zhang_suen_thin
from jaxcr.stereo.tip_consistency import (
    TipConsistency,
    epipolar_gap_px,
    reconcile_tips,
    trim_unexplained_tail,
    undistort_pixels,
)
from jaxcr.stereo.tip_fusion import fuse_traced_tips
from jaxcr.stereo.tip_geometry import (
    end_face_lengths,
    epipolar_distances,
    fundamental_from_poses,
)
from jaxcr.stereo.triangulation import triangulate_points
from jaxcr.stereo.view2d import tip_pixel, view_record

__all__ = [
    "StereoConfig",
    "StereoFailure",
    "entry_direction_px",
    "reconstruct_pair",
    "trace_stereo_tips",
    "traced_stereo_tips",
]


class StereoFailure(Exception):
    """A frame that cannot be reconstructed: ``reason`` code and a one-line message."""

    def __init__(self, reason: str, message: str):
        self.reason = reason
        super().__init__(f"{reason}: {message}")


@dataclass
class StereoConfig:
    """Pipeline settings. Lengths in metres.

    ``segmentation``: ``"chroma"`` (key colour ``key_rgb`` with ``tol_lo``/``tol_hi``),
    ``"plate"`` (background plate difference; shadows are segmented with the tube),
    ``"plate_shadow"`` (plate difference after the best shadow gain, which ignores
    shadows) or ``"both"`` (the product of chroma and plate alphas: foreground must differ
    from the plate and not be the key colour), or ``"trace"`` (the plate foreground of
    :mod:`jaxcr.segmentation.foreground`, settings ``plate_foreground``: the plate aligned to the frame,
    cues beyond the key colour with hysteresis, the tube traced from the projected robot
    base with gaps bridged; for real backgrounds; each view's ``tip_px`` is then the traced
    tip corrected by :func:`trace_stereo_tips`, with ``tip_source``).
    ``robot_base``: where the robot leaves the plate, base frame (default: base centre).
    ``n_segments``: number of tubes if known (else chosen from the diameter profile).
    ``refine_iterations``: sub-pixel refinement passes (silhouette centres, re-triangulate).
    ``tip_extension_px``: image-space extrapolation of each view's tip for the matching
    (recovers tips foreshortened in one view; see :func:`match_backbones`).
    ``joint_fit``: curvatures and bending planes from the joint chain fit to both views
    (:mod:`jaxcr.stereo.chain_fit`) instead of separate per-segment fits to the points.
    ``base``: how the base frame is given (:class:`jaxcr.stereo.base_frame.BaseSpec`:
    ArUco markers, a fixed ``T_cam_base`` or the entry pixels); without markers no marker
    squares are masked and ``robot_base`` defaults to the base origin (with ``entry_px``
    it is ignored: the entry point is the origin).
    ``single_view_tail``: extend the stored backbone beyond the last stereo match with the
    joint chain fit over the part one view alone sees, up to that view's tip pixel
    (flagged ``single_view``).
    ``tip_search_px``: how far each view's tip pixel is searched beyond the skeleton's end
    (:func:`tip_pixel`).
    ``shadow_tolerance_deg``: tolerance of the slope-angle segmentation that cuts a shadow
    branch off the start of each view's ordered skeleton (:func:`shadow_cut`; report
    sec. 5.3, Fig. 18 uses 10-30 deg); ``None`` disables it.
    ``calibration``: the rig's calibration uncertainty, passed to :func:`traced_stereo_tips`
    (``segmentation="trace"``; None: the fixed 5 px; ``jaxcr stereo`` reads it from the
    calibration file's ``uncertainty`` block or ``--calibration-sigma``).
    """

    layout: MarkerLayout = field(default_factory=MarkerLayout)
    key_rgb: tuple[float, float, float] = KEY_COLOURS["green"]
    tol_lo: float = 0.5
    tol_hi: float = 0.8
    segmentation: str = "chroma"
    plate_lo: float = 0.06
    plate_hi: float = 0.15
    robot_base: tuple[float, float, float] | None = None
    roi_half_px: int = 24
    n_segments: int | None = None
    max_segments: int = 4
    step: float = 5e-4
    smooth_sigma: float = 1.0e-3
    trim: float = 1.5e-3
    min_robot_pixels: int = 40
    # A connected "robot" region larger than this fraction of the view is the background not
    # matching the key (e.g. a black or wrongly exposed image), not a thin tube.
    max_robot_fraction: float = 0.5
    refine_iterations: int = 2
    tip_extension_px: int = 12
    joint_fit: bool = True
    shadow_tolerance_deg: float | None = 20.0
    base: BaseSpec = field(default_factory=BaseSpec)
    single_view_tail: bool = True
    tip_search_px: int = 40
    plate_foreground: PlateForegroundConfig = field(default_factory=PlateForegroundConfig)
    calibration: CalibrationUncertainty | None = None


def _given_base_pose(cam1: Camera, cam2: Camera, spec: BaseSpec) -> dict:
    """The stereo base pose without markers (same keys as
    :func:`jaxcr.stereo.aruco.stereo_base_pose`; no marker RMS): ``spec.T_cam1_base`` as
    given, or for ``entry_px`` the provisional frame at the triangulated entry point with
    camera 1's axes (rotated once the backbone's initial direction is known)."""
    if spec.mode == "T_cam_base":
        T1 = np.asarray(spec.T_cam1_base, np.float64)
        residual = None
    elif spec.mode == "entry_px":
        X, residual, depths = triangulate_entry(cam1, cam2, *spec.entry_px[:2])
        if min(depths) <= 0:
            raise StereoFailure("base", "the entry pixels triangulate behind a camera")
        T1 = np.eye(4)
        T1[:3, 3] = X
    else:
        raise ValueError(f"unknown base mode {spec.mode!r}")
    return {"T_cam1_base": T1, "T_cam2_base": relative_pose(cam1, cam2) @ T1,
            "rms_px": None, "n_markers": (0, 0), "entry_residual_px": residual}  # fmt: skip


def _with_pose(cam: Camera, T: np.ndarray) -> Camera:
    return eqx.tree_at(
        lambda c: c.T_cam_robot, cam, jax.device_put(np.asarray(T, np.dtype(cam.K.dtype)))
    )


def _f32(x) -> jax.Array:
    """numpy -> float32 device array (converted on the host and put on the device:
    ``jnp.asarray`` would compile a staging program per shape)."""
    return jax.device_put(np.asarray(x, np.float32))


def _essential_np(T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """:func:`jaxcr.stereo.triangulation.essential_matrix` in numpy float64 (per frame,
    without eager JAX dispatches)."""
    T21 = np.asarray(T2, np.float64) @ np.linalg.inv(np.asarray(T1, np.float64))
    t = T21[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ T21[:3, :3]


def _now() -> tuple[float, float]:
    """(wall clock, process CPU time) in seconds."""
    return time.perf_counter(), time.process_time()


def _tick(timings: dict, name: str, t0: tuple[float, float]) -> tuple[float, float]:
    """Add the wall time since ``t0`` to ``timings[name]`` and the process CPU time (all
    threads) to ``timings["cpu"][name]``; returns the new start."""
    t = _now()
    timings[name] = timings.get(name, 0.0) + (t[0] - t0[0])
    cpu = timings.setdefault("cpu", {})
    cpu[name] = cpu.get(name, 0.0) + (t[1] - t0[1])
    return t


def _as_float(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)


def _project_np(cam: Camera, pts: np.ndarray, T: np.ndarray | None = None) -> np.ndarray:
    """Pixels (n, 2) of base-frame points through ``cam`` (cv2.projectPoints, float64), with
    the extrinsic ``T`` (4x4, base -> camera; default ``cam.T_cam_robot``)."""
    T = np.asarray(cam.T_cam_robot if T is None else T, np.float64)
    uv, _ = cv2.projectPoints(
        np.ascontiguousarray(pts, np.float64).reshape(-1, 3),
        cv2.Rodrigues(T[:3, :3])[0],
        T[:3, 3],
        np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
    )
    return uv.reshape(-1, 2)


def entry_direction_px(cam: Camera, base: np.ndarray, *, length: float = 5e-3) -> np.ndarray | None:
    """Unit image direction (u, v) in which the robot leaves its base in ``cam``'s view: the
    projections of ``base`` and of ``base + length * z`` (base frame, metres; z the
    insertion axis), distorted pixels as the camera records them. None when the axis
    runs within half a pixel of the viewing ray (no image direction)."""
    base = np.asarray(base, np.float64)
    uv = _project_np(cam, np.stack([base, base + np.array([0.0, 0.0, length])]))
    d = uv[1] - uv[0]
    n = float(np.linalg.norm(d))
    return d / n if n > 0.5 else None


def _tip_epipolar_px(cams, vrec) -> float:
    """Epipolar consistency of the two views' ``tip_px``: the larger of the distances (px,
    on undistorted pixels) of each tip to the epiline of the other
    (:func:`jaxcr.stereo.tip_geometry.epipolar_distances`); a tip found on different points
    of the tube in the two views is far from the other's epiline."""
    und = []
    for c, v in zip(cams, vrec, strict=True):
        K = np.asarray(c.K, np.float64)
        x = np.asarray(v["tip_px"], np.float64).reshape(1, 1, 2)
        und.append(cv2.undistortPoints(x, K, np.asarray(c.dist, np.float64), P=K).reshape(2))
    F = fundamental_from_poses(np.asarray(cams[0].K, np.float64), cams[0].T_cam_robot,
                               np.asarray(cams[1].K, np.float64), cams[1].T_cam_robot)  # fmt: skip
    return round(max(epipolar_distances(F, und[0], und[1])), 2)


def trace_stereo_tips(cams, traces) -> tuple[list[np.ndarray], list[float]] | None:
    """Each view's traced tip corrected with the end face's length from both views (issue 16
    item 2, method ``trace_stereo`` of experiments/segmentation/real_like_tip.py).

    ``cams``: the two calibrated cameras (``K``, ``dist``, ``T_cam_robot`` in a frame shared
    by both). ``traces``: per view an object with the attributes of
    :class:`jaxcr.segmentation.foreground.TubeTrace` ``tip``, ``cap_px``, ``end_dir`` and
    ``end_half_width_px`` (distorted pixels, as :func:`plate_foreground` returns them).

    One view places its tip ``cap_px`` (the end face's foreshortened length, estimated from
    the end's shape) short of the silhouette's end ``tip + cap_px * end_dir``. Here the
    length comes from the tube's 3-D direction instead: the two silhouette ends and end
    directions (undistorted; the direction from the end to the point 5 px further out) give
    the axis (:func:`jaxcr.stereo.tip_geometry.end_face_lengths`), and the tip is the end
    moved back by the view's length ``a_k`` along ``end_dir``. Returns ``([tip1, tip2],
    [a1, a2])`` (tips (u, v) distorted pixels, float64), or None when a view has no finite
    end or no half width, or the two end directions leave the axis undetermined (near an
    epipolar plane); the caller keeps the one-view tips then.

    On the real_like preset at 1280x720 this raised the frames with both tips within 5 px
    from 66 % (one-view tips) to 86 % (experiments/results/segmentation/
    real_like_tip_r3_1280x720.md).
    """
    ends, dirs = [], []
    for t in traces:
        d = np.asarray(t.end_dir, np.float64)
        e = np.asarray(t.tip, np.float64) + t.cap_px * d
        if not (np.all(np.isfinite(e)) and t.end_half_width_px > 0):
            return None
        ends.append(e)
        dirs.append(d)
    eu = [undistort_pixels(c, e)[0] for c, e in zip(cams, ends, strict=True)]
    du = [undistort_pixels(c, e + 5.0 * d)[0] - x
          for c, e, d, x in zip(cams, ends, dirs, eu, strict=True)]  # fmt: skip
    res = end_face_lengths(
        np.asarray(cams[0].K, np.float64), cams[0].T_cam_robot,
        np.asarray(cams[1].K, np.float64), cams[1].T_cam_robot,
        eu[0], du[0] / np.linalg.norm(du[0]), eu[1], du[1] / np.linalg.norm(du[1]),
        traces[0].end_half_width_px, traces[1].end_half_width_px,
    )  # fmt: skip
    if res is None:
        return None
    # A view whose end face was measured by the capsule fit with ``cap_from_image`` keeps
    # that length (S42).
    a = [t.cap_px if getattr(t, "cap_from_image", False) else res[k]
         for k, t in enumerate(traces)]  # fmt: skip
    return [ends[k] - a[k] * dirs[k] for k in range(2)], a


def traced_stereo_tips(
    cams,
    traces,
    *,
    flag_px: float = 5.0,
    calibration: CalibrationUncertainty | None = None,
    run_on: bool = True,
    end_fit: bool | str = True,
    fuse_ends: bool = False,
    curl_ends: bool = False,
    refit_ends: bool = True,
    branch_tips: bool = True,
    branch_backbones: bool = True,
    mend_within_tolerance: bool = True,
) -> tuple[list[np.ndarray], str, TipConsistency | None, list]:
    """The two views' tips as ``jaxcr stereo --segmentation trace`` records them: the traced
    tips with the end face's length from both views (:func:`trace_stereo_tips`; each
    view's own traced tip where the two views leave it undetermined); where the two tips
    are over ``flag_px`` from each other's epipolar lines, the branches the tracers took at
    the junctions they passed are chosen again by both views together (each view's trace,
    its re-traces from its junctions, :func:`jaxcr.segmentation.foreground.
    trace_alternatives`, and its tube found again along the other view's trace,
    :func:`jaxcr.stereo.guided_retrace.guided_candidates`, ranked by its own turns at the
    view's junctions, :mod:`jaxcr.stereo.guided_ranking`; the consistent pair whose whole backbones triangulate
    consistently, :func:`jaxcr.stereo.branch_choice.choose_branches` with
    :func:`jaxcr.stereo.backbone_consistency.backbone_consistency`; one view keeps its
    trace unless both traces follow a crossing object, docs/decisions.md S39); then, still over
    ``flag_px``, a view whose tube hooks back over its own silhouette gets its tip where
    the way back ends (:func:`jaxcr.stereo.backbone_consistency.fold_back_tip`, action
    ``"folded"``), else a view's backbone end that the other view does not explain is cut
    back (:func:`jaxcr.stereo.tip_consistency.trim_unexplained_tail` with
    :func:`jaxcr.stereo.backbone_consistency.open_end_tails`, action ``"trimmed"``, or
    ``"rebranched"`` where the path to cut left no tube and the other view's end moves),
    else the tips are re-searched along the traced tubes
    (:func:`jaxcr.stereo.tip_consistency.reconcile_tips`). ``traces``: the two
    :class:`jaxcr.segmentation.foreground.TubeTrace`. Returns (tips [(2,), (2,)] distorted
    (u, v), source ``"trace_stereo"`` or ``"trace"`` (``"+branch"`` appended when a branch
    choice replaced a view's trace), the re-search's result or None when a tip is not
    finite, the two traces the tips belong to).

    ``calibration``: the rig's calibration uncertainty, given: the tips' re-search, which
    moves a tip onto the other's epipolar line, acts only on tips further apart than right
    tips can be under it (:func:`jaxcr.stereo.epipolar_tolerance.tip_epipolar_tolerance_px`,
    at least ``flag_px``; docs/decisions.md S37: a right pair 5.4 px apart was cut back, dev
    4177). The branch choice, fold and trim keep ``flag_px``: they act on whole backbones
    that leave over a tube width unexplained, which no calibration error of a few pixels
    makes (a tip gap of 7 px hid a trace 536 px off, dev 4074).

    ``run_on``: where one view's trace ends where its tube ends and the other view's trace
    explains it with its own beginning, then crosses background or turns sharply (it ran
    on past the tube's end onto a crossing object), that trace cut back there is offered to
    the branch choice and the first view's path along it is not
    (:mod:`jaxcr.stereo.run_on`, docs/decisions.md S41; on by default since stop 36).

    ``end_fit``: after the branch choice, the two chosen traces' tips placed by a blurred
    capsule end fitted to each one's cue map (:func:`jaxcr.segmentation.capsule_end.
    with_capsule_end`, docs/decisions.md S42; the paths and the branch choice are the
    tracer's), their two-view tips computed again, then the tip step; ``"image"``: and the
    fitted end face's length kept in the two-view step. On (``True``) by default since stop 36
    (S42); ``False`` gives the tracer's own end walk.

    ``fuse_ends`` (with ``calibration``; off: measured, not adopted, S40): tips the tip step
    calls ``"consistent"`` are replaced by the ones the two views' ends give when
    triangulated with each view's along/across covariance
    (:func:`jaxcr.stereo.tip_fusion.fuse_traced_tips`).

    ``refit_ends`` (on by default since stop 38, S47): last, each view's end is fitted on its
    cue map (:mod:`jaxcr.segmentation.curl_end`) and a view's tip may be replaced by the
    end of the fit held to a gentle bend where that end is at least 10 px from the tip and
    brings the pair within ``flag_px`` of each other's epipolar lines, 2 px nearer (the
    tube's cue faded before its end and the tracer stopped there); the result's action is
    then ``"refitted"`` for that view and its trace a copy ending in the fitted axis
    (:func:`jaxcr.stereo.curl_choice.curled_trace`, attribute ``curl_of`` the trace it
    replaces). About 0.3 CPU-s a frame (median; 2 s with ``curl_ends``). ``curl_ends`` (off: measured on two fresh sets, not
    kept, S46/S48): first, a curled end where that fit beats the gentle one clearly and the
    pair's epipolar distance drops by 2 px (action ``"curled"``;
    :func:`jaxcr.stereo.curl_choice.choose_curled_end`).

    ``branch_tips`` (on by default since stop 39, docs/decisions.md S49): where the traces'
    tips are over ``flag_px`` apart, a pair whose tips are within it may replace them when
    its backbones are no less consistent than the traces' (the check is blind where a trace
    follows a cable along the epipolar lines, so no alternative can be clearly better
    there) and each changed view ends over the margin from its trace's tip (another
    branch); such pairs rank first (:func:`jaxcr.stereo.branch_choice.choose_branches`'
    ``tip_flag_px``). ``branch_backbones`` (on by default since stop 39, S49): the branch
    choice also runs where the tips agree but the traces' backbones leave over
    ``CONSISTENT_PX`` unexplained (a wrong end that meets the other tip's epipolar line by
    chance).

    ``mend_within_tolerance`` False (with ``calibration``; measured at stop 40, not adopted,
    docs/decisions.md S50): where the tips are over ``flag_px`` but within the calibration's
    tolerance apart and the two backbones leave at most ``CONSISTENT_PX`` unexplained, the
    fold and the trim do not act (only the re-search, which keeps such a pair). It mends a
    right pair 5.5 px apart that the trim cut by 19 px (dev 4654) and no other of 450
    development frames, and leaves a 12 px overshoot under a wide calibration uncut (its
    backbones leave 6 px unexplained: S37's case, ``tests/stereo/test_epipolar_tolerance.py``)."""
    traces, tips, src = _branch_step(cams, traces, flag_px, run_on=run_on, tips_gate=branch_tips,
                                     backbones_flag=branch_backbones)  # fmt: skip
    chosen = traces
    if end_fit:
        # After the branch choice (its candidates and decisions are the tracer's), the
        # chosen traces' ends placed by the fit, and their two-view tips again.
        traces = [with_capsule_end(t, cap_from_image=end_fit == "image") for t in traces]
        tips, own = _stereo_or_own_tips(cams, traces)
        src = own + ("+branch" if src.endswith("+branch") else "")
    research_px = None
    if calibration is not None:
        research_px = tip_epipolar_tolerance_px(cams, tips, calibration, floor_px=flag_px)
    out = _tip_step(cams, traces, tips, src, flag_px, research_px=research_px,
                    mend_within_tolerance=mend_within_tolerance)  # fmt: skip
    consistent = out[2] is not None and out[2].action == "consistent"
    if fuse_ends and calibration is not None and consistent:
        fused = fuse_traced_tips(cams, out[3], out[0], calibration)
        if fused is not None and fused.applied:
            out = (fused.tips, out[1], out[2], out[3])
    if curl_ends or refit_ends:
        cc = choose_curled_end(cams, chosen, out[0], curl=curl_ends, refit=refit_ends,
                               refit_gap_px=flag_px)  # fmt: skip
        if cc is not None:
            res = TipConsistency(cc.tips, cc.action, cc.view, float("nan"),
                                 cc.epipolar_before_px, cc.epipolar_after_px)  # fmt: skip
            chosen = list(chosen)
            chosen[cc.view] = curled_trace(chosen[cc.view], cc.fit, cc.action)
            return cc.tips, out[1], res, chosen
    # The traces returned are the branch choice's (a placed copy is the same path: callers
    # tell a replaced branch by identity, looking through a curled copy's ``curl_of``).
    return out[0], out[1], out[2], chosen


def _tip_step(
    cams, traces, tips, src, flag_px: float, *, research_px: float | None = None,
    mend_within_tolerance: bool = True,
):  # fmt: skip
    """:func:`traced_stereo_tips` after the branch choice: a fold, a trim or the tips'
    re-search (its return value; flagged over ``research_px`` when given, else
    ``flag_px``). ``mend_within_tolerance`` False (with ``research_px``; measured at stop 40,
    not adopted: docs/decisions.md S50): a pair within ``research_px`` whose backbones leave
    at most ``CONSISTENT_PX`` unexplained is neither folded nor trimmed."""
    if not all(np.all(np.isfinite(t)) for t in tips):
        return tips, src, None, traces
    res = None
    gap = epipolar_gap_px(cams, tips)
    mend = gap > flag_px
    if mend:
        bc = backbone_consistency(
            cams, _ending_at(traces[0].backbone, tips[0]), _ending_at(traces[1].backbone, tips[1])
        )
        if not (mend_within_tolerance or research_px is None or gap > research_px):
            # S50 (off by default): a pair within the tolerance that explains itself is
            # left to the re-search.
            mend = bc.inconsistent_px > CONSISTENT_PX
    if mend:
        fold = fold_back_tip(cams, bc, [t.width_px for t in traces])
        if fold is not None:
            j, tip_j, _ = fold
            new = [np.asarray(t, np.float64) for t in tips]
            new[j] = tip_j
            res = TipConsistency(new, "folded", j, float("nan"), gap,
                                 epipolar_gap_px(cams, new))  # fmt: skip
        else:
            res = trim_unexplained_tail(cams, traces, tips, bc, tails=open_end_tails(cams, bc))
    if res is None:
        res = reconcile_tips(
            cams, traces, tips, flag_px=flag_px if research_px is None else research_px
        )
    return [np.asarray(t, np.float64) for t in res.tips], src, res, traces


def _branch_step(
    cams,
    traces,
    flag_px: float,
    *,
    both_if_traces_cross: bool = True,
    run_on: bool = False,
    tips_gate: bool = False,
    backbones_flag: bool = False,
):
    """:func:`traced_stereo_tips`' branch choice: (the two traces, their tips, source).

    One choice among each view's trace, its re-traces from its own junctions and its tube
    searched again along the other view's trace
    (:func:`jaxcr.stereo.guided_retrace.guided_candidates`, docs/decisions.md S35), each
    guided candidate with its own turns at its view's junctions and offered only where
    none of the view's own re-traces explains the other view's trace
    (:mod:`jaxcr.stereo.guided_ranking`, S36: a guided path agrees with the trace it was
    searched along by construction, a re-trace that agrees is independent evidence).
    Round 14 offered the guided candidates only where the views' own candidates held no
    pair that explains itself; that missed the frames whose own candidates hold a wrong
    pair that explains itself (a re-trace onto a cable both views see: dev 4079, 4185).
    Where both views' traces follow a crossing object, a pair of two re-traces that each
    follow fewer is offered too (``both_if_traces_cross``, S39: neither trace is evidence
    for the other view then; dev 4187, both traces on a cable); False: as S36.
    ``tips_gate`` and ``backbones_flag``: :func:`traced_stereo_tips`' ``branch_tips`` and
    ``branch_backbones`` (S49)."""
    traces = list(traces)
    tips, src = _stereo_or_own_tips(cams, traces)
    # A pair's tips and inconsistency are asked for by the flag, by `explains` and again by
    # the choice (and its tips are a function of the pair): each computed once per pair.
    pair_tips, pair_bad = {(id(traces[0]), id(traces[1])): tips}, {}

    def tips_of(a, b):
        key = (id(a), id(b))
        if key not in pair_tips:
            pair_tips[key] = _stereo_or_own_tips(cams, [a, b])[0]
        return pair_tips[key]

    def inconsistency(a, b, tips):
        key = (id(a), id(b))
        if key not in pair_bad:
            pair_bad[key] = backbone_consistency(
                cams, _ending_at(a.backbone, tips[0]), _ending_at(b.backbone, tips[1])
            ).inconsistent_px
        return pair_bad[key]

    flagged = epipolar_gap_px(cams, tips) > flag_px
    if backbones_flag and not flagged and all(np.all(np.isfinite(t)) for t in tips):
        flagged = inconsistency(traces[0], traces[1], tips) > CONSISTENT_PX
    if flagged and all(getattr(t, "retrace", None) is not None for t in traces):

        def choose(cands):
            if len(cands[0]) + len(cands[1]) <= 2:
                return None
            return choose_branches(
                cams,
                cands,
                tips_of=tips_of,
                match_px=3.0 * flag_px,
                # 1.25 tube widths (20 px for the 16 px tubes of real_like at 1280x720).
                margin_px=1.25 * float(np.mean([t.width_px for t in traces])),
                inconsistency_of=inconsistency,
                # A re-trace may follow more crossing objects than its trace when the pair
                # explains itself: a tube crossing its own silhouette is an X too (S36).
                more_crossings_if_consistent=True,
                both_if_traces_cross=both_if_traces_cross,
                tip_flag_px=flag_px if tips_gate else None,
            )

        cands = [[t] + trace_alternatives(t) for t in traces]
        # One choice among the views' own candidates and the guided ones (S36): a view's
        # guided candidate ranked by its own turns at the view's junctions, and offered
        # only where none of the view's own re-traces explains the other view's trace.

        def explains(a, b):
            tips = tips_of(a, b)
            return (
                all(np.all(np.isfinite(t)) for t in tips)
                and epipolar_gap_px(cams, tips) <= 3.0 * flag_px
                and inconsistency(a, b, tips) <= CONSISTENT_PX
            )

        cut_back = []
        guided = guided_candidates(cams, traces, cut_back=cut_back)
        if run_on:  # S41: a trace that ran on past the other's end, cut back, is offered
            guided = with_run_on(guided, traces, cut_back)
        guided = with_own_turns(guided, traces)
        guided = offered_guided(guided, cands, explains)
        cands = [c + g for c, g in zip(cands, guided, strict=True)]
        choice = choose(cands)
        if choice is not None and choice.indices != (0, 0):
            traces = [cands[k][choice.indices[k]] for k in range(2)]
            tips, src = _stereo_or_own_tips(cams, traces)
            src = src + "+branch"
    return traces, tips, src


def _ending_at(backbone, tip) -> np.ndarray:
    """The traced ``backbone`` (n, 2) with its last point (the traced tip) replaced by
    ``tip``."""
    bb = np.asarray(backbone, np.float64).reshape(-1, 2)
    return np.vstack([bb[:-1], np.asarray(tip, np.float64)[None]])


def _stereo_or_own_tips(cams, traces) -> tuple[list[np.ndarray], str]:
    st = trace_stereo_tips(cams, traces)
    if st is not None:
        return [np.asarray(t, np.float64) for t in st[0]], "trace_stereo"
    return [np.asarray(t.tip, np.float64) for t in traces], "trace"


def _ending_near(uv: np.ndarray, tip) -> np.ndarray:
    """The ordered skeleton ``uv`` (n, 2) cut after its point nearest ``tip`` (2,) and
    ended at ``tip``; unchanged when ``tip`` is not finite. The 3-D backbone of
    ``--segmentation trace`` then ends where the tip was placed (a trace cut back, a
    tip moved on along the predicted path)."""
    tip = np.asarray(tip, np.float64)
    if not np.all(np.isfinite(tip)) or len(uv) < 2:
        return uv
    i = int(np.argmin(np.linalg.norm(uv - tip[None], axis=1)))
    return np.concatenate([uv[: max(i, 1)], tip[None]])


def _traced_tips(vrec: list[dict], traces, traced) -> None:
    """``--segmentation trace``: each view's ``tip_px`` from the tracer instead of the
    skeleton's end, with ``tip_source``: ``"trace_stereo"`` (:func:`trace_stereo_tips`),
    else ``"trace"`` (the view's own traced tip, where the two views leave the end face's
    length undetermined), else ``"skeleton"`` (no finite traced tip); ``"+branch"``
    appended for a view whose trace :func:`traced_stereo_tips` replaced by another branch
    (its ``backbone_px`` is then that trace's path, not the mask's skeleton), ``"+cut"`` or
    ``"+extended"`` (or ``"+trimmed"``, ``"+rebranched"``, ``"+folded"``) for the view its epipolar re-search moved.
    ``traced``: :func:`traced_stereo_tips` of ``traces`` (computed before triangulation:
    the robot masks are the chosen traces' and the triangulated skeletons end at the
    tips, :func:`_ending_near`). The skeleton's end stays as ``tip_skeleton_px``; ``backbone_px`` loses its points beyond the new tip (along
    the tube's end direction) and ends at it."""
    tips, source, recheck, chosen = traced
    for k, (v, t) in enumerate(zip(vrec, chosen, strict=True)):
        v["tip_skeleton_px"] = v["tip_px"]
        if np.all(np.isfinite(tips[k])):
            tip, src = tips[k], source.replace("+branch", "")
        else:
            v["tip_source"] = "skeleton"
            continue
        if getattr(t, "curl_of", t) is not traces[k]:
            src = src + "+branch"
        if recheck is not None and recheck.view == k:
            src = src + "+" + recheck.action
        line = np.asarray(v["backbone_px"], np.float64)[:-1]  # the skeleton's end dropped
        if t is not traces[k]:
            # Another branch than the mask's skeleton followed, or a curled end fitted:
            # the chosen trace's path.
            line = np.asarray(t.backbone, np.float64)[:-1]
        d = np.asarray(t.end_dir, np.float64)
        if np.all(np.isfinite(d)) and np.linalg.norm(d) > 0:
            beyond = (line - tip) @ d >= 0.0
        else:  # no end direction (tip not refined): the polyline is kept whole
            beyond = np.zeros(len(line), bool)
        n = len(line)
        while n > 1 and beyond[n - 1]:
            n -= 1
        v["backbone_px"] = np.round(np.concatenate([line[:n], tip[None]]), 2).tolist()
        v["tip_px"] = [round(float(x), 2) for x in tip]
        v["tip_source"] = src


def _marker_mask(cam: Camera, layout: MarkerLayout, shape, margin: float = 0.003) -> np.ndarray:
    """Projected white marker squares (+ margin) of the plate: True inside."""
    m = np.zeros(shape, np.uint8)
    t = np.linspace(0, 1, 8)[:, None]
    polys = []
    for cx, cy in layout.centres.values():
        h = layout.size * 2.0 / 3.0 + margin
        sq = np.array(
            [[cx - h, cy - h, 0], [cx + h, cy - h, 0], [cx + h, cy + h, 0], [cx - h, cy + h, 0]]
        )
        # Densified edges, so that lens distortion bends them correctly.
        polys.append(np.concatenate([sq[k] + t * (sq[(k + 1) % 4] - sq[k]) for k in range(4)]))
    uv = _project_np(cam, np.concatenate(polys)).reshape(len(polys), -1, 2)
    cv2.fillPoly(m, [np.round(q).astype(np.int32) for q in uv], 1)
    return m.astype(bool)


_THIN_BLOCK = 64


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1) of the mask's foreground (cv2.boundingRect, no full-image nonzero)."""
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(mask, np.uint8))
    return y, y + h, x, x + w


def _crop_window(box, shape, bh: int, bw: int) -> tuple[int, int]:
    """Top-left corner of a (bh, bw) window holding ``box`` plus a 2-pixel margin, inside
    an image of ``shape``."""
    h, w = shape
    r0, c0 = max(box[0] - 2, 0), max(box[2] - 2, 0)
    return min(r0, h - bh), min(c0, w - bw)


_thin_batch = jax.jit(jax.vmap(zhang_suen_thin))


def _thin_cropped_views(
    masks: list[np.ndarray], block: int = _THIN_BLOCK, jit_call=_direct
) -> list[tuple[np.ndarray, tuple[int, int]]]:
    """Zhang-Suen thinning of each view's robot mask on its bounding box only: the boxes
    (plus a 2-pixel margin) are padded to one common square window whose side is ``block``
    times a power of two (cut to the image's height and width), so that an image size
    compiles one or two shapes (e.g. 256x256 and 480x512 at 640x480; issue 18,
    docs/decisions.md S23), and thinned in one vmapped call. Thinning is local, so each
    result equals thinning the whole image. Returns per view the skeleton crop and its
    top-left corner (row, col) in the image."""
    if len({m.shape for m in masks}) > 1:  # views of different sizes: one call each
        return [_thin_cropped_views([m], block, jit_call)[0] for m in masks]
    shape = masks[0].shape
    boxes = [_bbox(m) for m in masks]
    side = block
    while side < max(max(b[1] - b[0], b[3] - b[2]) for b in boxes) + 4:
        side *= 2
    bh, bw = min(side, shape[0]), min(side, shape[1])
    corners = [_crop_window(b, shape, bh, bw) for b in boxes]
    crops = np.stack([m[r : r + bh, c : c + bw] for m, (r, c) in zip(masks, corners, strict=True)])
    skel = np.asarray(jit_call(_thin_batch, jax.device_put(crops)))
    return [(skel[k], corners[k]) for k in range(len(masks))]


def _thin_cropped(mask: np.ndarray, block: int = _THIN_BLOCK) -> np.ndarray:
    """Full-image skeleton of one mask via :func:`_thin_cropped_views` (for tests/tools)."""
    ((sk, (r, c)),) = _thin_cropped_views([mask], block)
    out = np.zeros(mask.shape, bool)
    out[r : r + sk.shape[0], c : c + sk.shape[1]] = sk
    return out


def _bucket(n: int, size: int = 256) -> int:
    return max(size, -(-n // size) * size)


def _pad_rows(x: np.ndarray, n: int) -> np.ndarray:
    return np.concatenate([x, np.repeat(x[-1:], n - len(x), axis=0)]) if n > len(x) else x


def _view_profile(cam, alpha, kproj, p, tang):
    """Per view: projections ``uv0`` of the backbone points ``p`` (n, 3), image normals of
    the backbone (tangents ``tang``), silhouette widths and centre offsets across the tube
    (:func:`jaxcr.stereo.diameter.profile_widths`) and the squared view weights (0 where
    unusable)."""
    uv0, ok0 = project_points(cam, p)
    uv1, _ = project_points(cam, p + 1e-4 * tang)
    du = uv1 - uv0
    nrm = jnp.stack([-du[:, 1], du[:, 0]], 1)
    nrm = nrm / jnp.maximum(jnp.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    wdt, off = profile_widths(alpha, uv0, nrm, kproj)
    wv = view_weights(cam, p, tang) ** 2
    # No weight where another part of the robot lies beside an edge (wrong cloth level).
    wv = wv * edge_clearance(alpha, uv0, nrm, wdt, off)
    return uv0, ok0, nrm, wdt, off, wv


def _view_diameters(cam, alpha, kproj, p, tang):
    """Per view: the cylinder-method diameters, the view weights, the report's
    3-D-interpolation diameters (see :mod:`jaxcr.stereo.diameter`) and, from the same
    profiles, the joint chain fit's silhouette observations (centres, normals, weights,
    diameters; :func:`jaxcr.stereo.chain_fit.observations_from_profiles`), and the
    projections ``uv0`` and centre offsets the sub-pixel refinement moves them by."""
    uv0, ok0, nrm, wdt, off, wv = _view_profile(cam, alpha, kproj, p, tang)
    d = cylinder_diameters(cam, p, tang, uv0, nrm, wdt, off)
    wv = jnp.where(ok0 & (wdt > 0.5) & jnp.isfinite(d), wv, 0.0)
    rep = report_interpolation_diameters(cam, p, uv0, wdt)
    clean = edge_clearance(alpha, uv0, nrm, wdt, off)
    obs = observations_from_profiles(cam, p, tang, uv0, ok0, nrm, wdt, off, clean)
    return (jnp.where(jnp.isfinite(d), d, 0.0), wv, rep, *obs, uv0, off)


@jax.jit
def _masked_alpha(alphas, near):
    """Both views' alpha (2, H, W) limited to the dilated robot masks ``near`` (2, H, W)."""
    return alphas * near.astype(alphas.dtype)


def _refinement_profiles(measured) -> tuple[np.ndarray, ...]:
    """Both views' (weights, uv0, normals, offsets) for the sub-pixel refinement (float64,
    (2, ...)) from :func:`_views_diameters`' outputs: the refinement and the diameter stage
    share one compiled program (issue 18, docs/decisions.md S23)."""
    return tuple(np.asarray(measured[i], np.float64) for i in (1, 7, 4, 8))


@jax.jit
def _views_diameters(cam1, cam2, alphas, kprojs, p, tang):
    """Both views' (diameters, weights, report diameters, chain-fit centres, normals,
    weights, diameters, projections uv0, centre offsets), stacked (2, ...); ``alphas``
    (2, H, W) limited to the robot (:func:`_masked_alpha`), ``kprojs`` (2, H, W)."""
    out = [
        _view_diameters(cam, alphas[k], kprojs[k], p, tang) for k, cam in enumerate((cam1, cam2))
    ]
    return tuple(jnp.stack(x) for x in zip(*out, strict=True))


def _padded_with_tangents(p: np.ndarray) -> tuple[jax.Array, jax.Array]:
    """Backbone points and unit tangents (central differences), padded to a bucketed
    length (repeating the last row), as float32 device arrays."""
    tang = np.gradient(p, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    nb = _bucket(len(p))
    return (
        _f32(_pad_rows(p, nb)),
        _f32(_pad_rows(tang, nb)),
    )


_triangulate = jax.jit(triangulate_points)


@functools.partial(jax.jit, static_argnames="mode")
def _segment_views(images, plates, key, tol_lo, tol_hi, plate_lo, plate_hi, mode):
    """Alpha (2, H, W), key projection (2, H, W) and mask ``alpha > 0.5`` (uint8) of both
    views (uint8 or float RGB (2, H, W, 3)) in one call; ``mode`` as
    ``StereoConfig.segmentation``."""

    def one(im, pl):
        a, kp = chroma_alpha_and_projection(im, key, tol_lo, tol_hi)
        if mode == "plate_shadow":
            a = plate_alpha_shadow_invariant(im, pl, plate_lo, plate_hi)
        elif mode == "plate":
            a = plate_alpha(im, pl, plate_lo, plate_hi)
        elif mode == "both":
            a = a * plate_alpha(im, pl, plate_lo, plate_hi)
        return a, kp, (a > 0.5).astype(jnp.uint8)

    return jax.vmap(one)(images, plates)


def _image_stack(images) -> np.ndarray:
    """Images (RGB (H, W, 3) or masks (H, W)) as one (2, H, W[, 3]) array: uint8 kept
    (converted on the device), other RGB as float32 in [0, 1]. Views of different sizes
    are zero-padded at the bottom/right to the larger size (cropped back by the caller;
    profiles sampled right at the smaller view's border then see zeros beyond it)."""
    ims = [np.asarray(im) for im in images]
    if not all(im.dtype == np.uint8 for im in ims):
        ims = [_as_float(im) if im.ndim == 3 else im.astype(np.float32) for im in ims]
    h = max(im.shape[0] for im in ims)
    w = max(im.shape[1] for im in ims)
    pad = lambda im: np.pad(  # noqa: E731
        im, [(0, h - im.shape[0]), (0, w - im.shape[1])] + [(0, 0)] * (im.ndim - 2)
    )
    return np.stack([pad(im) for im in ims])


_POOL: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(2, thread_name_prefix="jaxcr-stereo")
    return _POOL


_FIT_PAD = 512


@jax.jit
@jax.vmap
def _segment_fits(points, weights):
    """Plane angles, plane normal and arc fit of each segment (vmapped over segments)."""
    _, n = fit_plane(points, weights)
    arc = fit_arc(points, weights)
    return plane_angles(n), n, arc


def _smooth_path(rc: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Ordered pixels (n, 2) row/col -> smoothed (u, v) (n, 2) (removes the staircase)."""
    uv = rc[:, ::-1].astype(np.float64)
    if len(uv) < 5:
        return uv
    return gaussian_filter1d(uv, sigma, axis=0, mode="nearest")


def _extend_tip(uv: np.ndarray, n: int) -> np.ndarray:
    """Append ``n`` samples (1 px apart) continuing the path's last 5 px straight on."""
    if n <= 0 or len(uv) < 6:
        return uv
    d = uv[-1] - uv[-6]
    d = d / max(np.linalg.norm(d), 1e-9)
    return np.concatenate([uv, uv[-1] + np.arange(1, n + 1)[:, None] * d[None]])


def _skeleton_tail(uv: np.ndarray, uv_end: np.ndarray, tol_px: float = 3.0) -> np.ndarray | None:
    """The ordered skeleton pixels (u, v) of one view beyond ``uv_end``, the projection of
    the last reconstructed backbone point (the tube the stereo matching lost there, for
    :func:`jaxcr.stereo.chain_fit.tail_observations`): everything after the last skeleton
    sample within ``tol_px`` of it (the last, so that a tip crossing the shaft in this view
    is not mistaken for the shaft). ``None`` if no sample is that close."""
    near = np.flatnonzero(np.linalg.norm(uv - uv_end[None], axis=1) <= tol_px)
    return uv[near[-1] + 1 :] if len(near) else None


_chain_points = jax.jit(chain_points)
_TAIL_GRID = 257


def _single_view_tail(s: np.ndarray, p: np.ndarray, joint: dict, step: float, jit_call=_direct):
    """Backbone samples (arclengths (t,), points (t, 3)) beyond the last stereo sample
    ``p[-1]``, every ``step`` m, over the part of the tube one view alone sees: the joint
    chain fit (:func:`jaxcr.stereo.chain_fit.fit_segments_jointly` with ``tails``) extends
    its last arc over that view's skeleton pixels, constrained across the tube by that view
    and in depth by the arc's continuation. The chain's points from its arclength nearest
    ``p[-1]`` to its end, translated to start at ``p[-1]`` (the stored backbone stays
    continuous; the chain is a smooth model of the same curve, within its RMS)."""
    fit, seg_start = joint["fit"], np.asarray(joint["seg_start"], np.float64)
    end = float(seg_start[-1] + joint["arc_length"][-1])
    # the segments padded as in the fit (one compile for 1-4 segments)
    curv, start = pad_chain(fit["curvatures"], seg_start)
    args = [np.asarray(x, np.float32) for x in (fit["base"], fit["R0"], curv, start)]
    c0, half = float(s[-1]), 5e-3
    for _ in range(2):  # coarse (39 um steps), then fine (0.3 um) search
        grid = np.linspace(c0 - half, c0 + half, _TAIL_GRID)
        X = np.asarray(
            jit_call(_chain_points, *(jax.device_put(a) for a in args), _f32(grid))[0], np.float64
        )
        c0 = float(grid[np.argmin(np.linalg.norm(X - p[-1], axis=1))])
        half = 2.0 * half / (_TAIL_GRID - 1)
    k = int(np.floor((end - c0) / step + 1e-9))
    if k < 1:
        return np.zeros(0), np.zeros((0, 3))
    sc = c0 + step * np.arange(0, k + 1)
    nb = _TAIL_GRID * -(-len(sc) // _TAIL_GRID)  # the search grid's program again
    Xt = np.asarray(
        jit_call(
            _chain_points,
            *(jax.device_put(a) for a in args),
            _f32(_pad_rows(sc[:, None], nb)[:, 0]),
        )[0],
        np.float64,
    )[: len(sc)]
    return float(s[-1]) + step * np.arange(1, k + 1), Xt[1:] - Xt[0] + p[-1]


MAX_BACKBONE_M = 5.0  # the same bound as a calibration file's translations (jaxcr/io/units.py)


def _consistent_points(P: np.ndarray, err: list[np.ndarray], poses) -> np.ndarray:
    """Triangulated points that reproject within 2 px in both views, are finite, and lie in
    front of both cameras (a point behind a camera can reproject well and still be wrong)."""
    good = (err[0] < 2.0) & (err[1] < 2.0) & np.all(np.isfinite(P), axis=1)
    for T in poses:
        z = P @ np.asarray(T[2, :3], np.float64) + float(np.asarray(T[2, 3]))
        good &= np.nan_to_num(z, nan=-1.0) > 0.0
    return good


def _check_backbone_length(P: np.ndarray) -> None:
    """A frame whose triangulated backbone is longer than :data:`MAX_BACKBONE_M` fails with
    reason ``correspondence`` (matches from a wrong segmentation triangulate far away; the
    resampling would otherwise try to allocate a grid of that length)."""
    length = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
    if not length <= MAX_BACKBONE_M:
        raise StereoFailure(
            "correspondence",
            f"triangulated backbone is {length:.3g} m long (over {MAX_BACKBONE_M} m): "
            "the two views' segmentations do not match",
        )


def _resample(p: np.ndarray, step: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth ordered 3-D points along their arclength (Gaussian kernel, local linear) and
    resample at ``step``. Returns ``(s (k,), p (k, 3))``, s from the first point.

    Each output point uses only the samples within ``8 sigma`` of it along the arclength
    (the kernel beyond is below ``exp(-32) ~ 1e-14``; equal to the dense sum to ~1e-15 m,
    tests), which makes the cost linear in the length instead of quadratic."""
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    for _ in range(2):
        grid = np.arange(0.0, s[-1] + 1e-12, step)
        lo = np.searchsorted(s, grid - 8.0 * sigma, side="left")
        hi = np.searchsorted(s, grid + 8.0 * sigma, side="right")
        idx = lo[:, None] + np.arange(max(int((hi - lo).max()), 1))[None]
        inside = idx < hi[:, None]
        idx = np.minimum(idx, len(s) - 1)
        ds = s[idx] - grid[:, None]
        w = np.where(inside, np.exp(-0.5 * (ds / sigma) ** 2), 0.0)
        # Local linear regression (unbiased at the ends).
        sw, sx, sxx = w.sum(1), (w * ds).sum(1), (w * ds * ds).sum(1)
        pw = p[idx]  # (k, window, 3)
        sy = np.einsum("kw,kwd->kd", w, pw)
        sxy = np.einsum("kw,kwd->kd", w * ds, pw)
        det = sw * sxx - sx * sx
        q = (sxx[:, None] * sy - sx[:, None] * sxy) / np.maximum(det, 1e-300)[:, None]
        # Across a gap in the matched points longer than the window (a stretch neither
        # segmentation matched, over 8 sigma) a grid point sees one sample or none: its local
        # line is undetermined (det ~ 0 up to rounding gave points at 1e300 m and a crash,
        # audit r31). There, and only there (elsewhere the result is as before), the points
        # are interpolated linearly along the arclength. The weighted variance det / sw^2 of
        # two samples a pixel apart is ~1e-8 m^2; one sample gives 0 (rounding ~1e-20).
        flat = ~(det > (1e-3 * sigma) ** 2 * sw * sw)
        if flat.any():
            q[flat] = np.stack([np.interp(grid[flat], s, p[:, d]) for d in range(3)], 1)
        p = q
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
    return s, p


def reconstruct_pair(
    image1: np.ndarray,
    image2: np.ndarray,
    cam1: Camera,
    cam2: Camera,
    config: StereoConfig | None = None,
    plates: tuple[np.ndarray, np.ndarray] | None = None,
    *,
    jit_call=None,
) -> dict:
    """Reconstruct the backbone of one stereo pair (see module docstring).

    ``image1``/``image2``: RGB (H, W, 3) uint8 or float [0, 1]. ``cam1``/``cam2``: the
    stereo calibration (extrinsics in any common frame; the base frame is found from the
    markers). ``plates``: background images of the empty scene (needed for
    ``segmentation="plate"``/``"both"``). ``jit_call``: how the large compiled stages
    (thinning, profiles and diameters, segment fits, the joint chain fit) are called,
    ``jit_call(fn, *args)`` (default ``fn(*args)``; ``jaxcr stereo`` passes
    :func:`jaxcr.io.exported.cached_call`, so that a second process loads their traced
    programs instead of tracing them again). Returns a dict (numpy arrays, base frame,
    metres).
    """
    cfg = config or StereoConfig()
    call = jit_call or _direct
    if cfg.segmentation not in ("chroma", "plate", "plate_shadow", "both", "trace"):
        raise ValueError(f"unknown segmentation {cfg.segmentation!r}")
    timings: dict[str, float] = {}
    t0 = _now()
    imgs = [np.asarray(image1), np.asarray(image2)]
    cams = [cam1, cam2]
    for k, (im, cam) in enumerate(zip(imgs, cams, strict=True)):
        if im.ndim != 3 or (im.shape[1], im.shape[0]) != (cam.width, cam.height):
            raise StereoFailure(
                "calibration_size",
                f"view {k + 1} image is {im.shape[1]}x{im.shape[0]} but its calibration is "
                f"{cam.width}x{cam.height}",
            )
    if cfg.segmentation in ("plate", "plate_shadow", "both", "trace") and plates is None:
        raise StereoFailure("plate", "segmentation needs background plates, none given")
    # 1. Base frame: from the markers (the two views' detections in two threads: OpenCV
    # releases the GIL), a given T_cam_base, or the entry pixels (a provisional frame at the
    # triangulated entry point, axes of camera 1, rotated in step 6; jaxcr.stereo.base_frame).
    bspec = cfg.base
    use_markers = bspec.mode == "markers"
    if use_markers:
        dets = list(_pool().map(lambda im: detect_markers(im, cfg.layout), imgs))
        t0 = _tick(timings, "markers_detect", t0)
        try:
            pose = stereo_base_pose(cam1, cam2, dets[0], dets[1], cfg.layout)
        except ValueError as err:
            # A marker-free rig that left "base" out lands here: say what to write instead.
            raise StereoFailure(
                "markers",
                f"{err}; a rig without markers gives its base in stereo.json as "
                '"base": {"entry_px": {camera: [u, v]}} or {"T_cam_base": 4x4} '
                "(docs/stereo-format.md)",
            ) from None
        t0 = _tick(timings, "markers_pose", t0)
    else:
        pose = _given_base_pose(cam1, cam2, bspec)
    cams = [_with_pose(cam1, pose["T_cam1_base"]), _with_pose(cam2, pose["T_cam2_base"])]
    if bspec.mode == "entry_px":
        base = np.zeros(3)  # the entry point is the origin
    elif cfg.robot_base is not None:
        base = np.asarray(cfg.robot_base, float)
    else:
        base = cfg.layout.base_centre if use_markers else np.zeros(3)
    # 2. Alpha, key projection and the thresholded mask of both views in one jitted call.
    stack = _image_stack(imgs)
    plate_stack = _image_stack(plates) if cfg.segmentation != "chroma" else stack
    alpha_j, kproj_j, mask_j = _segment_views(
        jax.device_put(stack),
        jax.device_put(plate_stack),
        _f32(cfg.key_rgb),
        cfg.tol_lo,
        cfg.tol_hi,
        cfg.plate_lo,
        cfg.plate_hi,
        mode="chroma" if cfg.segmentation == "trace" else cfg.segmentation,
    )
    masks = np.asarray(mask_j)
    if cfg.segmentation == "trace":
        # The traced robot of each view (jaxcr.segmentation.foreground), entered at the
        # projected base along the projected insertion axis (the base frame's z: known with
        # markers or a given T_cam_base; in entry_px mode z is provisional until the
        # backbone is triangulated, so the tracer finds the direction from the mask).
        tr = [
            plate_foreground(
                imgs[k],
                plates[k],
                _project_np(cams[k], base[None])[0],
                None if bspec.mode == "entry_px" else entry_direction_px(cams[k], base),
                cfg=cfg.plate_foreground,
            )  # fmt: skip
            for k in range(2)
        ]
        # The two views' tips and chosen branches before triangulation, so that the 3-D
        # backbone is made of the traces the tips belong to and ends at the tips.
        traced = traced_stereo_tips(cams, tr, calibration=cfg.calibration)
        masks = _image_stack([t.mask.astype(np.uint8) for t in traced[3]])
        alpha_j = jax.device_put(masks.astype(np.float32))
    t0 = _tick(timings, "segmentation", t0)
    # 3. Per view: closing, marker squares, base (Hough), flood fill.
    views = []
    for k, cam in enumerate(cams):
        # Closing fills pinholes where the metal mirrors the cloth.
        hk, wk = imgs[k].shape[:2]  # (views of different sizes were padded)
        mask = cv2.morphologyEx(
            np.ascontiguousarray(masks[k][:hk, :wk]), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)
        )
        mask = mask > 0
        if use_markers:
            mask &= ~_marker_mask(cam, cfg.layout, mask.shape)
        buv = _project_np(cam, base[None])[0]
        loc = locate_base(mask, (buv[0], buv[1]), cfg.roi_half_px)
        if not loc.found:
            raise StereoFailure("robot_not_found", f"no robot pixels near the base in view {k + 1}")
        robot = flood_component(mask, loc.seed)
        if np.count_nonzero(robot) < cfg.min_robot_pixels:
            raise StereoFailure("robot_not_found", f"robot region too small in view {k + 1}")
        frac = np.count_nonzero(robot) / robot.size
        if frac > cfg.max_robot_fraction:
            raise StereoFailure(
                "robot_not_found",
                f"robot region covers {frac:.0%} of view {k + 1}: the background does not "
                "match the key colour",
            )
        views.append({"robot": robot, "loc": loc})
    t0 = _tick(timings, "base_floodfill", t0)
    # 4. Thinning: both views' bounding-box crops in one vmapped call.
    thinned = _thin_cropped_views([v["robot"] for v in views], jit_call=call)
    t0 = _tick(timings, "thinning", t0)
    # 5. Ordering from the base, on the crops.
    for k, (v, (sk, (r0, c0))) in enumerate(zip(views, thinned, strict=True)):
        seed = v["loc"].seed
        try:
            rc = order_skeleton(sk, (seed[0] - r0, seed[1] - c0)) + np.array([r0, c0])
        except ValueError:
            raise StereoFailure("robot_not_found", f"empty skeleton in view {k + 1}") from None
        v["skeleton_rc"] = rc
    t0 = _tick(timings, "ordering", t0)
    for v in views:
        rc = v["skeleton_rc"]
        if cfg.shadow_tolerance_deg is not None:
            # Shadow removal (report sec. 5.3): drop a shadow branch before the base.
            seed = v["loc"].seed
            uv_seed = np.array([seed[1], seed[0]], float)
            rc = rc[shadow_cut(_smooth_path(rc), uv_seed, cfg.shadow_tolerance_deg) :]
        v["skeleton_rc"] = rc
        v["uv"] = _smooth_path(rc)
    if cfg.segmentation == "trace":
        for v, tip in zip(views, traced[0], strict=True):
            # The record's skeleton (tip_skeleton_px, backbone_px) stays the whole one.
            v["uv_skeleton"] = v["uv"]
            v["uv"] = _ending_near(v["uv"], tip)
    t0 = _tick(timings, "shadow_removal", t0)
    # A swapped camera order that the entry check missed (entry pixels near each other):
    # the two whole skeletons under the given and the exchanged order (issue 16, S19).
    order = camera_order_check(cams, *[v.get("uv_skeleton", v["uv"]) for v in views])
    t0 = _tick(timings, "camera_order", t0)
    # 6. Correspondence and triangulation (normalised coordinates).
    xn = [
        cv2.undistortPoints(
            _extend_tip(v["uv"], cfg.tip_extension_px).reshape(-1, 1, 2),
            np.asarray(c.K, np.float64),
            np.asarray(c.dist, np.float64),
        ).reshape(-1, 2)
        for c, v in zip(cams, views, strict=True)
    ]
    T1, T2 = pose["T_cam1_base"], pose["T_cam2_base"]
    E = _essential_np(T1, T2)
    f = float(np.asarray(cam1.K)[0, 0])
    y1, y2, quality = match_backbones(
        E, xn[0], xn[1], cap=8.0 / f, n_real1=len(views[0]["uv"]), n_real2=len(views[1]["uv"])
    )
    t0 = _tick(timings, "correspondence", t0)
    nb = _bucket(len(y1))
    P = np.asarray(
        _triangulate(
            _f32(T1[:3]),
            _f32(T2[:3]),
            _f32(_pad_rows(y1, nb)),
            _f32(_pad_rows(y2, nb)),
        ),
        np.float64,
    )[: len(y1)]
    # Reject points whose reprojection misses either view by > 2 px (bad matches).
    err = []
    for T, y in zip((T1, T2), (y1, y2), strict=True):
        Pc = P @ np.asarray(T[:3, :3], np.float64).T + np.asarray(T[:3, 3], np.float64)
        err.append(np.linalg.norm(Pc[:, :2] / Pc[:, 2:] - y, axis=1) * f)
    good = _consistent_points(P, err, (T1, T2))
    if good.sum() < 10:
        raise StereoFailure("correspondence", f"only {int(good.sum())} consistent stereo matches")
    _check_backbone_length(P[good])
    s, p = _resample(P[good], cfg.step, cfg.smooth_sigma)
    s0 = float(np.linalg.norm(p[0] - base))  # the part hidden at the base, assumed straight
    s = s + s0
    t0 = _tick(timings, "triangulation", t0)
    # Sub-pixel refinement: move each backbone point's projections onto the centre of the
    # silhouette across the tube (from the width profiles) and re-triangulate. Views that
    # see the tube nearly end-on (small weight) keep the projection. The alpha is limited
    # to the (dilated) robot region of each view.
    near = jax.device_put(
        _image_stack([cv2.dilate(v["robot"].astype(np.uint8), np.ones((5, 5))) for v in views])
    )
    alpha_near = _masked_alpha(alpha_j, near)  # once for refinement, diameters, joint fit
    for _ in range(cfg.refine_iterations):
        pj, tj = _padded_with_tangents(p)
        wv, uv0, nrm, off = _refinement_profiles(
            call(_views_diameters, cams[0], cams[1], alpha_near, kproj_j, pj, tj)
        )
        ys = []
        for k, c in enumerate(cams):
            shift = np.where(wv[k] > 0.25**2, np.clip(off[k], -2.0, 2.0), 0.0)
            uv = uv0[k] + shift[:, None] * nrm[k]
            ys.append(
                cv2.undistortPoints(
                    np.ascontiguousarray(uv).reshape(-1, 1, 2),
                    np.asarray(c.K, np.float64),
                    np.asarray(c.dist, np.float64),
                ).reshape(-1, 2)
            )
        Pr = np.asarray(
            _triangulate(
                _f32(T1[:3]),
                _f32(T2[:3]),
                _f32(ys[0]),
                _f32(ys[1]),
            ),
            np.float64,
        )[: len(p)]
        if not np.all(np.isfinite(Pr)):
            break
        s, p = _resample(Pr, cfg.step, cfg.smooth_sigma)
        s = s + float(np.linalg.norm(p[0] - base))
    t0 = _tick(timings, "refinement", t0)
    if bspec.mode == "entry_px":
        # z along the tube's initial direction (the refined backbone near the entry; the first
        # triangulation is too rough there: 9-10 deg off on a 320x240 set vs 1-2 deg): the
        # provisional frame (origin at the entry point, camera 1's axes) is rotated about
        # its origin, so the base point (the origin) stays where it is.
        z = initial_direction(s, p, bspec.direction_length, origin=np.zeros(3))
        if z is None:
            raise StereoFailure(
                "correspondence", "too little backbone near the entry for its direction"
            )
        R = frame_from_direction(np.zeros(3), z)[:3, :3]  # provisional axes = camera 1's
        p = p @ R
        T1 = pose["T_cam1_base"].copy()
        T1[:3, :3] = R
        T2 = relative_pose(cam1, cam2) @ T1
        pose.update(T_cam1_base=T1, T_cam2_base=T2)
        cams = [_with_pose(cam1, T1), _with_pose(cam2, T2)]
    # 7. Diameters.
    pj, tj = _padded_with_tangents(p)
    d_all, w_all, r_all, *chain_obs = (
        np.asarray(x)[:, : len(p)]
        for x in call(_views_diameters, cams[0], cams[1], alpha_near, kproj_j, pj, tj)[:7]
    )
    d_all, w_all, r_all = (np.asarray(x, np.float64) for x in (d_all, w_all, r_all))
    diam_views, wts, rep = list(d_all), list(w_all), list(r_all)
    tang = np.gradient(p, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    W = wts[0] + wts[1]
    diam = (wts[0] * diam_views[0] + wts[1] * diam_views[1]) / np.maximum(W, 1e-12)
    # Another part of the robot touching the silhouette (a curled tip crossing) can only
    # widen a view's profile: where both views are usable and disagree by > 15 %, trust
    # the narrower one.
    both = (wts[0] > 0.1) & (wts[1] > 0.1)
    lo_d = np.minimum(diam_views[0], diam_views[1])
    disagree = np.abs(diam_views[0] - diam_views[1]) > 0.15 * np.maximum(lo_d, 1e-12)
    diam = np.where(both & disagree, lo_d, diam)
    diam = np.where(W > 1e-6, diam, np.nan)
    fill = np.isnan(diam)
    if fill.all():
        raise StereoFailure("correspondence", "no usable silhouette widths")
    if fill.any():
        diam[fill] = np.interp(s[fill], s[~fill], diam[~fill])
    diam_report = 0.5 * (rep[0] + rep[1])
    t0 = _tick(timings, "diameter", t0)
    # Segments, planes, arcs.
    seg = segment_backbone(s, diam, cfg.n_segments, cfg.max_segments)
    starts = list(seg["starts"]) + [len(s)]
    # Conditioning of the correspondence: |cos| between the backbone tangent and the
    # normal of the epipolar plane through the point (0: the backbone runs along the
    # epipolar lines, where matching cannot fix the position along it).
    C1 = np.linalg.inv(T1)[:3, 3]
    C2 = np.linalg.inv(T2)[:3, 3]
    n_epi = np.cross(C1 - p, C2 - p)
    n_epi /= np.maximum(np.linalg.norm(n_epi, axis=1, keepdims=True), 1e-12)
    epi_cond = np.abs(np.sum(tang * n_epi, axis=1))
    # All segments' plane and arc fits in one vmapped call (zero-weight padding).
    n_seg = len(seg["starts"])
    k_pad = max(cfg.max_segments, n_seg)
    pts_all = np.zeros((k_pad, _FIT_PAD, 3), np.float32)
    w_all = np.zeros((k_pad, _FIT_PAD), np.float32)
    w_all[:, :3] = 1.0  # dummy rows for unused slots (never read)
    pts_all[:, 1, 0] = pts_all[:, 2, 1] = 1e-3
    for k in range(n_seg):
        a, b = starts[k], starts[k + 1]
        sa = s[a] if k > 0 else s[0]
        sb = s[b - 1] if b < len(s) else s[-1]
        keep = (s >= sa + (cfg.trim if k > 0 else 0.0)) & (
            s <= sb - (cfg.trim if b < len(s) else 0.0)
        )
        keep &= (np.arange(len(s)) >= a) & (np.arange(len(s)) < b)
        pts = (p[keep] if keep.sum() >= 5 else p[a:b])[:_FIT_PAD]
        pts_all[k] = _pad_rows(pts, _FIT_PAD)
        w_all[k] = 0.0
        w_all[k, : len(pts)] = 1.0
    angs, normals, arcs = call(_segment_fits, jax.device_put(pts_all), jax.device_put(w_all))
    angs, normals = np.asarray(angs, np.float64), np.asarray(normals, np.float64)
    arcs = {key: np.asarray(v, np.float64) for key, v in arcs.items()}
    table = []
    for k in range(n_seg):
        a, b = starts[k], starts[k + 1]
        ang, n = angs[k], normals[k]
        arc = {key: v[k] for key, v in arcs.items()}
        s_start = 0.0 if k == 0 else float(seg["boundaries_s"][k - 1])
        s_end = float(s[-1]) if k == len(seg["starts"]) - 1 else float(seg["boundaries_s"][k])
        table.append(
            {
                "segment": k + 1,
                "s_start_mm": 1e3 * s_start,
                "s_end_mm": 1e3 * s_end,
                "length_mm": 1e3 * (s_end - s_start),
                "diameter_mm": 1e3 * float(seg["diameters"][k]),
                "phi_xy_deg": float(ang[0]),
                "phi_zx_deg": float(ang[1]),
                "phi_yz_deg": float(ang[2]),
                "curvature_1pm": float(arc["curvature"]),
                "arc_length_fit_mm": 1e3 * float(arc["arc_length"]),
                "arc_rms_mm": 1e3 * float(arc["rms"]),
                "epipolar_conditioning": float(np.median(epi_cond[a:b])),
                "view_weight_min": float(np.median(np.minimum(wts[0][a:b], wts[1][a:b]))),
                "normal": np.asarray(n, np.float64).tolist(),
            }
        )
    boundary_p = np.array(
        [[np.interp(b, s, p[:, i]) for i in range(3)] for b in seg["boundaries_s"]]
    ).reshape(-1, 3)
    t0 = _tick(timings, "segments_fits", t0)
    single_view = np.zeros(len(s), bool)
    for row in table:
        row["single_view_mm"] = 0.0
    if cfg.joint_fit and len(s) >= 10:
        # Curvatures and bending planes of all segments from one fit of the tangent-
        # continuous constant-curvature chain to both views' silhouettes
        # (jaxcr.stereo.chain_fit); the separate per-segment fits stay as "*_independent".
        joint = fit_segments_jointly(
            cams,
            [alpha_near[k] for k in range(2)],
            [kproj_j[k] for k in range(2)],
            s,
            p,
            seg["boundaries_s"],
            observations=chain_obs,  # the diameter stage's profiles, not measured again
            tails=[
                _skeleton_tail(v["uv"], _project_np(c, p[-1:])[0])
                for c, v in zip(cams, views, strict=True)
            ],
            jit_call=call,
        )
        for k, row in enumerate(table):
            for key in ("phi_xy_deg", "phi_zx_deg", "phi_yz_deg", "curvature_1pm", "normal"):
                row[key + "_independent"] = row[key]
            row["phi_xy_deg"], row["phi_zx_deg"], row["phi_yz_deg"] = map(
                float, joint["angles_deg"][k]
            )
            row["curvature_1pm"] = float(joint["kappa"][k])
            row["normal"] = joint["normal"][k].tolist()
            row["chain_rms_px"] = float(joint["rms_px"])
        t0 = _tick(timings, "joint_fit", t0)
        if cfg.single_view_tail and int(np.sum(joint["n_tail"])) > 0:
            s_t, p_t = _single_view_tail(s, p, joint, cfg.step, call)
            # The tail ends where its projection in the view that sees it reaches that
            # view's tip pixel: the chain's last arc extrapolates past the tube's end
            # (dev seed 302, a curled frame: 44 mm appended where 22 mm were missing).
            v_see = int(np.argmax(joint["n_tail"]))
            tip = tip_pixel(views[v_see]["uv"], views[v_see]["robot"],
                            search_px=cfg.tip_search_px)  # fmt: skip
            uv_t = _project_np(cams[v_see], np.concatenate([p[-1:], p_t]))
            keep = int(np.argmin(np.linalg.norm(uv_t - tip[None], axis=1)))
            s_t, p_t = s_t[:keep], p_t[:keep]
            if len(s_t):
                # The stored backbone goes on where one view alone sees the tube (flagged);
                # per-view diameters/weights are NaN/0 there, the diameter the last one.
                n0 = len(s)
                s, p = np.concatenate([s, s_t]), np.concatenate([p, p_t])
                diam = np.concatenate([diam, np.full(len(s_t), diam[-1])])
                nan2 = np.full((2, len(s_t)), np.nan)
                diam_views = list(np.concatenate([np.stack(diam_views), nan2], axis=1))
                wts = list(np.concatenate([np.stack(wts), np.zeros((2, len(s_t)))], axis=1))
                diam_report = np.concatenate([diam_report, nan2[0]])
                single_view = np.r_[single_view[:n0], np.ones(len(s_t), bool)]
                last = table[-1]
                last["s_end_mm"] = 1e3 * float(s[-1])
                last["length_mm"] = last["s_end_mm"] - last["s_start_mm"]
                last["single_view_mm"] = 1e3 * float(s[-1] - s[n0 - 1])
        _tick(timings, "single_view_tail", t0)
    vrec = [
        view_record(v.get("uv_skeleton", v["uv"]), v["robot"], search_px=cfg.tip_search_px)
        for v in views
    ]
    if cfg.segmentation == "trace":
        _traced_tips(vrec, tr, traced)
    return {
        "s": s,
        "p": p,
        "diameter": diam,
        "diameter_views": np.stack(diam_views),
        "diameter_weights": np.stack(wts),
        "diameter_report": diam_report,
        "segments": table,
        "boundary_s": np.asarray(seg["boundaries_s"]),
        "boundary_p": boundary_p,
        "T_cam1_base": pose["T_cam1_base"],
        "T_cam2_base": pose["T_cam2_base"],
        "marker_rms_px": pose["rms_px"],
        "n_markers": pose["n_markers"],
        "skeleton_rc": [v["skeleton_rc"] for v in views],
        "robot_masks": [v["robot"] for v in views],
        "seed_rc": [v["loc"].seed for v in views],
        "n_matches": int(good.sum()),
        "single_view": single_view,
        "s_stereo_end": float(s[~single_view][-1]),
        "base_mode": bspec.mode,
        "entry_residual_px": pose.get("entry_residual_px"),
        "views_px": vrec,
        "tip_epipolar_px": _tip_epipolar_px(cams, vrec),
        "camera_order_suspect": order.suspect,
        "camera_order_px": [order.inconsistent_px, order.exchanged_px, order.length_px],
        "camera_order_tip_px": list(order.tip_px),
        "timings": timings,
    }
