"""Progressive object modelling with a continuum manipulator (issue 6): arm kinematics and
arc planning (Algorithm 1), RGB-D point clouds, keypoint/RANSAC/ICP pairwise registration,
loop closure with virtual mates (Algorithm 2), model merging and PLY output."""

from jaxcr.registration.pairwise import PairResult, register_pair

__all__ = ["PairResult", "register_pair"]
