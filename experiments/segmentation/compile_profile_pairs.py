"""Summarise interleaved before/after runs of ``compile_profile.py`` (issue 18, compilation
rows): per run, the first and second process's wall and CPU seconds, the 1-min load before
each, the XLA (backend) CPU seconds and trace CPU seconds of every program matching
``--programs``, and the medians per tree.

Run (from the repository root), after ``compile_profile.py ... --name NAME_before_1`` etc.::

    python experiments/segmentation/compile_profile_pairs.py --name OUT \
        --before NAME_before_1 NAME_before_2 --after NAME_after_1 NAME_after_2 \
        [--programs forward_batch _fk_batch] [--title TEXT]

Reads and writes experiments/results/segmentation/*.json / OUT.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def _row(name: str, tree: str, progs: list[str]) -> tuple[list[str], dict]:
    d = json.loads((RESULTS / f"{name}.json").read_text())
    out, figs = [], {}
    for proc in ("first", "second"):
        r = d["runs"][proc]
        wall, cpu = r["process"]
        kin = []
        for pname, st in sorted(r["programs"].items()):
            if any(p in pname for p in progs):
                for stage in ("trace", "backend"):
                    if stage in st:
                        kin.append(f"{pname} {stage} {st[stage][1]:.2f}")
        figs[proc] = (wall, cpu)
        out.append(f"| {name} | {tree} | {proc} | {r['load_before']:.1f} | {wall:.1f} | "
                   f"{cpu:.1f} | {'; '.join(kin) or '-'} |")  # fmt: skip
    return out, figs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--name", required=True)
    ap.add_argument("--before", nargs="+", required=True)
    ap.add_argument("--after", nargs="+", required=True)
    ap.add_argument("--programs", nargs="+", default=["forward_batch", "_fk_batch"])
    ap.add_argument("--title", default="", help="Markdown text written above the tables")
    a = ap.parse_args()
    rows, per = [], {"before": [], "after": []}
    for b, f in zip(a.before, a.after, strict=True):  # in the order they ran: interleaved
        for name, tree in ((b, "before"), (f, "after")):
            r, figs = _row(name, tree, a.programs)
            rows += r
            per[tree].append(figs)
    lines = [
        *([a.title, ""] if a.title else []),
        "| run | tree | process | load before | wall s | CPU s | kinematics programs (CPU s) |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "| tree | process | median wall s | median CPU s |",
        "|---|---|---|---|",
    ]
    for tree in ("before", "after"):
        for proc in ("first", "second"):
            w = statistics.median(f[proc][0] for f in per[tree])
            c = statistics.median(f[proc][1] for f in per[tree])
            lines.append(f"| {tree} | {proc} | {w:.1f} | {c:.1f} |")
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
