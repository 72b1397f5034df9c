"""First and second process of every ``jaxcr`` command a user runs repeatedly (issue 18, K4).

For each command (row) and each tree: a first process with an empty compilation cache
(``JAXCR_CACHE_DIR=<work>/cache/<tree>/<row>``), then a second, identical process with the
same cache (its own output folder, so that nothing resumes). Per process: wall and CPU
(user + sys of the child, ``os.wait4``), and from ``k4_probe.py``: seconds of tracing,
lowering and backend compilation (XLA, or loading an executable from the cache), cache hits,
import seconds, exit code. The small inputs are made once by ``jaxcr ... synth`` (development
seeds 0-3) into ``<work>/inputs`` with a throwaway cache.

    python experiments/scale/second_process_k4.py --work /tmp/warm33/k4 \
        --tree after=. [--tree before=/tmp/warm33/before] [--rows fk_ctr,fk_cc] \
        --jsonl OUT.jsonl

Rows of several trees are interleaved (row by row, trees in the given order). The JSON lines
are summarised by ``--report OUT.jsonl [...] --md FILE``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROBE = HERE / "k4_probe.py"


def jaxcr_env(tree: Path, cache: Path | None) -> dict:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAX_", "XLA_", "JAXCR_"))}  # fmt: skip
    env.update(PYTHONPATH=str(tree), JAX_PLATFORMS="cpu", JAXCR_PROGRESS="0")
    if cache is not None:
        env["JAXCR_CACHE_DIR"] = str(cache)
    return env


def run_probe(tree: Path, cache: Path, argv: list[str], log: Path) -> dict:
    out_json = log.with_suffix(".json")
    cmd = ["nice", "-n", "10", sys.executable, str(PROBE), str(out_json), "--", *argv]
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, env=jaxcr_env(tree, cache), stdout=fh, stderr=subprocess.STDOUT,
                             cwd=str(log.parent))  # fmt: skip
        _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    rec = {"wall_s": round(wall, 2), "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
           "maxrss_mb": round(ru.ru_maxrss / 1024), "status": os.waitstatus_to_exitcode(status)}  # fmt: skip
    if out_json.exists():
        rec.update({k: round(v, 3) if isinstance(v, float) else v
                    for k, v in json.loads(out_json.read_text()).items()})  # fmt: skip
    return rec


def jaxcr(tree: Path, cache: Path, *argv) -> None:
    """A setup command (inputs), run to completion; its failure stops the script."""
    cmd = [sys.executable, "-m", "jaxcr", *map(str, argv)]
    r = subprocess.run(cmd, env=jaxcr_env(tree, cache), capture_output=True, text=True)
    if r.returncode not in (0, 1):
        sys.exit(f"setup failed: {' '.join(cmd)}\n{r.stdout}\n{r.stderr}")


def make_inputs(tree: Path, d: Path) -> None:
    import cv2
    import numpy as np

    if (d / "done").exists():
        return
    d.mkdir(parents=True, exist_ok=True)
    cache = d / "cache"
    jaxcr(tree, cache, "synth", "--preset", "orthogonal", "--size", "160x120", "--frames", "4",
          "--seed", "0", "-o", d / "syn", "--quiet")  # fmt: skip
    frames = json.loads((d / "syn" / "dataset.json").read_text())["frames"]
    q = np.array([f["q"] for f in frames], float)
    # 100 joint rows around the dataset's frames (TEST_CTR-like robot of the synth preset)
    rows = q[np.arange(100) % len(q)] * (1 + 0.01 * np.linspace(-1, 1, 100)[:, None])
    (d / "q_ctr.csv").write_text("\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    cc = {"kind": "constant_curvature", "n_points": 33,
          "sections": [{"length": 0.05, "radius": 0.003}, {"length": 0.04, "radius": 0.002}],
          "joints": ["kappa", "phi"]}  # fmt: skip
    (d / "cc.json").write_text(json.dumps(cc))
    rng = np.random.default_rng(0)
    qcc = np.column_stack([rng.uniform(0, 20, 100), rng.uniform(-3, 3, 100),
                           rng.uniform(0, 20, 100), rng.uniform(-3, 3, 100)])  # fmt: skip
    (d / "q_cc.csv").write_text("\n".join(",".join(f"{v:.9g}" for v in r) for r in qcc) + "\n")
    # a measured backbone: the fk centreline of the first row, every 4th point, in mm
    jaxcr(tree, cache, "fk", d / "syn", d / "q_ctr.csv", "-o", d / "fk_in")
    with np.load(d / "fk_in" / "centrelines.npz") as z:
        p = z["p"][0]
    pts = p[np.r_[0 : len(p) : 4, len(p) - 1]] * 1000.0
    with open(d / "bb.csv", "w") as fh:
        fh.write("# unit: mm\nx,y,z\n")
        np.savetxt(fh, pts, delimiter=",", fmt="%.6f")
    jaxcr(tree, cache, "segment", d / "syn", "-o", d / "segout", "--quiet")
    jaxcr(tree, cache, "stereo", "synth", "--size", "128x96", "--frames", "2", "--seed", "0",
          "-o", d / "ster")  # fmt: skip
    jaxcr(tree, cache, "motion", "synth", "--size", "64x48", "--frames", "6", "--seed", "0",
          "-o", d / "mot")  # fmt: skip
    jaxcr(tree, cache, "model-object", "synth", "--size", "64x48", "--seed", "0", "-o", d / "mo")
    jaxcr(tree, cache, "manifold", "synth", "--size", "48x36", "--frames", "12", "--seed", "0",
          "-o", d / "man")  # fmt: skip
    jaxcr(tree, cache, "manifold", "train", d / "man", "-o", d / "man.npz", "--bins", "24",
          "--step", "0.05")  # fmt: skip
    # chessboards: one board (6 x 5 inner corners) under 6 homographies per camera
    board = np.full((240, 320), 255, np.uint8)
    for r in range(6):
        for c in range(7):
            if (r + c) % 2 == 0:
                board[60 + r * 20 : 80 + r * 20, 90 + c * 20 : 110 + c * 20] = 0
    for side, dx in (("L", 0.0), ("R", 6.0)):
        (d / side).mkdir(exist_ok=True)
        for k in range(6):
            a = 0.15 * np.sin(k * 1.3)
            H = np.array([[1 + 0.05 * np.cos(k), 0.1 * np.sin(k), dx + 4 * k - 10],
                          [-0.08 * np.sin(k), 1 + 0.04 * np.sin(k), 3 * k - 8],
                          [a * 1e-3, 0.5e-3 * np.cos(k * 2.1), 1.0]])  # fmt: skip
            img = cv2.warpPerspective(board, H, (320, 240), borderValue=255)
            cv2.imwrite(str(d / side / f"{k:03d}.png"), img)
    (d / "done").write_text("")


def rows(d: Path) -> dict[str, list]:
    """Row name -> argv with ``{out}`` for the process's output folder."""
    return {
        "synth": ["synth", "--preset", "orthogonal", "--size", "160x120", "--frames", "4",
                  "--seed", "1", "-o", "{out}", "--quiet"],
        "demo": ["demo", "--frames", "2", "--size", "160x120", "--seed", "2", "-o", "{out}"],
        "fk_ctr": ["fk", d / "syn", d / "q_ctr.csv", "-o", "{out}"],
        "fk_cc": ["fk", d / "cc.json", d / "q_cc.csv", "-o", "{out}"],
        "fit": ["fit", d / "syn", "--backbone", d / "bb.csv", "-o", "{out}"],
        "segment": ["segment", d / "syn", "-o", "{out}", "--quiet"],
        "evaluate": ["evaluate", d / "segout", "-o", "{out}", "--no-plot"],
        "stereo": ["stereo", d / "ster", "-o", "{out}"],
        "stereo_synth": ["stereo", "synth", "--size", "128x96", "--frames", "2", "--seed", "3",
                         "-o", "{out}"],
        "manifold_train": ["manifold", "train", d / "man", "-o", "{out}.npz", "--bins", "24",
                           "--step", "0.05"],
        "manifold_query": ["manifold", "query", d / "man.npz", d / "man", "-o", "{out}"],
        "motion": ["motion", d / "mot", "-o", "{out}"],
        "model_object": ["model-object", d / "mo", "-o", "{out}"],
        "calibrate": ["calibrate", d / "L", d / "R", "--cols", "6", "--rows", "5", "--pitch",
                      "0.01", "-o", "{out}.yaml"],
        "warmup": ["warmup", d / "syn"],
    }  # fmt: skip


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/warm33/k4"))
    ap.add_argument("--tree", action="append", default=[], help="NAME=PATH")
    ap.add_argument("--rows", default="", help="comma-separated row names (default: all)")
    ap.add_argument("--jsonl", type=Path, default=None)
    ap.add_argument("--report", nargs="*", type=Path, default=None, help="JSON lines to table")
    ap.add_argument("--md", type=Path, default=None)
    ap.add_argument("--compare", default="", help="rows whose outputs to compare across runs")
    a = ap.parse_args()
    if a.compare:
        for row in a.compare.split(","):
            print(compare(a.work / "runs", row))
        return
    if a.report:
        print(table([json.loads(x) for f in a.report for x in f.read_text().splitlines() if x]))
        return
    trees = [(n, Path(p).resolve()) for n, p in (t.split("=", 1) for t in a.tree)]
    inputs = a.work / "inputs"
    make_inputs(trees[0][1], inputs)
    all_rows = rows(inputs)
    names = [r for r in a.rows.split(",") if r] or list(all_rows)
    for name in names:
        for tree_name, tree in trees:
            base = a.work / "runs" / tree_name / name
            cache = a.work / "cache" / tree_name / name
            for d in (base, cache):
                shutil.rmtree(d, ignore_errors=True)
            base.mkdir(parents=True)
            rec = {"row": name, "tree": tree_name, "load_before": uptime()}
            for which in ("first", "second"):
                argv = [str(x).replace("{out}", str(base / f"out_{which}")) for x in all_rows[name]]
                rec[which] = run_probe(tree, cache, argv, base / f"{which}.log")
                # traced programs stored by jaxcr.io.exported.cached_call (0: none, or a fallback)
                rec[which]["stored"] = len(list((cache / "exported").glob("*.jaxexport")))
            rec["load_after"] = uptime()
            rec["argv"] = " ".join(["jaxcr", *map(str, all_rows[name])]).replace(str(inputs), "IN")
            print(json.dumps(rec), flush=True)
            if a.jsonl:
                with open(a.jsonl, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")


def compare(runs: Path, row: str) -> str:
    """Largest difference of every tree's and process's outputs from the first tree's first
    process: ``centrelines.npz`` (fk rows) or ``fit.json``'s q and rms (fit)."""
    import numpy as np

    outs = sorted(runs.glob(f"*/{row}/out_*"))
    if not outs:
        return f"{row}: no outputs"
    ref_dir = outs[0]
    lines = []
    for d in outs:
        if row.startswith("fk"):
            with np.load(ref_dir / "centrelines.npz") as a, np.load(d / "centrelines.npz") as b:
                diff = max(float(np.nanmax(np.abs(a[k].astype(float) - b[k].astype(float))))
                           for k in ("p", "R", "rho", "residual", "energy", "num_steps", "ok"))  # fmt: skip
            same = (ref_dir / "tips.csv").read_bytes() == (d / "tips.csv").read_bytes()
            lines.append(f"{d.relative_to(runs)}: max |diff| {diff:.3g}, tips.csv identical {same}")
        elif row == "fit":
            a, b = (json.loads((x / "fit.json").read_text()) for x in (ref_dir, d))
            dq = float(np.max(np.abs(np.subtract(a["q"], b["q"]))))
            lines.append(f"{d.relative_to(runs)}: max |dq| {dq:.3g}, rms {b['rms']:.6g} "
                         f"(ref {a['rms']:.6g})")  # fmt: skip
    return f"{row} (reference {ref_dir.relative_to(runs)}):\n" + "\n".join(lines)


def _load(s: str) -> str:
    return s.split("load average:")[-1].strip().split(",")[0] if "load average" in s else "?"


def table(recs: list[dict]) -> str:
    out = ["| row | tree | first: wall / CPU s | first: trace / lower / backend s (n) | "
           "second: wall / CPU s | second: import / trace / lower / backend s (n) | "
           "second: cache hits / misses | stored programs | exit codes | load (1-min) before, after |",
           "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in recs:
        f, s = r["first"], r["second"]
        out.append(
            f"| {r['row']} | {r['tree']} | {f['wall_s']:.1f} / {f['cpu_s']:.1f} | "
            f"{f.get('trace_s', 0):.1f} / {f.get('lower_s', 0):.1f} / {f.get('backend_s', 0):.1f}"
            f" ({int(f.get('backend_n', 0))}) | **{s['wall_s']:.1f} / {s['cpu_s']:.1f}** | "
            f"{s.get('import_s', 0):.1f} / {s.get('trace_s', 0):.1f} / {s.get('lower_s', 0):.1f} / "
            f"{s.get('backend_s', 0):.1f} ({int(s.get('backend_n', 0))}) | "
            f"{int(s.get('hits', 0))} / {int(s.get('misses', 0))} | {s.get('stored', '?')} | "
            f"{f['status']}, {s['status']} | {_load(r['load_before'])}, {_load(r['load_after'])} |"
        )
    return "\n".join(out)


if __name__ == "__main__":
    main()
