"""Does ``jaxcr calibrate``'s identifiability check refuse what it should, accept what it
should, and is its predicted sigma calibrated? (issue 16 item 4)

Usage::

    python experiments/stereo/calibrate_identifiability.py [--seeds 0:50] [--out NAME]

Board detections are rendered with ``cv2.projectPoints`` (7 x 6 inner corners, 20 mm,
320 x 240 camera, f = 300 px, principal point at the image centre, k1 = -0.12, k2 = 0.05,
Gaussian detection noise 0.15 px) for four rig cases per seed:

* ``varied``: 10 board poses, tilts ~N(0, 0.4 rad) about each axis, all intrinsics free
  (a usual calibration set): should be accepted;
* ``one_pose_free``: one board pose (35 deg tilt) seen 3 times, fx, fy, cx, cy and
  distortion free (the real rig's case, fx/fy 1204/952 with exit 0): should be refused;
* ``one_pose_fixed``: the same single pose with --fix-principal-point --fix-aspect-ratio
  (truth without distortion, --no-distortion): should be accepted, with |f - f_true| / sigma
  distributed as a standard normal if sigma is calibrated;
* ``facing``: 3 boards facing the camera (tilt 0), translated, fixed principal point and
  aspect ratio, no distortion: the focal length is free (Zhang 2000), should be refused.

Writes ``experiments/results/<NAME>.md`` and ``.json``. The thresholds (5 % refusal, 1 %
warning) were chosen on seeds 0-9 (tests use their own seeds); the reported run uses
seeds 100-149, never looked at before.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import cv2
import numpy as np

from jaxcr.stereo.calibration import (
    IntrinsicConstraints,
    board_points,
    calibrate_camera,
    identifiability_problems,
)

SIZE = (320, 240)
OBJ = board_points("chessboard", 7, 6, 0.02)
K_TRUE = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
D_TRUE = np.array([-0.12, 0.05, 0.0, 0.0, 0.0])
NOISE = 0.15
T0 = np.array([-0.06, 0.05, 0.33])


def _detections(poses, d, rng):
    img = []
    for r, t in poses:
        p, _ = cv2.projectPoints(OBJ, r, t, K_TRUE, d)
        img.append((p.reshape(-1, 2) + rng.normal(0, NOISE, (len(OBJ), 2))).astype(np.float32))
    return [OBJ] * len(poses), img


def run_case(case: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    flip = np.array([np.pi, 0.0, 0.0])
    if case == "varied":
        poses = [(flip + rng.normal(0, 0.4, 3), T0 + rng.normal(0, 0.02, 3)) for _ in range(10)]
        c, d = IntrinsicConstraints(), D_TRUE
    elif case in ("one_pose_free", "one_pose_fixed"):
        axis = rng.normal(size=2)
        axis /= np.linalg.norm(axis)
        # tilt the board (facing the camera: Rx(pi)) by 35 deg about an in-plane axis
        R = cv2.Rodrigues(np.r_[np.radians(35) * axis, 0.0])[0] @ cv2.Rodrigues(flip)[0]
        pose = (cv2.Rodrigues(R)[0].ravel(), T0 + rng.normal(0, 0.02, 3))
        if case == "one_pose_free":
            poses, c, d = [pose] * 3, IntrinsicConstraints(), D_TRUE
        else:
            c = IntrinsicConstraints(
                fix_principal_point=True, fix_aspect_ratio=True, no_distortion=True
            )
            poses, d = [pose], np.zeros(5)
    elif case == "facing":
        poses = [(flip, T0 + np.r_[rng.normal(0, 0.02, 2), 0.05 * k]) for k in range(3)]
        c = IntrinsicConstraints(
            fix_principal_point=True, fix_aspect_ratio=True, no_distortion=True
        )
        d = np.zeros(5)
    else:
        raise ValueError(case)
    obj, img = _detections(poses, d, rng)
    cal = calibrate_camera(obj, img, SIZE, c)
    refused, warned = identifiability_problems(cal)
    f_name = "f" if "f" in cal.std else "fx"
    return {
        "case": case,
        "seed": seed,
        "refused": bool(refused),
        "warned": bool(warned),
        "fx": float(cal.K[0, 0]),
        "fy": float(cal.K[1, 1]),
        "sigma_f": cal.std[f_name],
        "z_f": float((cal.K[0, 0] - 300.0) / cal.std[f_name])
        if np.isfinite(cal.std[f_name])
        else None,
        "rms": cal.rms,
        "tilt_deg": [float(t) for t in cal.tilt_deg],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="100:150", help="start:stop (default %(default)s)")
    ap.add_argument("--out", default="calibrate_identifiability")
    args = ap.parse_args()
    a, b = (int(x) for x in args.seeds.split(":"))
    rows = [run_case(case, s) for case in ("varied", "one_pose_free", "one_pose_fixed", "facing")
            for s in range(a, b)]  # fmt: skip
    expect = {"varied": False, "one_pose_free": True, "one_pose_fixed": False, "facing": True}
    lines = [
        "# `jaxcr calibrate`: identifiability check on synthetic detections",
        "",
        f"Command: `python experiments/stereo/calibrate_identifiability.py --seeds {args.seeds}` "
        f"(seeds {a}-{b - 1}, {b - a} per case, not used while choosing the thresholds).",
        f"Camera 320x240, f = 300 px, noise {NOISE} px; refusal at 5 % (focal) / 5 % of the "
        "image (principal point), warning at a fifth. No published numbers exist; the "
        "previous behaviour was to accept every case (exit 0).",
        "",
        "| case | expected | refused | warned | fx median [min, max] | |z_f| <= 1 | |z_f| <= 2 |",
        "|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for case, exp in expect.items():
        rs = [r for r in rows if r["case"] == case]
        n = len(rs)
        ref = sum(r["refused"] for r in rs)
        warn = sum(r["warned"] and not r["refused"] for r in rs)
        fx = np.array([r["fx"] for r in rs])
        z = np.array([abs(r["z_f"]) for r in rs if r["z_f"] is not None])
        z1 = f"{np.mean(z <= 1):.0%}" if len(z) and not exp else "-"
        z2 = f"{np.mean(z <= 2):.0%}" if len(z) and not exp else "-"
        lines.append(
            f"| {case} | {'refuse' if exp else 'accept'} | {ref}/{n} | {warn}/{n} | "
            f"{np.median(fx):.1f} [{fx.min():.1f}, {fx.max():.1f}] | {z1} | {z2} |"
        )
        summary[case] = {"n": n, "refused": ref, "warned": warn, "z_le_1": z1, "z_le_2": z2}
    lines += [
        "",
        "|z_f| = |f - 300| / predicted sigma: a calibrated sigma gives about 68 % within 1 and "
        "95 % within 2 (only for the accepted cases, whose models are exact except `varied`'s "
        "free k3/p1/p2, which the truth has at 0). `warned` counts accepted runs with any "
        "WARNING: a focal length or principal point above a fifth of its limit, or a ray at "
        "the image corners uncertain by over 1 % of the half-diagonal (the `varied` boards "
        "cover the middle third of the image, so the fitted distortion is extrapolated there).",
        "",
        f"Machine: {platform.platform()}, OpenCV {cv2.__version__}.",
    ]
    out = Path(__file__).parent.parent / "results" / "stereo"
    out.mkdir(exist_ok=True)
    (out / f"{args.out}.md").write_text("\n".join(lines) + "\n")
    (out / f"{args.out}.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
