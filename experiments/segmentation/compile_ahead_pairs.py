"""First and second process of ``jaxcr segment`` (or ``jaxcr demo``) for several trees,
interleaved (issue 18 compilation rows, docs/decisions.md S30): per run the wall and CPU
seconds (user + system of the child) of a process with an empty persistent cache and of one
with the cache it filled, the 1-min load before each, how many entries each process added to
the cache (XLA executables, stored traced programs), and whether every tree's outputs equal the
first tree's (``compare_outputs.py``: results.jsonl fields other than timings, mask/centreline
files byte for byte).

Run::

    python experiments/segmentation/compile_ahead_pairs.py --tree before=DIR --tree after=DIR \
        [--rounds 2] [--work /tmp/compile_ahead_pairs] [--name NAME] \
        [--max-load L --max-wait S] (--dataset DS | --demo) [-- extra options of the command]

``--max-load``: before each process, wait (up to ``--max-wait`` seconds) until the 1-min load
average is below L, so that the trees' runs see alike (and low) loads on a shared machine.

Each tree is a jaxcr source folder (e.g. a ``git archive`` of a commit); its ``jaxcr`` runs with
``PYTHONPATH=DIR``. Writes experiments/results/segmentation/NAME.md.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parents[1] / "experiments" / "results" / "segmentation"


def _entries(cache: Path) -> tuple[int, int]:
    """(XLA executables, stored traced programs) in a jaxcr cache folder."""
    if not cache.exists():
        return 0, 0
    exe = sum(1 for p in cache.iterdir() if p.is_file() and not p.name.startswith("."))
    ex = cache / "exported"
    return exe, (sum(1 for p in ex.iterdir() if p.suffix == ".jaxexport") if ex.exists() else 0)


def _wait_for_load(max_load: float | None, max_wait: float) -> None:
    t0 = time.monotonic()
    while max_load is not None and os.getloadavg()[0] >= max_load:
        if time.monotonic() - t0 > max_wait:
            return
        time.sleep(5)


def run(tree: str, cache: Path, argv: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, JAXCR_CACHE_DIR=str(cache), JAX_PLATFORMS="cpu",
               JAXCR_PROGRESS="0")  # fmt: skip
    env.pop("JAXCR_COMPILE_CACHE", None)
    load = os.getloadavg()[0]
    before = _entries(cache)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "jaxcr", *argv], env=env, cwd=tree,
                       capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"jaxcr {' '.join(argv)} failed ({p.returncode}): {p.stderr[-2000:]}")
    after = _entries(cache)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return {"load": load, "wall": wall, "cpu": cpu,
            "new": (after[0] - before[0], after[1] - before[1])}  # fmt: skip


def _segment_out(out: Path, demo: bool) -> Path:
    if not demo:
        return out
    found = sorted(p.parent for p in out.rglob("results.jsonl"))
    return found[0] if found else out


def _same(a: Path, b: Path) -> str:
    p = subprocess.run([sys.executable, str(HERE / "compare_outputs.py"), str(a), str(b)],
                       capture_output=True, text=True)  # fmt: skip
    return " ".join((p.stdout.strip().splitlines() or ["?"])[-1:])


def main() -> None:
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", action="append", required=True, help="LABEL=DIR")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", default="/tmp/compile_ahead_pairs")
    ap.add_argument("--name", default="compile_ahead_pairs")
    ap.add_argument("--max-load", type=float, default=None)
    ap.add_argument("--max-wait", type=float, default=600.0)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--dataset")
    g.add_argument("--demo", action="store_true")
    a = ap.parse_args(argv[:cut])
    extra = argv[cut + 1 :]
    trees = [t.split("=", 1) for t in a.tree]
    rows = []
    for r in range(1, a.rounds + 1):
        outs = {}
        for label, tree in trees:
            w = Path(a.work) / f"{label}_{r}"
            shutil.rmtree(w, ignore_errors=True)
            w.mkdir(parents=True)
            for proc in ("first", "second"):
                out = w / proc
                if a.demo:
                    cmd = ["demo", "-o", str(out), *extra]
                else:
                    cmd = ["segment", a.dataset, "-o", str(out), "--overwrite", "--quiet",
                           "--no-overlays", *extra]  # fmt: skip
                _wait_for_load(a.max_load, a.max_wait)
                res = run(tree, w / "cache", cmd)
                seg = _segment_out(out, a.demo)
                outs.setdefault(proc, []).append(seg)
                same = _same(outs[proc][0], seg) if len(outs[proc]) > 1 else "(reference)"
                rows.append(f"| {r} | {label} | {proc} | {res['load']:.1f} | {res['wall']:.1f} | "
                            f"{res['cpu']:.1f} | {res['new'][0]} / {res['new'][1]} | {same} |")  # fmt: skip
                print(rows[-1], flush=True)
    cmd = " ".join(["python", "experiments/segmentation/compile_ahead_pairs.py", *argv])
    what = "jaxcr demo" if a.demo else "jaxcr segment"
    text = [f"# `{what}` first / second process, trees interleaved\n",
            f"Command: `{cmd}`\n",
            "new entries = XLA executables / stored traced programs the process added to the "
            "cache; outputs = `compare_outputs.py` against the first tree of the round "
            "(segment outputs, timings aside).\n",
            "| round | tree | process | load before | wall s | CPU s | new entries | outputs |",
            "|---|---|---|---|---|---|---|---|", *rows]  # fmt: skip
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.md").write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
