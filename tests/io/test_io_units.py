"""Length units in calibration, dataset and stereo files (issue 16 item 3): the same rig
written in m, cm and mm loads as identical cameras; misspelt keys are refused naming the
nearest known key; implausible lengths (the real ``units: mm`` -> 426 m baseline) are refused
with the unit that would make them plausible."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from jaxcr.cli import main
from jaxcr.cli.stereo import load_stereo_dataset
from jaxcr.errors import InputError
from jaxcr.io.calibration import camera_from_dict, load_camera, load_stereo
from jaxcr.io.dataset import check_dataset, load_dataset
from jaxcr.io.images import write_png

K = np.array([[520.5, 0.0, 319.2], [0.0, 518.25, 241.7], [0.0, 0.0, 1.0]])
D = np.array([[-0.21, 0.07, 0.001, -0.0005, -0.01]])
T_M = np.array(
    [[0.0, -1.0, 0.0, 0.0123], [1.0, 0.0, 0.0, -0.0217], [0.0, 0.0, 1.0, 0.3141], [0, 0, 0, 1.0]]
)
R21 = cv2.Rodrigues(np.array([0.02, -0.3, 0.01]))[0]
T21_M = np.array([-0.4261, 0.0113, 0.0352])  # the real rig's 426 mm baseline, in metres
SCALE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}  # written number per metre
# The loaders store float32 cameras: two spellings of one length (0.3141 m vs 314.1 mm * 1e-3
# in float64) round to float32 values at most 1 ulp apart, i.e. relative 2^-23 ~ 1.2e-7; 1e-6
# leaves a margin of ~8 ulp.
RTOL = 1e-6


def _fs(path, **entries):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in entries.items():
        fs.write(k, v)
    fs.release()
    return path


def _in_unit(T, unit):
    T = np.array(T, float)
    T[:3, 3] *= SCALE[unit]
    return T


def _same_camera(a, b):
    for name in ("K", "dist", "T_cam_robot"):
        np.testing.assert_allclose(
            np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), rtol=RTOL, atol=1e-9
        )
    assert (a.width, a.height) == (b.width, b.height)


# ------------------------------------------------------------------- same rig, three units


@pytest.mark.parametrize("ext", ["yaml", "xml", "json"])
def test_single_camera_file_in_m_cm_mm_is_one_camera(tmp_path, ext):
    cams = {}
    for unit in SCALE:
        entries = dict(camera_matrix=K, distortion_coefficients=D, image_width=640,
                       image_height=480, T_cam_robot=_in_unit(T_M, unit), unit=unit)  # fmt: skip
        p = tmp_path / f"c_{unit}.{ext}"
        if ext == "json":
            p.write_text(json.dumps({k: np.asarray(v).tolist() if isinstance(v, np.ndarray)
                                     else v for k, v in entries.items()}))  # fmt: skip
        else:
            _fs(p, **entries)
        cams[unit] = load_camera(p)
    # reference: the metre values themselves
    np.testing.assert_allclose(np.asarray(cams["m"].T_cam_robot), T_M, rtol=RTOL, atol=1e-9)
    _same_camera(cams["m"], cams["cm"])
    _same_camera(cams["m"], cams["mm"])


@pytest.mark.parametrize("ext", ["yaml", "json"])
def test_stereo_file_in_m_cm_mm_is_one_rig(tmp_path, ext):
    rigs = {}
    for unit in SCALE:
        entries = dict(K1=K, D1=D, K2=K, D2=D * 0.5, image_width=640, image_height=480, R=R21,
                       T=(T21_M * SCALE[unit]).reshape(3, 1), T_cam_robot=_in_unit(T_M, unit),
                       unit=unit)  # fmt: skip
        p = tmp_path / f"s_{unit}.{ext}"
        if ext == "json":
            p.write_text(json.dumps({k: np.asarray(v).tolist() if isinstance(v, np.ndarray)
                                     else v for k, v in entries.items()}))  # fmt: skip
        else:
            _fs(p, **entries)
        rigs[unit] = load_stereo(p)
    # reference: camera 2's pose composed by hand, X2 = R21 (T_M X) + t21 (metres)
    T21 = np.eye(4)
    T21[:3, :3], T21[:3, 3] = R21, T21_M
    np.testing.assert_allclose(np.asarray(rigs["m"][1].T_cam_robot), T21 @ T_M, rtol=RTOL,
                               atol=1e-7)  # fmt: skip
    for unit in ("cm", "mm"):
        for a, b in zip(rigs["m"], rigs[unit], strict=True):
            _same_camera(a, b)


def _tiny_dataset(root, camera_entry, extra_top=None, truth=None, frame_extra=None):
    root.mkdir(parents=True, exist_ok=True)
    write_png(root / "img.png", np.zeros((24, 32, 3), np.uint8))
    frame = {"id": "000", "q": [0.0, 0.0], "images": {"main": "img.png"}}
    if truth is not None:
        np.save(root / "c.npy", truth)
        frame["truth"] = {"centreline": "c.npy"}
    frame.update(frame_extra or {})
    d = {
        "format": "jaxcr.dataset/1",
        "robot": {"kind": "single_segment", "length": 0.05, "radius": 0.002},
        "cameras": {"main": camera_entry},
        "frames": [frame],
        **(extra_top or {}),
    }
    (root / "dataset.json").write_text(json.dumps(d))
    return root


K_SMALL = [[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]]


def test_dataset_camera_entry_in_m_cm_mm_is_one_camera(tmp_path):
    cams = {}
    for unit in SCALE:
        entry = {"K": K_SMALL, "size": [32, 24], "T_cam_robot": _in_unit(T_M, unit).tolist(),
                 "unit": unit}  # fmt: skip
        cams[unit] = load_dataset(_tiny_dataset(tmp_path / unit, entry)).cameras["main"]
    # a calibration file in mm referenced by path gives the same camera too
    _fs(tmp_path / "mmfile.yaml", camera_matrix=np.array(K_SMALL), image_width=32,
        image_height=24, T_cam_robot=_in_unit(T_M, "mm"), unit="mm")  # fmt: skip
    ds = load_dataset(_tiny_dataset(tmp_path / "file", "../mmfile.yaml"))
    np.testing.assert_allclose(np.asarray(cams["m"].T_cam_robot), T_M, rtol=RTOL, atol=1e-9)
    for c in (cams["cm"], cams["mm"], ds.cameras["main"]):
        _same_camera(cams["m"], c)


def _stereo_json(root, calib_unit, json_unit, **extra):
    root.mkdir(parents=True, exist_ok=True)
    _fs(root / "stereo.yaml", K1=K, K2=K, image_width=640, image_height=480, R=R21,
        T=(T21_M * SCALE[calib_unit]).reshape(3, 1), unit=calib_unit)  # fmt: skip
    s = SCALE[json_unit]
    meta = {
        "format": "jaxcr.stereo/1",
        "calibration": "stereo.yaml",
        "markers": {
            "centres": {
                "2": [0, 0],
                "3": [0.06 * s, 0],
                "0": [0, 0.06 * s],
                "1": [0.06 * s, 0.06 * s],
            },
            "size": 0.024 * s,
        },  # fmt: skip
        "robot_base": [0.03 * s, 0.01 * s, 0.0],
        "frames": [{"id": "000", "images": {"cam1": "a.png", "cam2": "b.png"}}],
        "unit": json_unit,
        **extra,
    }
    (root / "stereo.json").write_text(json.dumps(meta))
    return root


def test_stereo_json_in_m_cm_mm_is_one_setup(tmp_path):
    sets = {u: load_stereo_dataset(_stereo_json(tmp_path / u, u, u)) for u in SCALE}
    ref = sets["m"]["config"]
    assert ref.layout.size == 0.024 and ref.layout.centres[1] == (0.06, 0.06)
    for u in ("cm", "mm"):
        cfg = sets[u]["config"]
        np.testing.assert_allclose(cfg.layout.size, ref.layout.size, rtol=RTOL)
        for k, c in ref.layout.centres.items():
            np.testing.assert_allclose(cfg.layout.centres[k], c, rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(cfg.robot_base, ref.robot_base, rtol=RTOL, atol=1e-12)
        for a, b in (("cam1", "cam1"), ("cam2", "cam2")):
            _same_camera(sets["m"][a], sets[u][b])


# ------------------------------------------------------------------------- misspelt keys


@pytest.mark.parametrize(
    "key, value, near",
    [("units", "mm", "unit"), ("Unit", "mm", "unit"), ("camera_matrx", K.tolist(), "camera_matrix"),
     ("T_cam_robt", T_M.tolist(), "T_cam_robot"), ("distortion", [0.0] * 5, "distortion_coefficients")],
)  # fmt: skip
def test_misspelt_camera_key_names_the_nearest(key, value, near):
    d = {"K": K.tolist(), "size": [640, 480], key: value}
    if key == "camera_matrx":
        del d["K"]
    with pytest.raises(InputError, match=rf"unknown key '{key}' \(did you mean '{near}'\?\)") as ei:
        camera_from_dict(d, file="c.json", prefix="cameras.main.")
    assert ei.value.field == f"cameras.main.{key}" and ei.value.file == "c.json"


def test_unrelated_key_lists_the_known_keys_and_informational_keys_pass(tmp_path):
    with pytest.raises(InputError, match=r"unknown key 'zzzzqq' \(known keys: camera_matrix, K"):
        camera_from_dict({"K": K.tolist(), "size": [640, 480], "zzzzqq": 1})
    # what OpenCV's calibration sample writes beside the camera is accepted and ignored
    p = _fs(tmp_path / "cv.yaml", calibration_time="Mon", nr_of_frames=25, board_width=9,
            camera_matrix=K, distortion_coefficients=D, image_width=640, image_height=480,
            avg_reprojection_error=0.21)  # fmt: skip
    np.testing.assert_allclose(np.asarray(load_camera(p).K), K, rtol=RTOL)


def test_dataset_and_stereo_json_misspellings(tmp_path):
    entry = {"K": K_SMALL, "size": [32, 24]}
    errs = check_dataset(
        _tiny_dataset(
            tmp_path / "a",
            {**entry, "units": "mm"},
            extra_top={"camras": {}},
            frame_extra={"mask": {}},
        )  # fmt: skip
    ).all_errors
    text = [e.format() for e in errs]
    assert any("field 'camras': unknown key (did you mean 'cameras'?)" in t for t in text), text
    assert any("field 'cameras.main.units': unknown key 'units' (did you mean 'unit'?)" in t
               for t in text), text  # fmt: skip
    assert any("field 'mask': unknown key (did you mean 'masks'?)" in t for t in text), text
    errs = check_dataset(_tiny_dataset(tmp_path / "b", entry, extra_top={"unit": "mm"})).errors
    assert "no file-wide unit" in errs[0].message and errs[0].field == "unit"
    with pytest.raises(InputError, match=r"unknown key 'units' \(did you mean 'unit'\?\)"):
        load_stereo_dataset(_stereo_json(tmp_path / "s", "m", "m", units="mm"))
    with pytest.raises(InputError, match=r"unknown key 'robot_bas' \(did you mean 'robot_base'"):
        load_stereo_dataset(_stereo_json(tmp_path / "t", "m", "m", robot_bas=[0, 0, 0]))


# ------------------------------------------------------------------ implausible lengths


def test_the_426_m_baseline_is_refused_with_the_unit(tmp_path, capsys):
    """The real failure: a stereo file in millimetres with ``units: mm`` (not ``unit``) was
    read as 426 m of baseline. Now the key is refused, and without any unit key the baseline
    is refused with the unit that makes it plausible."""
    mm = dict(K1=K, K2=K, image_width=640, image_height=480, R=R21,
              T=(T21_M * 1000).reshape(3, 1))  # fmt: skip
    p = _fs(tmp_path / "units.yaml", **mm, units="mm")
    with pytest.raises(InputError, match=r"unknown key 'units' \(did you mean 'unit'\?\)"):
        load_stereo(p)
    p = _fs(tmp_path / "nounit.yaml", **mm)
    with pytest.raises(InputError) as ei:
        load_stereo(p)
    msg = ei.value.format()
    assert ei.value.field == "T" and "stereo baseline |T| of 427.7 m is implausible" in msg
    assert 'millimetres (427.7 mm = 0.4277 m), set "unit": "mm"' in msg
    # through the CLI: exit 2 and one line
    root = _stereo_json(tmp_path / "rig", "m", "m")
    _fs(root / "stereo.yaml", **mm, units="mm")
    assert main(["stereo", str(root), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "did you mean 'unit'" in err[0], err
    # a file in metres declared as mm: baseline under 1 mm, the hint is metres
    p = _fs(tmp_path / "small.yaml", **{**mm, "T": T21_M.reshape(3, 1)}, unit="mm")
    with pytest.raises(InputError, match=r'under 1 mm.*if it is in metres .*"unit": "m"'):
        load_stereo(p)


def test_implausible_translations_elsewhere(tmp_path):
    with pytest.raises(InputError, match=r'translation of 315.1 m is implausible.*"unit": "mm"'):
        camera_from_dict({"K": K.tolist(), "size": [640, 480],
                          "T_cam_robot": _in_unit(T_M, "mm").tolist()})  # fmt: skip
    with pytest.raises(InputError, match=r"marker size of 24 m.*millimetres"):
        load_stereo_dataset(_stereo_json(tmp_path / "s", "m", "mm", unit="m"))
    # a truth centreline in millimetres
    pts = np.c_[np.zeros(5), np.zeros(5), np.linspace(0, 50, 5)]
    check = check_dataset(_tiny_dataset(tmp_path / "d", {"K": K_SMALL, "size": [32, 24]},
                                        truth=pts))  # fmt: skip
    msgs = [e.message for e in check.all_errors]
    assert any("centreline reaches 50 m" in m and "millimetres" in m for m in msgs), msgs


def test_stereo_json_T_cam_base_honours_unit(tmp_path):
    """``base.T_cam_base`` is a length in stereo.json's ``unit`` (audit r31: a file in mm that
    said ``"unit": "mm"`` was refused with the advice to set ``"unit": "mm"``). The same base
    in m, cm and mm loads as one pose; metres under ``"unit": "mm"`` (0.31 mm from the camera)
    is refused with the metres hint."""
    specs = {}
    for u in SCALE:
        extra = {"base": {"T_cam_base": _in_unit(T_M, u).tolist()}}
        specs[u] = load_stereo_dataset(_stereo_json(tmp_path / u, u, u, **extra))["config"].base
    for u in ("cm", "mm"):
        np.testing.assert_allclose(specs[u].T_cam1_base, specs["m"].T_cam1_base, rtol=RTOL,
                                   atol=1e-12)  # fmt: skip
    extra = {"base": {"T_cam_base": T_M.tolist()}}
    with pytest.raises(InputError, match=r'base translation .*under 10 mm.*"unit": "m"') as ei:
        load_stereo_dataset(_stereo_json(tmp_path / "x", "m", "mm", **extra))
    assert ei.value.field == "base.T_cam_base"


def test_stereo_json_missing_plate_names_the_camera(tmp_path):
    """A plate given for one camera of two (audit r31: the message listed both cameras but
    not which plate was missing)."""
    root = _stereo_json(tmp_path / "p", "m", "m", background_plates={"cam1": "a.png"})
    with pytest.raises(InputError, match=r"no plate path for 'cam2'") as ei:
        load_stereo_dataset(root)
    assert ei.value.field == "background_plates"
