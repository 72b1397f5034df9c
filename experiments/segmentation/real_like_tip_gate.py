"""Round 20 (issue 16 item 2, docs/decisions.md S49): the two-view branch choice when the
traces' own backbones already look consistent, or their tips already agree.

The branch choice (:func:`jaxcr.stereo.branch_choice.choose_branches`) lets an alternative
replace a view's trace only when the pair's backbones leave over 1.25 tube widths less
unexplained than the traces' own pair. Where a trace follows a crossing cable that runs
along the epipolar lines, its pair with the other view explains itself (the check is blind
along epipolar lines) while its tips are flagged: no alternative can be 1.25 widths better,
and the right one, whose tips agree, is not chosen (round 19's fresh 4672, 4723). And where
the tips agree by chance but the backbones do not (4575), the choice never runs. Variants,
each :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with ``calibration=REAL_LIKE_CALIBRATION``
on the stored traces (the stored alternatives returned for ``trace_alternatives``):

* ``ref`` -- as committed before S49 (``branch_tips=False, branch_backbones=False``; the
  defaults since S49 are ``both``);
* ``tips`` -- ``branch_tips=True``: where the traces' tips are over 5 px apart, a pair whose
  tips are within 5 px passes the gate when its backbones are no less consistent than the
  traces', it follows no more crossing objects and each changed view's tip is over the
  margin (1.25 tube widths) from its trace's; and such pairs rank first;
* ``backbones`` -- ``branch_backbones=True``: the choice also runs where the tips agree but
  the traces' backbones leave over 40 px unexplained;
* ``both`` -- ``tips`` and ``backbones``.

    python experiments/segmentation/real_like_tip_gate.py --seeds 4560-4829 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_gate.py --summary ROWS.json
"""

from __future__ import annotations

import time
from pathlib import Path

from tip_harness import (
    harness_main,
    merged_rows,
    resumed_rows,
    stored_alternatives,
    stored_records,
    tip_errors,
    variant_table,
    write_rows,
)

from jaxcr.stereo import pipeline
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION

VARIANTS = {
    "ref": {"branch_tips": False, "branch_backbones": False},
    "tips": {"branch_tips": True, "branch_backbones": False},
    "backbones": {"branch_tips": False, "branch_backbones": True},
    "both": {"branch_tips": True, "branch_backbones": True},
}


def _run(cams, traces, kw):
    t0 = time.process_time()
    tips, src, res, chosen = pipeline.traced_stereo_tips(
        cams, traces, calibration=REAL_LIKE_CALIBRATION, **kw
    )
    cpu = time.process_time() - t0
    branch = [getattr(c, "curl_of", c) is not t for c, t in zip(chosen, traces, strict=True)]
    return tips, src, None if res is None else res.action, branch, cpu


def evaluate(seeds, store: Path, out: Path, variants=None) -> None:
    """Each of ``variants`` (name -> keywords of ``traced_stereo_tips``; this round's
    ``VARIANTS`` by default) on each stored frame, rows written as they complete."""
    variants = VARIANTS if variants is None else variants
    rows = resumed_rows(out)
    for seed, rec in stored_records(seeds, store, rows):
        cams, truth, traces = rec["calib"], rec["truth"], rec["traces"]
        row = {"seed": seed}
        with stored_alternatives(rec):
            for name, kw in variants.items():
                tips, src, act, branch, cpu = _run(cams, traces, kw)
                row[name] = {"err_px": tip_errors(tips, truth), "source": src, "action": act,
                             "branch": branch, "cpu_s": cpu}  # fmt: skip
        rows.append(row)
        print(seed, *[(n, [round(x, 1) for x in row[n]["err_px"]]) for n in variants],
              flush=True)  # fmt: skip
        write_rows(out, rows)


def summary(path: Path, variants=None) -> None:
    """Each variant on even seeds (design) and odd ones (held out); the frames each fixes
    and breaks against ``ref``; comma-separated rows files are merged."""
    variants = VARIANTS if variants is None else variants
    rows = merged_rows(path)
    for title, sel in (("even seeds (design)", [r for r in rows if r["seed"] % 2 == 0]),
                       ("odd seeds (held out)", [r for r in rows if r["seed"] % 2 == 1]),
                       ("all", rows)):  # fmt: skip
        variant_table(sel, title, variants)
        for n in variants:
            if n == "ref":
                continue
            fixed = [r["seed"] for r in sel
                     if max(r[n]["err_px"]) <= 5 < max(r["ref"]["err_px"])]  # fmt: skip
            broken = [r["seed"] for r in sel
                      if max(r["ref"]["err_px"]) <= 5 < max(r[n]["err_px"])]  # fmt: skip
            moved = sum(any(abs(a - b) > 0.5 for a, b in zip(r[n]["err_px"], r["ref"]["err_px"],
                                                              strict=True)) for r in sel)  # fmt: skip
            print(f"- {n}: fixed {fixed}, broken {broken}, frames with a tip moved > 0.5 px "
                  f"{moved}")  # fmt: skip


def main() -> int:
    return harness_main(__doc__, "/tmp/real_like_tip_gate", evaluate, summary)


if __name__ == "__main__":
    raise SystemExit(main())
