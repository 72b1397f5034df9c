"""Run `jaxcr stereo DIR -o OUT [args]` in-process, pickling each camera_order_check call's
inputs and result to OUT_order.pkl (a list, frame order)."""

import pickle
import sys

import jaxcr.stereo.pipeline as pl
from jaxcr.cli import main

calls = []
orig = pl.camera_order_check


def wrapped(cams, b1, b2, **kw):
    res = orig(cams, b1, b2, **kw)
    calls.append(
        {
            "cams": [{"K": c.K, "dist": c.dist, "T_cam_robot": c.T_cam_robot} for c in cams],
            "b1": b1,
            "b2": b2,
            "res": res,
        }
    )
    return res


pl.camera_order_check = wrapped
out = sys.argv[sys.argv.index("-o") + 1]
try:
    rc = main(["stereo", *sys.argv[1:]])
finally:
    import numpy as np

    calls = [
        {**c, "cams": [{k: np.asarray(v) for k, v in d.items()} for d in c["cams"]]} for c in calls
    ]
    pickle.dump(calls, open(out.rstrip("/") + "_order.pkl", "wb"))
sys.exit(rc)
