"""XLA:CPU compile options against run time for a first ``jaxcr segment`` process (issue 18,
compilation row; docs/decisions.md S22).

For each variant (a name and an ``XLA_FLAGS`` string, applied to every program of the process),
``jaxcr segment DATASET`` runs in a new process with an empty cache folder of its own; the
variants are interleaved ROUNDS times (A B C A B C ...) so that each has its reference in the
same minutes. Recorded per process: summary.json ``compile_s``, process wall and CPU seconds,
the median per-frame ``time_s`` of frames after the first chunk (no compilation in them), the
1-min load; and per variant ``jaxcr evaluate``'s mean IoU and the largest coefficient
difference to the first variant.

Run (from the repository root)::

    PYTHONPATH=$PWD python experiments/segmentation/compile_options.py DATASET \
        [--variants 'base=;o1=--xla_backend_optimization_level=1'] [--rounds 2] \
        [--work /tmp/jaxcr_compile_options] [--name compile_options] [-- segment options]

Writes experiments/results/segmentation/NAME.md and .json.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results" / "segmentation"
DEFAULT_VARIANTS = (
    "base=;o1=--xla_backend_optimization_level=1;"
    "noexp=--xla_llvm_disable_expensive_passes=true"
)


def _run(argv: list[str], env: dict) -> tuple[subprocess.CompletedProcess, float, float]:
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "jaxcr", *argv], env=env, capture_output=True,
                       text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    return p, wall, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--variants", default=DEFAULT_VARIANTS)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--work", default="/tmp/jaxcr_compile_options")
    ap.add_argument("--name", default="compile_options")
    ap.add_argument("extra", nargs="*")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    variants = [v.split("=", 1) for v in a.variants.split(";") if v]
    runs: dict[str, list[dict]] = {name: [] for name, _ in variants}
    evals: dict[str, dict] = {}
    for rnd in range(a.rounds):
        for name, flags in variants:
            out, cache = work / f"out_{name}", work / f"cache_{name}_{rnd}"
            shutil.rmtree(cache, ignore_errors=True)
            env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu",
                       JAXCR_PROGRESS="0", JAXCR_CACHE_DIR=str(cache))  # fmt: skip
            env.pop("JAXCR_COMPILE_CACHE", None)
            env["XLA_FLAGS"] = " ".join(filter(None, [os.environ.get("XLA_FLAGS", ""), flags]))
            load = os.getloadavg()[0]
            p, wall, cpu = _run(["segment", a.dataset, "-o", str(out), "--overwrite", "--quiet",
                                 "--no-overlays", "--batch-size", str(a.batch_size), *a.extra],
                                env)  # fmt: skip
            if p.returncode not in (0, 1):
                raise SystemExit(f"{name}: segment failed ({p.returncode}): {p.stderr[-2000:]}")
            summary = json.loads((out / "summary.json").read_text())
            recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines() if x]
            later = [r["time_s"] for r in recs[a.batch_size :]]
            runs[name].append({
                "compile_s": summary["compile_s"], "wall_s": wall, "cpu_s": cpu, "load": load,
                "time_s_later": statistics.median(later) if later else None,
            })  # fmt: skip
            print(name, rnd, runs[name][-1], flush=True)
            if rnd == 0:
                ev = subprocess.run([sys.executable, "-m", "jaxcr", "evaluate", str(out),
                                     "--no-plot"], env=env, capture_output=True, text=True)  # fmt: skip
                with open(out / "per_frame.csv") as fh:
                    rows = list(csv.DictReader(fh))
                ious = [float(r["iou"]) for r in rows if r.get("iou") not in (None, "", "nan")]
                evals[name] = {
                    "iou_mean": statistics.fmean(ious) if ious else float("nan"),
                    "n": len(ious), "evaluate_rc": ev.returncode,
                    "coeffs": {r["frame"]: r["coeffs"] for r in recs},
                }  # fmt: skip
    base = variants[0][0]
    for name, ev in evals.items():
        diffs = [
            max((abs(x - y) for x, y in zip(_flat(c), _flat(evals[base]["coeffs"][f]),
                                            strict=True)), default=0.0)
            for f, c in ev["coeffs"].items()
        ]  # fmt: skip
        ev["max_coeff_diff"] = max(diffs, default=0.0)
    res = {"command": " ".join(["python", *sys.argv]), "variants": dict(variants),
           "runs": runs, "evals": {k: {x: y for x, y in v.items() if x != "coeffs"}
                                   for k, v in evals.items()}}  # fmt: skip
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.json").write_text(json.dumps(res, indent=1) + "\n")
    lines = [
        "# XLA:CPU compile options: first `jaxcr segment` process",
        "",
        f"Reproduce: `PYTHONPATH=$PWD {res['command']}` (2-core CPU shared with other jobs; "
        f"variants interleaved, {a.rounds} round(s), medians; empty cache per process).",
        "",
        "| variant | XLA_FLAGS | compile s | process wall s | process CPU s | run ms/frame "
        "(after chunk 1) | mean IoU | max coeff diff to first | loads |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, flags in variants:
        rs = runs[name]
        t = [r["time_s_later"] for r in rs if r["time_s_later"] is not None]
        ev = res["evals"][name]
        lines.append(
            f"| {name} | `{flags}` | {statistics.median(r['compile_s'] for r in rs):.1f} | "
            f"{statistics.median(r['wall_s'] for r in rs):.1f} | "
            f"{statistics.median(r['cpu_s'] for r in rs):.1f} | "
            f"{1000 * statistics.median(t) if t else float('nan'):.0f} | {ev['iou_mean']:.4f} | "
            f"{ev['max_coeff_diff']:.2e} | {', '.join(f'{r['load']:.1f}' for r in rs)} |"
        )
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def _flat(x) -> list[float]:
    if isinstance(x, list):
        return [v for e in x for v in _flat(e)]
    return [float(x)]


if __name__ == "__main__":
    sys.exit(main())
