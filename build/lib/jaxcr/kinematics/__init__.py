"""Robot kinematic models mapping joint values q to a sampled centreline."""

from jaxcr.kinematics.base import FkResult, RobotModel
from jaxcr.kinematics.constant_curvature import ConstantCurvature
from jaxcr.kinematics.cosserat import (
    Centreline,
    integrate_centreline,
    integrate_steps,
    perturb_centreline,
)
from jaxcr.kinematics.ctr import TEST_CTR, ConcentricTubeRobot
from jaxcr.kinematics.robots import robot_from_dict, robot_to_dict
from jaxcr.kinematics.single_segment import SingleSegment, angles_to_rotation, rotation_to_angles

__all__ = [
    "TEST_CTR",
    "Centreline",
    "ConcentricTubeRobot",
    "ConstantCurvature",
    "FkResult",
    "RobotModel",
    "SingleSegment",
    "angles_to_rotation",
    "integrate_centreline",
    "integrate_steps",
    "perturb_centreline",
    "robot_from_dict",
    "robot_to_dict",
    "rotation_to_angles",
]
