"""Render an asymmetric circle grid (4 x 11, 20 mm same-row pitch) seen by two cameras, 10 poses."""

import json
import os

import cv2
import numpy as np

W, H = 640, 480
K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
D = np.array([-0.05, 0.01, 0, 0, 0])
PITCH = 0.02
SQ = PITCH / 2
COLS, ROWS = 4, 11
RAD = 0.0035
centres = np.array([[(2 * j + i % 2) * SQ, i * SQ] for i in range(ROWS) for j in range(COLS)])
cx0, cy0 = centres.mean(0)


def rot(ax, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[ax]


# camera 2 = [R | T] camera 1: 100 mm to the right, turned 8 deg towards the board
R21 = rot("y", -8.0)
T21 = np.array([-0.1, 0.0, 0.01])
ss = 3
u, v = np.meshgrid((np.arange(W * ss) + 0.5) / ss - 0.5, (np.arange(H * ss) + 0.5) / ss - 0.5)
pix = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
rays = cv2.undistortPoints(pix, K, D).reshape(-1, 2)
rays = np.c_[rays, np.ones(len(rays))]


def render(Rb, tb, Rc, tc):
    # board frame -> camera: X_c = Rc (Rb Xb + tb) + tc
    R = Rc @ Rb
    t = Rc @ tb + tc
    n = R[:, 2]
    d0 = n @ t
    lam = d0 / (rays @ n)
    X = rays * lam[:, None] - t
    Xb = X @ R  # board coords
    img = np.ones(len(rays))
    for c in centres:
        img[(Xb[:, 0] - c[0]) ** 2 + (Xb[:, 1] - c[1]) ** 2 < RAD**2] = 0.0
    out = np.clip(img, 0, 1).reshape(H, ss, W, ss) if False else img.reshape(H * ss, W * ss)
    out = out.reshape(H, ss, W, ss).mean((1, 3))
    out = cv2.GaussianBlur(out, (0, 0), 0.6) * 0.8 + 0.1
    out = out + np.random.default_rng(5020).normal(0, 0.01, out.shape)
    return (np.clip(out, 0, 1) * 255).astype(np.uint8)


tilts = [
    (0, 0),
    (20, 0),
    (-20, 0),
    (0, 20),
    (0, -20),
    (14, 14),
    (-14, 14),
    (14, -14),
    (-14, -14),
    (8, -4),
]
for k, (a, b) in enumerate(tilts):
    Rb = rot("x", a) @ rot("y", b) @ rot("z", 90)
    tb = np.array([0.05, 0.0, 0.4]) - Rb @ np.array([cx0, cy0, 0])
    for cam, (Rc, tc) in (("c1", (np.eye(3), np.zeros(3))), ("c2", (R21, T21))):
        os.makedirs(f"acirc/{cam}", exist_ok=True)
        cv2.imwrite(f"acirc/{cam}/{k:02d}.png", render(Rb, tb, Rc, tc))
json.dump(
    {"baseline_m": float(np.linalg.norm(T21)), "K": K.tolist()}, open("acirc/truth.json", "w")
)
print("ok", np.linalg.norm(T21))
