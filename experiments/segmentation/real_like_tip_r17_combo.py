"""Round 17 (issue 16 item 2, docs/decisions.md S41, S42): the merged defaults of
:func:`jaxcr.stereo.pipeline.traced_stereo_tips` (``run_on`` and ``end_fit`` on) against the
stop-35 steps (both off), on stored development traces, in the same run.

    python experiments/segmentation/real_like_tip_r17_combo.py --seeds LIST --store STORE \\
        --out ROWS
    python experiments/segmentation/real_like_tip_r17_combo.py --summary ROWS.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from tip_harness import (
    harness_main,
    resumed_rows,
    stored_alternatives,
    stored_records,
    write_rows,
)

from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION

VARIANTS = {"before": {"run_on": False, "end_fit": False}, "after": {}}


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        row = {"seed": seed}
        with stored_alternatives(rec):
            for name, kw in VARIANTS.items():
                t0 = time.process_time()
                tips = pipeline.traced_stereo_tips(
                    rec["calib"], rec["traces"], calibration=REAL_LIKE_CALIBRATION, **kw
                )[0]
                row[name] = [float(np.linalg.norm(np.asarray(t) - g))
                             for t, g in zip(tips, rec["truth"], strict=True)]  # fmt: skip
                row[name + "_cpu_s"] = time.process_time() - t0
        rows.append(row)
        write_rows(out, rows)
        print(seed, {k: [round(x, 1) for x in row[k]] for k in VARIANTS}, flush=True)


def summary(path: Path) -> None:
    rows = json.loads(path.read_text())["rows"]
    for half, sel in (("even", 0), ("odd", 1)):
        rs = [r for r in rows if r["seed"] % 2 == sel]
        if not rs:
            continue
        ok = {n: sum(max(r[n]) <= 5 for r in rs) for n in VARIANTS}
        fixed = [r["seed"] for r in rs if max(r["before"]) > 5 >= max(r["after"])]
        broken = [r["seed"] for r in rs if max(r["after"]) > 5 >= max(r["before"])]
        cpu = {n: float(np.median([r[n + "_cpu_s"] for r in rs])) for n in VARIANTS}
        print(f"{half} seeds, {len(rs)} frames: both tips within 5 px before {ok['before']}, "
              f"after {ok['after']}; fixed {fixed}; broken {broken}; CPU s a frame median "
              f"before {cpu['before']:.3f}, after {cpu['after']:.3f}")  # fmt: skip


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_r17_combo", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
