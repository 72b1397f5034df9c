"""One camera: the 2-D results alone (no triangulation).

A stereo dataset with one camera gives, per frame, that view's tip pixel and backbone
polyline (:mod:`jaxcr.stereo.view2d`) from the same per-view steps as
:func:`jaxcr.stereo.pipeline.reconstruct_pair`: foreground alpha (chroma key and/or
background plate; with ``segmentation="trace"`` the plate foreground traced from the base
pixel, :func:`jaxcr.segmentation.foreground.plate_foreground`, whose tip becomes ``tip_px``
with ``tip_source`` ``"trace"``: one view has no second view to correct the end face with),
closing, base localisation and flood fill from the base pixel, Zhang-Suen thinning, ordering
from the base and the shadow cut. With the chroma key, its mask is checked for a real
background (:mod:`jaxcr.stereo.key_check`: no second view checks it). Nothing 3-D is measured: no depth,
diameters in metres, segments or plane/arc fits. The base pixel is the dataset's entry
pixel, or the projection of the base point through a given ``T_cam_base``.
"""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera
from jaxcr.stereo.base_locate import flood_component, locate_base
from jaxcr.stereo.key_check import key_mask_check
from jaxcr.stereo.ordering import order_skeleton
from jaxcr.stereo.pipeline import (
    StereoConfig,
    StereoFailure,
    _f32,
    _image_stack,
    _now,
    _segment_views,
    _smooth_path,
    _thin_cropped_views,
    _tick,
    _traced_tips,
    _with_pose,
    entry_direction_px,
)
from jaxcr.stereo.shadow import shadow_cut
from jaxcr.stereo.trace_check import trace_check as check_trace
from jaxcr.stereo.view2d import view_record

__all__ = ["base_pixel", "reconstruct_view"]


def base_pixel(cam: Camera, config: StereoConfig) -> tuple[float, float]:
    """The pixel (u, v) where the robot enters the one view: ``entry_px[0]``, or the base
    point (``robot_base``, default the origin) projected through ``T_cam1_base``."""
    spec = config.base
    if spec.mode == "entry_px":
        return tuple(float(x) for x in spec.entry_px[0])
    if spec.mode != "T_cam_base":
        raise ValueError("one camera needs base mode 'entry_px' or 'T_cam_base'")
    T = np.asarray(spec.T_cam1_base, np.float64)
    X = np.zeros(3) if config.robot_base is None else np.asarray(config.robot_base, np.float64)
    uv, _ = cv2.projectPoints(
        X.reshape(1, 1, 3), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
        np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64),
    )  # fmt: skip
    return tuple(float(x) for x in uv.reshape(2))


def reconstruct_view(
    image: np.ndarray,
    cam: Camera,
    *,
    config: StereoConfig | None = None,
    plate: np.ndarray | None = None,
) -> dict:
    """The 2-D backbone of one view (module docstring). ``image``: RGB (H, W, 3) uint8 or
    float [0, 1]; ``plate``: the empty scene (for plate segmentations). Returns
    ``{"views_px": [{"tip_px", "backbone_px"}], "skeleton_rc", "robot_mask", "base_px",
    "key_check", "trace_check", "timings"}`` (``key_check``: with the chroma key, the
    :class:`jaxcr.stereo.key_check.KeyMaskCheck` of its mask, else None; ``trace_check``:
    with the trace, the :class:`jaxcr.stereo.trace_check.TraceCheck` of its backbone, else
    None). Per-frame problems
    raise :class:`StereoFailure`."""
    cfg = config or StereoConfig()
    timings: dict = {}
    t0 = _now()
    im = np.asarray(image)
    if im.ndim != 3 or (im.shape[1], im.shape[0]) != (cam.width, cam.height):
        raise StereoFailure(
            "calibration_size",
            f"view 1 image is {im.shape[1]}x{im.shape[0]} but its calibration is "
            f"{cam.width}x{cam.height}",
        )
    if cfg.segmentation != "chroma" and plate is None:
        raise StereoFailure("plate", "segmentation needs a background plate, none given")
    buv = base_pixel(cam, cfg)
    trace = None
    if cfg.segmentation == "trace":
        # The plate foreground traced from the base pixel (as each view of reconstruct_pair),
        # entered along the projected insertion axis when T_cam_base gives it.
        from jaxcr.segmentation.foreground import plate_foreground

        direction = None
        if cfg.base.mode == "T_cam_base":
            X = np.zeros(3) if cfg.robot_base is None else np.asarray(cfg.robot_base, float)
            direction = entry_direction_px(_with_pose(cam, cfg.base.T_cam1_base), X)
        trace = plate_foreground(im, plate, np.asarray(buv), direction, cfg=cfg.plate_foreground)
        mask_k = trace.mask.astype(np.uint8)
    else:
        stack = _image_stack([im])
        plates = _image_stack([plate]) if cfg.segmentation != "chroma" else stack
        _, _, mask_j = _segment_views(
            jnp.asarray(stack), jnp.asarray(plates), _f32(cfg.key_rgb), cfg.tol_lo, cfg.tol_hi,
            cfg.plate_lo, cfg.plate_hi, mode=cfg.segmentation,
        )  # fmt: skip
        mask_k = np.asarray(mask_j)[0]
    t0 = _tick(timings, "segmentation", t0)
    mask = cv2.morphologyEx(
        np.ascontiguousarray(mask_k), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)
    ) > 0  # fmt: skip
    loc = locate_base(mask, buv, cfg.roi_half_px)
    if not loc.found:
        raise StereoFailure("robot_not_found", "no robot pixels near the base in view 1")
    robot = flood_component(mask, loc.seed)
    if np.count_nonzero(robot) < cfg.min_robot_pixels:
        raise StereoFailure("robot_not_found", "robot region too small in view 1")
    frac = np.count_nonzero(robot) / robot.size
    if frac > cfg.max_robot_fraction:
        raise StereoFailure(
            "robot_not_found",
            f"robot region covers {frac:.0%} of view 1: the background does not match the key "
            "colour",
        )
    # One view has no second view to check the chroma key with: measure whether its mask
    # looks like a real background (audit r31 S18; jaxcr.stereo.key_check).
    key_check = key_mask_check(mask, robot) if cfg.segmentation == "chroma" else None
    t0 = _tick(timings, "base_floodfill", t0)
    ((sk, (r0, c0)),) = _thin_cropped_views([robot])
    t0 = _tick(timings, "thinning", t0)
    try:
        rc = order_skeleton(sk, (loc.seed[0] - r0, loc.seed[1] - c0)) + np.array([r0, c0])
    except ValueError:
        raise StereoFailure("robot_not_found", "empty skeleton in view 1") from None
    if cfg.shadow_tolerance_deg is not None:
        uv_seed = np.array([loc.seed[1], loc.seed[0]], float)
        rc = rc[shadow_cut(_smooth_path(rc), uv_seed, cfg.shadow_tolerance_deg) :]
    uv = _smooth_path(rc)
    _tick(timings, "ordering", t0)
    vrec = [view_record(uv, robot, search_px=cfg.tip_search_px)]
    trace_check = None
    if trace is not None:
        tip = np.asarray(trace.tip, np.float64)
        _traced_tips(vrec, [trace], ([tip], "trace", None, [trace]))
        # No second view checks a traced tip: whether the trace stopped at the entry or ran
        # out of the image (S33).
        width = trace.measured_width_px or trace.width_px
        trace_check = check_trace(vrec[0]["backbone_px"], width, (cam.width, cam.height))
    return {
        "views_px": vrec,
        "skeleton_rc": rc,
        "robot_mask": robot,
        "base_px": list(buv),
        "key_check": key_check,
        "trace_check": trace_check,
        "timings": timings,
    }
