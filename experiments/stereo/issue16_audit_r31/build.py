"""Write real_like frames the way a lab would (issue 16 audit r31). Usage: build.py SEED OUT"""

import json
import os
import pickle
import sys

import cv2
import numpy as np

from jaxcr.stereo.aruco import MarkerLayout

seed, out = int(sys.argv[1]), sys.argv[2]
f = pickle.load(open(f"rl_{seed}.pkl", "rb"))
v1, v2 = f.views
os.makedirs(out, exist_ok=True)


def mkd(p):
    os.makedirs(os.path.dirname(p), exist_ok=True)
    return p


def bgr(a):
    return cv2.cvtColor(a, cv2.COLOR_RGB2BGR)


# frames: PNG, JPEG, odd names
cv2.imwrite(mkd(f"{out}/rec/left cam/Frame 0001.PNG"), bgr(v1.image))
cv2.imwrite(mkd(f"{out}/rec/right cam/Frame 0001.PNG"), bgr(v2.image))
cv2.imwrite(
    mkd(f"{out}/rec/left cam/frame_0002.jpg"), bgr(v1.image), [cv2.IMWRITE_JPEG_QUALITY, 90]
)
cv2.imwrite(
    mkd(f"{out}/rec/right cam/frame_0002.jpg"), bgr(v2.image), [cv2.IMWRITE_JPEG_QUALITY, 90]
)
# a frame of a different size (a crop) for cam2
cv2.imwrite(mkd(f"{out}/rec/right cam/frame_small.png"), bgr(v2.image[:480, :640]))
# plates (with their own drift), JPEG for cam2
cv2.imwrite(mkd(f"{out}/plates/empty_L.png"), bgr(v1.plate))
cv2.imwrite(mkd(f"{out}/plates/empty_R.jpeg"), bgr(v2.plate), [cv2.IMWRITE_JPEG_QUALITY, 92])
c1, c2 = v1.calib_camera, v2.calib_camera
T21 = c2.T_cam_robot @ np.linalg.inv(c1.T_cam_robot)


def fs_write(path, unit_key="unit", unit="mm", scale=1000.0, names=("K1", "D1", "K2", "D2")):
    fs = cv2.FileStorage(mkd(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", c1.width)
    fs.write("image_height", c1.height)
    fs.write(names[0], c1.K)
    fs.write(names[1], c1.dist.reshape(1, -1))
    fs.write(names[2], c2.K)
    fs.write(names[3], c2.dist.reshape(1, -1))
    fs.write("R", T21[:3, :3])
    fs.write("T", T21[:3, 3:] * scale)
    if unit_key:
        fs.write(unit_key, unit)
    fs.release()


fs_write(f"{out}/calib/stereo_mm.yml", names=("M1", "D1", "M2", "D2"))
fs_write(f"{out}/calib/stereo_units_typo.yml", unit_key="units")
fs_write(f"{out}/calib/stereo_mm_nounit.yml", unit_key=None)
fs_write(f"{out}/calib/stereo_m.xml", unit_key=None, scale=1.0)
json.dump(
    {
        "unit": "mm",
        "K1": c1.K.tolist(),
        "D1": c1.dist.tolist(),
        "K2": c2.K.tolist(),
        "D2": c2.dist.tolist(),
        "R": T21[:3, :3].tolist(),
        "T": (T21[:3, 3] * 1000).tolist(),
        "image_width": c1.width,
        "image_height": c1.height,
    },
    open(f"{out}/calib/stereo_mm.json", "w"),
)
# single camera file (cam1), OpenCV sample style
fs = cv2.FileStorage(f"{out}/calib/left.yml", cv2.FILE_STORAGE_WRITE)
fs.write("camera_matrix", c1.K)
fs.write("distortion_coefficients", c1.dist.reshape(1, -1))
fs.write("image_width", c1.width)
fs.write("image_height", c1.height)
fs.write("avg_reprojection_error", 0.3)
fs.release()
lay = MarkerLayout()
T1 = c1.T_cam_robot.copy()
T1mm = T1.copy()
T1mm[:3, 3] *= 1000
truth = {
    "seed": seed,
    "tip_px": {"L": v1.tip_px.tolist(), "R": v2.tip_px.tolist()},
    "entry_px": {"L": v1.entry_px.tolist(), "R": v2.entry_px.tolist()},
    "entry_true_px": {"L": v1.entry_true_px.tolist(), "R": v2.entry_true_px.tolist()},
    "T_cam1_base_m": T1.tolist(),
    "robot_base_m": lay.base_centre.tolist(),
    "drift_px": {"L": v1.drift_px.tolist(), "R": v2.drift_px.tolist()},
    "backbone_px": {"L": v1.backbone_px.tolist(), "R": v2.backbone_px.tolist()},
}
json.dump(truth, open(f"{out}/truth.json", "w"))
frames = [
    {
        "id": "f0001",
        "images": {"L": "rec/left cam/Frame 0001.PNG", "R": "rec/right cam/Frame 0001.PNG"},
    },
    {
        "id": "f0002",
        "images": {"L": "rec/left cam/frame_0002.jpg", "R": "rec/right cam/frame_0002.jpg"},
    },
]
base_entry = {
    "entry_px": {"L": [round(x, 1) for x in v1.entry_px], "R": [round(x, 1) for x in v2.entry_px]}
}
plates = {"L": "plates/empty_L.png", "R": "plates/empty_R.jpeg"}


def stereo(name, **kw):
    d = {
        "format": "jaxcr.stereo/1",
        "calibration": "calib/stereo_mm.yml",
        "cameras": ["L", "R"],
        "base": base_entry,
        "background": {"key": "green"},
        "background_plates": plates,
        "frames": frames,
    }
    d.update(kw)
    d = {k: v for k, v in d.items() if v is not None}
    os.makedirs(f"{out}/{name}", exist_ok=True)

    # datasets are sub folders; paths relative: rewrite with ../
    def rel(x):
        if isinstance(x, str):
            return "../" + x
        if isinstance(x, dict):
            return {
                k: rel(v) if k in ("images",) or isinstance(v, str) and ("/" in v) else v
                for k, v in x.items()
            }
        return x

    d2 = dict(d)
    d2["calibration"] = "../" + d["calibration"]
    if "background_plates" in d2:
        d2["background_plates"] = {k: "../" + p for k, p in d2["background_plates"].items()}
    d2["frames"] = [
        {"id": fr["id"], "images": {k: "../" + p for k, p in fr["images"].items()}}
        for fr in d["frames"]
    ]
    json.dump(d2, open(f"{out}/{name}/stereo.json", "w"), indent=1)


stereo("s_entry")
# S19: the cameras listed in the wrong order for the L->R calibration (entry pixels 7 px apart)
stereo("s_cams_swapped", cameras=["R", "L"])
stereo("s_json_calib", calibration="calib/stereo_mm.json")
stereo(
    "s_Tcb_mm",
    base={"T_cam_base": T1mm.tolist()},
    unit="mm",
    robot_base=(lay.base_centre * 1000).tolist(),
)
stereo(
    "s_Tcb_m_robotbase_mm",
    base={"T_cam_base": T1.tolist()},
    unit="mm",
    robot_base=(lay.base_centre * 1000).tolist(),
)
stereo("s_Tcb_mm_nounit", base={"T_cam_base": T1mm.tolist()}, robot_base=lay.base_centre.tolist())
stereo("s_units_typo", calibration="calib/stereo_units_typo.yml")
stereo("s_nounit", calibration="calib/stereo_mm_nounit.yml")
stereo("s_m_xml", calibration="calib/stereo_m.xml")
stereo("s_missing_plate", background_plates={"L": "plates/empty_L.png"})
stereo(
    "s_small",
    frames=[
        {
            "id": "small",
            "images": {"L": "rec/left cam/Frame 0001.PNG", "R": "rec/right cam/frame_small.png"},
        }
    ],
)
stereo(
    "s_one_cam",
    calibration="calib/left.yml",
    cameras=["L"],
    base={"entry_px": {"L": base_entry["entry_px"]["L"]}},
    background_plates={"L": "plates/empty_L.png"},
    frames=[{"id": fr["id"], "images": {"L": fr["images"]["L"]}} for fr in frames],
)
stereo("s_key_typo", backgroud_plates=plates)
print("ok", out)
