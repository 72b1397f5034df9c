"""Camera calibration files: OpenCV FileStorage (YAML ``.yaml``/``.yml``, XML ``.xml``) and JSON.

Single camera (any of the three formats)
----------------------------------------
=========================  ===============================================================
key                        meaning
=========================  ===============================================================
``camera_matrix``          3x3 intrinsics, pixels (OpenCV ``!!opencv-matrix`` or nested
                           list); JSON may use ``K`` instead
``distortion_coefficients``OpenCV order ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]``
                           as 1xN or Nx1 (or a flat list); JSON may use ``dist``
``image_width``,           image size in pixels; JSON may use ``"size": [w, h]``
``image_height``
``T_cam_robot``            optional 4x4, maps robot-frame points (metres) to the camera
                           frame; identity if absent
``unit``                   optional, ``"m"`` (default), ``"cm"`` or ``"mm"``: unit of
                           the translations in this file (converted to metres)
=========================  ===============================================================

Any other key is an error naming it and the nearest known key (``units: mm`` is refused with
"did you mean 'unit'?", never ignored), except the informational keys OpenCV's calibration
samples and ``jaxcr calibrate`` write, which are accepted and ignored (:data:`INFO_KEYS`).
Translations must be plausible (:mod:`jaxcr.io.units`): ``T_cam_robot`` within 5 m, a stereo
baseline ``|T|`` between 1 mm and 5 m; otherwise the error suggests the unit.

Distortion length rule: N must be 4, 5, 8, 12 or 14. N = 4 means ``k3 = 0``. Only the
five-parameter model ``(k1, k2, p1, p2, k3)`` is implemented, so for N > 5 every entry after
the fifth must be exactly 0 (rational/thin-prism/tilt models are rejected, not silently
truncated).

Stereo pair (as labs save the output of ``cv2.stereoCalibrate``)
----------------------------------------------------------------
Intrinsics ``K1``/``D1``, ``K2``/``D2`` (also accepted: ``M1``/``M2`` as in OpenCV's
``stereo_calib`` sample, or ``camera_matrix_1``/``distortion_coefficients_1`` ...), image
size ``image_width``/``image_height`` (shared) or ``image_width_1``... per camera,
``R`` (3x3) and ``T`` (3x1) mapping camera-1 points to camera 2 (``X2 = R X1 + T``, the
``cv2.stereoCalibrate`` convention), optional ``E``/``F`` (checked for shape and
finiteness only), optional ``T_cam_robot`` for camera 1 and ``unit``. Camera 2's extrinsic is
composed: ``T_cam2_robot = [R | T] @ T_cam1_robot``. ``unit`` applies to ``T`` and
``T_cam_robot``.

Optional ``uncertainty`` block (written by ``jaxcr calibrate``): the calibration's standard
deviations, ``focal_rel`` (of fx and fy, relative; the larger of the two cameras'),
``principal_px`` (of cx and cy, px; the larger), ``rotation_deg`` (of ``R``'s rotation
vector per axis, deg; the largest axis), ``translation`` (of ``T`` per axis, the largest, in
the block's ``unit``, default the file's), all required; and, informational, OpenCV's
per-parameter values ``std_intrinsics_1``/``_2`` (9: fx fy cx cy k1 k2 p1 p2 k3, px, of
``cv2.calibrateCameraExtended``), ``std_rotation_deg`` (3), ``std_translation`` (3, the
block's unit) of the stereo fit (:func:`jaxcr.stereo.calibration.stereo_pose_std`).
:func:`load_stereo_uncertainty` reads it as a
:class:`jaxcr.stereo.epipolar_tolerance.CalibrationUncertainty` (whose pose components are
per camera: the rig's ``R``, ``T`` deviations divided by sqrt(2), two cameras moved
independently giving the rig's); ``jaxcr stereo`` passes it to the tips' re-search
(docs/decisions.md S37).

Format version
--------------
Files written by jaxcr (``jaxcr calibrate``, :func:`save_camera`, :func:`save_stereo`) carry
``format: jaxcr.calibration/1``. The key is optional on reading (labs' own OpenCV files have
none, and earlier jaxcr versions ignore it). A ``jaxcr.calibration/N`` with ``N`` above
:data:`CALIBRATION_FORMAT_VERSION` is refused (written by a newer jaxcr, whose keys this
version may misread), as is another jaxcr file kind (``jaxcr.stereo/1``, a dataset's stereo
description, given as the calibration); a ``format`` value not starting with ``jaxcr.`` is
someone else's and ignored.

Every problem raises :class:`jaxcr.errors.InputError` naming the file and the field.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from jaxcr.camera import Camera, camera_from_arrays
from jaxcr.errors import InputError
from jaxcr.io.jsonfile import read_json
from jaxcr.io.results import atomic_write_bytes, atomic_write_text
from jaxcr.io.units import (
    MIN_BASELINE_M,
    check_known_keys,
    check_length,
    nearest_key,
    unit_scale,
)

_FS_EXT = (".yaml", ".yml", ".xml")
_DIST_LENGTHS = (4, 5, 8, 12, 14)
SINGLE_KEYS = ("camera_matrix", "K", "distortion_coefficients", "dist", "image_width",
               "image_height", "size", "T_cam_robot", "unit")  # fmt: skip
STEREO_KEYS = ("K1", "D1", "K2", "D2", "M1", "M2", "camera_matrix_1", "camera_matrix_2",
               "distortion_coefficients_1", "distortion_coefficients_2", "image_width",
               "image_height", "image_width_1", "image_height_1", "image_width_2",
               "image_height_2", "R", "T", "E", "F", "T_cam_robot", "unit",
               "uncertainty")  # fmt: skip
#: Keys of a stereo file's optional ``uncertainty`` block (see the module docstring).
UNCERTAINTY_KEYS = ("focal_rel", "principal_px", "rotation_deg", "translation", "unit",
                    "std_intrinsics_1", "std_intrinsics_2", "std_rotation_deg",
                    "std_translation")  # fmt: skip
# Plausible upper bounds of the block's standard deviations: past them the calibration is
# useless or the number is in another unit (a percentage for focal_rel, metres written
# under "unit": "mm" for translation).
MAX_FOCAL_REL = 0.1
MAX_PRINCIPAL_PX = 50.0
MAX_ROTATION_DEG = 5.0
MAX_TRANSLATION_STD_M = 0.05
# Written by OpenCV's calibration / stereo_calib samples, cv2.stereoRectify users and
# jaxcr calibrate; accepted and ignored (they never change the cameras).
INFO_KEYS = ("calibration_time", "calibration_date", "nframes", "nr_of_frames", "board_width",
             "board_height", "square_size", "aspect_ratio", "aspectRatio", "flags",
             "fix_aspect_ratio", "avg_reprojection_error", "per_view_reprojection_errors",
             "extrinsic_parameters", "image_points", "grid_points", "camera_name",
             "R1", "R2", "P1", "P2", "Q", "roi1", "roi2", "validRoi1", "validRoi2",
             "rms", "rms_1", "rms_2", "rms_stereo", "per_view_rms_1", "per_view_rms_2",
             "per_view_rms_stereo", "calibrate_flags", "tilt_deg_1", "tilt_deg_2",
             "distance_1", "distance_2", "coverage_1", "coverage_2", "jaxcr_version",
             "format", "meta")  # fmt: skip


# ---------------------------------------------------------------------------- raw reading


def _fs_node_value(node: Any) -> Any:
    if node.isMap():
        try:
            m = node.mat()
        except cv2.error:
            m = None
        if m is not None:
            return np.asarray(m, np.float64)
        return {k: _fs_node_value(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_fs_node_value(node.at(i)) for i in range(node.size())]
    if node.isInt() or node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    return None


def read_filestorage(path: str | os.PathLike) -> dict[str, Any]:
    """All top-level entries of an OpenCV FileStorage file as Python/numpy values."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError("calibration file not found", file=path)
    if os.path.getsize(path) == 0:
        raise InputError("calibration file is empty", file=path)
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:
        # cv2 raises cv2.error (sometimes wrapped in SystemError) with a multi-line message
        # (a SystemError "returned a result with an exception set" carries it as its cause)
        src = err.__cause__ if isinstance(err, SystemError) and err.__cause__ else err
        lines = [ln.strip() for ln in str(src).splitlines() if ln.strip()]
        msg = lines[-1] if lines and "exception set" not in lines[-1] else "parse error"
        msg = msg.split(" error: ", 1)[-1]  # drop "OpenCV(x.y) /path/to/source.cpp:N"
        raise InputError(f"not a readable OpenCV FileStorage file ({msg})", file=path) from None
    try:
        if not fs.isOpened():
            raise InputError("not a readable OpenCV FileStorage file", file=path)
        root = fs.root()
        if not root.isMap():
            raise InputError("expected a map of named entries at the top level", file=path)
        return {k: _fs_node_value(fs.getNode(k)) for k in root.keys()}
    except (cv2.error, SystemError) as err:
        # (a SystemError "returned a result with an exception set" carries it as its cause)
        src = err.__cause__ if isinstance(err, SystemError) and err.__cause__ else err
        lines = [ln.strip() for ln in str(src).splitlines() if ln.strip()]
        msg = lines[-1] if lines and "exception set" not in lines[-1] else "parse error"
        msg = msg.split(" error: ", 1)[-1]  # drop "OpenCV(x.y) /path/to/source.cpp:N"
        raise InputError(f"cannot parse OpenCV FileStorage file ({msg})", file=path) from None
    finally:
        fs.release()


def read_raw(path: str | os.PathLike) -> dict[str, Any]:
    """Top-level entries of a calibration file (FileStorage by extension, else JSON)."""
    path = os.fspath(path)
    if path.lower().endswith(_FS_EXT):
        return read_filestorage(path)
    if not path.lower().endswith(".json"):
        raise InputError(
            "unknown calibration file type (expected .yaml, .yml, .xml or .json)", file=path
        )
    if not os.path.exists(path):
        raise InputError("calibration file not found", file=path)
    d = read_json(path)
    if not isinstance(d, dict):
        raise InputError("expected a JSON object", file=path)
    return d


# ------------------------------------------------------------------------------ validation


def _get(d: Mapping[str, Any], names: tuple[str, ...], file, prefix: str, required=True):
    for n in names:
        if n in d and d[n] is not None:
            return n, d[n]
    if required:
        alt = f" (or {', '.join(repr(n) for n in names[1:])})" if len(names) > 1 else ""
        raise InputError(f"missing required key{alt}", file=file, field=prefix + names[0])
    return names[0], None


def _matrix(value, shape_ok, want: str, file, field) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"expected a {want} matrix of numbers", file=file, field=field) from None
    if not shape_ok(a.shape):
        raise InputError(f"expected a {want} matrix, got shape {a.shape}", file=file, field=field)
    if not np.all(np.isfinite(a)):
        raise InputError("contains NaN or infinite values", file=file, field=field)
    return a


def check_intrinsics(K, file=None, field="camera_matrix") -> np.ndarray:
    """Validated 3x3 intrinsics (finite, fx, fy > 0, last row [0, 0, 1])."""
    K = _matrix(K, lambda s: s == (3, 3), "3x3", file, field)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(
            f"focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}",
            file=file,
            field=field,
        )
    if K[1, 0] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise InputError("expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]", file=file, field=field)
    return K


def check_intrinsics_range(K, width: int, height: int, file=None, field="camera_matrix") -> None:
    """Plausibility of intrinsics for a ``width x height`` image, with bounds no physical
    camera comes near: horizontal and vertical field of view within 0.1..179 degrees, and the
    principal point within one image size of the image (``-w <= cx <= 2w``, same for cy)."""
    K = np.asarray(K, np.float64)
    for f, n, name in ((K[0, 0], width, "fx"), (K[1, 1], height, "fy")):
        fov = np.degrees(2.0 * np.arctan2(n / 2.0, f))
        if not 0.1 <= fov <= 179.0:
            raise InputError(
                f"{name}={f:g} px gives a {fov:.3g} deg field of view over {n} px "
                "(expected 0.1..179 deg)",
                file=file,
                field=field,
            )
    for c, n, name in ((K[0, 2], width, "cx"), (K[1, 2], height, "cy")):
        if not -n <= c <= 2 * n:
            raise InputError(
                f"principal point {name}={c:g} px is far outside the {width}x{height} image",
                file=file,
                field=field,
            )


def check_distortion(dist, file=None, field="distortion_coefficients") -> np.ndarray:
    """Validated distortion reduced to the 5 OpenCV coefficients (see module docstring)."""
    d = _matrix(dist, lambda s: len(s) <= 2 and (len(s) < 2 or 1 in s), "1xN or Nx1", file, field)
    d = d.reshape(-1)
    if d.size not in _DIST_LENGTHS:
        raise InputError(
            f"expected 4, 5, 8, 12 or 14 coefficients, got {d.size}", file=file, field=field
        )
    if d.size == 4:
        return np.concatenate([d, [0.0]])
    if np.any(d[5:] != 0):
        raise InputError(
            "only the 5-parameter model (k1, k2, p1, p2, k3) is supported; coefficients after "
            "the fifth must be 0",
            file=file,
            field=field,
        )
    return d[:5]


def max_image_radius(K, width: int, height: int) -> float:
    """Largest normalised radius sqrt(x^2 + y^2) of the image, x, y = K^-1 (u, v, 1) over the
    corners of the pixel area (``-0.5 <= u <= width - 0.5``, same for v): the distorted radius
    the distortion model must reach monotonically (dimensionless, tan of the off-axis angle
    for an undistorted camera)."""
    K = np.asarray(K, np.float64)
    u = np.array([-0.5, width - 0.5, -0.5, width - 0.5])
    v = np.array([-0.5, -0.5, height - 0.5, height - 0.5])
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return float(np.max(np.hypot(x, y)))


def radial_fold(dist) -> tuple[float, float] | None:
    """Where the radial distortion r_d(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) (OpenCV, r the
    normalised undistorted radius) stops increasing: ``(r_c, r_d(r_c))`` at the smallest
    r_c > 0 with dr_d/dr = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6 = 0, or None when r_d increases
    for every r > 0. Beyond r_c two ray directions map to one distorted radius."""
    k1, k2, _p1, _p2, k3 = (float(v) for v in np.asarray(dist, np.float64).reshape(-1)[:5])
    coeffs = np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])  # in t = r^2, highest power first
    nz = np.flatnonzero(coeffs)
    roots = np.roots(coeffs[nz[0] :]) if nz[0] < 3 else np.array([])
    t = [r.real for r in roots if abs(r.imag) <= 1e-9 * max(1.0, abs(r)) and r.real > 0]
    if not t:
        return None
    tc = min(t)
    rc = float(np.sqrt(tc))
    return rc, rc * (1.0 + k1 * tc + k2 * tc**2 + k3 * tc**3)


def check_distortion_range(dist, K, width: int, height: int, file=None,
                           field="distortion_coefficients") -> None:  # fmt: skip
    """Refuse radial distortion that is not monotone over the image: the distorted radius must
    increase with the undistorted one up to the image's largest radius
    (:func:`max_image_radius`). Otherwise pixels near the corners have no ray (the model's
    distorted radius peaks inside the image) and two directions meet at one radius, so the
    model cannot describe this camera (typically coefficients in the wrong units or order, or
    a calibration extrapolated far outside the pattern's coverage). Tangential terms are not
    part of the check."""
    fold = radial_fold(dist)
    if fold is None:
        return
    rc, rd_c = fold
    rho = max_image_radius(K, width, height)
    if rd_c <= rho:
        k1, k2, _, _, k3 = (float(v) for v in np.asarray(dist, np.float64).reshape(-1)[:5])
        raise InputError(
            f"radial distortion (k1={k1:g}, k2={k2:g}, k3={k3:g}) is not monotone over the "
            f"{width}x{height} image: the distorted radius peaks at {rd_c:.3g} (undistorted "
            f"radius {rc:.3g}, {np.degrees(np.arctan(rc)):.3g} deg off-axis) below the image "
            f"corners' {rho:.3g}, so part of the image has no ray and directions fold onto "
            "each other",
            file=file,
            field=field,
        )


def check_transform(T, file=None, field="T_cam_robot", scale: float = 1.0) -> np.ndarray:
    """Validated 4x4 rigid transform (rotation orthonormal to 1e-4, det +1, last row 0 0 0 1);
    the translation is multiplied by ``scale`` (unit conversion to metres) and must then be
    within 5 m (:func:`jaxcr.io.units.check_length`)."""
    T = _matrix(T, lambda s: s == (4, 4), "4x4", file, field)
    R = T[:3, :3]
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError("last row must be [0, 0, 0, 1]", file=file, field=field)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InputError("rotation part is not a proper rotation matrix", file=file, field=field)
    T = T.copy()
    T[:3, 3] *= scale
    check_length(float(np.linalg.norm(T[:3, 3])), "translation", scale, file, field)
    return T


def _size_value(v, file, field) -> int:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise InputError("expected a positive integer", file=file, field=field) from None
    if not np.isfinite(f) or f != int(f) or f <= 0:
        raise InputError(f"expected a positive integer, got {v!r}", file=file, field=field)
    return int(f)


def _image_size(d, file, prefix: str, suffix: str = "") -> tuple[int, int]:
    if "size" in d and not suffix:
        size = d["size"]
        if not isinstance(size, list | tuple | np.ndarray) or len(size) != 2:
            raise InputError("expected [width, height]", file=file, field=prefix + "size")
        return (
            _size_value(size[0], file, prefix + "size[0]"),
            _size_value(size[1], file, prefix + "size[1]"),
        )
    names_w = (f"image_width{suffix}", "image_width") if suffix else ("image_width",)
    names_h = (f"image_height{suffix}", "image_height") if suffix else ("image_height",)
    kw, w = _get(d, names_w, file, prefix)
    kh, h = _get(d, names_h, file, prefix)
    return _size_value(w, file, prefix + kw), _size_value(h, file, prefix + kh)


def _unit_scale(d, file, prefix) -> float:
    check_format(d, file, prefix)
    return unit_scale(d, file, prefix)


#: The calibration file format this version writes and the newest it reads.
CALIBRATION_FORMAT_VERSION = 1
CALIBRATION_FORMAT = f"jaxcr.calibration/{CALIBRATION_FORMAT_VERSION}"


def check_format(d: Mapping[str, Any], file=None, prefix: str = "") -> None:
    """Refuse a ``format`` this version cannot read (module docstring, "Format version")."""
    fmt = d.get("format")
    if not isinstance(fmt, str) or not fmt.startswith("jaxcr."):
        return  # absent, or another tool's informational key
    kind, _, ver = fmt.partition("/")
    if kind != "jaxcr.calibration":
        raise InputError(
            f"a {kind} file, not a calibration (expected format {CALIBRATION_FORMAT})",
            file=file, field=prefix + "format",
        )  # fmt: skip
    if not ver.isdigit():
        raise InputError(
            f"unreadable format {fmt!r} (expected {CALIBRATION_FORMAT})",
            file=file, field=prefix + "format",
        )  # fmt: skip
    if int(ver) > CALIBRATION_FORMAT_VERSION:
        raise InputError(
            f"format {fmt} was written by a newer jaxcr; this version reads up to "
            f"{CALIBRATION_FORMAT} (upgrade jaxcr)",
            file=file, field=prefix + "format",
        )  # fmt: skip


def camera_from_dict(d: Mapping[str, Any], file: str | None = None, prefix: str = "") -> Camera:
    """Build a :class:`Camera` from a single-camera mapping (file or inline dataset entry).

    ``prefix`` is prepended to field names in error messages (e.g. ``"cameras.main."``).
    """
    if not isinstance(d, Mapping):
        raise InputError(
            "expected a mapping of camera fields", file=file, field=prefix.rstrip(".") or None
        )
    if "K1" in d or "M1" in d:
        raise InputError(
            "a stereo calibration (K1/M1 ...), expected a single-camera one (camera_matrix)",
            file=file,
            field=prefix.rstrip(".") or None,
        )
    check_known_keys(d, SINGLE_KEYS, file, prefix, informational=INFO_KEYS)
    scale = _unit_scale(d, file, prefix)
    kK, K = _get(d, ("camera_matrix", "K"), file, prefix)
    K = check_intrinsics(K, file, prefix + kK)
    kd, dist = _get(d, ("distortion_coefficients", "dist"), file, prefix, required=False)
    dist = np.zeros(5) if dist is None else check_distortion(dist, file, prefix + kd)
    w, h = _image_size(d, file, prefix)
    check_intrinsics_range(K, w, h, file, prefix + kK)
    check_distortion_range(dist, K, w, h, file, prefix + kd)
    T = d.get("T_cam_robot")
    T = np.eye(4) if T is None else check_transform(T, file, prefix + "T_cam_robot", scale)
    return camera_from_arrays(K, dist, T, w, h)


def load_camera(path: str | os.PathLike) -> Camera:
    """Read a single-camera calibration file (``.yaml``/``.yml``/``.xml``/``.json``)."""
    path = os.fspath(path)
    return camera_from_dict(read_raw(path), file=path)


def load_stereo(path: str | os.PathLike) -> tuple[Camera, Camera]:
    """Read a stereo calibration file into two cameras (second extrinsic composed, see module
    docstring)."""
    path = os.fspath(path)
    d = read_raw(path)
    if ("camera_matrix" in d or "K" in d) and not any(k in d for k in ("K1", "M1")):
        raise InputError(
            "a single-camera calibration (camera_matrix), expected a stereo one "
            "(K1 D1 K2 D2 R T, as saved after cv2.stereoCalibrate)",
            file=path,
        )
    check_known_keys(d, STEREO_KEYS, path, informational=INFO_KEYS)
    scale = _unit_scale(d, path, "")
    cams_intr = []
    for i in (1, 2):
        kK, K = _get(d, (f"K{i}", f"M{i}", f"camera_matrix_{i}"), path, "")
        K = check_intrinsics(K, path, kK)
        kd, D = _get(d, (f"D{i}", f"distortion_coefficients_{i}"), path, "", required=False)
        D = np.zeros(5) if D is None else check_distortion(D, path, kd)
        size = _image_size(d, path, "", suffix=f"_{i}")
        check_intrinsics_range(K, *size, path, kK)
        check_distortion_range(D, K, *size, path, kd)
        cams_intr.append((K, D, size))
    R = _matrix(
        d.get("R") if "R" in d else _missing(path, "R"), lambda s: s == (3, 3), "3x3", path, "R"
    )
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InputError("not a proper rotation matrix", file=path, field="R")
    t = _matrix(
        d.get("T") if "T" in d else _missing(path, "T"),
        lambda s: s in ((3,), (3, 1), (1, 3)),
        "3x1",
        path,
        "T",
    ).reshape(3)
    for key in ("E", "F"):
        if key in d and d[key] is not None:
            _matrix(d[key], lambda s: s == (3, 3), "3x3", path, key)
    if d.get("uncertainty") is not None:
        uncertainty_from_dict(d["uncertainty"], path, scale)
    T1 = d.get("T_cam_robot")
    T1 = np.eye(4) if T1 is None else check_transform(T1, path, "T_cam_robot", scale)
    T21 = np.eye(4)
    T21[:3, :3] = R
    T21[:3, 3] = t * scale
    check_length(float(np.linalg.norm(T21[:3, 3])), "stereo baseline |T|", scale, path, "T",
                 lo=MIN_BASELINE_M)  # fmt: skip
    T2 = T21 @ T1
    (K1, D1, s1), (K2, D2, s2) = cams_intr
    return (camera_from_arrays(K1, D1, T1, *s1), camera_from_arrays(K2, D2, T2, *s2))


def _std_value(v, file, field, hi: float, what: str) -> float:
    try:
        f = float(np.asarray(v, np.float64).reshape(()))
    except (TypeError, ValueError):
        raise InputError("expected a number", file=file, field=field) from None
    if not np.isfinite(f) or f < 0:
        raise InputError(f"expected a finite standard deviation >= 0, got {v!r}", file=file,
                         field=field)  # fmt: skip
    if f > hi:
        raise InputError(f"{f:g} is implausible ({what})", file=file, field=field)
    return f


def uncertainty_from_dict(block, file=None, file_scale: float = 1.0, prefix="uncertainty."):
    """The :class:`jaxcr.stereo.epipolar_tolerance.CalibrationUncertainty` of a stereo file's
    ``uncertainty`` block (module docstring); ``file_scale``: metres per unit of the file's
    ``unit`` (the block's own ``unit`` overrides it). InputError naming ``uncertainty.<key>``
    for a missing, unknown, non-finite, negative or implausible value."""
    from jaxcr.stereo.epipolar_tolerance import CalibrationUncertainty

    if not isinstance(block, Mapping):
        raise InputError("expected a map of standard deviations", file=file,
                         field=prefix.rstrip("."))  # fmt: skip
    check_known_keys(block, UNCERTAINTY_KEYS, file, prefix)
    scale = unit_scale(block, file, prefix) if "unit" in block else file_scale
    for k in ("focal_rel", "principal_px", "rotation_deg", "translation"):
        if block.get(k) is None:
            raise InputError("missing required key", file=file, field=prefix + k)
    focal = _std_value(block["focal_rel"], file, prefix + "focal_rel", MAX_FOCAL_REL,
                       f"a fraction of the focal length, at most {MAX_FOCAL_REL:g}; "
                       "0.002 is 0.2 %")  # fmt: skip
    principal = _std_value(block["principal_px"], file, prefix + "principal_px",
                           MAX_PRINCIPAL_PX, f"pixels, at most {MAX_PRINCIPAL_PX:g}")  # fmt: skip
    rot = _std_value(block["rotation_deg"], file, prefix + "rotation_deg", MAX_ROTATION_DEG,
                     f"degrees, at most {MAX_ROTATION_DEG:g}")  # fmt: skip
    trans = _std_value(block["translation"], file, prefix + "translation", np.inf, "")
    check_length(trans * scale, "translation standard deviation", scale, file,
                 prefix + "translation", hi=MAX_TRANSLATION_STD_M, typical=3e-4)  # fmt: skip
    for k, n in (("std_intrinsics_1", 9), ("std_intrinsics_2", 9), ("std_rotation_deg", 3),
                 ("std_translation", 3)):  # fmt: skip
        if block.get(k) is not None:
            a = _matrix(block[k], lambda s, n=n: int(np.prod(s)) == n, f"1x{n}", file, prefix + k)
            if np.any(a < 0):
                raise InputError("standard deviations must be >= 0", file=file, field=prefix + k)
    return CalibrationUncertainty(
        focal_rel=focal,
        principal_px=principal,
        rotation_rad=float(np.radians(rot) / np.sqrt(2.0)),
        translation_m=float(trans * scale / np.sqrt(2.0)),
    )


def load_stereo_uncertainty(path: str | os.PathLike):
    """The ``uncertainty`` block of a stereo calibration file as a
    :class:`jaxcr.stereo.epipolar_tolerance.CalibrationUncertainty`, or None when the file
    has none (module docstring)."""
    path = os.fspath(path)
    d = read_raw(path)
    if d.get("uncertainty") is None:
        return None
    return uncertainty_from_dict(d["uncertainty"], path, _unit_scale(d, path, ""))


#: ``--calibration-sigma``'s keys: the block's, with the translation's unit in its name.
SIGMA_FLAG_KEYS = ("focal_rel", "principal_px", "rotation_deg", "translation_m",
                   "translation_cm", "translation_mm")  # fmt: skip


def parse_calibration_sigma(text: str, flag: str = "--calibration-sigma"):
    """``jaxcr stereo --calibration-sigma``'s value: ``none`` (None), or
    ``focal_rel=F,principal_px=P,rotation_deg=A,translation_mm=T`` (``translation_m`` or
    ``_cm`` also; every key once, all four given; the same meaning as a calibration file's
    ``uncertainty`` block) as a :class:`jaxcr.stereo.epipolar_tolerance.CalibrationUncertainty`.
    InputError naming ``--calibration-sigma.<key>`` otherwise."""
    if text.strip().lower() == "none":
        return None
    block: dict[str, Any] = {}
    for item in text.split(","):
        key, eq, value = (x.strip() for x in item.partition("="))
        if not eq:
            raise InputError(f"expected key=value, got {item.strip()!r} (or 'none')",
                             field=flag)  # fmt: skip
        if key not in SIGMA_FLAG_KEYS:
            near = nearest_key(key, SIGMA_FLAG_KEYS)
            hint = (
                f" (did you mean {near!r}?)" if near else f" (known: {', '.join(SIGMA_FLAG_KEYS)})"
            )
            raise InputError(f"unknown key {key!r}{hint}", field=f"{flag}.{key}")
        name = "translation" if key.startswith("translation_") else key
        if name in block:
            raise InputError("given twice", field=f"{flag}.{key}")
        try:
            block[name] = float(value)
        except ValueError:
            raise InputError(f"expected a number, got {value!r}", field=f"{flag}.{key}") from None
        if name == "translation":
            block["unit"] = key.split("_", 1)[1]
    missing = [k for k in ("focal_rel", "principal_px", "rotation_deg") if k not in block]
    missing += [] if "translation" in block else ["translation_mm"]
    if missing:
        raise InputError(f"missing {', '.join(missing)}", field=f"{flag}.{missing[0]}")
    try:
        return uncertainty_from_dict(block, None, 1.0, prefix="")
    except InputError as err:
        field = err.field if err.field != "translation" else f"translation_{block['unit']}"
        raise InputError(err.message, field=f"{flag}.{field}") from None


#: Keys of a dataset camera entry that takes one camera of a stereo calibration file.
STEREO_ENTRY_KEYS = ("stereo", "camera", "T_rig_robot", "unit")


def camera_from_stereo_entry(
    d: Mapping[str, Any], root: str | os.PathLike, file: str | None = None, prefix: str = ""
) -> Camera:
    """One camera of a stereo calibration file, for a dataset camera entry
    ``{"stereo": "calib/stereo.yaml", "camera": 1 | 2, "T_rig_robot": 4x4, "unit": "m"}``.

    ``stereo`` is relative to ``root`` (the dataset folder). Intrinsics, distortion and size are
    camera ``camera``'s; its pose is the file's (camera 2: ``[R | T] @ T_cam_robot`` of the file,
    see :func:`load_stereo`) composed with ``T_rig_robot`` (the robot frame -> the file's
    robot frame, i.e. camera 1's frame when the file has no ``T_cam_robot``; default identity;
    its translation in the entry's ``unit``). Both cameras of a rig normally carry the same
    ``T_rig_robot`` (``jaxcr fit --fit-pose --frame`` updates every entry alike).
    """
    from jaxcr.io.units import check_known_keys

    check_known_keys(d, STEREO_ENTRY_KEYS, file, prefix)
    rel = d.get("stereo")
    if not isinstance(rel, str) or not rel:
        raise InputError(
            "expected the stereo calibration file's path", file, field=prefix + "stereo"
        )
    path = os.path.join(os.fspath(root), rel)
    if not os.path.exists(path):
        raise InputError(f"stereo calibration file not found: {rel}", file, field=prefix + "stereo")
    which = d.get("camera")
    if isinstance(which, bool) or which not in (1, 2):
        raise InputError(
            f"expected 1 or 2 (which camera of the stereo file), got {which!r}",
            file,
            field=prefix + "camera",
        )
    scale = _unit_scale(d, file, prefix)
    cam = load_stereo(path)[which - 1]
    T = d.get("T_rig_robot")
    if T is None:
        return cam
    T = check_transform(T, file, prefix + "T_rig_robot", scale)
    return camera_from_arrays(
        np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
        np.asarray(cam.T_cam_robot, np.float64) @ T,
        cam.width,
        cam.height,
    )


def _missing(file, field):
    raise InputError("missing required key", file=file, field=field)


# --------------------------------------------------------------------------------- writing


def _json_floats(a) -> list:
    """Nested lists of floats; float32 values are written with their shortest round-trip
    decimal (0.03, not 0.029999999329447746)."""
    a = np.asarray(a)
    if a.dtype == np.float32:
        return np.vectorize(lambda x: float(str(x)), otypes=[np.float64])(a).tolist()
    return a.astype(np.float64).tolist()


def camera_to_dict(camera: Camera) -> dict[str, Any]:
    """JSON-ready inline description (the dataset.json ``cameras.<name>`` form)."""
    return {
        "K": _json_floats(camera.K),
        "dist": _json_floats(camera.dist),
        "size": [int(camera.width), int(camera.height)],
        "T_cam_robot": _json_floats(camera.T_cam_robot),
    }


def _write_fs(path: str, entries: dict[str, Any]) -> None:
    ext = os.path.splitext(path)[1]
    tmp = f"{path}.tmp{os.getpid()}{ext}"  # FileStorage picks the format from the extension
    fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
    try:
        for k, v in entries.items():
            if isinstance(v, Mapping):  # a nested map (the uncertainty block)
                fs.startWriteStruct(k, cv2.FileNode_MAP)
                for k2, v2 in v.items():
                    fs.write(k2, v2)
                fs.endWriteStruct()
            else:
                fs.write(k, v)
    finally:
        fs.release()
    os.replace(tmp, path)


def _write_entries(path: str, entries: dict) -> None:
    """Write calibration ``entries`` atomically, the format from the extension: YAML/XML via
    ``cv2.FileStorage``, or JSON with the same key names."""
    if path.lower().endswith(_FS_EXT):
        _write_fs(path, entries)
    elif path.lower().endswith(".json"):

        def plain(v):
            if isinstance(v, Mapping):
                return {k: plain(x) for k, x in v.items()}
            return v.tolist() if isinstance(v, np.ndarray) else v

        js = {k: plain(v) for k, v in entries.items()}
        atomic_write_text(path, json.dumps(js, indent=2) + "\n")
    else:
        raise InputError(
            "unknown calibration file type (expected .yaml, .yml, .xml or .json)", file=path
        )


def save_camera(camera: Camera, path: str | os.PathLike) -> None:
    """Write a single-camera file; format from the extension (YAML/XML via
    ``cv2.FileStorage``, or JSON with the FileStorage key names). Atomic."""
    path = os.fspath(path)
    entries = {
        "camera_matrix": np.asarray(camera.K, np.float64),
        "distortion_coefficients": np.asarray(camera.dist, np.float64).reshape(1, 5),
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "T_cam_robot": np.asarray(camera.T_cam_robot, np.float64),
        "unit": "m",
        "format": CALIBRATION_FORMAT,
    }
    _write_entries(path, entries)


def save_stereo(cam1: Camera, cam2: Camera, path: str | os.PathLike) -> None:
    """Write a stereo file in the layout :func:`load_stereo` reads (R, T between the two
    cameras, plus E = [T]x R and F = K2^-T E K1^-1 as cv2.stereoCalibrate reports them)."""
    _write_entries(os.fspath(path), _stereo_entries(cam1, cam2))


def _stereo_entries(cam1: Camera, cam2: Camera) -> dict[str, Any]:
    T1 = np.asarray(cam1.T_cam_robot, np.float64)
    T2 = np.asarray(cam2.T_cam_robot, np.float64)
    T21 = T2 @ np.linalg.inv(T1)
    R, t = T21[:3, :3], T21[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    K1 = np.asarray(cam1.K, np.float64)
    K2 = np.asarray(cam2.K, np.float64)
    F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
    entries = {
        "K1": K1,
        "D1": np.asarray(cam1.dist, np.float64).reshape(1, 5),
        "K2": K2,
        "D2": np.asarray(cam2.dist, np.float64).reshape(1, 5),
        "image_width_1": int(cam1.width),
        "image_height_1": int(cam1.height),
        "image_width_2": int(cam2.width),
        "image_height_2": int(cam2.height),
        "R": R,
        "T": t.reshape(3, 1),
        "E": E,
        "F": F,
        "T_cam_robot": T1,
        "unit": "m",
        "format": CALIBRATION_FORMAT,
    }
    return entries


def save_calibration(res: dict, path: str) -> None:
    """Write the result of :func:`jaxcr.stereo.calibration.calibrate_stereo` (``K1 D1 K2 D2 R T
    size1 size2 rms_1 rms_2 rms_stereo``, optionally ``cal1 cal2 per_view_rms_stereo flags``)
    with :func:`save_stereo`, then append the RMS values and the per-view report.

    Atomic: the file is assembled under a temporary name in the destination folder (same
    suffix, which selects the format) and renamed over ``path`` only when complete, so an
    interrupted or failed write never leaves a truncated calibration (or one without RMS)."""
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=dest.suffix, dir=dest.parent)
    os.close(fd)
    try:
        _write_calibration(res, tmp)
        atomic_write_bytes(dest, Path(tmp).read_bytes())
    finally:
        Path(tmp).unlink(missing_ok=True)


def _write_calibration(res: dict, path: str) -> None:
    T2 = np.eye(4)
    T2[:3, :3] = res["R"]
    T2[:3, 3] = res["T"]
    c1 = camera_from_arrays(res["K1"], res["D1"], np.eye(4), *res["size1"])
    c2 = camera_from_arrays(res["K2"], res["D2"], T2, *res["size2"])
    entries = _stereo_entries(c1, c2)
    extra = {k: res[k] for k in ("rms_1", "rms_2", "rms_stereo")}
    if "cal1" in res:  # per-view report (absent in hand-made result dicts)
        pv = np.asarray(res["per_view_rms_stereo"], np.float64)
        extra["per_view_rms_stereo"] = np.sqrt(np.mean(pv**2, axis=1)).reshape(1, -1)
        for i in (1, 2):
            cal = res[f"cal{i}"]
            extra[f"per_view_rms_{i}"] = cal.per_view_rms.reshape(1, -1)
            extra[f"tilt_deg_{i}"] = cal.tilt_deg.reshape(1, -1)
            extra[f"distance_{i}"] = cal.distance.reshape(1, -1)
            extra[f"coverage_{i}"] = float(cal.coverage)
    if "flags" in res:
        extra["calibrate_flags"] = res["flags"]
    block = uncertainty_block(res)
    if block is not None:
        extra["uncertainty"] = block
    # one document (an appended FileStorage document is invisible to read_filestorage)
    _write_entries(path, {**entries, **extra})


def uncertainty_block(res: dict) -> dict[str, Any] | None:
    """The ``uncertainty`` block (module docstring, ``unit: m``) of a
    :func:`jaxcr.stereo.calibration.calibrate_stereo` result: OpenCV's
    ``stdDeviationsIntrinsics`` of each camera and the stereo fit's ``R``, ``T`` deviations,
    summarised; None when the result carries none, or a deviation is not finite or beyond
    the reader's plausible range (:func:`uncertainty_from_dict`)."""
    cals = [res.get("cal1"), res.get("cal2")]
    if any(c is None or getattr(c, "std_intrinsics_cv", None) is None for c in cals):
        return None
    if res.get("std_R_rad") is None or res.get("std_T") is None:
        return None
    std_i = [np.asarray(c.std_intrinsics_cv, np.float64).reshape(9) for c in cals]
    Ks = [np.asarray(res[f"K{i}"], np.float64) for i in (1, 2)]
    rot = np.degrees(np.asarray(res["std_R_rad"], np.float64).reshape(3))
    trans = np.asarray(res["std_T"], np.float64).reshape(3)
    if not all(np.all(np.isfinite(a)) for a in (*std_i, rot, trans)):
        return None
    focal = max(max(s[0] / K[0, 0], s[1] / K[1, 1]) for s, K in zip(std_i, Ks, strict=True))
    block = {
        "focal_rel": float(focal),
        "principal_px": float(max(np.max(s[2:4]) for s in std_i)),
        "rotation_deg": float(np.max(rot)),
        "translation": float(np.max(trans)),
        "unit": "m",
        "std_intrinsics_1": std_i[0].reshape(1, 9),
        "std_intrinsics_2": std_i[1].reshape(1, 9),
        "std_rotation_deg": rot.reshape(1, 3),
        "std_translation": trans.reshape(1, 3),
    }
    try:  # never write a block the reader refuses (e.g. --max-std raised past 10 % of f)
        uncertainty_from_dict(block)
    except InputError:
        return None
    return block
