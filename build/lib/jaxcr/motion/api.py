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
    """Segment what the robot moves in one video (M-L paper): superpixels tracked by optical
    flow, their motion correlated with the end-effector's image motion.

    Parameters:
        ds: a motion video (:func:`jaxcr.io.motion_dataset.load_motion_dataset`).
        config: :class:`~jaxcr.motion.pipeline.MotionConfig` (default ``MotionConfig()``).
        eval_frame: frame whose probability maps are reported (default the dataset's, else
            the first touch frame, else the last frame).
        on_step: called with each frame's :class:`~jaxcr.motion.run.StepRecord`.

    Returns:
        :class:`~jaxcr.motion.run.MotionResult`: ``maps[model]`` (H, W) object probability on
        the evaluation frame, ``labels_eval``, ``ee_uv`` (n, 2) end-effector pixels, records.
    """
    from jaxcr.motion.run import run_motion

    return run_motion(ds, config, on_step, eval_frame)
