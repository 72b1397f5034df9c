"""First and second ``jaxcr synth`` process of two trees, interleaved (issue 18, docs/decisions.md
S25): per run the wall and CPU seconds (user + system of the child) of a process with an empty
persistent cache and of one with the cache it filled, the 1-min load before each.

Run::

    python experiments/segmentation/synth_compile_pairs.py --tree before=DIR --tree after=DIR \
        [--rounds 2] [--work /tmp/synth_pairs] [--name synth_compile_s25] [-- synth options]

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

RESULTS = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def run(tree: str, cache: str, out: str, extra: list[str]) -> tuple[float, float, float]:
    env = dict(os.environ, PYTHONPATH=tree, JAXCR_CACHE_DIR=cache, JAX_PLATFORMS="cpu")
    env.pop("JAXCR_COMPILE_CACHE", None)
    load = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jaxcr", "synth", "-o", out, "--quiet", *extra],
                   env=env, cwd=tree, check=True, capture_output=True)  # fmt: skip
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return load, wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", action="append", required=True, help="LABEL=DIR")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work", default="/tmp/synth_pairs")
    ap.add_argument("--name", default="synth_compile_s25")
    ap.add_argument("extra", nargs="*")
    a = ap.parse_args()
    trees = [t.split("=", 1) for t in a.tree]
    rows = []
    for r in range(1, a.rounds + 1):
        for label, tree in trees:
            w = Path(a.work) / f"{label}_{r}"
            shutil.rmtree(w, ignore_errors=True)
            w.mkdir(parents=True)
            for proc in ("first", "second"):
                load, wall, cpu = run(tree, str(w / "cache"), str(w / proc), a.extra)
                rows.append(f"| {r} | {label} | {proc} | {load:.1f} | {wall:.1f} | {cpu:.1f} |")
                print(rows[-1], flush=True)
    cmd = " ".join(["python", "experiments/segmentation/synth_compile_pairs.py", *sys.argv[1:]])
    text = [f"# `jaxcr synth` first / second process, trees interleaved\n\nCommand: `{cmd}`\n",
            "| round | tree | process | load before | wall s | CPU s |", "|---|---|---|---|---|---|",
            *rows]  # fmt: skip
    (RESULTS / f"{a.name}.md").write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
