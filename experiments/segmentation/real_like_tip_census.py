"""Where the real_like tip target is lost (issue 16 item 2, stop 40): every frame of a store
run through :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as shipped, each failing frame
(a view's tip over 5 px from the truth) put in the first class of this list that it fits:

1. ``after the choice`` -- the chosen traces' one-view tips (the capsule end of S42) are both
   within 5 px; the two-view end faces or the tip step moved a view off;
2. ``choice replaced a right trace`` -- a failing view's own trace ended within 5 px and the
   branch choice replaced it;
3. ``right candidate not chosen`` -- every failing view holds a candidate (its trace or a
   stored re-trace; the guided candidates are not stored) ending within 5 px;
4. ``end placement`` -- a failing view's nearest candidate ends 5-15 px off;
5. ``no candidate at the end`` -- a failing view's nearest candidate ends over 15 px off.

Per frame also the tip step's action and whether a failing view's tip lies within 12 px of
the scene's occluder (the rod the preset puts in front of the robot; needs ``--cache``). A
mechanical split, not a measurement of causes.

    python experiments/segmentation/real_like_tip_census.py --seeds 4560-4919 \\
        --store STORE --cache CACHE --out ROWS
    python experiments/segmentation/real_like_tip_census.py --summary ROWS.json
"""

from __future__ import annotations

import collections
import pickle
from pathlib import Path

import jax.numpy as jnp
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

from jaxcr.kinematics.fit import closest_points_on_polyline
from jaxcr.segmentation.capsule_end import with_capsule_end
from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION

CLASSES = ("after the choice", "choice replaced a right trace", "right candidate not chosen",
           "end placement", "no candidate at the end")  # fmt: skip
OCCLUDER_PX = 12.0


def _polyline_distance(p: np.ndarray, poly: np.ndarray) -> float:
    c = closest_points_on_polyline(
        jnp.asarray(p[None], jnp.float32), jnp.asarray(poly, jnp.float32)
    )
    return float(np.linalg.norm(np.asarray(c[0], np.float64) - p))


def _occluders(cache: Path | None, seed: int) -> list:
    path = None if cache is None else cache / f"real_like_1280x720_{seed}.pkl"
    if path is None or not path.exists():
        return [None, None]
    with open(path, "rb") as f:
        fr = pickle.load(f)
    return [None if v.occluder_px is None else np.asarray(v.occluder_px, np.float64).reshape(-1, 2)
            for v in fr.views]  # fmt: skip


def classify(row: dict) -> str | None:
    """The class (``CLASSES``) of a row, None when both views are within 5 px."""
    v = row["views"]
    fail = [k for k in range(2) if v[k]["final"] > 5.0]
    if not fail:
        return None
    if all(x["capsule"] <= 5.0 for x in v):
        return CLASSES[0]
    if any(v[k]["trace"] <= 5.0 and v[k]["replaced"] for k in fail):
        return CLASSES[1]
    nearest = [v[k]["nearest_candidate"] for k in fail]
    if all(x <= 5.0 for x in nearest):
        return CLASSES[2]
    return CLASSES[3] if max(nearest) <= 15.0 else CLASSES[4]


def evaluate(seeds, store: Path, cache: Path | None, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        with stored_alternatives(rec):
            tips, src, res, chosen = pipeline.traced_stereo_tips(
                cams, traces, calibration=REAL_LIKE_CALIBRATION
            )
        occ = _occluders(cache, seed)
        final = tip_errors(tips, truth)
        views = []
        for k in range(2):
            c = getattr(chosen[k], "curl_of", chosen[k])
            cands = [traces[k], *rec["alts"][k]]
            tip = np.asarray(tips[k], np.float64)
            views.append({
                "final": final[k],
                "trace": tip_errors([traces[k].tip], [truth[k]])[0],
                "capsule": tip_errors([with_capsule_end(c).tip], [truth[k]])[0],
                "replaced": c is not traces[k],
                "nearest_candidate": min(tip_errors([x.tip], [truth[k]])[0] for x in cands),
                "occluder_px": None if occ[k] is None or not np.all(np.isfinite(tip))
                else _polyline_distance(tip, occ[k]),
            })  # fmt: skip
        row = {"seed": seed, "views": views, "source": src,
               "action": None if res is None else res.action}  # fmt: skip
        row["class"] = classify(row)
        rows.append(row)
        print(seed, [round(x, 1) for x in final], row["class"], row["action"], flush=True)
        write_rows(out, rows)


def summary(path) -> None:
    rows = merged_rows(path)
    n = len(rows)
    fails = [r for r in rows if r["class"] is not None]
    print(f"{n} frames; {n - len(fails)} with both tips within 5 px; {len(fails)} failing\n")
    print("| class | frames | of which a failing tip on the occluder | seeds |\n|---|---|---|---|")
    for c in CLASSES:
        sel = [r for r in fails if r["class"] == c]
        occ = [r for r in sel if any(v["final"] > 5.0 and v["occluder_px"] is not None
                                     and v["occluder_px"] <= OCCLUDER_PX for v in r["views"])]  # fmt: skip
        seeds = ", ".join(str(r["seed"]) for r in sel)
        print(f"| {c} | {len(sel)} ({100.0 * len(sel) / n:.1f} %) | {len(occ)} | {seeds} |")
    acts = collections.Counter((r["action"], r["class"] is None) for r in rows)
    print("\n| tip step's action | frames passing | frames failing |\n|---|---|---|")
    for a in sorted({k[0] for k in acts}, key=str):
        print(f"| {a} | {acts[(a, True)]} | {acts[(a, False)]} |")


if __name__ == "__main__":
    raise SystemExit(harness_main(__doc__, "/tmp/real_like_tip_census", evaluate, summary,
                                  cache=True))  # fmt: skip
