"""``jaxcr calibrate LEFT RIGHT -o stereo.yaml``: stereo calibration from chessboard or
circle-grid image pairs with OpenCV, written as an OpenCV FileStorage stereo file
(``K1 D1 K2 D2 R T E F`` and image sizes, the layout :func:`jaxcr.io.calibration.load_stereo`
reads, ``unit: m``) plus the RMS reprojection errors ``rms_1``, ``rms_2`` (each camera
alone, ``cv2.calibrateCamera``) and ``rms_stereo`` (``cv2.stereoCalibrate`` with the
intrinsics fixed), per pair ``per_view_rms_1/_2/_stereo``, board tilts ``tilt_deg_1/_2``,
distances ``distance_1/_2``, coverages ``coverage_1/_2``, ``calibrate_flags`` and the
``uncertainty`` block: the standard deviations of each camera's intrinsics
(``cv2.calibrateCameraExtended``'s stdDeviationsIntrinsics) and of the stereo fit's R and T,
which ``jaxcr stereo --segmentation trace`` uses for the tips (docs/stereo-format.md, "The
calibration's uncertainty").

Inputs. LEFT and RIGHT are folders (all ``*.png``/``*.jpg`` files, paired by sorted name) or
glob patterns, not the same images. ``--pattern chessboard`` uses ``--cols x --rows`` inner
corners (``cv2.findChessboardCornersSB``); ``circles``/``acircles`` a symmetric/asymmetric
circle grid (``cv2.findCirclesGrid``), ``--cols`` circles per row, ``--rows`` rows. Pairs
where the pattern is not found in both images are skipped and listed.

Spacing: give ``--pitch`` (or the older ``--square``), in metres.
  chessboard, circles: pitch = square = distance between neighbouring corners / circle
    centres.
  acircles: pitch = distance between neighbouring circle centres IN ONE ROW; rows are
    pitch/2 apart and every other row is shifted by pitch/2. ``--square`` is HALF the pitch
    (OpenCV's convention). Worked example: OpenCV's acircles_pattern.png (4 x 11) printed with
    40 mm between circle centres along a row: --pattern acircles --cols 4 --rows 11
    --pitch 0.04 (same as --square 0.02). Passing the row pitch as --square scales the whole
    rig (baseline, distances) by 2.

Fitting fewer intrinsics (OpenCV's CALIB_* flags, applied to each camera's
cv2.calibrateCamera; the stereo step keeps the intrinsics fixed):
  --fix-principal-point  CALIB_FIX_PRINCIPAL_POINT: cx, cy stay at the image centre
                         ((w-1)/2, (h-1)/2).
  --fix-aspect-ratio     CALIB_FIX_ASPECT_RATIO: fx = fy (square pixels), one focal length.
  --zero-tangent-dist    CALIB_ZERO_TANGENT_DIST: p1 = p2 = 0.
  --fix-k1/--fix-k2/--fix-k3  CALIB_FIX_K1..K3: that radial coefficient stays 0.
  --no-distortion        all five coefficients 0 (ZERO_TANGENT_DIST | FIX_K1 | FIX_K2 | FIX_K3).
On a rig with one or two board poses, --fix-principal-point --fix-aspect-ratio
--no-distortion (one focal length per camera) is the fit the views can carry.

Are the intrinsics determined? Each board orientation gives two constraints on the
pinhole intrinsics (Zhang 2000), so free fx, fy, cx, cy (or f, cx, cy) need the board in at
least 2 distinct orientations (normals > 5 deg apart), fx, fy or f alone 1. And after each
camera's fit, the predicted 1-sigma of every fitted intrinsic is computed from the fit's
Jacobian (cv2.projectPoints), marginalised over the board poses, at the detection noise the
fit shows (never below 0.1 px). The calibration is refused (exit 1, nothing written, with
the reason and what to do) when the orientations are too few, a focal length's 1-sigma
exceeds --max-std of itself, or the principal point's exceeds --max-std of the image's
larger side (a single board pose with free fx, fy, cx, cy; boards all facing the camera,
which leave the focal length free). It warns (WARNING lines, exit 0) above a fifth
of those limits, and when a ray's pixel at the image corners is uncertain by more than a
fifth of --max-std of the half-diagonal (distortion extrapolated outside the board's
coverage). The output lists per pair the RMS reprojection error of each camera and of the
stereo fit and the board's tilt (angle of its normal to the optical axis) and distance, and
per camera the number of distinct board orientations (normals > 5 deg apart), the tilt and
distance ranges and the fraction of the image the board covered.

Background plates. --plate-left/--plate-right: an image of the scene without the robot, for
a board the robot crosses. In a view where the pattern is not found, the pixels differing
from the plate by more than --plate-threshold grey levels (grown by 3 px) are replaced by the
plate's and the detection is retried (the board must not have moved).

Exit 0 on success, 1 if calibration failed (no usable pair, intrinsics not determined by the
views, stereo RMS above --max-rms, a baseline under 1 mm, or a radial distortion that is not
monotone over the image, which the calibration loaders refuse), 2 on bad input.
"""

from __future__ import annotations

import argparse
import glob
import os
from pathlib import Path

import cv2
import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.calibration import save_calibration
from jaxcr.stereo.calibration import (  # noqa: F401  (re-exported for older callers)
    MAX_STD,
    CameraCalibration,
    IntrinsicConstraints,
    advice,
    board_points,
    calibrate_camera,
    calibrate_stereo,
    fill_from_plate,
    find_pattern,
    identifiability_problems,
    initial_camera_matrix,
    views_summary,
)


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
    p.add_argument(
        "--cols",
        type=int,
        required=True,
        help="inner corners per row (chessboard), circles per row (circle grids)",
    )
    p.add_argument(
        "--rows",
        type=int,
        required=True,
        help="inner corners per column (chessboard), rows of circles (circle grids)",
    )
    sp = p.add_mutually_exclusive_group(required=True)
    sp.add_argument(
        "--pitch",
        type=float,
        default=None,
        help="metres between neighbouring corners / circle centres; for acircles "
        "between neighbours in one row (see Spacing below)",
    )
    sp.add_argument(
        "--square",
        type=float,
        default=None,
        help="OpenCV's spacing in metres: the pitch, but HALF the row pitch for acircles",
    )
    p.add_argument(
        "--fix-principal-point",
        action="store_true",
        help="CALIB_FIX_PRINCIPAL_POINT: keep cx, cy at the image centre",
    )
    p.add_argument(
        "--fix-aspect-ratio",
        action="store_true",
        help="CALIB_FIX_ASPECT_RATIO: fit one focal length (fx = fy)",
    )
    p.add_argument(
        "--zero-tangent-dist", action="store_true", help="CALIB_ZERO_TANGENT_DIST: p1 = p2 = 0"
    )
    for k in (1, 2, 3):
        p.add_argument(f"--fix-k{k}", action="store_true", help=f"CALIB_FIX_K{k}: k{k} = 0")
    p.add_argument(
        "--no-distortion", action="store_true", help="no lens distortion: all five coefficients 0"
    )
    p.add_argument(
        "--max-std",
        type=float,
        default=MAX_STD,
        help="refuse (exit 1) when a fitted focal length's predicted 1-sigma exceeds "
        "this fraction of itself, or the principal point's this fraction of "
        "the image's larger side (default %(default)s); warn above a fifth",
    )
    p.add_argument(
        "--max-rms",
        type=float,
        default=2.0,
        help="fail (exit 1) when the stereo RMS exceeds this (px, default %(default)s)",
    )
    p.add_argument(
        "--plate-left",
        default=None,
        help="camera-1 background plate (scene without the robot), see below",
    )
    p.add_argument("--plate-right", default=None, help="camera-2 background plate")
    p.add_argument(
        "--plate-threshold",
        type=float,
        default=40.0,
        help="grey levels (0-255) by which a robot pixel differs from the plate "
        "(default %(default)s)",
    )
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


def spacing_from_args(pattern: str, pitch: float | None, square: float | None) -> float:
    """OpenCV's ``square`` (metres) from ``--pitch`` or ``--square`` (see Spacing in the
    module docstring): equal for chessboards and symmetric grids, half the row pitch for
    acircles."""
    value, name = (pitch, "--pitch") if pitch is not None else (square, "--square")
    if value is None or not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a finite number > 0 (metres), got {value}")
    if pitch is not None and pattern == "acircles":
        return pitch / 2.0
    return value


def constraints_from_args(args) -> IntrinsicConstraints:
    return IntrinsicConstraints(
        fix_principal_point=args.fix_principal_point,
        fix_aspect_ratio=args.fix_aspect_ratio,
        zero_tangent_dist=args.zero_tangent_dist,
        fix_k=tuple(k for k in (1, 2, 3) if getattr(args, f"fix_k{k}")),
        no_distortion=args.no_distortion,
    )


def _print_report(res: dict, lf: list[str], rf: list[str]) -> None:
    """Per pair: file names, RMS of camera 1, 2 and stereo (px), board tilt (deg) and
    distance (m) in each camera; then per camera the intrinsics with their 1-sigma and the
    spread of the views."""
    c1, c2 = res["cal1"], res["cal2"]
    print("pair  rms_1  rms_2  rms_stereo  tilt_1  tilt_2  dist_1  dist_2  images")
    for j, k in enumerate(res["used"]):
        st = float(np.sqrt(np.mean(res["per_view_rms_stereo"][j] ** 2)))
        mark = " (board found after filling from the plate)" if k in res["via_plate"] else ""
        print(f"{k:4d}  {c1.per_view_rms[j]:5.3f}  {c2.per_view_rms[j]:5.3f}  {st:10.3f}  "
              f"{c1.tilt_deg[j]:6.1f}  {c2.tilt_deg[j]:6.1f}  {c1.distance[j]:6.3f}  "
              f"{c2.distance[j]:6.3f}  {Path(lf[k]).name} / {Path(rf[k]).name}{mark}")  # fmt: skip
    for i, cal in ((1, c1), (2, c2)):
        sd = ", ".join(f"{n} +- {v:.3g}" for n, v in cal.std.items())
        print(f"camera {i}: fx {cal.K[0, 0]:.2f}, fy {cal.K[1, 1]:.2f}, cx {cal.K[0, 2]:.2f}, "
              f"cy {cal.K[1, 2]:.2f} px; 1-sigma at {cal.sigma_px:.2f} px noise: {sd}")  # fmt: skip
        print(f"camera {i} views: {views_summary(cal)}")


def run(args) -> int:
    if args.cols < 2 or args.rows < 2:
        raise InputError("--cols and --rows must be >= 2")
    from jaxcr.limits import MAX_SIDE, check_count

    # a ceiling (the audit, experiments/contract_audit.py item 3: --cols 100000 ran the
    # detection): a board square spans >= 4 px for OpenCV's detectors, so at most
    # MAX_SIDE / 4 squares (one more than the corners) fit the largest image
    for flag, v in (("cols", args.cols), ("rows", args.rows)):
        check_count(v, flag, 2, MAX_SIDE // 4 - 1, "a square of at least 4 px in 8192 px")
    square = spacing_from_args(args.pattern, args.pitch, args.square)
    for name, v in (("--max-rms", args.max_rms), ("--max-std", args.max_std),
                    ("--plate-threshold", args.plate_threshold)):  # fmt: skip
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a finite number > 0, got {v}")
    if not args.out.lower().endswith((".yaml", ".yml", ".xml", ".json")):
        raise InputError("output must end in .yaml, .yml, .xml or .json", file=args.out)
    lf, rf = _list_images(args.left), _list_images(args.right)
    if [os.path.realpath(f) for f in lf] == [os.path.realpath(f) for f in rf]:
        raise InputError(
            "LEFT and RIGHT are the same images; a stereo calibration needs one folder per camera",
            file=args.right,
        )
    if len(lf) != len(rf):
        raise InputError(f"{len(lf)} left but {len(rf)} right images")
    from jaxcr.cli._common import check_writable_folder

    # before the detection and the fit (the audit, experiments/contract_audit.py item 6)
    check_writable_folder(os.path.dirname(os.path.abspath(args.out)), "output folder")
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
    plates = []
    for path, ims in ((args.plate_left, left), (args.plate_right, right)):
        plate = None if path is None else read_raw(path, cv2.IMREAD_GRAYSCALE)
        if plate is not None and plate.shape != ims[0].shape:
            raise InputError(
                f"plate is {plate.shape[1]}x{plate.shape[0]}, the images "
                f"{ims[0].shape[1]}x{ims[0].shape[0]}",
                file=path,
            )
        plates.append(plate)
    constraints = constraints_from_args(args)
    try:
        res = calibrate_stereo(left, right, args.pattern, args.cols, args.rows, square,
                               constraints, tuple(plates), args.plate_threshold)  # fmt: skip
    except ValueError as err:
        print(f"jaxcr calibrate: {err}")
        return 1
    # (a result dict without the per-camera fits, e.g. from a caller's own calibrate_stereo,
    # is written after the remaining checks)
    has_fits = "cal1" in res and "cal2" in res
    if has_fits:
        _print_report(res, lf, rf)
    refused = False
    for i in (1, 2) if has_fits else ():
        cal = res[f"cal{i}"]
        bad, weak = identifiability_problems(cal, args.max_std)
        for w in weak:
            print(f"WARNING: camera {i}: weakly determined: {w} ({views_summary(cal)}; "
                  f"{advice(cal)})")  # fmt: skip
        if bad:
            refused = True
            print(f"jaxcr calibrate: camera {i}: the views do not determine the intrinsics "
                  f"being fitted: {'; '.join(bad)} (over --max-std {args.max_std:g}); "
                  f"{views_summary(cal)}. To fix: {advice(cal)}. Nothing written")  # fmt: skip
    if refused:
        return 1
    if not res["rms_stereo"] <= args.max_rms:
        print(f"jaxcr calibrate: stereo RMS {res['rms_stereo']:.3f} px exceeds --max-rms "
              f"{args.max_rms}; nothing written (wrong pattern size?)")  # fmt: skip
        return 1
    from jaxcr.io.calibration import check_distortion_range
    from jaxcr.io.units import MIN_BASELINE_M

    baseline = float(np.linalg.norm(res["T"]))
    if not baseline >= MIN_BASELINE_M:
        print(f"jaxcr calibrate: the baseline is {baseline * 1e3:.3g} mm (under "
              f"{MIN_BASELINE_M * 1e3:g} mm): LEFT and RIGHT look like one camera; "
              "nothing written")  # fmt: skip
        return 1
    try:  # the loaders refuse such a file, so it is not written
        for i in (1, 2):
            check_distortion_range(res[f"D{i}"], res[f"K{i}"], *res[f"size{i}"], field=f"D{i}")
    except InputError as err:
        print(f"jaxcr calibrate: {err.format()}; nothing written (too few pattern views "
              "near the image corners?)")  # fmt: skip
        return 1
    res["flags"] = constraints.describe()
    save_calibration(res, args.out)
    from jaxcr.io.calibration import uncertainty_block

    if has_fits and uncertainty_block(res) is None:
        print("WARNING: no 'uncertainty' block written (a standard deviation is not finite "
              "or implausibly large): jaxcr stereo will use the fixed 5 px for the tips "
              "unless given --calibration-sigma")  # fmt: skip
    skipped = sorted(set(range(len(lf))) - set(res["used"]))
    print(f"used {len(res['used'])} of {len(lf)} pairs (intrinsic constraints: "
          f"{res['flags']}); RMS reprojection error: camera 1 {res['rms_1']:.3f} px, "
          f"camera 2 {res['rms_2']:.3f} px, stereo {res['rms_stereo']:.3f} px")  # fmt: skip
    for k in skipped:
        print(f"  skipped (pattern not found): {lf[k]} / {rf[k]}")
    print(f"wrote {args.out}")
    return 0
