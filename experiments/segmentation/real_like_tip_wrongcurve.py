"""Round 15a (issue 16 item 2, docs/decisions.md S36): the "wrong curve" class of the
real_like tip failures. Variants of ``traced_stereo_tips``' branch choice compared with the
method as at c5406ad (``ref``) on the same stored traces in one process.

Input: stored traces (``real_like_tip_spline.py trace --store STORE``: per seed both views'
:func:`plate_foreground` traces, their ``trace_alternatives``, the calibrated cameras and the
true tips). Per seed:

* ``ref`` -- the method as at c5406ad (round 14, S35): the guided candidates
  (:func:`jaxcr.stereo.guided_retrace.guided_candidates`, turns copied from the trace they
  may replace) offered in a second stage only;
* ``one`` -- the guided candidates in one stage (round 14's ``guided_one``);
* ``one_own`` -- one stage, each guided candidate with its own turn and crossings at its
  view's junctions (:func:`jaxcr.stereo.guided_ranking.with_own_turns`);
* ``two_own`` -- two stages (as ``ref``), own turns;
* ``one_own_x`` -- ``one_own``, and an alternative that follows more crossing objects than
  its view's trace allowed when the pair explains itself
  (``choose_branches(more_crossings_if_consistent=True)``);
* ``one_own_g`` -- ``one_own``, a view's guided candidate offered only where none of the
  view's own re-traces explains the other view's trace
  (:func:`jaxcr.stereo.guided_ranking.offered_guided`); ``one_own_gx`` the same with
  ``more_crossings_if_consistent``;
* ``pipeline`` -- this tree's :func:`traced_stereo_tips` (the stored alternatives returned
  for ``trace_alternatives``, which is deterministic);
* ``oracle_guided`` -- the candidate pair nearest the truth (the ceiling of any choice).

    python experiments/segmentation/real_like_tip_wrongcurve.py --seeds 4000-4100 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_wrongcurve.py --summary ROWS.json
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
from real_like_tip_guided import _errs, _variant  # the sibling script's round-14 variants
from real_like_tip_spline import _oracle  # the candidate ceiling
from tip_harness import (
    dev_seeds,
    harness_parser,
    resumed_rows,
    stored_alternatives,
    stored_records,
    variant_table,
    write_rows,
)

from jaxcr.benchmarks import parse_seeds
from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.branch_choice import CONSISTENT_PX, choose_branches
from jaxcr.stereo.guided_ranking import offered_guided, with_own_turns
from jaxcr.stereo.guided_retrace import guided_candidates
from jaxcr.stereo.tip_consistency import epipolar_gap_px

VARIANTS = ("ref", "one", "one_own", "two_own", "one_own_x", "one_own_g", "one_own_gx", "pipeline")


def _pipeline(rec):
    with stored_alternatives(rec):
        tips, _, res, chosen = pipeline.traced_stereo_tips(rec["calib"], rec["traces"])
    kind = [
        "trace" if c is t else ("guided" if getattr(c, "departure", None) == -1 else "alt")
        for c, t in zip(chosen, rec["traces"], strict=True)
    ]
    return tips, None if res is None else res.action, kind


def _explains(cams, a, b) -> bool:
    """The pipeline's test of a pair that explains itself: tips within the choice's
    ``match_px`` (15) of each other's epipolar lines, backbones within
    ``CONSISTENT_PX``."""
    tips = pipeline._stereo_or_own_tips(cams, [a, b])[0]
    if not all(np.all(np.isfinite(t)) for t in tips) or epipolar_gap_px(cams, tips) > 15.0:
        return False
    return (
        backbone_consistency(
            cams, pipeline._ending_at(a.backbone, tips[0]), pipeline._ending_at(b.backbone, tips[1])
        ).inconsistent_px
        <= CONSISTENT_PX
    )


def _one_choice(rec, cands, **choose_kw):
    """``pipeline._branch_step`` with given candidates (one choice) and ``choose_branches``
    keywords, then the tip step: (tips, action, chosen kinds, flagged)."""
    cams, traces = rec["calib"], list(rec["traces"])
    tips, src = pipeline._stereo_or_own_tips(cams, traces)
    width = float(np.mean([t.width_px for t in traces]))
    flagged = epipolar_gap_px(cams, tips) > 5.0
    if flagged and len(cands[0]) + len(cands[1]) > 2:

        def bad(a, b, tips):
            return backbone_consistency(
                cams,
                pipeline._ending_at(a.backbone, tips[0]),
                pipeline._ending_at(b.backbone, tips[1]),
            ).inconsistent_px

        choice = choose_branches(
            cams, cands, tips_of=lambda a, b: pipeline._stereo_or_own_tips(cams, [a, b])[0],
            match_px=15.0, margin_px=1.25 * width, inconsistency_of=bad, **choose_kw,
        )  # fmt: skip
        if choice is not None and choice.indices != (0, 0):
            traces = [cands[k][choice.indices[k]] for k in range(2)]
            tips, src = pipeline._stereo_or_own_tips(cams, traces)
            src += "+branch"
    tips, src, res, chosen = pipeline._tip_step(cams, traces, tips, src, 5.0)
    kind = [
        "trace" if c is t else ("guided" if getattr(c, "departure", None) == -1 else "alt")
        for c, t in zip(chosen, rec["traces"], strict=True)
    ]
    return tips, None if res is None else res.action, kind, flagged


def evaluate(seeds, store: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams = rec["calib"]
        base = [[t] + list(a) for t, a in zip(rec["traces"], rec["alts"], strict=True)]
        t0 = time.process_time()
        g = guided_candidates(cams, rec["traces"])
        g_cpu = time.process_time() - t0
        t0 = time.process_time()
        g_own = with_own_turns([[copy.copy(c) for c in x] for x in g], rec["traces"])
        own_cpu = time.process_time() - t0
        plus, plus_own = ([base[k] + x[k] for k in range(2)] for x in (g, g_own))
        row = {"seed": seed, "guided_cpu_s": g_cpu, "own_turn_cpu_s": own_cpu,
               "guided_err_px": [[float(np.linalg.norm(c.tip - rec["truth"][k])) for c in g[k]]
                                 for k in range(2)],
               "guided_turn": [[[float(c.crossing_turn_deg), int(c.crossings_followed)]
                                for c in x] for x in g],
               "guided_own_turn": [[[float(c.crossing_turn_deg), int(c.crossings_followed)]
                                    for c in x] for x in g_own]}  # fmt: skip
        for name, cands in (("ref", (base, g)), ("one", plus), ("one_own", plus_own),
                            ("two_own", (base, g_own))):  # fmt: skip
            t0 = time.process_time()
            tips, act, kind, flagged = _variant(rec, cands)
            row[name] = {"err_px": _errs(tips, rec["truth"]), "action": act, "chosen": kind,
                         "flagged": bool(flagged), "cpu_s": time.process_time() - t0}  # fmt: skip
        t0 = time.process_time()
        tips, act, kind, flagged = _one_choice(rec, plus_own, more_crossings_if_consistent=True)
        row["one_own_x"] = {"err_px": _errs(tips, rec["truth"]), "action": act, "chosen": kind,
                            "flagged": bool(flagged), "cpu_s": time.process_time() - t0}  # fmt: skip
        g_off = offered_guided(g_own, base, lambda a, b, cams=cams: _explains(cams, a, b))
        row["n_guided_offered"] = [len(x) for x in g_off]
        plus_g = [base[k] + g_off[k] for k in range(2)]
        for name, kw in (("one_own_g", {}), ("one_own_gx", {"more_crossings_if_consistent": True})):
            t0 = time.process_time()
            tips, act, kind, flagged = _one_choice(rec, plus_g, **kw)
            row[name] = {"err_px": _errs(tips, rec["truth"]), "action": act, "chosen": kind,
                         "flagged": bool(flagged), "cpu_s": time.process_time() - t0}  # fmt: skip
        t0 = time.process_time()
        tips, act, kind = _pipeline(rec)
        row["pipeline"] = {"err_px": _errs(tips, rec["truth"]), "action": act, "chosen": kind,
                           "cpu_s": time.process_time() - t0}  # fmt: skip
        row["oracle_guided"] = {"err_px": _oracle(rec, plus)}
        rows.append(row)
        print(seed, {k: [round(x, 1) for x in row[k]["err_px"]] for k in
                     (*VARIANTS, "oracle_guided")},
              "g", row["guided_err_px"], row["guided_turn"], row["guided_own_turn"],
              flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path, sets: dict) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    names = [n for n in (*VARIANTS, "oracle_guided") if n in next(iter(rows.values()))]
    for title, seeds in sets.items():
        variant_table([rows[s] for s in seeds if s in rows], title, names)
    allr = [rows[s] for s in sorted(rows)]
    for n in [n for n in names if n not in ("ref", "oracle_guided")]:
        fixed = [r["seed"] for r in allr if max(r["ref"]["err_px"]) > 5 >= max(r[n]["err_px"])]
        broken = [r["seed"] for r in allr if max(r["ref"]["err_px"]) <= 5 < max(r[n]["err_px"])]
        print(f"\n`{n}` against `ref`: fixed {len(fixed)} {fixed}; broken {len(broken)} {broken}")
        for r in allr:
            a, b = r["ref"]["err_px"], r[n]["err_px"]
            if max(abs(x - y) for x, y in zip(a, b, strict=True)) > 0.05:
                print(f"  {r['seed']}: {a[0]:.1f} / {a[1]:.1f} -> {b[0]:.1f} / {b[1]:.1f}"
                      f" ({'/'.join(r[n].get('chosen', []))}; {r[n].get('action')})")  # fmt: skip
    flagged = [r for r in allr if r["ref"]["flagged"]]
    print(f"\nflagged by the tips' epipolar test: {len(flagged)} of {len(allr)}")
    for n in [n for n in VARIANTS if n in names]:
        cf = [r[n]["cpu_s"] for r in flagged]
        print(
            f"{n}: two-view steps CPU s on flagged frames: median {np.median(cf):.2f}, "
            f"max {max(cf):.2f}"
        )
    own = [r["own_turn_cpu_s"] for r in allr]
    print(f"own turns CPU s a frame: median {np.median(own):.4f}, max {max(own):.4f}")


def main() -> int:
    ap = harness_parser(__doc__, "/tmp/real_like_tip_wrongcurve")
    ap.add_argument("--sets", default="", help="NAME=SEEDS;NAME=SEEDS for --summary")
    args = ap.parse_args()
    if args.summary is not None:
        sets = {"all": sorted(r["seed"] for r in json.loads(args.summary.read_text())["rows"])}
        for part in filter(None, args.sets.split(";")):
            name, s = part.split("=", 1)
            sets[name] = parse_seeds(s)
        summary(args.summary, sets)
        return 0
    seeds = dev_seeds(ap, args)
    evaluate(seeds, args.store, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
