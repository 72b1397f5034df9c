"""The per-frame guards between triangulation and resampling in the stereo pipeline: a frame
whose matches triangulate behind a camera or kilometres away fails with a reason instead of
crashing the run (found with `jaxcr stereo --segmentation plate` at 160x120, where np.arange
over a 1e20 m backbone raised 'Maximum allowed size exceeded')."""

import numpy as np
import pytest

from jaxcr.stereo.pipeline import (
    MAX_BACKBONE_M,
    StereoFailure,
    _check_backbone_length,
    _consistent_points,
)


def _pose(t):
    T = np.eye(4)
    T[:3, 3] = t
    return T


def test_points_behind_a_camera_are_not_consistent():
    # camera 1 at the origin looking down +z, camera 2 shifted 0.1 m along x (closed form:
    # the depth of P in camera k is P_z + t_z)
    T1, T2 = _pose([0.0, 0.0, 0.0]), _pose([-0.1, 0.0, 0.0])
    P = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [np.nan, 0.0, 0.5], [0.01, 0.0, 0.3]])
    err = [np.zeros(4), np.zeros(4)]
    assert _consistent_points(P, err, (T1, T2)).tolist() == [True, False, False, True]
    err[1][3] = 2.5  # reprojection error over 2 px in one view
    assert _consistent_points(P, err, (T1, T2)).tolist() == [True, False, False, False]


def test_an_implausibly_long_backbone_fails_the_frame():
    s = np.linspace(0.0, 0.1, 50)
    ok = np.stack([np.zeros_like(s), np.zeros_like(s), 0.3 + s], axis=1)  # 0.1 m, closed form
    _check_backbone_length(ok)
    far = ok.copy()
    far[-1, 2] = 1e20
    with pytest.raises(StereoFailure, match="correspondence|long"):
        _check_backbone_length(far)
    far[-1, 2] = np.inf
    with pytest.raises(StereoFailure):
        _check_backbone_length(far)
    just = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, MAX_BACKBONE_M * 1.01]])
    with pytest.raises(StereoFailure):
        _check_backbone_length(just)
