"""Motion-likelihood object segmentation (M-L paper): segment what the robot moves by
correlating the motion of tracked superpixels with the end-effector's image motion.

Modules, in pipeline order: :mod:`arm` (forward kinematics g), :mod:`calibration` (P by
normalised DLT + refinement, h(x) = pi(P g(x))), :mod:`superpixels` (SLIC in JAX),
:mod:`flow` (OpenCV pyramidal LK on a grid), :mod:`propagate` (labels carried by the flow),
:mod:`motion_models` (translation / robust homography, eqs. 4-9), :mod:`likelihood`
(eqs. 10-16), :mod:`pipeline` (the incremental tracker), :mod:`baseline` (frame differencing +
grabCut), :mod:`metrics` (P-R, L2, Tanimoto, KS), :mod:`dataset` and :mod:`run` (I/O and the
per-video driver).
"""

from jaxcr.motion.api import segment
from jaxcr.motion.arm import ArmModel, end_effector, end_effector_frame, joint_positions
from jaxcr.motion.calibration import end_effector_image, estimate_projection, projection_dlt
from jaxcr.motion.likelihood import gaussian_likelihood, remove_arm, running_average, threshold_map
from jaxcr.motion.metrics import l2_distance, pr_curve, precision_recall, tanimoto_distance
from jaxcr.motion.pipeline import MotionConfig, MotionTracker

__all__ = [
    "ArmModel",
    "MotionConfig",
    "MotionTracker",
    "end_effector",
    "end_effector_frame",
    "end_effector_image",
    "estimate_projection",
    "gaussian_likelihood",
    "joint_positions",
    "l2_distance",
    "pr_curve",
    "precision_recall",
    "projection_dlt",
    "remove_arm",
    "running_average",
    "segment",
    "tanimoto_distance",
    "threshold_map",
]
