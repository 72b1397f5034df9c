"""Write the raw inputs of a small synthetic stereo rig for docs/your-own-rig.md, and its truth.

    python docs/make_example_rig.py OUT [--frames 3] [--size 160x120] [--seed 7]

writes what a lab records on its own rig, in the layout the tutorial uses::

    OUT/rig/robot.json                 the robot (constant curvature, 3 sections), metres
    OUT/rig/calib/cam1/NN.png, cam2/   chessboard pairs (6 x 5 inner corners, 15 mm squares)
    OUT/rig/plates/cam1.png, cam2.png  background plates: the scene without the robot
    OUT/rig/frames/cam1/NNN.png, cam2/ the recording (stereo pairs of the robot)
    OUT/rig/backbones/NNN.csv          a recorded backbone per frame: millimetres, camera 1's
                                       frame, base first (what a tracker registered to camera 1
                                       gives), with 0.1 mm of measurement noise

and beside it what the tutorial's results are checked against (never read by the tutorial)::

    OUT/truth/truth.json               true intrinsics, distortion, camera poses, q per frame,
                                       tip pixels per view, T_cam1_robot
    OUT/truth/backbone_NNN.npy         true backbone (N, 3), camera 1's frame, metres

The robot and the scene come from the stereo preset (``jaxcr.synth.stereo_ctr``: ray-cast
tube over green cloth, lens distortion, sensor noise), rendered with ``kinds=("general",)`` and
three tubes, so each frame is a three-section constant-curvature backbone that the robot.json
model can represent. Its markers are in the images but the tutorial does not use them (it
gives the base by its entry pixels). The chessboards are drawn here by ray casting each
pixel's sub-samples (3 x 3) through the true lens (``cv2.undistortPoints``) onto the board
plane, then blurred (0.6 px) and given 1 % noise. Deterministic for a seed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

#: Chessboard: inner corners per row and per column, square size (m).
BOARD_COLS, BOARD_ROWS, SQUARE = 6, 5, 0.015
#: Board poses: tilts (deg) about the board's own x and y axes, relative to facing the
#: bisector of the two cameras; distinct orientations so the intrinsics are determined.
BOARD_TILTS = [(0, 0), (20, 0), (-20, 0), (0, 20), (0, -20), (14, 14), (-14, 14), (14, -14),
               (-14, -14), (8, -4), (-6, 10), (4, 8)]  # fmt: skip


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _board_pose(centre: np.ndarray, normal: np.ndarray, tilt: tuple[float, float]):
    """Board frame -> base frame (R, t): board z along ``normal`` (towards the cameras),
    board x horizontal, then tilted."""
    z = normal / np.linalg.norm(normal)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1) @ _rot("x", tilt[0]) @ _rot("y", tilt[1])
    return R, centre


#: Sub-samples per pixel side of the board renderer.
SUB = 3
_rays_memo: dict[bytes, np.ndarray] = {}


def _pixel_rays(K, dist, size) -> np.ndarray:
    """(h * w * SUB * SUB, 3) rays (x, y, 1) of every pixel's sub-samples through the true lens:
    the same for every board a camera sees, so computed once per camera."""
    key = np.asarray(K, np.float64).tobytes() + np.asarray(dist, np.float64).tobytes()
    key += np.asarray(size).tobytes()
    if key not in _rays_memo:
        w, h = size
        n = SUB
        off = (np.arange(n) + 0.5) / n - 0.5
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        shape = (h, w, n, n)
        su = np.broadcast_to(uu[..., None, None] + off[None, None, None, :], shape).ravel()
        sv = np.broadcast_to(vv[..., None, None] + off[None, None, :, None], shape).ravel()
        pts = np.stack([su, sv], 1).reshape(-1, 1, 2).astype(np.float64)
        xy = cv2.undistortPoints(pts, K, dist).reshape(-1, 2)
        if len(_rays_memo) >= 2:  # a rig's two cameras at a time (17 MB each at 320x240)
            _rays_memo.pop(next(iter(_rays_memo)))
        _rays_memo[key] = np.c_[xy, np.ones(len(xy))]
    return _rays_memo[key]


def _render_board(K, dist, T_cam_base, R_b, t_b, size, rng) -> np.ndarray:
    """8-bit RGB view of the chessboard (pose R_b, t_b in the base frame) on a grey wall."""
    w, h = size
    n = SUB
    d_cam = _pixel_rays(K, dist, size)
    # board plane in the camera frame
    R_cb = T_cam_base[:3, :3] @ R_b
    t_cb = T_cam_base[:3, :3] @ t_b + T_cam_base[:3, 3]
    nrm = R_cb[:, 2]
    lam = (nrm @ t_cb) / (d_cam @ nrm)
    P = d_cam * lam[:, None]
    local = (P - t_cb) @ R_cb  # board coordinates (m)
    # corner (0, 0) of the inner grid at the origin offset so the grid is centred
    gx = local[:, 0] / SQUARE + (BOARD_COLS + 1) / 2
    gy = local[:, 1] / SQUARE + (BOARD_ROWS + 1) / 2
    inside = (gx >= 0) & (gx < BOARD_COLS + 1) & (gy >= 0) & (gy < BOARD_ROWS + 1)
    margin = (gx >= -1) & (gx < BOARD_COLS + 2) & (gy >= -1) & (gy < BOARD_ROWS + 2)
    val = np.full(len(gx), 0.45)  # grey wall
    val[margin] = 0.92  # white paper around the squares
    black = inside & ((np.floor(gx).astype(int) + np.floor(gy).astype(int)) % 2 == 0)
    val[black] = 0.06
    img = val.reshape(h, w, n * n).mean(axis=2)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    img = img + rng.normal(0, 0.01, img.shape)
    g = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _board_visible(cam, T_cam_base, R_b, t_b, size, margin=3.0) -> bool:
    """The board's white margin lies inside the image by ``margin`` px, in front of it."""
    a, b = (BOARD_COLS + 3) / 2 * SQUARE, (BOARD_ROWS + 3) / 2 * SQUARE
    P = np.array([[-a, -b, 0], [a, -b, 0], [a, b, 0], [-a, b, 0.0]]) @ R_b.T + t_b
    Pc = P @ T_cam_base[:3, :3].T + T_cam_base[:3, 3]
    if np.any(Pc[:, 2] <= 0):
        return False
    uv, _ = cv2.projectPoints(Pc, np.zeros(3), np.zeros(3), np.asarray(cam.K, float),
                              np.asarray(cam.dist, float))  # fmt: skip
    uv = uv.reshape(-1, 2)
    w, h = size
    return bool(np.all((uv >= margin) & (uv <= np.array([w - 1 - margin, h - 1 - margin]))))


def _write(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


#: The robot: three constant-curvature sections, the stereo preset's tube diameters; joints
#: kappa, phi, length per section (nominal lengths: the preset's mid-range).
ROBOT = {
    "kind": "constant_curvature",
    "name": "example rig, 3 sections",
    "sections": [
        {"length": L, "radius": d / 2}
        for L, d in zip((0.042, 0.034, 0.027), (0.0024, 0.0018, 0.0012), strict=True)
    ],
    "joints": ["kappa", "phi", "length"],
    "n_points": 64,
}


def make_rig(out: str | Path, *, frames: int = 3, size=(160, 120), seed: int = 7) -> Path:
    """Write OUT/rig (the raw inputs) and OUT/truth (see the module docstring); return OUT."""
    from jaxcr.io.calibration import load_stereo
    from jaxcr.synth.stereo_ctr import generate_stereo_set

    out = Path(out)
    rig, truth = out / "rig", out / "truth"
    rig.mkdir(parents=True, exist_ok=True)
    truth.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        src = generate_stereo_set(
            Path(tmp) / "s", n_frames=frames, seed=seed, size=size, kinds=("general",), n_tubes=3
        )
        meta = json.loads((src / "stereo.json").read_text())
        cam1, cam2 = load_stereo(src / "calib" / "stereo.yaml")
        T_cam_base = {k: np.array(v) for k, v in meta["meta"]["true_T_cam_base"].items()}
        for name in ("cam1", "cam2"):
            shutil.copy(src / "background" / f"{name}.png", _mk(rig / "plates") / f"{name}.png")
        rec = {"cameras": {}, "frames": []}
        for name, cam in (("cam1", cam1), ("cam2", cam2)):
            rec["cameras"][name] = {
                "K": np.asarray(cam.K).tolist(),
                "dist": np.asarray(cam.dist).tolist(),
                "T_cam_base": T_cam_base[name].tolist(),
            }
        rng = np.random.default_rng([seed, 1])
        T1 = T_cam_base["cam1"]
        for fr in meta["frames"]:
            fid = fr["id"]
            for name in ("cam1", "cam2"):
                shutil.copy(src / fr["images"][name], _mk(rig / "frames" / name) / f"{fid}.png")
            z = np.load(src / fr["truth"])
            p_cam1 = z["p"] @ T1[:3, :3].T + T1[:3, 3]
            np.save(truth / f"backbone_{fid}.npy", p_cam1)
            # The recorded backbone: 25 points along it, 0.1 mm noise, millimetres.
            idx = np.linspace(0, len(p_cam1) - 1, 25).round().astype(int)
            meas = p_cam1[idx] * 1000.0 + rng.normal(0, 0.1, (len(idx), 3))
            lines = ["# unit: mm", "# recorded backbone, camera 1's frame, base first", "x,y,z"]
            lines += [f"{a:.3f},{b:.3f},{c:.3f}" for a, b, c in meas]
            _mk(rig / "backbones")
            (rig / "backbones" / f"{fid}.csv").write_text("\n".join(lines) + "\n")
            tips = {}
            for name, cam in (("cam1", cam1), ("cam2", cam2)):
                T = T_cam_base[name]
                rvec = cv2.Rodrigues(T[:3, :3])[0]
                uv, _ = cv2.projectPoints(z["p"][-1:], rvec, T[:3, 3], np.asarray(cam.K, float),
                                          np.asarray(cam.dist, float))  # fmt: skip
                tips[name] = uv.reshape(2).tolist()
            T_base_robot = np.eye(4)
            T_base_robot[:3, :3] = z["R0"]
            T_base_robot[:3, 3] = z["p"][0]
            rec["frames"].append({
                "id": fid,
                "q": np.stack([z["seg_curvature"], z["seg_phi"], z["seg_length"]], 1)
                .ravel().tolist(),
                "tip_px": tips,
                "T_cam1_robot": (T1 @ T_base_robot).tolist(),
                "length": float(z["s"][-1]),
            })  # fmt: skip
        (rig / "robot.json").write_text(json.dumps(ROBOT, indent=1) + "\n")
        # Chessboard pairs, seen by both cameras: the board faces the bisector of the two
        # cameras, 3-5 cm above the base, 16 mm towards them.
        centres = [-T[:3, :3].T @ T[:3, 3] for T in (T_cam_base["cam1"], T_cam_base["cam2"])]
        target = np.array(meta["robot_base"]) + np.array([0.0, 0.0, 0.045])
        normal = sum(c - target for c in centres)
        normal[2] = 0.35 * np.linalg.norm(normal[:2])
        brng = np.random.default_rng([seed, 2])
        nz = normal / np.linalg.norm(normal)
        for k, tilt in enumerate(BOARD_TILTS):
            for _ in range(200):  # a board position that both views see whole
                R_b, t_b = _board_pose(target, normal, tilt)
                off = R_b @ np.r_[brng.uniform(-0.03, 0.03), brng.uniform(-0.025, 0.025), 0.0]
                t_b = target + off + nz * brng.uniform(-0.01, 0.05)
                if all(_board_visible(c, T_cam_base[n], R_b, t_b, size)
                       for n, c in (("cam1", cam1), ("cam2", cam2))):  # fmt: skip
                    break
            for name, cam in (("cam1", cam1), ("cam2", cam2)):
                img = _render_board(np.asarray(cam.K, float), np.asarray(cam.dist, float),
                                    T_cam_base[name], R_b, t_b, size, brng)  # fmt: skip
                _write(rig / "calib" / name / f"{k:02d}.png", img)
        R12 = np.asarray(cam2.T_cam_robot, float)
        rec["baseline_m"] = float(np.linalg.norm(R12[:3, 3]))
        rec["board"] = {"cols": BOARD_COLS, "rows": BOARD_ROWS, "square_m": SQUARE}
        rec["size"] = list(size)
        (truth / "truth.json").write_text(json.dumps(rec, indent=1) + "\n")
    return out


def _mk(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="output folder (rig/ and truth/ are written inside)")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--size", default="160x120", help="image size WxH (default 160x120)")
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    make_rig(a.out, frames=a.frames, size=(w, h), seed=a.seed)
    print(f"wrote {a.out}/rig (the raw inputs) and {a.out}/truth (the ground truth)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
