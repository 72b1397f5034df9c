"""Round 19 (issue 16 item 2, docs/decisions.md S46): a curled tube end fitted to each view's
cue map (:func:`jaxcr.segmentation.curl_end.fit_curl_end`) offered beside the two-view tips,
chosen by the other view; features and errors on stored development traces.

Per stored seed: ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as committed
(``calibration=REAL_LIKE_CALIBRATION``, the stored alternatives); then, for each view, the
curl fit on the chosen trace's path and cue map, and what the other view says of it: the
epipolar gap of the pair with that view's tip replaced by the curl tip (and both replaced),
and the pair's backbone inconsistency (:func:`jaxcr.stereo.backbone_consistency.
backbone_consistency`, px of backbone neither view explains) with that view's path ending
in the fitted axis. The rules are evaluated from these rows by ``--summary`` (no frame is
run again to evaluate a rule).

    python experiments/segmentation/real_like_tip_curl.py --seeds 4380-4559 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_curl.py --summary ROWS.json
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
    tip_errors,
    write_rows,
)

from jaxcr.segmentation.curl_end import fit_curl_end
from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION
from jaxcr.stereo.tip_consistency import epipolar_gap_px


def _ending_at(bb, tip):
    return pipeline._ending_at(np.asarray(bb, np.float64), np.asarray(tip, np.float64))


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        with stored_alternatives(rec):
            t0 = time.process_time()
            tips, src, res, chosen = pipeline.traced_stereo_tips(
                cams, traces, calibration=REAL_LIKE_CALIBRATION
            )
            ref_cpu = time.process_time() - t0
        row = {"seed": seed, "ref": {"err_px": tip_errors(tips, truth), "source": src,
                                     "action": None if res is None else res.action,
                                     "tips": [list(map(float, t)) for t in tips],
                                     "cpu_s": ref_cpu}}  # fmt: skip
        row["ref"]["gap_px"] = epipolar_gap_px(cams, tips)
        bbs = [_ending_at(t.backbone, p) for t, p in zip(chosen, tips, strict=True)]
        row["ref"]["inconsistent_px"] = (
            backbone_consistency(cams, *bbs).inconsistent_px
            if all(np.all(np.isfinite(t)) for t in tips) else float("nan"))  # fmt: skip
        views = []
        for j, t in enumerate(chosen):
            t0 = time.process_time()
            f = fit_curl_end(t.score, t.backbone, t.width_px)
            cpu = time.process_time() - t0
            if f is None or not all(np.all(np.isfinite(p)) for p in tips):
                views.append({"fit": False, "cpu_s": cpu})
                continue
            v = {
                "fit": True,
                "cpu_s": cpu,
                "turn_deg": f.turn_deg,
                "cost_ratio": f.cost / max(f.gentle_cost, 1e-12),
                "half_width": f.half_width,
                "width_px": float(t.width_px),
            }
            for name, tip, bb in (
                ("curl", f.tip, f.backbone),
                ("gentle", f.gentle_tip, f.gentle_backbone),
            ):
                new = [np.asarray(p, np.float64) for p in tips]
                new[j] = tip
                nb = list(bbs)
                nb[j] = bb
                v[name] = {
                    "tip": list(map(float, tip)),
                    "err_px": float(np.linalg.norm(tip - truth[j])),
                    "move_px": float(np.linalg.norm(tip - tips[j])),
                    "gap_px": epipolar_gap_px(cams, new),
                    "inconsistent_px": backbone_consistency(cams, *nb).inconsistent_px,
                }
            views.append(v)  # fmt: skip
        row["curl"] = views
        rows.append(row)
        print(seed, [round(x, 1) for x in row["ref"]["err_px"]],
              "gap", round(row["ref"]["gap_px"], 1),
              *[(n, [round(v[n]["err_px"], 1) if v["fit"] else None for v in views],
                 [round(v[n]["gap_px"], 1) if v["fit"] else None for v in views])
                for n in ("curl", "gentle")], flush=True)  # fmt: skip
        write_rows(out, rows)


def rule_tips(row: dict, *, min_gain_px: float, max_gap_px: float, min_turn_deg: float):
    """The tips a rule keeps for a row: view j's curl tip replaces the two-view tip where it
    moves the tip over a quarter width... (see docs/decisions.md S46)."""
    tips_err = list(row["ref"]["err_px"])
    best, gap0 = None, row["ref"]["gap_px"]
    for j, v in enumerate(row["curl"]):
        if not v["fit"] or abs(v["turn_deg"]) < min_turn_deg:
            continue
        gain = gap0 - v["gap_px"]
        if gain >= min_gain_px and v["gap_px"] <= max_gap_px and (best is None or gain > best[1]):
            best = (j, gain)
    if best is not None:
        tips_err[best[0]] = row["curl"][best[0]]["err_px"]
    return tips_err, best


def summary(path: Path) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    rows = [rows[s] for s in sorted(rows)]
    print(f"{len(rows)} frames; ref within 5 px both views: "
          f"{sum(max(r['ref']['err_px']) <= 5 for r in rows)}")  # fmt: skip
    print("\nseed | ref err | ref gap | incons | curl err | curl gap | curl incons | turn | ratio")
    for r in rows:
        bad = max(r["ref"]["err_px"]) > 5
        c = r["curl"]
        print(("F " if bad else "  ") + str(r["seed"]),
              [round(x, 1) for x in r["ref"]["err_px"]], round(r["ref"]["gap_px"], 1),
              round(r["ref"]["inconsistent_px"], 1),
              [round(v.get("err_px", np.nan), 1) for v in c],
              [round(v.get("gap_px", np.nan), 1) for v in c],
              [round(v.get("inconsistent_px", np.nan), 1) for v in c],
              [round(v.get("turn_deg", np.nan)) for v in c],
              [round(v.get("cost_ratio", np.nan), 2) for v in c])  # fmt: skip


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_curl", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
