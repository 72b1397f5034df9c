"""Round 13 (issue 16 item 2, docs/decisions.md S31): the two-view branch choice of
``traced_stereo_tips`` scored by one smooth 3-D curve fitted to both views' backbones
(:func:`jaxcr.stereo.curve3d.fit_spline_pair`) instead of the monotone matching's
per-pair triangulation (:func:`jaxcr.stereo.backbone_consistency.backbone_consistency`),
compared in the same run on the same stored traces.

Step 1 (``trace``): per seed, both views of a cached ``real_like`` frame (``real_like_tip.py
--render-only --cache``) traced by :func:`plate_foreground` with the default config, and
each trace's :func:`trace_alternatives`, pickled into ``--store`` (scratch). Step 2
(``eval``): per stored seed, the variants below, each view's tip error against the truth.

* ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as committed (the stored
  alternatives returned for ``trace_alternatives``, which is deterministic);
* ``spline`` -- the same, the branch choice's inconsistency the spline fit's unexplained
  length (flagged frames only, as the reference);
* ``dtw_both``, ``spline_both`` -- ``ref`` and ``spline`` with pairs in which both views
  leave their traces offered too (``choose_branches(any_pair=True)``);
* ``oracle`` -- the candidate pair (trace or alternatives, end-face tips) nearest the
  truth: the ceiling of any branch choice over these candidates.

    python experiments/segmentation/real_like_tip_spline.py trace --seeds 4000-4039 \\
        --cache CACHE --store STORE
    python experiments/segmentation/real_like_tip_spline.py eval --seeds 4000-4039 \\
        --store STORE --out experiments/results/segmentation/real_like_tip_r13_dev_rows
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path

import numpy as np
from tip_harness import FORBIDDEN_FROM

from jaxcr.benchmarks import parse_seeds
from jaxcr.segmentation.foreground import (
    PlateForegroundConfig,
    plate_foreground,
    trace_alternatives,
)
from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.branch_choice import choose_branches
from jaxcr.stereo.curve3d import fit_spline_pair
from jaxcr.stereo.tip_consistency import epipolar_gap_px


def trace(seeds, cache: Path, store: Path) -> None:
    cfg = PlateForegroundConfig()
    store.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        dst = store / f"{seed}.pkl"
        if dst.exists():
            continue
        src = cache / f"real_like_1280x720_{seed}.pkl"
        while not src.exists():
            time.sleep(5)
        time.sleep(0.5)
        with open(src, "rb") as f:
            fr = pickle.load(f)
        t0 = time.process_time()
        traces = [plate_foreground(v.image, v.plate, v.entry_px, v.entry_dir_px, cfg=cfg)
                  for v in fr.views]  # fmt: skip
        alts = [trace_alternatives(t) for t in traces]
        rec = {"seed": seed, "traces": traces, "alts": alts,
               "calib": [v.calib_camera for v in fr.views],
               "truth": [np.asarray(v.tip_px) for v in fr.views],
               "cpu_s": time.process_time() - t0}  # fmt: skip
        tmp = dst.with_suffix(".tmp")
        with open(tmp, "wb") as f:
            pickle.dump(rec, f, protocol=4)
        os.replace(tmp, dst)
        print(seed, "traced", flush=True)


def _spline_unexplained(cams, a, b, tips) -> float:
    fit = fit_spline_pair(
        cams, pipeline._ending_at(a.backbone, tips[0]), pipeline._ending_at(b.backbone, tips[1])
    )
    return np.inf if fit is None else fit.unexplained_px


def _branch_step(
    cams, traces, alts, flag_px: float, score: str, every_frame: bool, any_pair: bool = False
):
    """``pipeline._branch_step`` with the stored alternatives and a choice of score."""
    traces = list(traces)
    tips, src = pipeline._stereo_or_own_tips(cams, traces)
    if (every_frame or epipolar_gap_px(cams, tips) > flag_px) and all(
        getattr(t, "retrace", None) is not None for t in traces
    ):
        cands = [[t] + list(a) for t, a in zip(traces, alts, strict=True)]
        if len(cands[0]) + len(cands[1]) > 2:
            if score == "dtw":
                inc = lambda a, b, tips: backbone_consistency(  # noqa: E731
                    cams, pipeline._ending_at(a.backbone, tips[0]),
                    pipeline._ending_at(b.backbone, tips[1])).inconsistent_px  # fmt: skip
            else:
                inc = lambda a, b, tips: _spline_unexplained(cams, a, b, tips)  # noqa: E731
            choice = choose_branches(
                cams, cands, tips_of=lambda a, b: pipeline._stereo_or_own_tips(cams, [a, b])[0],
                match_px=3.0 * flag_px,
                margin_px=1.25 * float(np.mean([t.width_px for t in traces])),
                inconsistency_of=inc,
                any_pair=any_pair,
            )  # fmt: skip
            if choice is not None and choice.indices != (0, 0):
                traces = [cands[k][choice.indices[k]] for k in range(2)]
                tips, src = pipeline._stereo_or_own_tips(cams, traces)
                src = src + "+branch"
    return traces, tips, src


def _variant(rec, score: str, every_frame: bool, any_pair: bool = False):
    cams = rec["calib"]
    traces, tips, src = _branch_step(
        cams, rec["traces"], rec["alts"], 5.0, score, every_frame, any_pair
    )
    tips, src, res, chosen = pipeline._tip_step(cams, traces, tips, src, 5.0)
    act = None if res is None else res.action
    branch = [c is not t for c, t in zip(chosen, rec["traces"], strict=True)]
    return tips, act, branch


def _oracle(rec, cands=None):
    """The worse view's error of the candidate pair nearest the truth (end-face tips): the
    ceiling of any choice among ``cands`` (per view; default each trace and its
    alternatives). Also used by real_like_tip_guided.py."""
    cams = rec["calib"]
    if cands is None:
        cands = [[t] + list(a) for t, a in zip(rec["traces"], rec["alts"], strict=True)]
    best = None
    for a in cands[0]:
        for b in cands[1]:
            tips = pipeline._stereo_or_own_tips(cams, [a, b])[0]
            e = [float(np.linalg.norm(t - g)) for t, g in zip(tips, rec["truth"], strict=True)]
            if best is None or max(e) < max(best):
                best = e
    return best


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = []
    jpath = out.with_suffix(".json")
    if jpath.exists():
        rows = json.loads(jpath.read_text())["rows"]
    done = {r["seed"] for r in rows}
    variants = {"ref": ("dtw", False, False), "spline": ("spline", False, False),
                "dtw_both": ("dtw", False, True),
                "spline_both": ("spline", False, True)}  # fmt: skip
    for seed in seeds:
        if seed in done or not (store / f"{seed}.pkl").exists():
            continue
        with open(store / f"{seed}.pkl", "rb") as f:
            rec = pickle.load(f)
        row = {"seed": seed, "n_alts": [len(a) for a in rec["alts"]]}
        for name, (score, every, both) in variants.items():
            t0 = time.process_time()
            tips, act, branch = _variant(rec, score, every, both)
            row[name] = {
                "err_px": [float(np.linalg.norm(np.asarray(t) - g))
                           for t, g in zip(tips, rec["truth"], strict=True)],
                "action": act, "branch": branch, "cpu_s": time.process_time() - t0,
            }  # fmt: skip
        row["oracle"] = {"err_px": _oracle(rec)}
        row["trace"] = {"err_px": [float(np.linalg.norm(t.tip - g))
                                   for t, g in zip(rec["traces"], rec["truth"], strict=True)]}  # fmt: skip
        rows.append(row)
        print(seed, {k: [round(x, 1) for x in row[k]["err_px"]] for k in
                     ("trace", *variants, "oracle")}, flush=True)  # fmt: skip
        tmp = jpath.with_suffix(".tmp")
        tmp.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
        os.replace(tmp, jpath)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("step", choices=["trace", "eval"])
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--cache", type=Path)
    ap.add_argument("--store", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("/tmp/real_like_tip_spline"))
    args = ap.parse_args()
    seeds = parse_seeds(args.seeds)
    if any(s >= FORBIDDEN_FROM for s in seeds):
        ap.error(f"seeds from {FORBIDDEN_FROM} are reserved for the fresh run")
    if args.step == "trace":
        trace(seeds, args.cache, args.store)
    else:
        evaluate(seeds, args.store, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
