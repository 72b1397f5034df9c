"""Two-view test cameras and OpenCV projection shared by the stereo curve tests
(tests/stereo/test_curve3d.py, test_guided_retrace.py, test_guided_ranking.py): a 1280x720 pinhole with distortion,
posed by a Rodrigues vector and a translation, and ``cv2.projectPoints`` as the reference
projection."""

from types import SimpleNamespace

import cv2
import numpy as np


def cam(rvec, tvec, dist=(-0.05, 0.01, 0.0, 0.0, 0.0)):
    """A camera-like namespace (K, dist, T_cam_robot) as the stereo functions read it."""
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = tvec
    return SimpleNamespace(K=K, dist=np.asarray(dist, np.float64), T_cam_robot=T)


def project(cam, X):
    """Pixels (N, 2) of points ``X`` (N, 3) in the robot frame, by ``cv2.projectPoints``."""
    T = cam.T_cam_robot
    uv, _ = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3],
                              cam.K, cam.dist)  # fmt: skip
    return uv.reshape(-1, 2)
