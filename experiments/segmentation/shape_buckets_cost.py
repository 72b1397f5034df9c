"""Per-frame cost of shape buckets (docs/decisions.md S29): the same dataset segmented with
``--shape-buckets on`` and ``off`` in alternating processes, each on a cache its mode already
filled (no compilation), so the difference is the padded area (and the traced-size program).

    python experiments/segmentation/shape_buckets_cost.py --work W --repeats 2 \\
        --case 600x450:cache_on_0:cache_off_0 --case 640x480:cache_on_0:cache_off_0

W: the work folder of experiments/segmentation/shape_buckets.py (datasets ds_<size>, caches
cache_<mode>_<round>). Reports per process: median ``time_s`` (wall ms per frame, from
summary.json), process wall and CPU seconds, the 1-min load.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from jaxcr.benchmarks.compile import _commit, _load, run_child

OUT = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--work", required=True)
    p.add_argument("--case", action="append", required=True, help="SIZE:ON_CACHE:OFF_CACHE")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--name", default="shape_buckets_cost_s29")
    p.add_argument("--commit", default=None)
    a = p.parse_args()
    work = Path(a.work)
    rows = []
    import os

    for rep in range(a.repeats):
        for case in a.case:
            size, on_c, off_c = case.split(":")
            modes = (
                (("off", off_c), ("on", on_c)) if rep % 2 == 0 else (("on", on_c), ("off", off_c))
            )
            for mode, cache in modes:
                env = {k: v for k, v in os.environ.items() if not k.startswith("JAXCR_")}
                env["JAXCR_CACHE_DIR"] = str(work / cache)
                out = work / f"cost_{size}_{mode}"
                argv = ["segment", str(work / f"ds_{size}"), "-o", str(out), "--quiet",
                        "--overwrite", "--shape-buckets", mode]  # fmt: skip
                l0 = _load()
                r = run_child(argv, env, str(work))
                l1 = _load()
                s = json.loads((out / "summary.json").read_text()) if r.rc == 0 else {}
                rows.append((rep, size, mode, r.rc, s.get("median_time_s"), s.get("compile_s"),
                             r.wall_s, r.cpu_s, l0, l1))  # fmt: skip
                print(rows[-1], flush=True)
    lines = ["# Shape buckets (S29): per-frame cost of the padding, warm caches", "",
             f"Commit {a.commit or _commit()}; command: `python experiments/segmentation/"
             f"shape_buckets_cost.py --work W --repeats {a.repeats} "
             + " ".join(f"--case {c}" for c in a.case) + f" --name {a.name}` (W: the work "
             "folder of `shape_buckets.py`, whose caches hold each mode's programs). Modes "
             "alternate per repeat. `time_s`: wall ms per frame of a chunk (the CLI's figure).",
             "", "| repeat | size | buckets | exit | median time_s (ms/frame) | compile_s | "
             "wall s | CPU s | load |", "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for rep, size, mode, rc, t, c, w, cpu, l0, l1 in rows:
        ts = "-" if t is None else f"{1e3 * t:.1f}"
        cs = "-" if c is None else f"{c:.2f}"
        lines.append(f"| {rep} | {size} | {mode} | {rc} | {ts} | {cs} | {w:.1f} | {cpu:.1f} | "
                     f"{l0:.1f} -> {l1:.1f} |")  # fmt: skip
    (OUT / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print(OUT / f"{a.name}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
