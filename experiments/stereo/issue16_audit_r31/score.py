"""Tip error (px) of each view of a jaxcr stereo run against a builder's truth.json:
python score.py RUN_DIR DATASET/truth.json"""

import json
import sys

import numpy as np

out, truth = sys.argv[1], json.load(open(sys.argv[2]))
for line in open(f"{out}/results.jsonl"):
    r = json.loads(line)
    s = f"{r['id']} ok={r['ok']} {r.get('reason', '')} {str(r.get('message', ''))[:150]}"
    for cam, v in (r.get("views") or {}).items():
        t = np.array(truth["tip_px"][cam])
        tp = np.array(v["tip_px"])
        bb = np.array(v.get("backbone_px") or [[np.nan, np.nan]])
        s += f" | {cam}: tip_err={np.linalg.norm(tp - t):.1f}px n_bb={len(bb)} bb0={np.round(bb[0], 0).tolist()} bbend_to_tip={np.linalg.norm(bb[-1] - tp):.1f} src={v.get('tip_source')}"
    s += f" epi={r.get('tip_epipolar_px')} entry_res={r.get('entry_residual_px')}"
    print(s)
