"""Round 17c (issue 16 item 2, docs/decisions.md S42): the one-view tip placed by a blurred
capsule end fitted to the cue map (:func:`jaxcr.segmentation.capsule_end.with_capsule_end`)
instead of the tracer's end walk, on stored development traces, one view and two views,
before and after in the same run.

Input: stored traces (``real_like_tip_spline.py trace --store STORE``). Per seed:

* ``trace`` -- each view's stored one-view tip (the tracer's ``refine_tip_details``);
* ``fit`` -- each view's one-view tip after :func:`with_capsule_end` (the trace itself where
  the fit returns None: ``fitted`` False);
* ``ref`` -- this tree's :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
  ``calibration=REAL_LIKE_CALIBRATION`` (the stored alternatives returned for
  ``trace_alternatives``, which is deterministic);
* ``capsule`` -- the same with ``end_fit=True`` (the two traces and their alternatives
  placed by the fit; the guided candidates are not);
* ``capsule_image`` -- ``end_fit="image"``: and a fitted view keeps its fitted end face's
  length in the two-view step (not the one from the tube's 3-D direction).

The fit reads the full-resolution cue ``score`` the stored trace keeps (the one its own
``refine_tip_details`` read), so nothing is recomputed.

    python experiments/segmentation/real_like_tip_capsule.py --seeds 4000-4100 \\
        --store /tmp/tip34/traces --out ROWS
    python experiments/segmentation/real_like_tip_capsule.py --summary ROWS.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from tip_harness import (
    along_across as _along_across,
)
from tip_harness import (
    harness_main,
    resumed_rows,
    stored_alternatives,
    stored_records,
    variant_table,
    write_rows,
)
from tip_harness import (
    tip_errors as _errs,
)

from jaxcr.segmentation.capsule_end import with_capsule_end
from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION

#: the branch step and end placement as they were when the rows were made (stop 35, before
#: S41 ``run_on`` and S42 ``end_fit`` were on by default): ``ref`` is that tree's method
BEFORE_S41 = {"run_on": False}  # end_fit is the variant here


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        # Alternatives keyed by the trace's retrace context, which a placed copy shares.
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        row = {"seed": seed}
        with stored_alternatives(rec, key=lambda t: id(t.retrace)):
            t0 = time.process_time()
            placed = [with_capsule_end(t) for t in traces]
            fit_cpu = time.process_time() - t0
            row["trace"] = {"err_px": _errs([t.tip for t in traces], truth),
                            "along_across": [_along_across(t.end_dir, t.tip, g)
                                             for t, g in zip(traces, truth, strict=True)]}  # fmt: skip
            row["fit"] = {"err_px": _errs([t.tip for t in placed], truth),
                          "fitted": [p is not t for p, t in zip(placed, traces, strict=True)],
                          "along_across": [_along_across(t.end_dir, t.tip, g)
                                           for t, g in zip(placed, truth, strict=True)],
                          "cap_px": [float(t.cap_px) for t in placed],
                          "cpu_s": fit_cpu}  # fmt: skip
            for name, end_fit in (("ref", False), ("capsule", True), ("capsule_image", "image")):
                t0 = time.process_time()
                tips, src, res, _ = pipeline.traced_stereo_tips(
                    cams, traces, calibration=REAL_LIKE_CALIBRATION, end_fit=end_fit, **BEFORE_S41
                )
                row[name] = {"err_px": _errs(tips, truth), "source": src,
                             "action": None if res is None else res.action,
                             "cpu_s": time.process_time() - t0}  # fmt: skip
        rows.append(row)
        print(seed, {k: [round(x, 1) for x in row[k]["err_px"]]
                     for k in ("trace", "fit", "ref", "capsule", "capsule_image")}, flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    rows = [rows[s] for s in sorted(rows)]
    names = ("trace", "fit", "ref", "capsule", "capsule_image")
    for title, sel in (("even seeds (design)", [r for r in rows if r["seed"] % 2 == 0]),
                       ("odd seeds (held out)", [r for r in rows if r["seed"] % 2 == 1]),
                       ("all", rows)):  # fmt: skip
        variant_table(sel, title, names)
        for a, b in (("trace", "fit"), ("ref", "capsule"), ("ref", "capsule_image")):
            fx = [r["seed"] for r in sel if max(r[a]["err_px"]) > 5 >= max(r[b]["err_px"])]
            br = [r["seed"] for r in sel if max(r[a]["err_px"]) <= 5 < max(r[b]["err_px"])]
            vf = [f"{r['seed']}v{k + 1}" for r in sel for k in range(2)
                  if r[a]["err_px"][k] > 5 >= r[b]["err_px"][k]]  # fmt: skip
            vb = [f"{r['seed']}v{k + 1}" for r in sel for k in range(2)
                  if r[a]["err_px"][k] <= 5 < r[b]["err_px"][k]]  # fmt: skip
            print(f"\n`{a}` -> `{b}`: frames fixed {fx}, broken {br}; views fixed {vf}, "
                  f"broken {vb}")  # fmt: skip
    fitted = [f for r in rows for f in r["fit"]["fitted"]]
    print(f"\nviews placed by the fit: {sum(fitted)} of {len(fitted)}")
    for name in ("ref", "capsule", "capsule_image"):
        c = [r[name]["cpu_s"] for r in rows]
        print(f"{name} CPU s a frame: median {np.median(c):.3f}, max {max(c):.2f}")
    c = [r["fit"]["cpu_s"] for r in rows]
    print(f"fit of both views' traces, CPU s a frame: median {np.median(c):.3f}, max {max(c):.2f}")


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_capsule", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
