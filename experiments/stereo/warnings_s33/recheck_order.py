"""Re-run jaxcr.stereo.camera_order.camera_order_check on the inputs stored by dump_order.py
(docs/decisions.md S33): the S19 rule alone (tip_tol_px infinite) and the S33 rule.
Usage: recheck_order.py OUT_order.pkl..."""

import pickle
import sys
from types import SimpleNamespace

from jaxcr.stereo.camera_order import camera_order_check

for f in sys.argv[1:]:
    for k, c in enumerate(pickle.load(open(f, "rb"))):
        cams = [SimpleNamespace(**d) for d in c["cams"]]
        s19 = camera_order_check(cams, c["b1"], c["b2"], tip_tol_px=float("inf"))
        s33 = camera_order_check(cams, c["b1"], c["b2"])
        print(
            f"{f} call {k}: px [given, exchanged, total] = "
            f"[{s33.inconsistent_px}, {s33.exchanged_px}, {s33.length_px}], ends [given, "
            f"exchanged] = {list(s33.tip_px)}; suspect S19 rule {s19.suspect}, S33 {s33.suspect}"
        )
