"""`jaxcr fk` on TEST_CTR with two batch sizes, each in its own process, one persistent cache:
does the second size reuse the first one's compiled program (issue 18, CTR: "compiles once
per robot shape class, not per batch size")? Trees side by side (``git archive`` folders or
``.``), each with a fresh cache folder.

    python experiments/kinematics/fk_batch_buckets.py --tree before=/tmp/x/before --tree after=.
        [--rows 120 100] [--out experiments/results/kinematics/fk_batch_buckets.md]

Per process: wall and CPU seconds (``resource`` RUSAGE_CHILDREN, both cores summed); the
machine's 1-minute load before each. The two trees' centrelines of the second batch are
compared (max |dp|).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = "experiments/results/kinematics/fk_batch_buckets"


def _write_inputs(work: Path, rows: list[int], seed: int) -> list[Path]:
    from jaxcr.benchmarks.ctr_reference import TEST_ROBOT, Tubes, random_q
    from jaxcr.kinematics.ctr import TEST_CTR

    (work / "robot.json").write_text(json.dumps(TEST_CTR))
    rng = np.random.default_rng(seed)
    tubes = Tubes(TEST_ROBOT)
    paths = []
    for i, n in enumerate(rows):
        q = np.stack([random_q(rng, tubes) for _ in range(n)])
        p = work / f"q{i}_{n}.csv"
        np.savetxt(p, q, delimiter=",", fmt="%.9g")
        paths.append(p)
    return paths


def _run(tree: Path, args: list[str], cache: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "JAXCR_CACHE_DIR": str(cache)}
    load = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "jaxcr", "fk", *args], env=env,
                       capture_output=True, text=True, cwd=tree)  # fmt: skip
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"jaxcr fk failed in {tree}: {p.stderr.strip()[-400:]}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "load": round(load, 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", action="append", required=True, metavar="NAME=PATH")
    ap.add_argument("--rows", type=int, nargs=2, default=[120, 100])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=OUT)
    a = ap.parse_args(argv)
    trees = [(t.split("=", 1)[0], Path(t.split("=", 1)[1])) for t in a.tree]
    work = Path(tempfile.mkdtemp(prefix="fkbuckets_"))
    qs = _write_inputs(work, a.rows, a.seed)
    robot = work / "robot.json"
    rows, second_p = [], {}
    for name, tree in trees:
        cache = work / f"cache_{name}"
        res = []
        for i, q in enumerate(qs):
            out = work / f"out_{name}_{i}"
            res.append(_run(tree, [str(robot), str(q), "-o", str(out)], cache))
        second_p[name] = np.load(work / f"out_{name}_1" / "centrelines.npz", allow_pickle=False)[
            "p"
        ]
        rows.append({"tree": name, "first": res[0], "second": res[1]})
    names = [n for n, _ in trees]
    dp = (
        float(np.nanmax(np.abs(second_p[names[0]] - second_p[names[-1]])))
        if len(names) > 1
        else None
    )
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    lines = [
        "# `jaxcr fk` (TEST_CTR): a second batch size reusing the first one's program (issue 18)",
        "",
        "Command: `python experiments/kinematics/fk_batch_buckets.py "
        + " ".join(f"--tree {n}=<{p}>" for n, p in trees)
        + f" --rows {a.rows[0]} {a.rows[1]}` (commit {commit}). Each tree: a fresh cache, "
        f"`jaxcr fk robot.json Q{a.rows[0]}.csv`, then a second process `jaxcr fk robot.json "
        f"Q{a.rows[1]}.csv` with the same cache. CPU = both cores summed.",
        "",
        f"| tree | first process ({a.rows[0]} rows): wall / CPU s | second process "
        f"({a.rows[1]} rows): wall / CPU s | load |",
        "|---|---|---|---|",
    ]
    for r in rows:
        f, s = r["first"], r["second"]
        lines.append(
            f"| {r['tree']} | {f['wall_s']} / {f['cpu_s']} | {s['wall_s']} / {s['cpu_s']} | "
            f"{f['load']}, {s['load']} |"
        )
    if dp is not None:
        lines += ["", f"Second batch's centrelines, {names[0]} vs {names[-1]}: max |dp| = "
                  f"{dp:.3g} m."]  # fmt: skip
    Path(a.out).with_suffix(".md").write_text("\n".join(lines) + "\n")
    Path(a.out).with_suffix(".json").write_text(
        json.dumps({"rows": rows, "max_dp_m": dp, "commit": commit}, indent=1) + "\n"
    )
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
