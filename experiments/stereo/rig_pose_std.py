"""Is the stereo fit's predicted 1-sigma of R and T (``jaxcr.stereo.calibration.
stereo_pose_std``, which ``jaxcr calibrate`` writes to the calibration file's ``uncertainty``
block) the scatter of ``cv2.stereoCalibrate`` over detection noise? And what tip tolerance
does such a calibration give ``jaxcr stereo`` (docs/decisions.md S37)?

Usage::

    python experiments/stereo/rig_pose_std.py [--seeds 400] [--out NAME]

Board detections rendered with ``cv2.projectPoints`` (7 x 6 inner corners, 20 mm, 320 x 240,
f = 300 px, no distortion; camera 2 rotated 0.3 rad about y, baseline 0.1 m), Gaussian
noise per coordinate; per case (noise, board poses) ``--seeds`` noise draws, each fitted by
``cv2.stereoCalibrateExtended`` with the true intrinsics fixed. Reported per component of
R's rotation vector and T: the scatter of the fits over the mean predicted sigma; and the
tolerance (:func:`jaxcr.stereo.epipolar_tolerance.tip_epipolar_tolerance_px`, floor 5 px)
for a tip 0.33 m in front of the rig, with the mean predicted pose sigmas and OpenCV's
intrinsic sigmas of one draw's ``cv2.calibrateCameraExtended`` (fx fy cx cy free).

Writes ``experiments/results/<NAME>.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from jaxcr.camera import camera_from_arrays
from jaxcr.stereo.calibration import board_points, stereo_pose_std
from jaxcr.stereo.epipolar_tolerance import CalibrationUncertainty, tip_epipolar_tolerance_px

SIZE = (320, 240)
OBJ = board_points("chessboard", 7, 6, 0.02)
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
R21 = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
T21 = np.array([-0.1, 0.0, 0.015])
CASES = [(0.1, 5), (0.2, 5), (0.5, 5), (0.2, 3), (0.2, 10)]  # (noise px, board poses)


def poses(n, seed=5):
    rng = np.random.default_rng(seed)
    return [(rng.normal(0, 0.3, 3) + np.array([np.pi, 0, 0]),
             np.array([-0.06, 0.04, 0.33]) + rng.normal(0, 0.02, 3)) for _ in range(n)]  # fmt: skip


def detections(ps, noise, seed):
    rng = np.random.default_rng(seed)
    a, b = [], []
    for r, t in ps:
        Rb = cv2.Rodrigues(r)[0]
        for out, (rv, tv) in ((a, (r, t)), (b, (cv2.Rodrigues(R21 @ Rb)[0], R21 @ t + T21))):
            p, _ = cv2.projectPoints(OBJ, rv, tv, K, np.zeros(5))
            out.append((p.reshape(-1, 2) + rng.normal(0, noise, (len(OBJ), 2))).astype(np.float32))
    return a, b


def run_case(noise, n, seeds):
    ps = poses(n)
    obj = [OBJ] * n
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    fits, preds = [], []
    for s in range(seeds):
        a, b = detections(ps, noise, 1000 + s)
        res = cv2.stereoCalibrateExtended(obj, a, b, K, np.zeros(5), K, np.zeros(5), SIZE,
                                          None, None, flags=cv2.CALIB_FIX_INTRINSIC,
                                          criteria=crit)  # fmt: skip
        sr, st = stereo_pose_std(obj, a, b, K, np.zeros(5), K, np.zeros(5), res[5], res[6],
                                 res[9], res[10])  # fmt: skip
        fits.append(np.r_[cv2.Rodrigues(res[5])[0].ravel(), res[6].ravel()])
        preds.append(np.r_[sr, st])
    scatter = np.std(fits, axis=0, ddof=1)
    pred = np.mean(preds, axis=0)
    # the intrinsics' OpenCV sigmas (fx fy cx cy free, no distortion) on one draw
    a, _ = detections(ps, noise, 1000)
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
    cv = cv2.calibrateCameraExtended(obj, a, SIZE, K.copy(), np.zeros(5), flags=flags)
    sd = np.asarray(cv[5]).ravel()
    unc = CalibrationUncertainty(
        focal_rel=float(max(sd[0], sd[1]) / 300.0), principal_px=float(max(sd[2], sd[3])),
        rotation_rad=float(np.max(pred[:3]) / np.sqrt(2)),
        translation_m=float(np.max(pred[3:]) / np.sqrt(2)),
    )  # fmt: skip
    T2 = np.eye(4)
    T2[:3, :3], T2[:3, 3] = R21, T21
    cams = [camera_from_arrays(K, np.zeros(5), np.eye(4), *SIZE),
            camera_from_arrays(K, np.zeros(5), T2, *SIZE)]  # fmt: skip
    X = np.array([-0.03, 0.02, 0.33])
    tips = [K @ X / X[2], K @ (R21 @ X + T21) / (R21 @ X + T21)[2]]
    tol = tip_epipolar_tolerance_px(cams, [t[:2] for t in tips], unc)
    tol0 = tip_epipolar_tolerance_px(cams, [t[:2] for t in tips], unc, floor_px=0.0)
    return {"noise_px": noise, "poses": n, "seeds": seeds, "ratio": (scatter / pred).tolist(),
            "pred_rot_deg": np.degrees(pred[:3]).tolist(), "pred_T_mm": (pred[3:] * 1e3).tolist(),
            "focal_rel": unc.focal_rel, "principal_px": unc.principal_px,
            "tolerance_px": tol, "three_sigma_px": tol0}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=400)
    ap.add_argument("--out", default="stereo/rig_pose_std")
    args = ap.parse_args()
    rows = [run_case(noise, n, args.seeds) for noise, n in CASES]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    head = (f"# R and T's predicted sigma vs cv2.stereoCalibrate scatter\n\n`python "
            f"experiments/stereo/rig_pose_std.py --seeds {args.seeds}`, commit {commit}, "
            f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, load {load}.\n\n"
            "| noise px | poses | scatter / predicted (r_x r_y r_z t_x t_y t_z) | "
            "predicted R deg (max) | T mm (max) | focal_rel | principal px | 3 sigma px | "
            "tolerance px |\n|---|---|---|---|---|---|---|---|---|\n")  # fmt: skip
    lines = [f"| {r['noise_px']} | {r['poses']} | {' '.join(f'{x:.2f}' for x in r['ratio'])} | "
             f"{max(r['pred_rot_deg']):.4f} | {max(r['pred_T_mm']):.3f} | {r['focal_rel']:.4f} | "
             f"{r['principal_px']:.2f} | {r['three_sigma_px']:.2f} | {r['tolerance_px']:.1f} |"
             for r in rows]  # fmt: skip
    out = Path("experiments/results") / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(head + "\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps(rows) + "\n")
    print(head + "\n".join(lines))


if __name__ == "__main__":
    main()
