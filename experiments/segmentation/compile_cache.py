"""First vs second process compile time of ``jaxcr segment`` and ``jaxcr demo`` with the
persistent compilation cache (issue 18, compilation row).

For each image size: a synthetic ``orthogonal`` dataset of FRAMES frames; then ``jaxcr segment``
in a new process with the cache off, with an empty cache (first process, fills it) and again
with the filled cache (second process), REPEATS times each; the compile seconds are the
``compile_s`` of the run's summary.json (JAX's trace + lowering + backend-compile spans,
:class:`jaxcr.cli._timing.CompileTimer`), the wall seconds those of the whole process.
``jaxcr demo`` (synth + segment + evaluate) is timed by process wall clock only. The machine's
load (``/proc/loadavg``) is recorded before each run.

Run (from the repository root)::

    PYTHONPATH=$PWD python experiments/segmentation/compile_cache.py [--sizes 320x240,640x480] \
        [--repeats 1] [--frames 4] [--work /tmp/jaxcr_compile_cache]

Writes experiments/results/segmentation/NAME.md and .json (``--name``, default compile_cache).
"""

from __future__ import annotations

import argparse
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


def _load() -> list[float]:
    with open("/proc/loadavg") as fh:
        return [float(x) for x in fh.read().split()[:3]]


def _jaxcr(argv: list[str], cache: str | None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu", JAXCR_PROGRESS="0")
    if cache is None:
        env["JAXCR_COMPILE_CACHE"] = "0"
    else:
        env["JAXCR_CACHE_DIR"] = cache
        env.pop("JAXCR_COMPILE_CACHE", None)
    load = _load()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "jaxcr", *argv], env=env, capture_output=True,
                       text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU seconds of the process (user + system): much less sensitive to the machine's load
    # than wall seconds
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    if p.returncode != 0:
        raise SystemExit(f"jaxcr {' '.join(argv)} failed ({p.returncode}): {p.stderr[-2000:]}")
    return {"wall_s": wall, "cpu_s": cpu, "load_before": load}


def _segment(ds: Path, out: Path, cache: str | None) -> dict:
    r = _jaxcr(["segment", str(ds), "-o", str(out), "--overwrite", "--quiet", "--no-overlays"],
               cache)  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())
    r.update(compile_s=summary["compile_s"], run_s=summary["run_s"])
    return r


def _cpu(runs: list[dict]) -> str:
    """Median process CPU seconds, or n/a for runs recorded before it was measured."""
    return f"{_median(runs, 'cpu_s'):.1f}" if all("cpu_s" in r for r in runs) else "n/a"


def _median(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in runs)


def _write(rows: dict, a) -> None:
    """Write the .json and .md (after every block, so an interrupted run keeps its numbers)."""
    rows["load_after"] = _load()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.json").write_text(json.dumps(rows, indent=1) + "\n")
    lines = [
        "# Persistent compilation cache: first vs second process",
        "",
        f"Reproduce: `PYTHONPATH=$PWD {rows['command']}` (2-core CPU shared with other jobs; "
        "load = 1-min load average before each run).",
        "",
        f"`jaxcr segment` on a synthetic `orthogonal` dataset of {a.frames} frames "
        "(batch 4, --no-overlays), medians over "
        f"{a.repeats} run(s). compile = summary.json `compile_s` (trace + lower + XLA compile "
        "spans); wall = whole process. Previous (issue 18): 23-87 s first compile, no cache "
        "in most commands.",
        "",
        "| size | cache | compile s | run s | process wall s | process CPU s | load |",
        "|---|---|---|---|---|---|---|",
    ]
    names = {
        "off": "off",
        "first": "empty (1st process)",
        "second": "filled (2nd process)",
        "warmup": "`jaxcr warmup` (empty cache; wall/CPU only)",
        "after_warmup": "filled by `jaxcr warmup` (next process)",
    }
    for size, runs in rows["segment"].items():
        for k, rs in runs.items():
            if not rs:
                continue
            lines.append(
                f"| {size} | {names[k]} | {_median(rs, 'compile_s'):.1f} | "
                f"{_median(rs, 'run_s'):.1f} | {_median(rs, 'wall_s'):.1f} | {_cpu(rs)} | "
                f"{statistics.median(r['load_before'][0] for r in rs):.1f} |"
            )
    if rows["demo"]:
        lines += ["", f"`jaxcr demo --frames {a.frames}` (whole process wall clock):", "",
                  "| size | cache | wall s | process CPU s | load |", "|---|---|---|---|---|"]  # fmt: skip
        for size, runs in rows["demo"].items():
            for k, rs in runs.items():
                lines.append(
                    f"| {size} | {names[k]} | {_median(rs, 'wall_s'):.1f} | {_cpu(rs)} | "
                    f"{statistics.median(r['load_before'][0] for r in rs):.1f} |"
                )
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--work", default="/tmp/jaxcr_compile_cache")
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--no-segment", action="store_true", help="only the demo rows")
    ap.add_argument(
        "--warmup",
        action="store_true",
        help="also: `jaxcr warmup` into an empty cache, then `jaxcr segment`",
    )
    ap.add_argument("--demo-size", default=None, help="demo image size (default: first of --sizes)")
    ap.add_argument("--name", default="compile_cache", help="output file stem")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rows: dict = {"command": " ".join(["python", *sys.argv]), "frames": a.frames,
                  "cpus": os.cpu_count(), "segment": {}, "demo": {}}  # fmt: skip
    for size in [] if a.no_segment else a.sizes.split(","):
        ds = work / f"ds_{size}"
        if not (ds / "dataset.json").exists():
            _jaxcr(["synth", "--preset", "orthogonal", "--frames", str(a.frames), "--size", size,
                    "-o", str(ds), "--quiet"], None)  # fmt: skip
        runs: dict[str, list[dict]] = {"off": [], "first": [], "second": []}
        if a.warmup:
            runs.update(warmup=[], after_warmup=[])
        for rep in range(a.repeats):
            cache = work / f"cache_{size}_{rep}"
            shutil.rmtree(cache, ignore_errors=True)
            runs["first"].append(_segment(ds, work / "out", str(cache)))
            runs["second"].append(_segment(ds, work / "out", str(cache)))
            runs["off"].append(_segment(ds, work / "out", None))
            if a.warmup:
                wcache = work / f"cache_w_{size}_{rep}"
                shutil.rmtree(wcache, ignore_errors=True)
                w = _jaxcr(["warmup", str(ds), "--no-overlays"], str(wcache))
                runs["warmup"].append(dict(w, compile_s=float("nan"), run_s=float("nan")))
                runs["after_warmup"].append(_segment(ds, work / "out", str(wcache)))
            print(size, rep, {k: v[-1] for k, v in runs.items()}, flush=True)
        rows["segment"][size] = runs
        _write(rows, a)
    if not a.no_demo:
        for size in [a.demo_size] if a.demo_size else a.sizes.split(",")[:1]:
            runs = {"off": [], "first": [], "second": []}
            for rep in range(a.repeats):
                cache = work / f"cache_demo_{size}_{rep}"
                shutil.rmtree(cache, ignore_errors=True)
                argv = ["demo", "-o", str(work / "demo"), "--size", size, "--frames",
                        str(a.frames)]  # fmt: skip
                for key, c in (("off", None), ("first", str(cache)), ("second", str(cache))):
                    shutil.rmtree(work / "demo", ignore_errors=True)
                    runs[key].append(_jaxcr(argv, c))
                print("demo", size, rep, {k: v[-1] for k, v in runs.items()}, flush=True)
            rows["demo"][size] = runs
            _write(rows, a)
    _write(rows, a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
