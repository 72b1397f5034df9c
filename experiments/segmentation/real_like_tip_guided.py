"""Round 14 (issue 16 item 2, docs/decisions.md S35): candidates re-traced along the other
view's backbone (:mod:`jaxcr.stereo.guided_retrace`) added to the two-view branch choice
of ``traced_stereo_tips``, compared with the committed method on the same stored traces in
one process.

Input: the stored traces of round 13 (``real_like_tip_spline.py trace --store STORE``:
per seed both views' :func:`plate_foreground` traces, their ``trace_alternatives``, the
calibrated cameras and the true tips). Per seed:

* ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` as committed (the stored
  alternatives returned for ``trace_alternatives``, which is deterministic);
* ``guided_one`` -- the same, each view's candidates also holding its trace re-traced along
  the other view's trace (:func:`jaxcr.stereo.guided_retrace.guided_candidates`), on frames
  whose tips the epipolar flag catches (as the branch choice runs), in one choice;
* ``guided`` -- two stages, as the pipeline: the guided candidates are added only where the
  choice among the views' own candidates finds no pair whose whole backbones leave at most
  40 px unexplained;
* ``guided_bb`` (rows of the first run only) -- ``guided_one`` also on frames whose tips
  agree but whose whole backbones do not (over ``--bb-widths`` tube widths left
  unexplained, :func:`backbone_consistency`);
* ``pipeline`` -- :func:`traced_stereo_tips` of this tree (with the guided candidates
  adopted, equal to ``guided``);
* ``oracle`` / ``oracle_guided`` -- the candidate pair (trace or alternatives, and the
  guided candidates, end-face tips, before the tip step) nearest the truth.

    python experiments/segmentation/real_like_tip_guided.py --seeds 4000-4070 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_guided.py --summary ROWS.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from real_like_tip_spline import _oracle  # the sibling script's candidate ceiling
from tip_harness import (
    dev_seeds,
    harness_parser,
    resumed_rows,
    stored_alternatives,
    stored_records,
    variant_table,
    write_rows,
)
from tip_harness import (
    tip_errors as _errs,
)

from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.branch_choice import choose_branches
from jaxcr.stereo.guided_retrace import guided_candidates
from jaxcr.stereo.tip_consistency import epipolar_gap_px


def _inconsistent(cams, a, b, tips) -> float:
    return backbone_consistency(
        cams, pipeline._ending_at(a.backbone, tips[0]), pipeline._ending_at(b.backbone, tips[1])
    ).inconsistent_px


def _branch_step(cams, traces, cands, flag_px: float, bb_widths: float | None):
    """``pipeline._branch_step`` with given candidates (trace first in each list); with
    ``bb_widths`` also run where the tips agree but the backbones leave over that many
    widths unexplained."""
    traces = list(traces)
    tips, src = pipeline._stereo_or_own_tips(cams, traces)
    width = float(np.mean([t.width_px for t in traces]))
    flagged = epipolar_gap_px(cams, tips) > flag_px
    if not flagged and bb_widths is not None and all(np.all(np.isfinite(t)) for t in tips):
        flagged = _inconsistent(cams, traces[0], traces[1], tips) > bb_widths * width
    if flagged and all(getattr(t, "retrace", None) is not None for t in traces):

        def choose(cands):
            if len(cands[0]) + len(cands[1]) <= 2:
                return None
            return choose_branches(
                cams, cands, tips_of=lambda a, b: pipeline._stereo_or_own_tips(cams, [a, b])[0],
                match_px=3.0 * flag_px, margin_px=1.25 * width,
                inconsistency_of=lambda a, b, tips: _inconsistent(cams, a, b, tips),
            )  # fmt: skip

        if isinstance(cands, tuple):  # (own candidates, guided): the two-stage choice
            own, guided = cands
            cands = own
            choice = choose(own)
            settled = (
                choice is not None
                and _inconsistent(cams, *(own[k][choice.indices[k]] for k in range(2)), choice.tips)
                <= 40.0
            )
            if not settled and (guided[0] or guided[1]):
                cands = [c + g for c, g in zip(own, guided, strict=True)]
                choice = choose(cands)
        else:
            choice = choose(cands)
        if choice is not None and choice.indices != (0, 0):
            traces = [cands[k][choice.indices[k]] for k in range(2)]
            tips, src = pipeline._stereo_or_own_tips(cams, traces)
            src = src + "+branch"
    return traces, tips, src, flagged


def _variant(rec, cands, bb_widths=None):
    cams = rec["calib"]
    traces, tips, src, flagged = _branch_step(cams, rec["traces"], cands, 5.0, bb_widths)
    tips, src, res, chosen = pipeline._tip_step(cams, traces, tips, src, 5.0)
    act = None if res is None else res.action
    kind = [
        "trace" if c is t else ("guided" if getattr(c, "departure", None) == -1 else "alt")
        for c, t in zip(chosen, rec["traces"], strict=True)
    ]
    return tips, act, kind, flagged


def evaluate(seeds, store: Path, out: Path, bb_widths: float, tip_mode: str) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams = rec["calib"]
        base = [[t] + list(a) for t, a in zip(rec["traces"], rec["alts"], strict=True)]
        t0 = time.process_time()
        g = guided_candidates(cams, rec["traces"], tip_mode=tip_mode)
        g_cpu = time.process_time() - t0
        plus = [base[k] + g[k] for k in range(2)]
        row = {"seed": seed, "n_alts": [len(a) for a in rec["alts"]],
               "n_guided": [len(x) for x in g], "guided_cpu_s": g_cpu,
               "guided_err_px": [[float(np.linalg.norm(c.tip - rec["truth"][k])) for c in g[k]]
                                 for k in range(2)]}  # fmt: skip
        for name, cands, bbw in (("ref", base, None), ("guided_one", plus, None),
                                 ("guided", (base, g), None)):  # fmt: skip
            t0 = time.process_time()
            tips, act, kind, flagged = _variant(rec, cands, bbw)
            row[name] = {"err_px": _errs(tips, rec["truth"]), "action": act, "chosen": kind,
                         "flagged": bool(flagged), "cpu_s": time.process_time() - t0}  # fmt: skip
        # The pipeline's own function (the stored alternatives returned for
        # trace_alternatives, which is deterministic): after adoption equal to `guided`.
        with stored_alternatives(rec):
            t0 = time.process_time()
            tips, _, res, chosen = pipeline.traced_stereo_tips(cams, rec["traces"])
            row["pipeline"] = {"err_px": _errs(tips, rec["truth"]),
                               "action": None if res is None else res.action,
                               "cpu_s": time.process_time() - t0}  # fmt: skip
        row["oracle"] = {"err_px": _oracle(rec, base)}
        row["oracle_guided"] = {"err_px": _oracle(rec, plus)}
        row["trace"] = {"err_px": _errs([t.tip for t in rec["traces"]], rec["truth"])}
        rows.append(row)
        print(seed, {k: [round(x, 1) for x in row[k]["err_px"]] for k in
                     ("trace", "ref", "guided_one", "guided", "pipeline", "oracle",
                      "oracle_guided")},
              "g", [[round(x, 1) for x in e] for e in row["guided_err_px"]],
              f"{g_cpu:.2f}s", flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    rows = [rows[s] for s in sorted(rows)]
    names = [
        "trace",
        "ref",
        "guided_one",
        "guided",
        "guided_bb",
        "pipeline",
        "oracle",
        "oracle_guided",
    ]
    names = [n for n in names if n in rows[0]]

    variant_table([r for r in rows if 4000 <= r["seed"] <= 4070], "Contiguous 4000-4070", names)
    variant_table([r for r in rows if not 4000 <= r["seed"] <= 4070], "Outside 4000-4070", names)
    variant_table(rows, "All", names)
    fail = [r for r in rows if max(r["ref"]["err_px"]) > 5]
    for o in ("oracle", "oracle_guided"):
        reach = [r["seed"] for r in fail if max(r[o]["err_px"]) <= 5]
        print(f"\n`ref` fails {len(fail)}; `{o}` has a pair within 5 px in {len(reach)}: {reach}")
    for n in [n for n in ("guided_one", "guided", "guided_bb", "pipeline") if n in names]:
        diff = [
            f"{r['seed']} {r['ref']['err_px'][0]:.1f} / {r['ref']['err_px'][1]:.1f} -> "
            f"{r[n]['err_px'][0]:.1f} / {r[n]['err_px'][1]:.1f}"
            + (f" ({'/'.join(r[n]['chosen'])})" if "chosen" in r[n] else "")
            for r in rows
            if max(abs(a - b) for a, b in zip(r["ref"]["err_px"], r[n]["err_px"], strict=True))
            > 0.05
        ]
        broken = [r["seed"] for r in rows
                  if max(r["ref"]["err_px"]) <= 5 < max(r[n]["err_px"])]  # fmt: skip
        print(f"\n- `{n}` differs from `ref` on {len(diff)}: " + "; ".join(diff))
        print(f"  right in `ref`, wrong in `{n}`: {broken}")
    cpu = [r["guided_cpu_s"] for r in rows]
    print(
        f"\nguided_candidates CPU s a frame (both anchors, every frame): median "
        f"{np.median(cpu):.2f}, max {max(cpu):.2f}"
    )
    flagged = [r for r in rows if r["ref"]["flagged"]]
    print(f"frames flagged by the tips' epipolar test: {len(flagged)} of {len(rows)} "
          f"({sum(4000 <= r['seed'] <= 4070 for r in flagged)} of the 71 of 4000-4070)")  # fmt: skip
    for n in [n for n in ("ref", "guided_one", "guided", "guided_bb", "pipeline") if n in names]:
        c = [r[n]["cpu_s"] for r in rows]
        cf = [r[n]["cpu_s"] for r in flagged]
        print(f"{n} two-view steps CPU s a frame: median {np.median(c):.3f}, max {max(c):.2f}; "
              f"flagged frames median {np.median(cf):.2f}, max {max(cf):.2f}")  # fmt: skip


def main() -> int:
    ap = harness_parser(__doc__, "/tmp/real_like_tip_guided")
    ap.add_argument("--bb-widths", type=float, default=2.0)
    ap.add_argument("--tip-mode", choices=["refine", "line"], default="refine")
    args = ap.parse_args()
    if args.summary is not None:
        summary(args.summary)
        return 0
    seeds = dev_seeds(ap, args)
    evaluate(seeds, args.store, args.out, args.bb_widths, args.tip_mode)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
