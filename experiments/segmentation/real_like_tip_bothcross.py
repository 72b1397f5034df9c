"""Round 16b (issue 16 item 2, docs/decisions.md S39): the > 30 px frames whose candidates
hold no right pair; a pair of two re-traces offered where both views' traces follow a
crossing object (:func:`jaxcr.stereo.branch_choice.choose_branches`'
``both_if_traces_cross``), compared with the method as on main (6e47a73) in one run.

Input: stored traces (``real_like_tip_spline.py trace --store STORE``). Per seed:

* ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as on main (S36 branch
  choice, S37 re-search tolerance; this tree's functions with
  ``both_if_traces_cross=False``, main's code path), the stored alternatives returned for
  ``trace_alternatives`` (deterministic);
* ``both`` -- the same with ``both_if_traces_cross=True`` (adopted);
* ``pipeline`` -- this tree's :func:`traced_stereo_tips` with
  ``calibration=REAL_LIKE_CALIBRATION`` (as ``real_like_tip.py`` calls it; equal to
  ``both``).

(Commit 043f63e also had ``calib_bc``: the backbone-consistency level of the branch
choice, fold and trim scaled by the calibration's tip tolerance; tried, not kept, S39.)

Each row records whether the branch choice ran (the epipolar flag of the views' own
tips) and the CPU seconds of each variant.

    python experiments/segmentation/real_like_tip_bothcross.py --seeds 4000-4100 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_bothcross.py --summary ROWS.json
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
from tip_harness import tip_errors as _errs

from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION, tip_epipolar_tolerance_px
from jaxcr.stereo.tip_consistency import epipolar_gap_px

VARIANTS = {"ref": {"both_if_traces_cross": False}, "both": {"both_if_traces_cross": True}}


def _run(cams, traces0, kw):
    traces, tips, src = pipeline._branch_step(cams, list(traces0), 5.0, **kw)
    research = tip_epipolar_tolerance_px(cams, tips, REAL_LIKE_CALIBRATION, floor_px=5.0)
    tips2, _, res, chosen = pipeline._tip_step(cams, traces, tips, src, 5.0, research_px=research)
    kind = ["trace" if c is t else ("guided" if c.departure == -1 else "alt")
            for c, t in zip(chosen, traces0, strict=True)]  # fmt: skip
    return tips, tips2, None if res is None else res.action, kind


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth = rec["calib"], rec["truth"]
        own = pipeline._stereo_or_own_tips(cams, list(rec["traces"]))[0]
        row = {"seed": seed, "trace": _errs([t.tip for t in rec["traces"]], truth),
               "flagged": bool(epipolar_gap_px(cams, own) > 5.0),
               "crossings_followed": [int(getattr(t, "crossings_followed", 0))
                                      for t in rec["traces"]]}  # fmt: skip
        with stored_alternatives(rec):
            for name, kw in VARIANTS.items():
                t0 = time.process_time()
                branch, final, action, kind = _run(cams, rec["traces"], kw)
                row[name] = {"err_px": _errs(final, truth), "branch_px": _errs(branch, truth),
                             "action": action, "chosen": kind,
                             "cpu_s": time.process_time() - t0}  # fmt: skip
            t0 = time.process_time()
            tips, _, res, _ = pipeline.traced_stereo_tips(
                cams, rec["traces"], calibration=REAL_LIKE_CALIBRATION
            )
            row["pipeline"] = {"err_px": _errs(tips, truth), "cpu_s": time.process_time() - t0,
                               "action": None if res is None else res.action}  # fmt: skip
        rows.append(row)
        print(seed, {k: [round(x, 1) for x in row[k]["err_px"]] for k in ("ref", "both")},
              row["both"]["chosen"], flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    rows = [rows[s] for s in sorted(rows)]
    for name in (*VARIANTS, "pipeline"):
        for title, sel in (("4000-4100", [r for r in rows if 4000 <= r["seed"] <= 4100]),
                           ("all", rows)):  # fmt: skip
            ok = sum(max(r[name]["err_px"]) <= 5 for r in sel)
            views = sum(sum(e <= 5 for e in r[name]["err_px"]) for r in sel)
            over30 = [r["seed"] for r in sel if max(r[name]["err_px"]) > 30]
            print(f"{name} {title}: {ok} of {len(sel)} frames both views within 5 px "
                  f"({views} views); > 30 px: {over30}")  # fmt: skip
    for v in (*list(VARIANTS)[1:], "pipeline"):
        fixed = [r["seed"] for r in rows if max(r["ref"]["err_px"]) > 5 >= max(r[v]["err_px"])]
        broken = [r["seed"] for r in rows if max(r["ref"]["err_px"]) <= 5 < max(r[v]["err_px"])]
        print(f"\n`{v}` against `ref`: fixed {fixed}, broken {broken}")
        for r in rows:
            a, b = r["ref"]["err_px"], r[v]["err_px"]
            if max(abs(x - y) for x, y in zip(a, b, strict=True)) > 0.05:
                print(f"- {r['seed']}: {a[0]:.1f} / {a[1]:.1f} -> {b[0]:.1f} / {b[1]:.1f} "
                      f"({r['ref'].get('action')} -> {r[v].get('action')}; chosen "
                      f"{r['ref'].get('chosen')} -> {r[v].get('chosen')})")  # fmt: skip
    both_cross = [r["seed"] for r in rows if min(r["crossings_followed"]) > 0]
    print(f"\nframes whose two traces both follow a crossing object: {both_cross}")
    for name in (*VARIANTS, "pipeline"):
        for title, sel in (("flagged", [r for r in rows if r["flagged"]]),
                           ("unflagged", [r for r in rows if not r["flagged"]])):  # fmt: skip
            c = [r[name]["cpu_s"] for r in sel]
            if c:
                print(f"{name} CPU s a frame, {title} ({len(c)}): median {np.median(c):.3f}, "
                      f"max {max(c):.2f}")  # fmt: skip


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_bothcross", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
