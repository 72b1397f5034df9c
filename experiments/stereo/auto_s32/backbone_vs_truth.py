"""Backbone RMS, coverage and tip error against the truth of a `jaxcr stereo synth` set, for each run
folder given (docs/decisions.md S32): python backbone_vs_truth.py SET RUN [RUN ...]"""

import json
import sys
from pathlib import Path

import numpy as np

from jaxcr.stereo.evaluate import evaluate_frame

ds = Path(sys.argv[1])
for run in sys.argv[2:]:
    run = Path(run)
    for line in (run / "results.jsonl").read_text().splitlines():
        r = json.loads(line)
        if not r["ok"]:
            print(run.name, r["id"], "FAIL", r["message"][:100])
            continue
        fj = json.loads((run / "frames" / f"{r['id']}.json").read_text())
        npz = np.load(run / "frames" / f"{r['id']}.npz")
        truth = dict(np.load(ds / "truth" / f"{r['id']}.npz"))
        ev = evaluate_frame(
            {
                "p": npz["p"],
                "s": npz["s"],
                "segments": fj["segments"],
                "boundary_p": npz["boundary_p"],
            },
            truth,
        )
        print(
            run.name,
            r["id"],
            {
                k: (round(v, 3) if isinstance(v, float) else v)
                for k, v in ev.items()
                if not isinstance(v, (list, dict))
            },
            "epi",
            r.get("tip_epipolar_px"),
            [v.get("tip_source") for v in r["views"].values()],
        )
