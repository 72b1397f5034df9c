"""Round 17b (issue 16 item 2, docs/decisions.md S41): the > 30 px class of ``real_like``
tip failures (a wrong branch: a view's trace followed a crossing object or the board's
tape), classified on the pool of stored development traces, and a variant of the branch
choice beside this tree's method in the same run.

Input: stored traces (``real_like_tip_spline.py trace --store STORE``). Per seed:

* ``ref`` -- this tree's :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
  ``calibration=REAL_LIKE_CALIBRATION`` (as ``real_like_tip.py``'s ``trace_stereo`` calls
  it), the stored alternatives returned for ``trace_alternatives`` (deterministic);
* ``variant`` -- the same with the variant's hook on (see ``VARIANT_KW``);
* ``diag`` -- the branch choice taken apart: every candidate of each view (trace,
  re-traces, the guided paths before and after their gates), each pair's tips (as the
  choice places them), their errors against the truth, epipolar distance and backbone
  inconsistency, the pair chosen, and for the best pair by the oracle (the smallest
  larger-view error) the first of the choice's rules that kept it out (``why``).

    python experiments/segmentation/real_like_tip_wrongbranch.py --seeds LIST --store STORE \\
        --out ROWS
    python experiments/segmentation/real_like_tip_wrongbranch.py --summary ROWS.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from tip_harness import (
    dev_seeds,
    harness_parser,
    resumed_rows,
    stored_alternatives,
    stored_records,
    write_rows,
)
from tip_harness import tip_errors as _errs

from jaxcr.stereo import pipeline
from jaxcr.stereo.backbone_consistency import backbone_consistency
from jaxcr.stereo.branch_choice import CONSISTENT_PX, choose_branches
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION
from jaxcr.stereo.guided_ranking import offered_guided, with_own_turns
from jaxcr.stereo.guided_retrace import evidence_map, guided_candidate, guided_candidates
from jaxcr.stereo.tip_consistency import _beyond_evidence, epipolar_gap_px

#: keyword arguments of ``traced_stereo_tips`` for the variant (S41)
VARIANT_KW: dict = {"run_on": True, "end_fit": False}
#: the branch step and end placement as they were when the rows were made (stop 35, before
#: S41 ``run_on`` and S42 ``end_fit`` were on by default): ``ref`` is that tree's method
BEFORE_S41_S42 = {"run_on": False, "end_fit": False}


def _coverage(trace, level: float = 0.5) -> float:
    """Fraction of ``trace``'s backbone (1 px steps) whose evidence map reads >= level."""
    from jaxcr.stereo.backbone_consistency import resample_polyline
    from jaxcr.stereo.trace3d import _sample

    if trace.score is None:
        return float("nan")
    E = evidence_map(trace.score, width_px=float(trace.width_px))
    p = resample_polyline(np.asarray(trace.backbone, np.float64), 1.0)
    return float(np.mean(_sample(E, p[None])[0] >= level))


def _kind(c, k0):
    if c is k0:
        return "trace"
    return "guided" if getattr(c, "departure", 0) == -1 else "alt"


def diagnose(cams, traces, truth, flag_px: float = 5.0) -> dict:
    """The branch choice of :func:`pipeline._branch_step` taken apart (module docstring)."""
    traces = list(traces)
    own_tips, _ = pipeline._stereo_or_own_tips(cams, traces)
    flagged = bool(epipolar_gap_px(cams, own_tips) > flag_px)
    out = {"flagged": flagged, "own_err": _errs(own_tips, truth)}
    cands = [[t] + pipeline.trace_alternatives(t) for t in traces]
    pair_tips, pair_bad = {}, {}

    def tips_of(a, b):
        key = (id(a), id(b))
        if key not in pair_tips:
            pair_tips[key] = pipeline._stereo_or_own_tips(cams, [a, b])[0]
        return pair_tips[key]

    def inconsistency(a, b, tips):
        key = (id(a), id(b))
        if key not in pair_bad:
            pair_bad[key] = backbone_consistency(
                cams, pipeline._ending_at(a.backbone, tips[0]),
                pipeline._ending_at(b.backbone, tips[1]),
            ).inconsistent_px  # fmt: skip
        return pair_bad[key]

    def explains(a, b):
        tips = tips_of(a, b)
        return (all(np.all(np.isfinite(t)) for t in tips)
                and epipolar_gap_px(cams, tips) <= 3.0 * flag_px
                and inconsistency(a, b, tips) <= CONSISTENT_PX)  # fmt: skip

    # Guided paths: the gated ones as the pipeline makes them, and the raw ones (no gate).
    gated = with_own_turns(guided_candidates(cams, traces), traces)
    offered = offered_guided(gated, cands, explains)
    raw = [[], []]
    for av in (0, 1):
        g = guided_candidate(cams, av, traces[av], traces[1 - av])
        if g is not None:
            raw[1 - av].append(g)
    raw = with_own_turns(raw, traces)
    gate_info = []
    for av in (0, 1):
        j = 1 - av
        info = {"anchor": av, "anchor_ends": float(_beyond_evidence(traces[av], traces[av].tip,
                                                                     0.4, 2.0))}  # fmt: skip
        if raw[j]:
            g = raw[j][0]
            info.update(tail_px=g.guided.tail_px, width=float(traces[av].width_px),
                        cand_ends=float(_beyond_evidence(g, g.tip, 0.4, 2.0)),
                        err=_errs([g.tip], [truth[j]])[0], gated_in=bool(gated[j]),
                        offered=bool(offered[j]))  # fmt: skip
        gate_info.append(info)
    out["guided"] = gate_info
    # All candidates: own, + offered guided (the pipeline's), + raw guided not offered.
    full = []
    for v in (0, 1):
        c = list(cands[v])
        c += offered[v]
        extra = [g for g in raw[v] if not offered[v]]
        c += extra
        full.append(c)
    n_pipe = [len(cands[v]) + len(offered[v]) for v in (0, 1)]
    out["candidates"] = [
        [{"kind": _kind(c, traces[v]), "tip_err": _errs([c.tip], [truth[v]])[0],
          "followed": int(getattr(c, "crossings_followed", 0)),
          "turn": float(c.crossing_turn_deg), "in_pipeline": i < n_pipe[v],
          "coverage": _coverage(c),
          "off_px": float(c.guided.off_px) if getattr(c, "guided", None) is not None else None,
          "gaps": len(c.gaps or [])}
         for i, c in enumerate(full[v])]
        for v in (0, 1)
    ]  # fmt: skip
    pairs = []
    for i0, a in enumerate(full[0]):
        for i1, b in enumerate(full[1]):
            tips = tips_of(a, b)
            ok = all(np.all(np.isfinite(t)) for t in tips)
            e = epipolar_gap_px(cams, tips) if ok else float("inf")
            bad = float(inconsistency(a, b, tips)) if ok else float("inf")
            pairs.append({"i": [i0, i1], "err": _errs(tips, truth) if ok else [1e9, 1e9],
                          "epi": e, "bad": bad})  # fmt: skip
    out["pairs"] = pairs
    chosen = (0, 0)
    if flagged and all(getattr(t, "retrace", None) is not None for t in traces):
        cc = [cands[v] + offered[v] for v in (0, 1)]
        if len(cc[0]) + len(cc[1]) > 2:
            ch = choose_branches(
                cams, cc, tips_of=tips_of, match_px=3.0 * flag_px,
                margin_px=1.25 * float(np.mean([t.width_px for t in traces])),
                inconsistency_of=inconsistency, more_crossings_if_consistent=True,
                both_if_traces_cross=True,
            )  # fmt: skip
            if ch is not None:
                chosen = ch.indices
    out["chosen"] = list(chosen)
    best = min(pairs, key=lambda p: max(p["err"]))
    out["oracle"] = best
    out["why"] = _why(cams, full, n_pipe, best, chosen, pairs, flagged, traces)
    return out


def _why(cams, full, n_pipe, best, chosen, pairs, flagged, traces) -> str:
    """The first rule of the branch choice that kept the oracle pair ``best`` out."""
    if max(best["err"]) > 5:
        return "no right pair"
    i0, i1 = best["i"]
    if (i0, i1) == tuple(chosen):
        return "chosen"
    if not flagged:
        return "not flagged"
    if i0 >= n_pipe[0] or i1 >= n_pipe[1]:
        return "guided gated out"
    a, b = full[0][i0], full[1][i1]
    ta, tb = full[0][0], full[1][0]

    def fol(x):
        return int(getattr(x, "crossings_followed", 0))

    if i0 and i1:
        both = fol(ta) > 0 and fol(tb) > 0
        if not (both and fol(a) < fol(ta) and fol(b) < fol(tb)):
            return "both views leave their traces"
    if not best["epi"] <= 15.0:
        return "tips' epipolar distance"
    base = next(p for p in pairs if p["i"] == [0, 0])["bad"]
    margin = 1.25 * float(np.mean([t.width_px for t in traces]))
    if not best["bad"] < base - margin:
        return "gate: not clearly more consistent than the traces"
    alts_ok = all(fol(x) <= fol(full[v][0]) for v, (i, x) in enumerate(((i0, a), (i1, b))) if i)
    if not (alts_ok or best["bad"] <= CONSISTENT_PX):
        return "gate: follows more crossings"
    ch = next(p for p in pairs if p["i"] == list(chosen))
    ca, cb = full[0][chosen[0]], full[1][chosen[1]]
    kb = (best["bad"] > CONSISTENT_PX, fol(a) + fol(b),
          float(a.crossing_turn_deg) + float(b.crossing_turn_deg), best["bad"])  # fmt: skip
    kc = (ch["bad"] > CONSISTENT_PX, fol(ca) + fol(cb),
          float(ca.crossing_turn_deg) + float(cb.crossing_turn_deg), ch["bad"])  # fmt: skip
    names = ("ranking: consistent level", "ranking: crossings followed", "ranking: turns",
             "ranking: inconsistent length")  # fmt: skip
    for n, x, y in zip(names, kb, kc, strict=True):
        if x != y:
            return n
    return "ranking: epipolar distance"


def evaluate(seeds, store: Path, out: Path, diag: bool = True) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth = rec["calib"], rec["truth"]
        row = {"seed": seed, "store": str(store),
               "trace": _errs([t.tip for t in rec["traces"]], truth)}  # fmt: skip
        with stored_alternatives(rec):
            own = pipeline._stereo_or_own_tips(cams, list(rec["traces"]))[0]
            row["flagged"] = bool(epipolar_gap_px(cams, own) > 5.0)
            for name, kw in (("ref", BEFORE_S41_S42), ("variant", VARIANT_KW)):
                t0 = time.process_time()
                tips, src, res, chosen = pipeline.traced_stereo_tips(
                    cams, rec["traces"], calibration=REAL_LIKE_CALIBRATION, **kw
                )
                row[name] = {"err_px": _errs(tips, truth), "cpu_s": time.process_time() - t0,
                             "action": None if res is None else res.action, "src": src,
                             "chosen": [_kind(c, t) for c, t in
                                        zip(chosen, rec["traces"], strict=True)]}  # fmt: skip
            if diag and max(row["ref"]["err_px"]) > 5:
                t0 = time.process_time()
                row["diag"] = diagnose(cams, rec["traces"], truth)
                row["diag"]["cpu_s"] = time.process_time() - t0
        rows.append(row)
        d = row.get("diag", {})
        print(seed, [round(x, 1) for x in row["ref"]["err_px"]],
              [round(x, 1) for x in row["variant"]["err_px"]], d.get("why"),
              round(max(d["oracle"]["err"]), 1) if d else "", flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path) -> None:
    rows = sorted(json.loads(path.read_text())["rows"], key=lambda r: r["seed"])
    print("\n| seed | ref px (v1 / v2) | class | flagged | chosen | oracle pair px | why |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        e = r["ref"]["err_px"]
        if max(e) <= 30:
            continue
        d = r["diag"]
        o = d["oracle"]
        kinds = [d["candidates"][v][o["i"][v]]["kind"] for v in (0, 1)]
        print(f"| {r['seed']} | {e[0]:.1f} / {e[1]:.1f} | >30 | {d['flagged']} | "
              f"{'/'.join(r['ref']['chosen'])} | {o['err'][0]:.1f} / {o['err'][1]:.1f} "
              f"({'/'.join(kinds)}) | {d['why']} |")  # fmt: skip
    from collections import Counter

    over = [r for r in rows if max(r["ref"]["err_px"]) > 30]
    print(f"\n> 30 px frames: {len(over)};", dict(Counter(r["diag"]["why"] for r in over)))
    for half, sel in (("even", [r for r in rows if r["seed"] % 2 == 0]),
                      ("odd", [r for r in rows if r["seed"] % 2 == 1])):  # fmt: skip
        ok_r = sum(max(r["ref"]["err_px"]) <= 5 for r in sel)
        ok_v = sum(max(r["variant"]["err_px"]) <= 5 for r in sel)
        fixed = [
            r["seed"] for r in sel if max(r["ref"]["err_px"]) > 5 >= max(r["variant"]["err_px"])
        ]
        broken = [r["seed"] for r in sel
                  if max(r["ref"]["err_px"]) <= 5 < max(r["variant"]["err_px"])]  # fmt: skip
        print(
            f"\n{half} seeds ({len(sel)} frames): both views within 5 px ref {ok_r}, "
            f"variant {ok_v}; fixed {fixed}; broken {broken}"
        )
        for r in sel:
            a, b = r["ref"]["err_px"], r["variant"]["err_px"]
            if max(abs(x - y) for x, y in zip(a, b, strict=True)) > 0.05:
                print(f"- {r['seed']}: {a[0]:.1f} / {a[1]:.1f} -> {b[0]:.1f} / {b[1]:.1f}")
    for name in ("ref", "variant"):
        c = [r[name]["cpu_s"] for r in rows if r["flagged"]]
        if c:
            print(f"{name} CPU s a flagged frame: median {np.median(c):.2f}, max {max(c):.2f}")


def main() -> int:
    ap = harness_parser(__doc__, "/tmp/real_like_tip_wrongbranch")
    ap.add_argument("--no-diag", action="store_true", help="skip the diagnosis of failing frames")
    args = ap.parse_args()
    if args.summary is not None:
        summary(args.summary)
        return 0
    seeds = dev_seeds(ap, args)
    evaluate(seeds, args.store, args.out, diag=not args.no_diag)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
