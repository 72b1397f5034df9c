"""Rotation errors at tiny angles (issue 17 item 10): ``pose_error`` and the pose graph's
``_rotvec`` against float64 closed forms. ``arccos`` of the trace returned 0 for every angle
below ~0.014 deg on float32 poses (the cosine rounds to 1) and lost precision below
~1e-7 rad in float64."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.registration.metrics import pose_error, rotation_angle
from jaxcr.registration.pose_graph import _rotvec

EPS32 = float(np.finfo(np.float32).eps)


def _rodrigues(axis: np.ndarray, theta: float) -> np.ndarray:
    """Closed-form float64 rotation by ``theta`` (rad) about the unit ``axis``."""
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


ANGLES = [1e-9, 1e-7, 3e-6, 1e-4, 1e-2, 0.5, 2.0, 3.0]


@pytest.mark.parametrize("theta", ANGLES)
def test_pose_error_float64_matches_closed_form(theta):
    rng = np.random.default_rng(0)
    R_true = Rotation.random(random_state=1).as_matrix()
    T_true = _pose(R_true, rng.normal(size=3))
    T_est = T_true @ _pose(_rodrigues(rng.normal(size=3), theta), [0.0, 0.0, 0.0])
    rot_deg, trans = pose_error(T_est, T_true)
    # inv(T_true) @ T_est: two 4x4 float64 products, entries off by a few eps (2.2e-16):
    # the skew part, and so the angle, is off by ~1e-15 absolute; 1e-14 rad leaves 10x
    assert np.radians(rot_deg) == pytest.approx(theta, abs=1e-14, rel=1e-12)
    assert trans == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("theta_deg", [0.001, 0.005, 0.01, 0.02, 0.05])
def test_pose_error_float32_poses_below_arccos_resolution(theta_deg):
    """The issue's case: float32 poses and angles below ~0.03 deg."""
    theta = np.radians(theta_deg)
    R_true = Rotation.random(random_state=2).as_matrix()
    R_est = R_true @ _rodrigues(np.array([0.3, -1.0, 0.5]), theta)
    T_true = _pose(R_true, [0.1, 0.2, 0.3]).astype(np.float32)
    T_est = _pose(R_est, [0.1, 0.2, 0.3]).astype(np.float32)
    rot_deg, _ = pose_error(T_est, T_true)
    # Rounding each matrix entry to float32 (relative eps32 / 2) moves the rotation by at most
    # ~3 eps32 rad (a few entries per skew component, both matrices): tolerance 8 eps32 rad
    # (5e-7 rad = 3e-5 deg). arccos of the float32 trace gave 0 here.
    assert np.radians(rot_deg) == pytest.approx(theta, abs=8 * EPS32)


@pytest.mark.parametrize("theta", ANGLES)
def test_rotation_angle_matches_scipy(theta):
    R = _rodrigues(np.array([1.0, 2.0, -0.5]), theta)
    # scipy's quaternion-based magnitude is an independent float64 reference
    ref = Rotation.from_matrix(R).magnitude()
    assert rotation_angle(R) == pytest.approx(ref, abs=1e-15, rel=1e-12)
    assert rotation_angle(R) == pytest.approx(theta, abs=1e-15, rel=1e-12)


@pytest.mark.parametrize("theta", [1e-10, 1e-8, 1e-6, 1e-3, 0.3, 2.5])
def test_pose_graph_rotvec_matches_scipy(theta):
    axis = np.array([-0.2, 0.7, 0.4])
    R = _rodrigues(axis, theta)
    ref = Rotation.from_matrix(R).as_rotvec()
    expect = theta * axis / np.linalg.norm(axis)
    np.testing.assert_allclose(_rotvec(R), expect, rtol=1e-9, atol=1e-16)
    np.testing.assert_allclose(_rotvec(R), ref, rtol=1e-9, atol=1e-16)
