"""ArUco base frame on a ray-cast plate (jaxcr.synth.stereo_ctr renders the markers with
cv2.aruco.generateImageMarker as textures): detection, single- and two-view pose against
the true pose, robust rejection of a bad marker, and the no-marker failure."""

import numpy as np
import pytest

from jaxcr.camera import camera_from_arrays
from jaxcr.registration.metrics import rotation_angle
from jaxcr.stereo.aruco import (
    MarkerLayout,
    camera_base_pose,
    detect_markers,
    marker_object_corners,
    stereo_base_pose,
)
from jaxcr.synth.stereo_ctr import _Scene, render_view, stereo_cameras


def _rot_angle_deg(R):
    # atan2 form (log-map norm): arccos of the trace loses angles below ~0.03 deg in float32
    return float(np.degrees(rotation_angle(R)))


@pytest.fixture(scope="module")
def plate_views():
    layout = MarkerLayout()
    cams = stereo_cameras((640, 480), layout, np.random.default_rng(5))
    scene = _Scene(layout, (0.15, 0.62, 0.22), None, None, 0)
    imgs = [render_view(scene, c, np.random.default_rng(k))[0] for k, c in enumerate(cams)]
    # Calibration frame = camera 1 (as in the synthetic sets).
    T1 = cams[0].T_cam_robot
    c1 = camera_from_arrays(cams[0].K, cams[0].dist, np.eye(4), 640, 480)
    c2 = camera_from_arrays(
        cams[1].K, cams[1].dist, cams[1].T_cam_robot @ np.linalg.inv(T1), 640, 480
    )
    return layout, cams, imgs, (c1, c2)


def test_detect_all_markers(plate_views):
    layout, cams, imgs, _ = plate_views
    for img, cam in zip(imgs, cams, strict=True):
        det = detect_markers(img, layout)
        assert sorted(det) == [0, 1, 2, 3]
        # Corners agree with the projected layout corners (true pose) to < 0.5 px.
        import cv2

        for i, c in det.items():
            uv, _ = cv2.projectPoints(
                marker_object_corners(layout, i),
                cv2.Rodrigues(cam.T_cam_robot[:3, :3])[0],
                cam.T_cam_robot[:3, 3],
                cam.K,
                cam.dist,
            )
            assert np.abs(uv.reshape(4, 2) - c).max() < 0.5


def test_single_view_and_stereo_pose(plate_views):
    layout, cams, imgs, (c1, c2) = plate_views
    det = [detect_markers(im, layout) for im in imgs]
    for k in range(2):
        T, kept = camera_base_pose(
            camera_from_arrays(cams[k].K, cams[k].dist, np.eye(4), 640, 480), det[k], layout
        )
        assert len(kept) == 4
        assert _rot_angle_deg(T[:3, :3].T @ cams[k].T_cam_robot[:3, :3]) < 0.3
        assert np.linalg.norm(T[:3, 3] - cams[k].T_cam_robot[:3, 3]) < 1.0e-3
    r = stereo_base_pose(c1, c2, det[0], det[1], layout)
    assert _rot_angle_deg(r["T_cam1_base"][:3, :3].T @ cams[0].T_cam_robot[:3, :3]) < 0.15
    assert np.linalg.norm(r["T_cam1_base"][:3, 3] - cams[0].T_cam_robot[:3, 3]) < 0.5e-3
    assert r["rms_px"] < 0.5 and r["n_markers"] == (4, 4)
    # Marker 2's centre is the origin, Z out of the plate towards the cameras.
    Tb = np.linalg.inv(r["T_cam1_base"])
    assert Tb[2, 2] < 0  # base Z seen from camera 1 points against its viewing direction-ish


def test_bad_marker_dropped_and_one_view_enough(plate_views):
    layout, cams, imgs, (c1, c2) = plate_views
    det = [detect_markers(im, layout) for im in imgs]
    bad = {k: v.copy() for k, v in det[0].items()}
    bad[3] = bad[3] + np.array([6.0, -4.0])
    T, kept = camera_base_pose(c1, bad, layout)
    assert 3 not in kept and len(kept) == 3
    r = stereo_base_pose(c1, c2, {}, det[1], layout)
    assert r["n_markers"] == (0, 4)
    assert np.linalg.norm(r["T_cam1_base"][:3, 3] - cams[0].T_cam_robot[:3, 3]) < 1.5e-3
    with pytest.raises(ValueError, match="no ArUco marker"):
        stereo_base_pose(c1, c2, {}, {}, layout)


def test_layout_round_trip():
    lay = MarkerLayout()
    assert MarkerLayout.from_dict(lay.to_dict()) == lay
    np.testing.assert_allclose(lay.base_centre, [0.03, 0.03, 0.0])
    np.testing.assert_allclose(marker_object_corners(lay, 2).mean(axis=0), [0, 0, 0], atol=1e-15)
