"""Keyword-only entry point of motion-likelihood segmentation, ``jcr.motion.segment``."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from jaxcr.motion.pipeline import MotionConfig

if TYPE_CHECKING:  # jaxcr.io.motion_dataset imports jaxcr.motion: no import cycle at run time
    from jaxcr.io.motion_dataset import MotionDataset
    from jaxcr.motion.run import MotionResult, StepRecord


def segment(
    ds: MotionDataset,
    *,
    config: MotionConfig | None = None,
    eval_frame: int | None = None,
    on_step: Callable[[StepRecord], None] | None = None,
) -> MotionResult:
    """Segment what the robot moves in one video (``jcr.motion.segment``; M-L paper).

    Superpixels (SLIC) are tracked through the video by optical flow (pyramidal LK); the
    motion of each is compared with the end-effector's image motion h(x) = pi(P g(x))
    under a translation and a robust homography model (eqs. 4-9), and the likelihoods
    before and during contact are integrated into an object probability per superpixel
    (eqs. 10-16).

    Parameters
    ----------
    ds : MotionDataset
        One video with its joint values x (n, 5) in radians, contact flags ``touch`` (n,)
        and camera projection P (3, 4) (:func:`jaxcr.io.motion_dataset.load_motion_dataset`;
        ``jaxcr motion synth`` writes synthetic ones).
    config : MotionConfig, optional
        :class:`~jaxcr.motion.pipeline.MotionConfig` (default ``MotionConfig()``: lengths
        in pixels scaled with the frame width, threshold 0.85).
    eval_frame : int, optional
        Frame whose probability maps are reported (default the dataset's, else the first
        touch frame, else the last frame).
    on_step : callable, optional
        Called with each frame's :class:`~jaxcr.motion.run.StepRecord` as it is processed
        (progress, logging).

    Returns
    -------
    MotionResult
        ``maps[model]`` (H, W) object probability in [0, 1] on the evaluation frame for each
        motion model (``"translation"``, ``"homography"``), ``labels_eval`` (H, W) its
        superpixel labels, ``ee_uv`` (n, 2) end-effector pixels, ``records`` one per frame,
        ``failed`` {frame: reason} for unreadable frames (the run goes on without them) and
        ``warnings``; see :class:`~jaxcr.motion.run.MotionResult`.

    Examples
    --------
    The settings, in pixels (0: scaled with the frame width):

    >>> import jaxcr as jcr
    >>> config = jcr.motion.MotionConfig(threshold=0.8)
    >>> config.models, config.superpixel_step
    (('translation', 'homography'), 0)

    A synthetic video (an arm pushing an object) segmented end to end. Rendering and the
    first compilation take minutes on a loaded machine (3 min here at load 20, 2026-12-02),
    so these steps are not run as doctests; ``jaxcr motion`` runs the same function
    (``jaxcr motion synth`` then ``jaxcr motion``):

    >>> import tempfile
    >>> import jaxcr.io.motion_dataset, jaxcr.synth.motion_scenes
    >>> folder = jcr.synth.motion_scenes.generate_motion_video(
    ...     tempfile.mkdtemp(), "pushed_static", seed=0, size=(96, 72), n_frames=8)  # doctest: +SKIP
    >>> ds = jcr.io.motion_dataset.load_motion_dataset(folder)  # doctest: +SKIP
    >>> result = jcr.motion.segment(ds, config=config)  # doctest: +SKIP
    >>> result.maps["homography"].shape  # doctest: +SKIP
    (72, 96)
    """
    from jaxcr.motion.run import run_motion

    return run_motion(ds, config, on_step, eval_frame)
