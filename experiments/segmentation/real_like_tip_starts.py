"""Round 18b (issue 16 item 2, docs/decisions.md S45): the traces from the entry's other
starting directions offered to the branch choice, on stored development traces, before
and after in the same run.

The tracer starts from the entry along the given direction and turned by
``start_spread_deg`` either way, and keeps the longest of the three traces (a crease or
shadow at the base can divert one start). Where a rod runs past the entry beside the tube,
the longest is the rod's (real_like 4436, view 1: 52 px off, the start along the given
direction 4.5 px). :func:`jaxcr.segmentation.foreground.trace_alternatives` now offers the
other two as well (:func:`jaxcr.segmentation.foreground.start_alternatives`).

Input: stored traces (``real_like_tip_spline.py trace --store STORE``, made before S45:
they hold no start traces) and the rendered frames' cache (``--cache``, for the entry
direction the tracer was given). Per seed, per view, the three start traces are traced
again on the stored trace's mask (:func:`jaxcr.segmentation.foreground.trace_tube`, as
:func:`~jaxcr.segmentation.foreground.plate_foreground` does), the two not kept attached,
then:

* ``ref`` -- :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
  ``calibration=REAL_LIKE_CALIBRATION`` and the stored alternatives;
* ``starts`` -- the same with the start alternatives appended to each view's stored ones;
* ``rule`` -- and each view's trace the start along the given direction where it ends
  over a tube width from the longest's end and is at least half as long (:func:`along_given`; a view whose choice changes is traced
  from that start and its alternatives computed again, :func:`retraced_view`).

    python experiments/segmentation/real_like_tip_starts.py --seeds 3722-4379 \\
        --store STORE --cache CACHE --out ROWS
    python experiments/segmentation/real_like_tip_starts.py --summary ROWS.json
"""

from __future__ import annotations

import json
import pickle
import time
from pathlib import Path

import numpy as np
from tip_harness import (
    harness_main,
    resumed_rows,
    stored_alternatives,
    stored_records,
    tip_errors,
    variant_table,
    write_rows,
)

from jaxcr.segmentation import foreground as fg
from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION


def attach_starts(trace, entry_uv, direction_uv) -> int:
    """Trace ``trace``'s view again from ``entry_uv`` along ``direction_uv`` turned by 0 and
    +-``start_spread_deg`` (the stored trace's mask, scale and config) and attach the traces
    :func:`trace_tube` would not keep to its retrace state; the number attached."""
    ctx = trace.retrace
    cfg, k = ctx.cfg, ctx.k
    d = np.asarray(direction_uv, np.float64)
    entry = fg._to_low(np.asarray(entry_uv, np.float64), k)
    out = []
    for a in (0.0, -cfg.start_spread_deg, cfg.start_spread_deg):
        c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
        dr = np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])
        out.append(fg.trace_tube(ctx.seeds_l, entry, dr, cfg, frame=ctx.fs, plate=ctx.ps,
                                 _single=True))  # fmt: skip
    best = max(out, key=fg._trace_length)
    ctx.low.start_alternatives = [t for t in out if t is not best]
    ctx.low.starts_traced = out
    return len(ctx.low.start_alternatives)


def along_given(starts, *, min_fraction: float = 0.5) -> int:
    """Index of the start trace a rule keeps: the longest, unless the one along the given
    direction (index 0) ends elsewhere (over a tube width from the longest's tip) and is
    at least ``min_fraction`` as long (else a crease or shadow diverted it)."""
    lengths = [fg._trace_length(t) for t in starts]
    j = int(np.argmax(lengths))
    far = np.linalg.norm(starts[0].tip - starts[j].tip) > max(starts[j].width_px, 1.0)
    if far and lengths[0] >= min_fraction * lengths[j]:
        return 0
    return j


def retraced_view(trace, pick: int):
    """``trace``'s view traced from the start ``pick`` instead (as plate_foreground
    finishes a trace), with its alternatives (the junctions' re-traces and the other
    starts); (trace, alternatives)."""
    from dataclasses import replace

    ctx = trace.retrace
    starts = ctx.low.starts_traced
    low = starts[pick]
    low = fg._retrace_off_border(low, ctx.seeds_l, ctx.cfg, ctx.fs, ctx.ps)
    low.start_alternatives = [t for i, t in enumerate(starts) if i != pick]
    juncs = [j[0] for j in low.junctions]
    low.crossing_turn_deg = fg._path_turn(low.backbone, juncs, ctx.cfg)
    low.crossings_followed = fg._path_through(ctx.seeds_l, low.backbone, juncs, ctx.cfg,
                                              low.width_px)  # fmt: skip
    new = fg._finish(low, replace(ctx, low=low))
    return new, fg.trace_alternatives(new)


def evaluate(seeds, store: Path, cache: Path, out: Path) -> None:
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        with open(cache / f"real_like_1280x720_{seed}.pkl", "rb") as f:
            frame = pickle.load(f)
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        row = {"seed": seed}
        for t, v in zip(traces, frame.views, strict=True):
            attach_starts(t, v.entry_px, v.entry_dir_px)
        t0 = time.process_time()
        extra = [fg.start_alternatives(t, tips=[fg._to_low(np.asarray(a.tip), t.retrace.k)
                                                for a in alts])
                 for t, alts in zip(traces, rec["alts"], strict=True)]  # fmt: skip
        row["start_alternatives"] = [len(e) for e in extra]
        row["start_errors"] = [tip_errors([a.tip for a in e], [g] * len(e)) if e else []
                               for e, g in zip(extra, truth, strict=True)]  # fmt: skip
        starts_cpu = time.process_time() - t0
        for name, add in (("ref", False), ("starts", True)):
            if add and not any(extra):  # the same candidates: the same result
                row[name] = dict(row["ref"])
                continue
            r2 = dict(rec)
            if add:
                r2["alts"] = [list(a) + e for a, e in zip(rec["alts"], extra, strict=True)]
            with stored_alternatives(r2):
                t0 = time.process_time()
                tips, src, res, _ = pipeline.traced_stereo_tips(
                    cams, traces, calibration=REAL_LIKE_CALIBRATION
                )
            row[name] = {"err_px": tip_errors(tips, truth), "source": src,
                         "action": None if res is None else res.action,
                         "cpu_s": time.process_time() - t0 + (starts_cpu if add else 0.0)}  # fmt: skip
        picks = [along_given(t.retrace.low.starts_traced) for t in traces]
        longest = [int(np.argmax([fg._trace_length(x) for x in t.retrace.low.starts_traced]))
                   for t in traces]  # fmt: skip
        row["rule_changed"] = [p != q for p, q in zip(picks, longest, strict=True)]
        if not any(row["rule_changed"]):
            row["rule"] = dict(row["starts"])
        else:
            t0 = time.process_time()
            new_traces, new_alts = [], []
            for t, alts, e, p, q in zip(traces, rec["alts"], extra, picks, longest, strict=True):
                if p == q:
                    new_traces.append(t)
                    new_alts.append(list(alts) + e)
                else:
                    nt, na = retraced_view(t, p)
                    new_traces.append(nt)
                    new_alts.append(na)
            r2 = dict(rec, traces=new_traces, alts=new_alts)
            with stored_alternatives(r2):
                tips, src, res, _ = pipeline.traced_stereo_tips(
                    cams, new_traces, calibration=REAL_LIKE_CALIBRATION
                )
            row["rule"] = {"err_px": tip_errors(tips, truth), "source": src,
                           "action": None if res is None else res.action,
                           "one_view_err_px": tip_errors([t.tip for t in new_traces], truth),
                           "cpu_s": time.process_time() - t0}  # fmt: skip
        rows.append(row)
        print(seed, row["start_alternatives"], row["rule_changed"],
              {k: [round(x, 1) for x in row[k]["err_px"]] for k in ("ref", "starts", "rule")},
              flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path) -> None:
    rows = {r["seed"]: r for r in json.loads(path.read_text())["rows"]}
    rows = [rows[s] for s in sorted(rows)]
    names = ("ref", "starts", "rule")
    for title, sel in (("even seeds (design)", [r for r in rows if r["seed"] % 2 == 0]),
                       ("odd seeds (held out)", [r for r in rows if r["seed"] % 2 == 1]),
                       ("all", rows)):  # fmt: skip
        variant_table(sel, title, names)
        for v in ("starts", "rule"):
            fx = [r["seed"] for r in sel if max(r["ref"]["err_px"]) > 5 >= max(r[v]["err_px"])]
            br = [r["seed"] for r in sel if max(r["ref"]["err_px"]) <= 5 < max(r[v]["err_px"])]
            ch = [r["seed"] for r in sel if r["ref"]["err_px"] != r[v]["err_px"]]
            print(f"\n`ref` -> `{v}`: frames fixed {fx}, broken {br}; changed {ch}")
    n = [x for r in rows for x in r["start_alternatives"]]
    print(f"\nstart alternatives offered per view: {np.bincount(n).tolist()} (0, 1, 2)")
    c = [r["starts"]["cpu_s"] - r["ref"]["cpu_s"] for r in rows]
    print(f"extra CPU s a frame: median {np.median(c):.3f}, max {max(c):.2f}")


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_starts", evaluate, summary, cache=True)


if __name__ == "__main__":
    raise SystemExit(main())
