"""Round 16a (issue 16 item 2, docs/decisions.md S38): the tracer's end re-walked at full
resolution (:func:`jaxcr.segmentation.foreground.rewalk_end`), compared frame by frame
with the reference traces. (The re-walk was taken out of the tracer after round 16's fresh
run, decisions S38; this script reads stored rows and needs it only to make new ones.)

Input: two rows files of ``real_like_tip_end.py`` (its ``--out ROWS``), one on the
reference store (traces of the tracer before the change) and one on a store re-traced
with this tree (``real_like_tip_spline.py trace``), plus both stores for the tracer's CPU
(``cpu_s``: both views' :func:`plate_foreground` and :func:`trace_alternatives`). Printed:
frames with both views within 5 px (``pipeline``: ``traced_stereo_tips`` with the
preset's calibration, as real_like_tip.py calls it), every frame whose pipeline or
one-view trace error changed (px per view), fixed and broken frames, the one-view trace's
own score (views within 5 px) and the tracer's CPU per frame.

    python experiments/segmentation/real_like_tip_r16a_compare.py REF_ROWS.json NEW_ROWS.json \\
        --ref-store /tmp/tip34/traces --new-store /tmp/tip35a/traces
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np


def _rows(path: Path) -> dict:
    return {r["seed"]: r for r in json.loads(path.read_text())["rows"]}


def _cpu(store: Path, seeds) -> list[float]:
    out = []
    for s in seeds:
        with open(store / f"{s}.pkl", "rb") as f:
            out.append(float(pickle.load(f)["cpu_s"]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ref", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--ref-store", type=Path)
    ap.add_argument("--new-store", type=Path)
    args = ap.parse_args()
    ref, new = _rows(args.ref), _rows(args.new)
    seeds = sorted(set(ref) & set(new))
    print(f"{len(seeds)} frames in both")
    for name in ("pipeline",):
        for title, sel in (("4000-4100", [s for s in seeds if 4000 <= s <= 4100]), ("all", seeds)):
            a = sum(max(ref[s][name]["err_px"]) <= 5 for s in sel)
            b = sum(max(new[s][name]["err_px"]) <= 5 for s in sel)
            print(f"{name} {title} ({len(sel)}): reference {a}, this tree {b}")
    tr_a = sum(e <= 5 for s in seeds for e in ref[s]["trace"])
    tr_b = sum(e <= 5 for s in seeds for e in new[s]["trace"])
    print(
        f"one-view trace: views within 5 px: reference {tr_a}, this tree {tr_b} of {2 * len(seeds)}"
    )
    fixed = [
        s
        for s in seeds
        if max(ref[s]["pipeline"]["err_px"]) > 5 >= max(new[s]["pipeline"]["err_px"])
    ]
    broken = [
        s
        for s in seeds
        if max(ref[s]["pipeline"]["err_px"]) <= 5 < max(new[s]["pipeline"]["err_px"])
    ]
    print(f"fixed {fixed}, broken {broken}")
    print("\n| seed | trace px (ref -> new) | pipeline px (ref -> new) | action (ref -> new) |")
    print("|---|---|---|---|")
    for s in seeds:
        a, b = ref[s], new[s]
        ch = lambda x, y: max(abs(p - q) for p, q in zip(x, y, strict=True)) > 0.05  # noqa: E731
        if ch(a["trace"], b["trace"]) or ch(a["pipeline"]["err_px"], b["pipeline"]["err_px"]):
            print(f"| {s} | {a['trace'][0]:.1f} / {a['trace'][1]:.1f} -> "
                  f"{b['trace'][0]:.1f} / {b['trace'][1]:.1f} | "
                  f"{a['pipeline']['err_px'][0]:.1f} / {a['pipeline']['err_px'][1]:.1f} -> "
                  f"{b['pipeline']['err_px'][0]:.1f} / {b['pipeline']['err_px'][1]:.1f} | "
                  f"{a['pipeline']['action']} -> {b['pipeline']['action']} |")  # fmt: skip
    if args.ref_store and args.new_store:
        ca, cb = np.array(_cpu(args.ref_store, seeds)), np.array(_cpu(args.new_store, seeds))
        print(f"\ntracer CPU s a frame (both views + alternatives): reference median "
              f"{np.median(ca):.2f} (total {ca.sum():.0f}), this tree median {np.median(cb):.2f} "
              f"(total {cb.sum():.0f}); ratio of totals {cb.sum() / ca.sum():.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
