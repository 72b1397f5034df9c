"""``jaxcr calibrate LEFT RIGHT -o stereo.yaml``: stereo calibration from chessboard or
circle-grid image pairs with OpenCV, written as an OpenCV FileStorage stereo file
(``K1 D1 K2 D2 R T E F`` and image sizes, the layout :func:`jaxcr.io.calibration.load_stereo`
reads) plus the RMS reprojection errors ``rms_1``, ``rms_2`` (each camera alone,
``cv2.calibrateCamera``) and ``rms_stereo`` (``cv2.stereoCalibrate`` with the intrinsics
fixed), in pixels.

LEFT and RIGHT are folders (all ``*.png``/``*.jpg`` files, paired by sorted name) or glob
patterns. ``--pattern chessboard`` uses ``--cols x --rows`` inner corners
(``cv2.findChessboardCornersSB``); ``circles``/``acircles`` a symmetric/asymmetric circle
grid (``cv2.findCirclesGrid``). ``--square`` is the corner (or circle) spacing in metres.
Pairs where the pattern is not found in both images are skipped and listed; at least 3
usable pairs are required. Exit 0 on success, 1 if calibration failed (too few pairs,
stereo RMS above ``--max-rms``, or a radial distortion that is not monotone over the image,
which the calibration loaders refuse), 2 on bad input.
"""

from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path

import cv2
import numpy as np

from jaxcr.errors import InputError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="stereo calibration from chessboard / circle-grid image pairs (OpenCV)",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("left", help="folder or glob of camera-1 images")
    p.add_argument("right", help="folder or glob of camera-2 images")
    p.add_argument("-o", "--out", required=True, help="output .yaml/.yml/.xml/.json")
    p.add_argument("--pattern", choices=["chessboard", "circles", "acircles"], default="chessboard")
    p.add_argument("--cols", type=int, required=True, help="inner corners (circles) per row")
    p.add_argument("--rows", type=int, required=True, help="inner corners (circles) per column")
    p.add_argument("--square", type=float, required=True, help="spacing in metres")
    p.add_argument("--max-rms", type=float, default=2.0,
                   help="fail (exit 1) when the stereo RMS exceeds this (px, default %(default)s)")  # fmt: skip
    p.set_defaults(func=run)


def _list_images(spec: str) -> list[str]:
    if os.path.isdir(spec):
        files = [
            str(f)
            for f in sorted(Path(spec).iterdir())
            if f.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
        ]
    else:
        files = sorted(glob.glob(spec))
    if not files:
        raise InputError("no images found", file=spec)
    return files


def board_points(pattern: str, cols: int, rows: int, square: float) -> np.ndarray:
    """(cols*rows, 3) object points of the calibration target (z = 0, metres), in the order
    OpenCV's detectors return them."""
    if pattern == "acircles":
        pts = [
            ((2 * c + r % 2) * square, r * square, 0.0) for r in range(rows) for c in range(cols)
        ]
        return np.array(pts, np.float32)
    g = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    return np.c_[g * square, np.zeros(len(g))].astype(np.float32)


def find_pattern(gray: np.ndarray, pattern: str, cols: int, rows: int) -> np.ndarray | None:
    """Sub-pixel image points (n, 2) of the target, or None when it is not found."""
    if pattern == "chessboard":
        ok, c = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
    else:
        flag = cv2.CALIB_CB_SYMMETRIC_GRID if pattern == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        ok, c = cv2.findCirclesGrid(gray, (cols, rows), flags=flag)
    return c.reshape(-1, 2).astype(np.float32) if ok else None


def calibrate_stereo(
    left: list[np.ndarray],
    right: list[np.ndarray],
    pattern: str,
    cols: int,
    rows: int,
    square: float,
) -> dict:
    """Calibrate from grayscale image pairs; returns ``K1 D1 K2 D2 R T size1 size2 rms_1
    rms_2 rms_stereo used`` (indices of the pairs used). Raises ``ValueError`` with fewer
    than 3 usable pairs."""
    obj = board_points(pattern, cols, rows, square)
    o, p1, p2, used = [], [], [], []
    for k, (a, b) in enumerate(zip(left, right, strict=True)):
        ca = find_pattern(a, pattern, cols, rows)
        cb = find_pattern(b, pattern, cols, rows)
        if ca is not None and cb is not None:
            o.append(obj)
            p1.append(ca)
            p2.append(cb)
            used.append(k)
    if len(used) < 3:
        raise ValueError(f"the pattern was found in only {len(used)} image pairs (need >= 3)")
    s1 = (left[0].shape[1], left[0].shape[0])
    s2 = (right[0].shape[1], right[0].shape[0])
    rms1, K1, D1, _, _ = cv2.calibrateCamera(o, p1, s1, None, None)
    rms2, K2, D2, _, _ = cv2.calibrateCamera(o, p2, s2, None, None)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        o, p1, p2, K1, D1, K2, D2, s1, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit
    )
    return {"K1": K1, "D1": D1.ravel()[:5], "K2": K2, "D2": D2.ravel()[:5], "R": R, "T": T.ravel(),
            "size1": s1, "size2": s2, "rms_1": float(rms1), "rms_2": float(rms2),
            "rms_stereo": float(rms), "used": used}  # fmt: skip


def save_calibration(res: dict, path: str) -> None:
    """Write with :func:`jaxcr.io.calibration.save_stereo`, then append the RMS values.

    Atomic: the file is assembled under a temporary name in the destination folder (same
    suffix, which selects the format) and renamed over ``path`` only when complete, so an
    interrupted or failed write never leaves a truncated calibration (or one without RMS)."""
    import tempfile

    from jaxcr.io.results import atomic_write_bytes

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
    from jaxcr.camera import camera_from_arrays
    from jaxcr.io.calibration import save_stereo

    T2 = np.eye(4)
    T2[:3, :3] = res["R"]
    T2[:3, 3] = res["T"]
    c1 = camera_from_arrays(res["K1"], res["D1"], np.eye(4), *res["size1"])
    c2 = camera_from_arrays(res["K2"], res["D2"], T2, *res["size2"])
    save_stereo(c1, c2, path)
    if path.lower().endswith((".yaml", ".yml", ".xml")):
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_APPEND)
        for k in ("rms_1", "rms_2", "rms_stereo"):
            fs.write(k, res[k])
        fs.release()
    else:
        import json

        d = json.loads(Path(path).read_text())
        d.update({k: res[k] for k in ("rms_1", "rms_2", "rms_stereo")})
        Path(path).write_text(json.dumps(d, indent=2) + "\n")


def run(args) -> int:
    if args.cols < 2 or args.rows < 2:
        raise InputError("--cols and --rows must be >= 2")
    if not args.square > 0:
        raise InputError("--square must be > 0 (metres)")
    if not args.out.lower().endswith((".yaml", ".yml", ".xml", ".json")):
        raise InputError("output must end in .yaml, .yml, .xml or .json", file=args.out)
    lf, rf = _list_images(args.left), _list_images(args.right)
    if len(lf) != len(rf):
        raise InputError(f"{len(lf)} left but {len(rf)} right images")
    from jaxcr.io.images import read_raw

    # checked reader: names the file, never decodes a header declaring > MAX_PIXELS pixels
    imgs = [read_raw(f, cv2.IMREAD_GRAYSCALE) for f in lf + rf]
    left, right = imgs[: len(lf)], imgs[len(lf) :]
    for files, ims in ((lf, left), (rf, right)):
        for f, im in zip(files, ims, strict=True):
            if im.shape != ims[0].shape:
                raise InputError(
                    f"image size {im.shape[1]}x{im.shape[0]} differs from "
                    f"{ims[0].shape[1]}x{ims[0].shape[0]} of {files[0]} (one camera, one size)",
                    file=f,
                )
    try:
        res = calibrate_stereo(left, right, args.pattern, args.cols, args.rows, args.square)
    except ValueError as err:
        print(f"jaxcr calibrate: {err}")
        return 1
    if not res["rms_stereo"] <= args.max_rms:
        print(f"jaxcr calibrate: stereo RMS {res['rms_stereo']:.3f} px exceeds --max-rms "
              f"{args.max_rms}; nothing written (wrong pattern size?)")  # fmt: skip
        return 1
    from jaxcr.io.calibration import check_distortion_range

    try:  # the loaders refuse such a file, so it is not written
        for i in (1, 2):
            check_distortion_range(res[f"D{i}"], res[f"K{i}"], *res[f"size{i}"], field=f"D{i}")
    except InputError as err:
        print(f"jaxcr calibrate: {err.format()}; nothing written (too few pattern views "
              "near the image corners?)")  # fmt: skip
        return 1
    save_calibration(res, args.out)
    skipped = sorted(set(range(len(lf))) - set(res["used"]))
    print(f"used {len(res['used'])} of {len(lf)} pairs; RMS reprojection error: camera 1 "
          f"{res['rms_1']:.3f} px, camera 2 {res['rms_2']:.3f} px, stereo {res['rms_stereo']:.3f} px")  # fmt: skip
    for k in skipped:
        print(f"  skipped (pattern not found): {lf[k]} / {rf[k]}")
    print(f"wrote {args.out}")
    return 0
