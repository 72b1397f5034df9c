"""Two-view tip geometry (:mod:`jaxcr.stereo.tip_geometry`, issue 16 item 2): epipolar
distances against ``cv2.computeCorrespondEpilines`` and the end face's foreshortening
against a disc projected through two pinhole cameras (closed form: the rim's extent beyond
the projected centre)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxcr.stereo.tip_geometry import end_face_lengths, epipolar_distances, fundamental_from_poses
from jaxcr.synth.scene import look_at_pose


def _look_at(eye, target):
    return look_at_pose(eye, target, up=(0.0, 0.0, 1.0))


K1 = np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]])
K2 = np.array([[850.0, 0, 620], [0, 860, 350], [0, 0, 1]])
T1 = _look_at(np.array([0.30, -0.05, 0.10]), [0.0, 0.0, 0.06])
T2 = _look_at(np.array([0.05, -0.30, 0.12]), [0.0, 0.0, 0.06])


def _proj(K, T, X):
    Xc = (T[:3, :3] @ np.atleast_2d(X).T).T + T[:3, 3]
    x = (K @ Xc.T).T
    return x[:, :2] / x[:, 2:]


def test_epipolar_distances_match_cv2():
    F = fundamental_from_poses(K1, T1, K2, T2)
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.02, -0.02, 0.03], [0.02, 0.02, 0.09], (6, 3))
    x1, x2 = _proj(K1, T1, X), _proj(K2, T2, X)
    for a, b in zip(x1, x2, strict=True):
        # The same point: both distances are rounding (F entries ~1e-6, pixels ~1e3).
        assert max(epipolar_distances(F, a, b)) < 1e-6
    x2n = x2 + rng.normal(0, 5.0, x2.shape)
    l2 = cv2.computeCorrespondEpilines(x1.reshape(-1, 1, 2), 1, F).reshape(-1, 3)
    l1 = cv2.computeCorrespondEpilines(x2n.reshape(-1, 1, 2), 2, F).reshape(-1, 3)
    for a, b, la, lb in zip(x1, x2n, l1, l2, strict=True):
        d2, d1 = epipolar_distances(F, a, b)
        # OpenCV normalises the lines to a^2 + b^2 = 1 (float64): distances agree to
        # rounding relative to the pixel coordinates (1e3 x 1e-16, margin 1e3).
        assert d2 == pytest.approx(abs(lb @ np.r_[b, 1.0]), abs=1e-9)
        assert d1 == pytest.approx(abs(la @ np.r_[a, 1.0]), abs=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_end_face_lengths_match_a_projected_disc(seed):
    """A disc of radius 1.5 mm (the tube's end face, normal u) at a tip 0.3 m from both
    cameras. Truth per view: the projected rim's largest extent beyond the projected tip
    along the projected axis (a) and across it (R). The method is exact for orthographic
    views; perspective changes both by O(r / z) = 0.5 %: tolerance 3 % of R."""
    rng = np.random.default_rng(seed)
    X = np.array([0.0, 0.0, 0.06]) + rng.uniform(-0.01, 0.01, 3)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    r = 0.0015
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    phi = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    rim = X + r * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    args, truth = [], []
    for K, T in ((K1, T1), (K2, T2)):
        c = _proj(K, T, X)[0]
        d = _proj(K, T, X + 1e-4 * u)[0] - c
        d /= np.linalg.norm(d)
        n = np.array([-d[1], d[0]])
        q = _proj(K, T, rim) - c
        truth.append((float(np.max(q @ d)), float(np.max(np.abs(q @ n)))))
        args.append((c, d))
    out = end_face_lengths(K1, T1, K2, T2, args[0][0], args[0][1], args[1][0], args[1][1],
                           truth[0][1], truth[1][1], min_sin=0.0)  # fmt: skip
    assert out is not None
    a1, a2, axis = out
    assert min(np.linalg.norm(axis - u), np.linalg.norm(axis + u)) < 1e-6
    for a, (a_true, R) in zip((a1, a2), truth, strict=True):
        assert abs(a - a_true) < 0.03 * R, (a, a_true, R)


def test_end_face_lengths_refuses_an_axis_in_the_epipolar_plane():
    c1 = np.array([0.30, -0.05, 0.10])
    c2 = np.array([0.05, -0.30, 0.12])
    X = np.array([0.0, 0.0, 0.06])
    # The axis in the plane of X and both camera centres: both views see the same plane.
    u = np.cross(np.cross(c1 - X, c2 - X), c1 - X)
    u /= np.linalg.norm(u)
    args = []
    for K, T in ((K1, T1), (K2, T2)):
        c = _proj(K, T, X)[0]
        d = _proj(K, T, X + 1e-4 * u)[0] - c
        args += [c, d / np.linalg.norm(d)]
    assert end_face_lengths(K1, T1, K2, T2, *args, 5.0, 5.0) is None


def test_entry_direction_px_is_the_projected_insertion_axis():
    """The stereo pipeline hands the tracer the robot's entry direction (issue 16 item 2,
    open item b): the image direction of the base's z axis. Reference: the tangent of the
    hand-made pinhole projection along z (central differences of 1e-7 m, float64). The
    function uses a 5 mm chord, which turns from the tangent by at most about
    chord / depth = 0.005 / 0.3 ~ 0.017 rad: tolerance 0.02."""
    from jaxcr.camera import Camera
    from jaxcr.stereo.pipeline import entry_direction_px

    def cam(T):
        return Camera(K=K1.astype(np.float32), dist=np.zeros(5, np.float32),
                      T_cam_robot=T.astype(np.float32), width=1280, height=720)  # fmt: skip

    for base in (np.array([0.0, 0.0, 0.02]), np.array([0.01, -0.02, 0.0])):
        d = entry_direction_px(cam(T1), base)
        h = 1e-7
        ref = (_proj(K1, T1, base + [0, 0, h]) - _proj(K1, T1, base - [0, 0, h]))[0]
        ref /= np.linalg.norm(ref)
        assert np.linalg.norm(d - ref) < 0.02
    # An axis along the viewing ray has no image direction.
    T_on = look_at_pose(np.array([0.0, 0.0, 0.4]), [0.0, 0.0, 0.0], up=(1.0, 0.0, 0.0))
    assert entry_direction_px(cam(T_on), np.zeros(3)) is None
