"""A jaxcr.dataset/1 from a real_like frame, written as a lab would (audit r31): build_seg.py SEED OUT"""

import json
import os
import pickle
import sys

import cv2
import numpy as np

from jaxcr.stereo.aruco import MarkerLayout
from jaxcr.synth.stereo_ctr import cc_backbone, sample_robot, stereo_cameras

seed, out = int(sys.argv[1]), sys.argv[2]
f = pickle.load(open(f"rl_{seed}.pkl", "rb"))
rng = np.random.default_rng([seed, 16])
lay = MarkerLayout()
cams = stereo_cameras((1280, 720), lay, rng)
robot = sample_robot(rng, "general", lay, cams)
fine = cc_backbone(robot, 1e-3)
v1, v2 = f.views
os.makedirs(out, exist_ok=True)


def mkd(p):
    os.makedirs(os.path.dirname(p), exist_ok=True)
    return p


def bgr(a):
    return cv2.cvtColor(a, cv2.COLOR_RGB2BGR)


for n, v in (("L", v1), ("R", v2)):
    cv2.imwrite(mkd(f"{out}/img/{n}_take1.png"), bgr(v.image))
    cv2.imwrite(mkd(f"{out}/img/{n}_plate.png"), bgr(v.plate))
    cv2.imwrite(mkd(f"{out}/img/{n}_mask.png"), v.mask.astype(np.uint8) * 255)
k = len(robot.lengths)
rob = {
    "kind": "constant_curvature",
    "name": f"tendon-like, {k} sections",
    "sections": [
        {"length": round(float(L), 4), "radius": float(d / 2)}
        for L, d in zip(robot.lengths, robot.diameters, strict=False)
    ],
    "joints": ["kappa", "phi", "length"],
}
json.dump(rob, open(f"{out}/robot.json", "w"), indent=1)
# measured backbone: camera L's true frame, mm, base first, every ~3 mm, 0.1 mm noise
T1 = v1.camera.T_cam_robot
P = fine["p"][::3] @ T1[:3, :3].T + T1[:3, 3]
P = P + np.random.default_rng(seed + 99).normal(0, 1e-4, P.shape)
with open(f"{out}/backbone_L_mm.csv", "w") as fh:
    fh.write(
        "# unit: mm\nx;y;z\n"
        + "\n".join("{:.3f};{:.3f};{:.3f}".format(*tuple(1e3 * p)) for p in P)
        + "\n"
    )
np.save(f"{out}/backbone_L_mm.npy", P * 1e3)
# measured backbone in the *robot* frame (base frame translated to the base centre, R0): for fit without a dataset
Tb = np.eye(4)
Tb[:3, :3] = robot.R0
Tb[:3, 3] = robot.base
Pr = (fine["p"][::3] - robot.base) @ robot.R0
with open(f"{out}/backbone_robot_mm.csv", "w") as fh:
    fh.write(
        "# unit: mm\n"
        + "\n".join("{:.3f} {:.3f} {:.3f}".format(*tuple(1e3 * p)) for p in Pr)
        + "\n"
    )
q0 = [v for L in robot.lengths for v in (1.0, 0.0, float(L))]
c1 = v1.calib_camera


def ds(name, cameras, frame_images, extra=None, bg=None, masks=None):
    d = {
        "format": "jaxcr.dataset/1",
        "name": name,
        "robot": "../robot.json",
        "cameras": cameras,
        "frames": [
            {"id": "take1", "q": q0, "images": frame_images, **({"masks": masks} if masks else {})}
        ],
    }
    if bg:
        d["background_images"] = bg
    if extra:
        d.update(extra)
    os.makedirs(f"{out}/{name}", exist_ok=True)
    json.dump(d, open(f"{out}/{name}/dataset.json", "w"), indent=1)


inline = {
    "K": c1.K.tolist(),
    "dist": c1.dist.tolist(),
    "size": [1280, 720],
    "T_cam_robot": np.eye(4).tolist(),
    "unit": "mm",
}
ds(
    "one_cam",
    {"L": inline},
    {"L": "../img/L_take1.png"},
    bg={"L": ["../img/L_plate.png"]},
    masks={"L": "../img/L_mask.png"},
)
st = f"../../d{seed}/calib/stereo_mm.yml"
ds(
    "two_cam",
    {
        "L": {"stereo": st, "camera": 1, "unit": "mm"},
        "R": {"stereo": st, "camera": 2, "unit": "mm"},
    },
    {"L": "../img/L_take1.png", "R": "../img/R_take1.png"},
    bg={"L": ["../img/L_plate.png"], "R": ["../img/R_plate.png"]},
    masks={"L": "../img/L_mask.png", "R": "../img/R_mask.png"},
)
json.dump(
    {"tips": {"L": v1.tip_px.tolist(), "R": v2.tip_px.tolist()}}, open(f"{out}/tips.json", "w")
)
T_cam_robot_true = T1 @ Tb
json.dump(
    {
        "T_camL_robot": T_cam_robot_true.tolist(),
        "robot": {
            "L": robot.lengths.tolist(),
            "kappa": robot.kappas.tolist(),
            "phi": robot.phis.tolist(),
        },
        "tip_px": {"L": v1.tip_px.tolist(), "R": v2.tip_px.tolist()},
    },
    open(f"{out}/truth.json", "w"),
)
print("ok", k)
