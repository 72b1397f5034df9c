"""Candidate statistics of the chroma key mask per view (docs/decisions.md S32, jaxcr.stereo.key_check):
python key_stats.py SET_DIR... rl_SEED.pkl... (stereo synth sets; real_like pickles of
experiments/stereo/issue16_audit_r31/render.py)."""

import json
import pickle
import sys
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np

from jaxcr.io.calibration import load_stereo
from jaxcr.stereo.aruco import MarkerLayout
from jaxcr.stereo.base_locate import flood_component, locate_base
from jaxcr.stereo.chroma import KEY_COLOURS, chroma_alpha


def stats(img, buv, key="green"):
    a = np.asarray(
        chroma_alpha(
            jnp.asarray(img.astype(np.float32) / 255), jnp.asarray(KEY_COLOURS[key]), 0.5, 0.8
        )
    )
    m = cv2.morphologyEx((a > 0.5).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    b = np.r_[m[0], m[-1], m[1:-1, 0], m[1:-1, -1]]
    loc = locate_base(m, buv, 24)
    if loc.found:
        r = flood_component(m, loc.seed)
    else:
        r = np.zeros_like(m)
    rb = np.r_[r[0], r[-1], r[1:-1, 0], r[1:-1, -1]]
    return dict(
        nonkey=m.mean(),
        border=b.mean(),
        robot=r.mean(),
        clutter=(m & ~r).mean(),
        robot_border=rb.mean(),
    )


def fmt(d):
    return " ".join(f"{k}={v:.3f}" for k, v in d.items())


lay = MarkerLayout()
for arg in sys.argv[1:]:
    if arg.endswith(".pkl"):
        f = pickle.load(open(arg, "rb"))
        for k, v in enumerate(f.views):
            print("real_like", f.seed, k + 1, fmt(stats(v.image, tuple(v.entry_px))))
        continue
    d = Path(arg)
    meta = json.loads((d / "stereo.json").read_text())
    cams = load_stereo(d / meta["calibration"])
    key = meta.get("background", {}).get("key", "green")  # named key
    for fr in meta["frames"]:
        for n, cam in zip(meta["cameras"], cams, strict=True):
            T = np.array(meta["meta"]["true_T_cam_base"][n])
            rb = np.array(meta.get("robot_base", lay.base_centre))
            uv, _ = cv2.projectPoints(
                rb[None],
                cv2.Rodrigues(T[:3, :3])[0],
                T[:3, 3],
                np.asarray(cam.K, float),
                np.asarray(cam.dist, float),
            )
            img = cv2.cvtColor(cv2.imread(str(d / fr["images"][n])), cv2.COLOR_BGR2RGB)
            print(d.name, fr["id"], n, fmt(stats(img, tuple(uv.reshape(2)), key)))
