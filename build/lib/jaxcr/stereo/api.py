"""Keyword-only entry point of stereo shape sensing, ``jcr.stereo.reconstruct``, with its
result as an ``eqx.Module`` (the fields of :func:`jaxcr.stereo.pipeline.reconstruct_pair`'s
dict)."""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import numpy as np

from jaxcr.camera import Camera
from jaxcr.stereo.pipeline import StereoConfig, reconstruct_pair


class StereoReconstruction(eqx.Module):
    """The backbone of one stereo pair (numpy arrays; base frame, metres).

    Attributes:
        s: (n,) arc length from the base; p: (n, 3) backbone points.
        diameter: (n,) fused tube diameter; diameter_views: (2, n) per view;
            diameter_weights: (2, n) the fusion weights; diameter_report: per-segment summary.
        segments: the tube segments found (one mapping per segment: start/end s, diameter).
        boundary_s: (k,) arc lengths of segment boundaries; boundary_p: (k, 3) their points.
        T_cam1_base, T_cam2_base: (4, 4) base pose in each camera (from the ArUco markers).
        marker_rms_px: marker reprojection RMS (px); n_markers: markers used.
        skeleton_rc, robot_masks, seed_rc: per view, the ordered skeleton (row, col), the robot
            mask and the flood-fill seed.
        n_matches: matched skeleton points; timings: seconds per stage.
        views_px: per view, the 2-D results (``tip_px`` and the ``backbone_px`` polyline,
            OpenCV pixels). single_view: (n,) bool, points of the single-view tail (seen by
            one camera only); s_stereo_end: arc length where the stereo backbone ends.
        base_mode: ``"markers"``, ``"T_cam_base"`` or ``"entry_px"``; entry_residual_px: the
            entry pixels' triangulation residual (``entry_px`` only, else None).
        extra: any further outputs of ``reconstruct_pair`` not listed above (empty today).
    """

    s: np.ndarray
    p: np.ndarray
    diameter: np.ndarray
    diameter_views: np.ndarray
    diameter_weights: np.ndarray
    diameter_report: Any
    segments: Any
    boundary_s: np.ndarray
    boundary_p: np.ndarray
    T_cam1_base: np.ndarray
    T_cam2_base: np.ndarray
    marker_rms_px: float
    n_markers: int
    skeleton_rc: list
    robot_masks: list
    seed_rc: list
    n_matches: int
    timings: dict
    views_px: Any = None
    single_view: Any = None
    s_stereo_end: Any = None
    base_mode: Any = None
    entry_residual_px: Any = None
    extra: dict = eqx.field(default_factory=dict)


def reconstruct(
    image1: np.ndarray,
    image2: np.ndarray,
    cam1: Camera,
    cam2: Camera,
    *,
    config: StereoConfig | None = None,
    plates: tuple[np.ndarray, np.ndarray] | None = None,
) -> StereoReconstruction:
    """Reconstruct the backbone of one stereo pair (Shape Sensing of Tubular Continuum Robots
    using Stereo Vision).

    Parameters:
        image1, image2: RGB (H, W, 3) uint8 or float in [0, 1].
        cam1, cam2: the stereo calibration (:class:`~jaxcr.camera.Camera`).
        config: :class:`~jaxcr.stereo.pipeline.StereoConfig` (default ``StereoConfig()``).
        plates: background images of the empty scene (for ``segmentation="plate"``).

    Returns:
        :class:`StereoReconstruction`. Raises :class:`~jaxcr.stereo.pipeline.StereoFailure`
        (with a reason code) when a stage cannot proceed.
    """
    out = reconstruct_pair(image1, image2, cam1, cam2, config=config, plates=plates)
    known = {f.name for f in dataclasses.fields(StereoReconstruction)} - {"extra"}
    extra = {k: v for k, v in out.items() if k not in known}
    return StereoReconstruction(**{k: v for k, v in out.items() if k in known}, extra=extra)
