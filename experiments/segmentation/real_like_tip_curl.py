"""Round 19 (issue 16 item 2, docs/decisions.md S46): a curled tube end fitted to each view's
cue map (:func:`jaxcr.segmentation.curl_end.fit_curl_end`) offered beside the two-view tips,
chosen by the other view; features and errors on stored development traces.

Per stored seed: ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as committed
before S46 (``calibration=REAL_LIKE_CALIBRATION``, ``curl_ends=False``, the stored
alternatives); then, for each view, the
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

import time
from pathlib import Path

import numpy as np
from tip_harness import (
    harness_main,
    merged_rows,
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


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        with stored_alternatives(rec):
            t0 = time.process_time()
            tips, src, res, chosen = pipeline.traced_stereo_tips(
                cams, traces, calibration=REAL_LIKE_CALIBRATION, curl_ends=False
            )
            ref_cpu = time.process_time() - t0
        row = {"seed": seed, "ref": {"err_px": tip_errors(tips, truth), "source": src,
                                     "action": None if res is None else res.action,
                                     "tips": [list(map(float, t)) for t in tips],
                                     "cpu_s": ref_cpu}}  # fmt: skip
        row["ref"]["gap_px"] = epipolar_gap_px(cams, tips)
        bbs = [pipeline._ending_at(t.backbone, p) for t, p in zip(chosen, tips, strict=True)]
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


def rule_errors(
    row: dict,
    *,
    max_ratio: float,
    min_gap_drop_px: float,
    min_move_px: float,
    refit_move_px: float | None = None,
    refit_gap_px: float = 5.0,
):
    """Each view's tip error under the rule of :func:`jaxcr.stereo.curl_choice.
    choose_curled_end` with these settings, from the row's features: the view whose curl
    fit beats its gentle fit most (the lowest cost ratio, at most ``max_ratio``) has its tip
    replaced by the curl fit's where that moves it at least ``min_move_px`` and the pair's
    epipolar gap drops by at least ``min_gap_drop_px``; else (S47, with ``refit_move_px``)
    the view whose gentle fit's tip is at least ``refit_move_px`` away and brings the gap
    down by ``min_gap_drop_px`` to at most ``refit_gap_px`` (the lower gap of two); (errors,
    view or None)."""
    err = list(row["ref"]["err_px"])
    best = None
    for j, v in enumerate(row["curl"]):
        if not v["fit"] or v["cost_ratio"] > max_ratio:
            continue
        c = v["curl"]
        if c["move_px"] < min_move_px or c["gap_px"] > row["ref"]["gap_px"] - min_gap_drop_px:
            continue
        if best is None or v["cost_ratio"] < row["curl"][best]["cost_ratio"]:
            best = j
    if best is not None:
        err[best] = row["curl"][best]["curl"]["err_px"]
        return err, best
    if refit_move_px is None:
        return err, None
    for j, v in enumerate(row["curl"]):
        if not v["fit"]:
            continue
        g = v["gentle"]
        cap = min(row["ref"]["gap_px"] - min_gap_drop_px, refit_gap_px)
        if (
            g["move_px"] >= refit_move_px
            and g["gap_px"] <= cap
            and (best is None or g["gap_px"] < row["curl"][best]["gentle"]["gap_px"])
        ):
            best = j
    if best is not None:
        err[best] = row["curl"][best]["gentle"]["err_px"]
    return err, best


GRID = [dict(max_ratio=r, min_gap_drop_px=g, min_move_px=m)
        for r in (0.8, 0.85, 0.9, 0.93, 0.95, 0.97) for g in (0.0, 1.0, 2.0, 3.0)
        for m in (2.0, 4.0)]  # fmt: skip


def _count(rows, **kw) -> dict:
    """Frames with both tips within 5 px under the rule, the frames it fixes and breaks,
    how often it fires, and the views it moves over 1 px further from / nearer the truth."""
    out = {"ok": 0, "fixed": [], "broken": [], "fired": 0, "worse": [], "better": 0}
    for r in rows:
        e, j = rule_errors(r, **kw)
        a, b = max(r["ref"]["err_px"]) <= 5, max(e) <= 5
        out["ok"] += b
        if b and not a:
            out["fixed"].append(r["seed"])
        if a and not b:
            out["broken"].append(r["seed"])
        if j is not None:
            out["fired"] += 1
            d = e[j] - r["ref"]["err_px"][j]
            if d > 1.0:
                out["worse"].append(r["seed"])
            out["better"] += d < -1.0
    return out


def summary(path: Path) -> None:
    """The rule's grid on even seeds (design) and odd ones (held out), best even first (ties:
    fewer views made worse); ``path`` may list several rows files, comma separated."""
    rows = merged_rows(path)
    even = [r for r in rows if r["seed"] % 2 == 0]
    odd = [r for r in rows if r["seed"] % 2 == 1]

    def ref(sel):
        return sum(max(r["ref"]["err_px"]) <= 5 for r in sel)

    print(f"{len(rows)} frames; committed method, both tips within 5 px: even {ref(even)} of "
          f"{len(even)}, odd {ref(odd)} of {len(odd)}\n")  # fmt: skip
    scored = sorted(((_count(even, **kw), _count(odd, **kw), kw) for kw in GRID),
                    key=lambda x: (-x[0]["ok"], len(x[0]["worse"])))  # fmt: skip
    print("| max ratio | min gap drop | min move | even: ok / fixed / broken / fired / worse > 1 "
          "px / better > 1 px | odd: the same |\n|---|---|---|---|---|")  # fmt: skip
    for e, o, kw in scored[:16]:
        cells = [f"{c['ok']} / {c['fixed']} / {c['broken']} / {c['fired']} / {c['worse']} / "
                 f"{c['better']}" for c in (e, o)]  # fmt: skip
        print(f"| {kw['max_ratio']} | {kw['min_gap_drop_px']} | {kw['min_move_px']} | "
              f"{cells[0]} | {cells[1]} |")  # fmt: skip
    s46 = dict(max_ratio=0.9, min_gap_drop_px=2.0, min_move_px=2.0)
    print("\nS47 after S46's settings (the gentle fit's end where it is far from the tip): "
          "cells as above, against S46\n")  # fmt: skip
    print("| refit move | max gap after | even | odd |\n|---|---|---|---|")
    base_e = [dict(r, ref=dict(r["ref"], err_px=rule_errors(r, **s46)[0])) for r in even]
    base_o = [dict(r, ref=dict(r["ref"], err_px=rule_errors(r, **s46)[0])) for r in odd]
    for mv in (6.0, 8.0, 10.0, 12.0, 16.0):
        for mg in (3.0, 5.0, 100.0):
            kw = dict(s46, refit_move_px=mv, refit_gap_px=mg)
            cells = []
            for sel, base in ((even, base_e), (odd, base_o)):
                c = _count(sel, **kw)
                fx = [x for x in c["fixed"] if max(base[[r["seed"] for r in sel].index(x)]
                                                    ["ref"]["err_px"]) > 5]  # fmt: skip
                cells.append(f"{c['ok']} / fixed {fx} / broken {c['broken']} / fired {c['fired']}")
            print(f"| {mv} | {mg} | {cells[0]} | {cells[1]} |")
    cpu = [sum(v["cpu_s"] for v in r["curl"]) for r in rows]
    print(f"\nCurl fits' CPU a frame (both views): median {np.median(cpu):.2f} s, p90 "
          f"{np.percentile(cpu, 90):.2f} s, max {max(cpu):.1f} s")  # fmt: skip


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_curl", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
