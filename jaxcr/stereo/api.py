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
        tip_epipolar_px: the larger of the two views' ``tip_px`` distances to the epipolar
            line of the other view's (px, undistorted pixels; docs/stereo-format.md).
        camera_order_suspect: the two skeletons are explained much better with the cameras
            exchanged (:mod:`jaxcr.stereo.camera_order`); camera_order_px: [unexplained
            length under the given order, under the exchanged order, total length] (px);
            camera_order_tip_px: [given, exchanged], the two skeleton ends' residual (px),
            which a swapped order must explain too (docs/decisions.md S33).
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
    tip_epipolar_px: Any = None
    camera_order_suspect: Any = None
    camera_order_px: Any = None
    camera_order_tip_px: Any = None
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
    """Reconstruct the backbone of one stereo pair (``jcr.stereo.reconstruct``; Shape Sensing
    of Tubular Continuum Robots using Stereo Vision).

    Segmentation (chroma key or background plate), Zhang-Suen thinning, base-to-tip
    ordering, matching along epipolar lines and triangulation, the base frame from the ArUco
    markers (or ``config.base``), then the tube diameter and its segments. Host-side numpy
    and OpenCV around jitted JAX stages (thinning, matching).

    Parameters
    ----------
    image1, image2 : (H, W, 3) array
        RGB images of cameras 1 and 2, uint8 or float in [0, 1], the sizes of ``cam1`` and
        ``cam2``.
    cam1, cam2 : Camera
        The stereo calibration (:class:`~jaxcr.camera.Camera`: K (3, 3) pixels, dist (5,),
        T_cam_robot (4, 4) in metres, in any common frame; the base frame comes from the
        markers). :func:`jaxcr.io.calibration.load_stereo` reads an OpenCV stereo file.
    config : StereoConfig, optional
        :class:`~jaxcr.stereo.pipeline.StereoConfig` (default ``StereoConfig()``: chroma key
        on green, ArUco base frame; lengths in metres).
    plates : tuple of two (H, W, 3) arrays, optional
        Background images of the empty scene, needed for ``config.segmentation`` ``"plate"``,
        ``"plate_shadow"``, ``"both"`` and ``"trace"``.

    Returns
    -------
    StereoReconstruction
        numpy arrays in the base frame, metres: ``s`` (n,) arc length from the base, ``p``
        (n, 3) backbone points, ``diameter`` (n,), ``segments``, the base pose in each camera
        ``T_cam1_base`` (4, 4), per-view 2-D results ``views_px`` and ``timings`` (seconds
        per stage); see :class:`StereoReconstruction`.

    Raises
    ------
    StereoFailure
        A stage cannot proceed; ``reason`` is a short code (``"calibration_size"``,
        ``"plate"``, ``"markers"``, ``"robot_not_found"``, ``"correspondence"``, ...) and
        the message says why.

    Examples
    --------
    A stage that cannot proceed raises :class:`~jaxcr.stereo.pipeline.StereoFailure` with a
    reason code (here: blank images, so no base-frame markers):

    >>> import numpy as np
    >>> import jaxcr as jcr
    >>> cam1 = jcr.Camera.look_at((-0.02, 0, -0.3), (0, 0, 0), (0, -1, 0), 200.0, (160, 120))
    >>> cam2 = jcr.Camera.look_at((0.02, 0, -0.3), (0, 0, 0), (0, -1, 0), 200.0, (160, 120))
    >>> blank = np.full((120, 160, 3), 128, np.uint8)
    >>> try:
    ...     jcr.stereo.reconstruct(blank, blank, cam1, cam2)
    ... except jcr.stereo.StereoFailure as err:
    ...     print(err.reason)
    markers

    A synthetic pair with its true backbone (``jaxcr stereo synth``). The reconstruction
    compiles the JAX stages (a minute on a loaded machine), so it is skipped here;
    examples/stereo.py runs these steps and checks the result against the truth
    (tests/core/test_examples.py):

    >>> import tempfile
    >>> import jaxcr.io.stereo_dataset, jaxcr.synth.stereo_ctr
    >>> folder = jcr.synth.stereo_ctr.generate_stereo_set(
    ...     tempfile.mkdtemp(), n_frames=1, seed=4, size=(320, 240))  # doctest: +SKIP
    >>> ds = jcr.io.stereo_dataset.load_stereo_dataset(folder)  # doctest: +SKIP
    >>> image1, image2 = (jcr.io.stereo_dataset.read_rgb(ds["root"] / ds["frames"][0]["images"][c])
    ...                   for c in ("cam1", "cam2"))  # doctest: +SKIP
    >>> rec = jcr.stereo.reconstruct(image1, image2, ds["cam1"], ds["cam2"],
    ...                              config=ds["config"])  # doctest: +SKIP
    >>> rec.p.shape[1], len(rec.segments) >= 1  # doctest: +SKIP
    (3, True)
    """
    out = reconstruct_pair(image1, image2, cam1, cam2, config=config, plates=plates)
    known = {f.name for f in dataclasses.fields(StereoReconstruction)} - {"extra"}
    extra = {k: v for k, v in out.items() if k not in known}
    return StereoReconstruction(**{k: v for k, v in out.items() if k in known}, extra=extra)
