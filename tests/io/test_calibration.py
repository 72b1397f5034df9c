"""Calibration files: OpenCV FileStorage YAML/XML written by cv2 itself, JSON, stereo pairs
from cv2.stereoCalibrate conventions, and every bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from jaxcr.camera import Camera, project_points
from jaxcr.errors import InputError
from jaxcr.io.calibration import (
    camera_from_dict,
    load_camera,
    load_stereo,
    save_camera,
    save_stereo,
)

K = np.array([[520.5, 0.0, 319.2], [0.0, 518.25, 241.7], [0.0, 0.0, 1.0]])
D = np.array([[-0.21, 0.07, 0.001, -0.0005, -0.01]])
T = np.array([[0.0, -1.0, 0.0, 0.01], [1.0, 0.0, 0.0, -0.02], [0.0, 0.0, 1.0, 0.3], [0, 0, 0, 1.0]])


def write_fs(path, **entries):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in entries.items():
        fs.write(k, v)
    fs.release()
    return path


@pytest.mark.parametrize("ext", ["yaml", "yml", "xml"])
def test_read_filestorage_written_by_opencv(tmp_path, ext):
    p = write_fs(
        tmp_path / f"cam.{ext}",
        camera_matrix=K,
        distortion_coefficients=D,
        image_width=640,
        image_height=480,
        T_cam_robot=T,
    )
    cam = load_camera(p)
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose(np.asarray(cam.K), K, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(cam.dist), D[0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(cam.T_cam_robot), T, atol=1e-7)


def test_hand_written_yaml_with_legacy_header_and_column_distortion(tmp_path):
    p = tmp_path / "cam.yml"
    p.write_text(
        "%YAML:1.0\n---\n"
        "image_width: 96\nimage_height: 72\n"
        "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 100., 0., 47.5, 0., 100., 35.5, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 4\n   cols: 1\n   dt: d\n"
        "   data: [ 0.1, -0.01, 0., 0. ]\n"
    )
    cam = load_camera(p)
    np.testing.assert_allclose(np.asarray(cam.dist), [0.1, -0.01, 0, 0, 0], atol=1e-7)
    np.testing.assert_allclose(np.asarray(cam.T_cam_robot), np.eye(4))


@pytest.mark.parametrize("ext", ["yaml", "xml", "json"])
def test_save_load_round_trip(tmp_path, ext):
    cam = Camera.look_at([0.1, 0.2, -0.3], [0, 0, 0], [0, 1, 0], 300.0, (160, 120), dist=D[0])
    p = tmp_path / f"c.{ext}"
    save_camera(cam, p)
    back = load_camera(p)
    for a, b in ((cam.K, back.K), (cam.dist, back.dist), (cam.T_cam_robot, back.T_cam_robot)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-7)
    assert back.size == cam.size


def test_json_inline_keys_and_unit_mm(tmp_path):
    T_mm = T.copy()
    T_mm[:3, 3] *= 1000.0
    d = {
        "K": K.tolist(),
        "dist": D[0].tolist(),
        "size": [640, 480],
        "T_cam_robot": T_mm.tolist(),
        "unit": "mm",
    }
    p = tmp_path / "c.json"
    p.write_text(json.dumps(d))
    cam = load_camera(p)
    np.testing.assert_allclose(np.asarray(cam.T_cam_robot), T, atol=1e-6)


def test_distortion_length_rule():
    base = {"K": K.tolist(), "size": [640, 480]}
    for n in (4, 5, 8, 12, 14):
        dist = list(D[0][: min(n, 5)]) + [0.0] * (n - min(n, 5))
        cam = camera_from_dict({**base, "dist": dist})
        np.testing.assert_allclose(np.asarray(cam.dist)[: min(n, 5)], D[0][: min(n, 5)], rtol=1e-6)
    with pytest.raises(InputError, match="after the fifth must be 0") as ei:
        camera_from_dict({**base, "dist": [0.1, 0, 0, 0, 0, 0.2, 0, 0]}, file="c.json")
    assert ei.value.field == "dist" and ei.value.file == "c.json"
    with pytest.raises(InputError, match="got 6"):
        camera_from_dict({**base, "dist": [0.0] * 6})
    with pytest.raises(InputError, match="1xN or Nx1"):
        camera_from_dict({**base, "dist": [[0.0] * 5, [0.0] * 5]})


def test_stereo_from_stereo_calibrate_conventions(tmp_path):
    """Check R, T semantics with cv2 itself: X2 = R X1 + T, so camera 2's projection of a
    robot point equals cv2.projectPoints with the composed pose."""
    rng = np.random.default_rng(0)
    rvec = np.array([0.02, -0.3, 0.01])
    R, _ = cv2.Rodrigues(rvec)
    t = np.array([[-60.0], [1.0], [5.0]])  # millimetres, as many labs calibrate
    K2 = K.copy()
    K2[0, 0] = 530.0
    T_mm = T.copy()
    T_mm[:3, 3] *= 1e3  # with unit: mm every translation in the file is in millimetres
    p = write_fs(
        tmp_path / "stereo.yaml",
        M1=K,
        D1=D,
        M2=K2,
        D2=D * 0.5,
        R=R,
        T=t,
        E=np.eye(3),
        F=np.eye(3),
        image_width=640,
        image_height=480,
        T_cam_robot=T_mm,
        unit="mm",
    )
    c1, c2 = load_stereo(p)
    X = rng.normal(size=(10, 3)) * 0.02
    # reference for camera 2: robot -> cam1 (T) -> cam2 (R, t in metres) via cv2 only
    X1 = X @ T[:3, :3].T + T[:3, 3]
    ref, _ = cv2.projectPoints(X1, rvec, t[:, 0] * 1e-3, K2, D[0] * 0.5)
    import jax

    with jax.enable_x64(True):
        c2_64 = jax.tree.map(lambda a: np.asarray(a, np.float64), c2)
        uv, _ = project_points(c2_64, X)
    np.testing.assert_allclose(np.asarray(uv), ref[:, 0], atol=1e-3)  # float32-stored camera
    np.testing.assert_allclose(np.asarray(c1.T_cam_robot), T, atol=1e-6)
    # round trip through save_stereo (JSON)
    save_stereo(c1, c2, tmp_path / "s.json")
    d1, d2 = load_stereo(tmp_path / "s.json")
    np.testing.assert_allclose(np.asarray(d2.T_cam_robot), np.asarray(c2.T_cam_robot), atol=1e-6)
    np.testing.assert_allclose(np.asarray(d2.K), K2, rtol=1e-6)


# ------------------------------------------------------------------------------ bad inputs


def _good():
    return {
        "camera_matrix": K.tolist(),
        "distortion_coefficients": D.tolist(),
        "image_width": 640,
        "image_height": 480,
    }


@pytest.mark.parametrize(
    "mutate, field, message",
    [
        (lambda d: d.pop("camera_matrix"), "camera_matrix", "missing required key"),
        (lambda d: d.pop("image_width"), "image_width", "missing required key"),
        (lambda d: d.update(camera_matrix=[[1, 0, 0], [0, 1, 0]]), "camera_matrix", "3x3"),
        (
            lambda d: d.update(camera_matrix=[[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]]),
            "camera_matrix",
            "NaN",
        ),
        (
            lambda d: d.update(camera_matrix=[[-5, 0, 1], [0, 5, 1], [0, 0, 1]]),
            "camera_matrix",
            "positive",
        ),
        (
            lambda d: d.update(camera_matrix=[[5, 0, 1], [0, 5, 1], [0, 1, 1]]),
            "camera_matrix",
            r"\[0, 0, 1\]",
        ),
        (lambda d: d.update(camera_matrix="abc"), "camera_matrix", "matrix"),
        (lambda d: d.update(image_width=-3), "image_width", "positive integer"),
        (lambda d: d.update(image_height=10.5), "image_height", "positive integer"),
        (lambda d: d.update(T_cam_robot=np.eye(3).tolist()), "T_cam_robot", "4x4"),
        (lambda d: d.update(T_cam_robot=(2 * np.eye(4)).tolist()), "T_cam_robot", "last row"),
        (
            lambda d: d.update(T_cam_robot=np.diag([2.0, 1, 1, 1]).tolist()),
            "T_cam_robot",
            "rotation",
        ),
        (lambda d: d.update(unit="inch"), "unit", "expected one of"),
    ],
)
def test_bad_camera_json(tmp_path, mutate, field, message):
    d = _good()
    mutate(d)
    p = tmp_path / "cam.json"
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match=message) as ei:
        load_camera(p)
    assert ei.value.file == str(p)
    assert ei.value.field == field
    assert "\n" not in str(ei.value)


def test_bad_matrix_size_in_yaml(tmp_path):
    p = write_fs(tmp_path / "c.yaml", camera_matrix=np.eye(4), image_width=10, image_height=10)
    with pytest.raises(InputError, match=r"3x3 matrix, got shape \(4, 4\)") as ei:
        load_camera(p)
    assert ei.value.field == "camera_matrix" and ei.value.file == str(p)


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("c.yaml", "camera_matrix: [1, 2\n  ::: {\n", "FileStorage"),
        ("c.json", "{not json", "not valid JSON"),
        ("c.json", "[1, 2]", "JSON object"),
        ("c.txt", "x", "unknown calibration file type"),
    ],
)
def test_unparseable_files(tmp_path, name, content, message):
    p = tmp_path / name
    p.write_text(content)
    with pytest.raises(InputError, match=message) as ei:
        load_camera(p)
    assert ei.value.file == str(p)
    assert "\n" not in str(ei.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_camera(tmp_path / "none.yaml")


def test_stereo_missing_and_bad_fields(tmp_path):
    p = write_fs(tmp_path / "s.yaml", K1=K, K2=K, R=np.eye(3), image_width=640, image_height=480)
    with pytest.raises(InputError, match="missing") as ei:
        load_stereo(p)
    assert ei.value.field == "T"
    p = write_fs(
        tmp_path / "s2.yaml",
        K1=K,
        K2=K,
        R=2 * np.eye(3),
        T=np.zeros((3, 1)),
        image_width=640,
        image_height=480,
    )
    with pytest.raises(InputError, match="rotation") as ei:
        load_stereo(p)
    assert ei.value.field == "R"
    p = write_fs(
        tmp_path / "s3.yaml",
        K1=K,
        R=np.eye(3),
        T=np.zeros((3, 1)),
        image_width=640,
        image_height=480,
    )
    with pytest.raises(InputError, match="missing") as ei:
        load_stereo(p)
    assert ei.value.field == "K2"
    p = write_fs(
        tmp_path / "s4.yaml",
        K1=K,
        K2=K,
        R=np.eye(3),
        T=np.zeros((3, 1)),
        E=np.eye(2),
        image_width=640,
        image_height=480,
    )
    with pytest.raises(InputError, match="3x3") as ei:
        load_stereo(p)
    assert ei.value.field == "E"


@pytest.mark.parametrize("ext", ["yaml", "json"])
def test_written_files_carry_the_format_version(tmp_path, ext):
    """Files jaxcr writes say ``format: jaxcr.calibration/1`` (read back by OpenCV's own
    FileStorage reader for YAML, by json for JSON); a file without the key still loads."""
    cam = Camera.look_at([0.1, 0.2, -0.3], [0, 0, 0], [0, 1, 0], 300.0, (160, 120), dist=D[0])
    single, stereo = tmp_path / f"c.{ext}", tmp_path / f"s.{ext}"
    save_camera(cam, single)
    cam2 = Camera.look_at([0.15, 0.2, -0.3], [0, 0, 0], [0, 1, 0], 300.0, (160, 120))
    save_stereo(cam, cam2, stereo)
    for p in (single, stereo):
        if ext == "json":
            fmt = json.loads(p.read_text())["format"]
        else:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
            fmt = fs.getNode("format").string()
            fs.release()
        assert fmt == "jaxcr.calibration/1"
    d = json.loads(single.read_text()) if ext == "json" else None
    if d is not None:
        del d["format"]
        assert camera_from_dict(d).size == (160, 120)


@pytest.mark.parametrize(
    ("fmt", "message"),
    [
        ("jaxcr.calibration/2", "written by a newer jaxcr"),
        ("jaxcr.stereo/1", "a jaxcr.stereo file, not a calibration"),
        ("jaxcr.calibration/x", "unreadable format"),
    ],
)
def test_format_this_version_cannot_read_is_refused(tmp_path, fmt, message):
    cam = Camera.look_at([0.1, 0.2, -0.3], [0, 0, 0], [0, 1, 0], 300.0, (160, 120))
    cam2 = Camera.look_at([0.15, 0.2, -0.3], [0, 0, 0], [0, 1, 0], 300.0, (160, 120))
    single, stereo = tmp_path / "c.json", tmp_path / "s.json"
    save_camera(cam, single)
    save_stereo(cam, cam2, stereo)
    for p, load in ((single, load_camera), (stereo, load_stereo)):
        d = json.loads(p.read_text())
        d["format"] = fmt
        p.write_text(json.dumps(d))
        with pytest.raises(InputError, match=message) as e:
            load(p)
        assert e.value.field == "format" and str(p) in str(e.value)


def test_foreign_format_key_is_ignored(tmp_path):
    """A ``format`` not starting with ``jaxcr.`` belongs to another tool: read as before."""
    p = write_fs(tmp_path / "cam.yaml", camera_matrix=K, distortion_coefficients=D,
                 image_width=640, image_height=480, format="opencv-calib-v3")  # fmt: skip
    assert load_camera(p).size == (640, 480)
