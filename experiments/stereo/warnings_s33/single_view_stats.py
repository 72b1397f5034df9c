"""Per view of real_like dev seeds: one-camera trace (plate_foreground from the entry pixel,
as jaxcr.stereo.single_view with entry_px) and candidate single-view plausibility signals
against the true tip. Usage: single_view_stats.py SEED... (renders rl_SEED.pkl if missing)."""

import json
import os
import pickle
import sys

import numpy as np

from jaxcr.segmentation.foreground import PlateForegroundConfig, plate_foreground
from jaxcr.synth.real_like import render_real_like_frame

for seed in map(int, sys.argv[1:]):
    fn = f"rl_{seed}.pkl"
    if os.path.exists(fn):
        f = pickle.load(open(fn, "rb"))
    else:
        f = render_real_like_frame(seed)
        pickle.dump(f, open(fn, "wb"))
    for k, v in enumerate(f.views):
        t = plate_foreground(
            v.image, v.plate, np.asarray(v.entry_px, float), None, cfg=PlateForegroundConfig()
        )
        bb = np.asarray(t.backbone, float)
        L = float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1))) if len(bb) > 1 else 0.0
        tb = np.asarray(v.backbone_px, float)
        Ltrue = float(np.sum(np.linalg.norm(np.diff(tb, axis=0), axis=1)))
        H, W = v.image.shape[:2]
        tip = np.asarray(t.tip, float)
        edge = float(min(tip[0], tip[1], W - 1 - tip[0], H - 1 - tip[1]))

        def border_px(m, H=H, W=W):
            r, c = np.nonzero(m)
            if len(r) == 0:
                return -1.0
            return float(np.min(np.minimum.reduce([r, c, H - 1 - r, W - 1 - c])))

        row = dict(
            mask_edge=border_px(t.mask),
            true_mask_edge=border_px(v.mask),
            true_tip_edge=round(
                float(min(v.tip_px[0], v.tip_px[1], W - 1 - v.tip_px[0], H - 1 - v.tip_px[1])), 1
            ),
            seed=seed,
            view=k + 1,
            tip_err=round(float(np.linalg.norm(tip - v.tip_px)), 1),
            length=round(L, 1),
            true_length=round(Ltrue, 1),
            width=round(float(t.width_px), 2),
            mwidth=round(float(t.measured_width_px), 2),
            end_hw=round(float(t.end_half_width_px), 2),
            junctions=len(t.junctions),
            crossings=int(t.crossings_followed),
            turn=round(float(t.crossing_turn_deg), 1),
            gaps=len(t.gaps),
            gap_px=round(float(sum(np.linalg.norm(bb[b] - bb[a]) for a, b in t.gaps)), 1)
            if t.gaps
            else 0.0,
            reason=t.reason,
            edge_px=round(edge, 1),
            scale=int(t.scale),
        )
        print(json.dumps(row), flush=True)
