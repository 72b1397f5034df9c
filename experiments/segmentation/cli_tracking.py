"""The CLI's tracking figure (issue 18): `jaxcr segment --warm-start` on a dataset, each source
tree in its own process with its own compile cache, trees interleaved run by run.

Per tree: one first process (empty cache: the compile is paid and reported apart), then
``--repeats`` processes on the filled cache; each frame's ``time_s`` from ``results.jsonl``
(execution seconds per frame, compilation excluded, what a user reads), the process's wall
and CPU seconds, and whether the trees' masks and records agree byte for byte.

    python experiments/segmentation/cli_tracking.py --data DATASET --tree before=/tmp/base \
        --tree after=. --repeats 3 --name cli_tracking_640

DATASET e.g. from `jaxcr synth --preset orthogonal --size 640x480 --frames 16 --seed 11 -o D`.
Writes experiments/results/segmentation/<name>.md and .json.

A tree may carry its own `jaxcr segment` options after `::`, e.g. `--tree 'off=.::--roi off'
--tree 'auto=.::--roi auto'` (the same source with two settings, each in its own cache;
track31, decisions S28). The IoU of each tracked frame's mask against the dataset's
`masks/<camera>/<frame>.png` is reported when the dataset has them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"


def _run(tree: str, data: str, out: Path, cache: Path, extra: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve()), JAXCR_CACHE_DIR=str(cache))
    cmd = [sys.executable, "-m", "jaxcr", "segment", data, "-o", str(out), "--warm-start"]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists():  # a scratch folder of an earlier call of this script
        shutil.rmtree(out)
    log = out.with_suffix(".log")
    with open(log, "wb") as fh:
        proc = subprocess.Popen(cmd + ["--quiet", *extra], env=env, stdout=fh, stderr=fh)
        _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(
            f"{tree}: jaxcr segment exited {os.waitstatus_to_exitcode(status)} ({log})"
        )
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines() if x.strip()]
    recs = sorted((r for r in recs if "time_s" in r), key=lambda r: r["frame"])
    return {
        "load": load,
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "cold_ms": 1000 * recs[0]["time_s"],
        "warm_ms": [1000 * r["time_s"] for r in recs[1:]],
        "steps": [r["num_steps"] for r in recs[1:]],
        "compile_s": sum(r.get("compile_s", 0.0) for r in recs),
        "frames": len(recs),
        "iou": _ious(out, data),
    }


def _ious(out: Path, data: str) -> list[float]:
    """IoU of each tracked frame's output mask (frames after the first, every camera) against
    the dataset's mask of the same name; [] when the dataset has none."""
    truth_root = Path(data) / "masks"
    preds = sorted((out / "masks").rglob("*.png")) if truth_root.is_dir() else []
    first = min((p.stem for p in preds), default=None)  # the cold frame's id
    vals = []
    for pred in preds:
        truth = truth_root / pred.relative_to(out / "masks")
        if pred.stem == first or not truth.exists():
            continue
        a = cv2.imread(str(pred), cv2.IMREAD_GRAYSCALE) > 0
        b = cv2.imread(str(truth), cv2.IMREAD_GRAYSCALE) > 0
        u = np.logical_or(a, b).sum()
        vals.append(float(np.logical_and(a, b).sum() / u) if u else 1.0)
    return vals


def _same(a: Path, b: Path) -> bool:
    """Masks byte-equal and the records equal but for their timings."""
    ma, mb = sorted((a / "masks").rglob("*.png")), sorted((b / "masks").rglob("*.png"))
    if [p.relative_to(a) for p in ma] != [p.relative_to(b) for p in mb]:
        return False
    if any(x.read_bytes() != y.read_bytes() for x, y in zip(ma, mb, strict=True)):
        return False

    def untimed(v):  # every timing field (time_s, compile_s, at any depth) left out
        if isinstance(v, dict):
            return {k: untimed(x) for k, x in v.items() if k not in ("time_s", "compile_s")}
        return [untimed(x) for x in v] if isinstance(v, list) else v

    def recs(d):
        out = {}
        for line in (d / "results.jsonl").read_text().splitlines():
            r = json.loads(line) if line.strip() else {}
            if "frame" in r:
                out[r["frame"]] = untimed(r)
        return out

    return recs(a) == recs(b)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a jaxcr dataset folder")
    ap.add_argument("--tree", action="append", required=True, metavar="NAME=PATH",
                    help="a source tree (repeat; the first is the reference)")  # fmt: skip
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--name", default="cli_tracking")
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("segment_args", nargs="*", help="more `jaxcr segment` options, after --")
    args = ap.parse_args(argv)
    specs = dict(t.split("=", 1) for t in args.tree)
    trees = {n: v.split("::", 1)[0] for n, v in specs.items()}
    extra = {n: shlex.split(v.split("::", 1)[1]) if "::" in v else [] for n, v in specs.items()}
    work = Path(args.work or tempfile.mkdtemp(prefix="cli_tracking_"))
    res = {n: {"first": None, "runs": []} for n in trees}
    for n, path in trees.items():  # first processes: empty caches
        res[n]["first"] = _run(path, args.data, work / f"{n}_first", work / f"cache_{n}",
                               args.segment_args + extra[n])  # fmt: skip
        print(n, "first", round(res[n]["first"]["wall_s"], 1), "s", flush=True)
    for i in range(args.repeats):
        for n, path in trees.items():
            r = _run(path, args.data, work / f"{n}_{i}", work / f"cache_{n}",
                     args.segment_args + extra[n])  # fmt: skip
            res[n]["runs"].append(r)
            print(n, i, round(statistics.median(r["warm_ms"]), 1), "ms", flush=True)
    ref = next(iter(trees))
    same = {n: all(_same(work / f"{ref}_{i}", work / f"{n}_{i}") for i in range(args.repeats))
            for n in trees}  # fmt: skip
    lines = [
        f"# `jaxcr segment --warm-start`: the CLI's per-frame time ({args.name})",
        "",
        f"Command: `python experiments/segmentation/cli_tracking.py {' '.join(argv or sys.argv[1:])}`",
        f"Dataset: `{args.data}`; trees: "
        + ", ".join(f"{n} = `{p}`" for n, p in trees.items())
        + f". {platform.machine()}, Python {platform.python_version()}, {os.cpu_count()} CPUs.",
        "",
        "time_s: `results.jsonl`'s execution seconds per frame (compilation excluded); frame 0 is "
        "cold, the others warm-started from the previous frame. Medians over frames x repeats; "
        "the trees alternate run by run, each on its own filled compile cache after one first "
        "process on an empty one.",
        "",
        "| tree | tracked ms/frame (median) | cold ms (median) | steps (mean) | process wall s "
        "| process CPU s | first process wall / CPU s (empty cache) | outputs equal to "
        f"{ref} | IoU (mean of tracked frames; min) | load |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, r in res.items():
        warm = [x for run in r["runs"] for x in run["warm_ms"]]
        steps = [x for run in r["runs"] for x in run["steps"]]
        lines.append(
            f"| {n} | {statistics.median(warm):.1f} "
            f"| {statistics.median(run['cold_ms'] for run in r['runs']):.1f} "
            f"| {statistics.mean(steps):.1f} "
            f"| {statistics.median(run['wall_s'] for run in r['runs']):.1f} "
            f"| {statistics.median(run['cpu_s'] for run in r['runs']):.1f} "
            f"| {r['first']['wall_s']:.1f} / {r['first']['cpu_s']:.1f} | {same[n]} "
            + (
                f"| {statistics.mean(r['runs'][0]['iou']):.4f}; {min(r['runs'][0]['iou']):.4f} "
                if r["runs"][0].get("iou")
                else "| - "
            )
            + "| "
            + ", ".join(f"{run['load']:.1f}" for run in r["runs"])
            + " |"
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{args.name}.json").write_text(
        json.dumps({"command": lines[2], "trees": trees, "results": res, "same": same}, indent=1)
        + "\n"
    )
    (OUT / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
