"""Compile reuse and per-frame cost of shape buckets (docs/decisions.md S29).

For each mode (``--shape-buckets on`` / ``off``), in a new empty persistent cache: a first
``jaxcr segment`` on a dataset at the bucket's own size (``--first``, e.g. 640x480), then a
second process on a dataset at another size of the same bucket (``--second``, e.g. 600x450).
Modes alternate per round (``off`` first in even rounds). Per process: exit code, wall and CPU
seconds (``run_child``: RUSAGE_CHILDREN), the command's own ``compile_s`` and median
``time_s`` (summary.json), the 1-min load before and after. Then, per size, whether the two
modes' outputs are equal (mask PNG bytes, centreline max difference, energy relative
difference, IoU between the masks).

    python experiments/segmentation/shape_buckets.py --first 640x480 --second 600x450 \\
        --frames 8 --seed 11 --rounds 1 --name shape_buckets_s29
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from jaxcr.benchmarks.compile import _commit, _load, last_line, run_child

OUT = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def _env(cache: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAXCR_")}
    env["JAXCR_CACHE_DIR"] = cache
    return env


def _compare(a: Path, b: Path) -> dict:
    """Outputs of two runs of one dataset: masks, centrelines, energies."""
    from PIL import Image

    ra = {r["frame"]: r for r in map(json.loads, (a / "results.jsonl").read_text().splitlines())}
    rb = {r["frame"]: r for r in map(json.loads, (b / "results.jsonl").read_text().splitlines())}
    same_png, px, ious, dcl, de = 0, [], [], [], []
    n = 0
    for fid, x in ra.items():
        y = rb.get(fid)
        if not (y and x.get("ok") and y.get("ok")):
            continue
        n += 1
        for cam, rel in x["files"]["masks"].items():
            ma = np.asarray(Image.open(a / rel)) > 0
            mb = np.asarray(Image.open(b / y["files"]["masks"][cam])) > 0
            assert ma.shape == mb.shape, (ma.shape, mb.shape)
            same_png += (a / rel).read_bytes() == (b / y["files"]["masks"][cam]).read_bytes()
            px.append(int((ma != mb).sum()))
            ious.append(float((ma & mb).sum() / max((ma | mb).sum(), 1)))
        ca = np.load(a / x["files"]["centreline"], allow_pickle=False)
        cb = np.load(b / y["files"]["centreline"], allow_pickle=False)
        dcl.append(float(np.abs(ca - cb).max()))
        ea, eb = x["energy"]["total"], y["energy"]["total"]
        de.append(abs(ea - eb) / max(abs(ea), 1e-12))
    return {"frames": n, "masks_bytes_equal": same_png, "mask_px_diff_max": max(px, default=0),
            "iou_min": min(ious, default=1.0), "centreline_max_m": max(dcl, default=0.0),
            "energy_rel_max": max(de, default=0.0)}  # fmt: skip


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--first", default="640x480")
    p.add_argument("--second", default="600x450")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    p.add_argument("--name", default="shape_buckets_s29")
    p.add_argument("--commit", default=None, help="recorded commit (default: git's HEAD)")
    a = p.parse_args()
    work = Path(a.work or tempfile.mkdtemp(prefix="buckets-"))
    work.mkdir(parents=True, exist_ok=True)
    cwd = str(work)
    data = {}
    for size in (a.first, a.second):
        d = work / f"ds_{size}"
        if not (d / "dataset.json").exists():
            r = subprocess.run([sys.executable, "-m", "jaxcr", "--no-compile-cache", "synth",
                                "--preset", "orthogonal", "--size", size, "--frames",
                                str(a.frames), "--seed", str(a.seed), "-o", str(d)],
                               capture_output=True, text=True)  # fmt: skip
            if r.returncode:
                print(r.stderr, file=sys.stderr)
                return 1
        data[size] = d
    rows = []
    for rnd in range(a.rounds):
        modes = ("off", "on") if rnd % 2 == 0 else ("on", "off")
        for mode in modes:
            cache = str(work / f"cache_{mode}_{rnd}")
            for which, size in (("first", a.first), ("second", a.second)):
                out = work / f"out_{mode}_{size}_{rnd}"
                argv = ["segment", str(data[size]), "-o", str(out), "--quiet", "--overwrite",
                        "--shape-buckets", mode]  # fmt: skip
                l0 = _load()
                r = run_child(argv, _env(cache), cwd)
                l1 = _load()
                summ = {}
                if (out / "summary.json").exists():
                    summ = json.loads((out / "summary.json").read_text())
                rows.append(dict(round=rnd, mode=mode, process=which, size=size, rc=r.rc,
                                 wall=r.wall_s, cpu=r.cpu_s, compile_s=summ.get("compile_s"),
                                 time_s=summ.get("median_time_s"), load=(l0, l1),
                                 err="" if r.rc == 0 else last_line(r.stderr)))  # fmt: skip
                print(rows[-1], flush=True)
    cmp = {size: _compare(work / f"out_off_{size}_0", work / f"out_on_{size}_0")
           for size in (a.first, a.second)}  # fmt: skip
    lines = [f"# Shape buckets (S29): compile reuse and per-frame cost, {a.first} then {a.second}",
             "", f"Commit {a.commit or _commit()}; command: `python experiments/segmentation/shape_buckets.py "
             f"--first {a.first} --second {a.second} --frames {a.frames} --seed {a.seed} "
             f"--rounds {a.rounds} --name {a.name}`. Datasets: `jaxcr synth --preset orthogonal "
             f"--size WxH --frames {a.frames} --seed {a.seed}`. Each mode's two processes share "
             "one new empty cache (the first fills it). `uptime` load before -> after each "
             "process.", "",
             "| round | buckets | process | size | exit | compile_s | wall s | CPU s | "
             "median time_s (ms/frame) | load |", "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        cs = "-" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        ts = "-" if r["time_s"] is None else f"{1e3 * r['time_s']:.1f}"
        lines.append(f"| {r['round']} | {r['mode']} | {r['process']} | {r['size']} | {r['rc']} | "
                     f"{cs} | {r['wall']:.1f} | {r['cpu']:.1f} | {ts} | "
                     f"{r['load'][0]:.1f} -> {r['load'][1]:.1f} |" + (f" {r['err']}" if r["err"] else ""))  # fmt: skip
    lines += ["", "Outputs, buckets off vs on (round 0), per size:", "",
              "| size | frames | mask PNGs byte-equal | max mask px differing | min IoU between "
              "masks | max centreline difference (m) | max energy.total rel. difference |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for size, c in cmp.items():
        lines.append(f"| {size} | {c['frames']} | {c['masks_bytes_equal']} | {c['mask_px_diff_max']} "
                     f"| {c['iou_min']:.4f} | {c['centreline_max_m']:.2e} | {c['energy_rel_max']:.2e} |")  # fmt: skip
    path = OUT / f"{a.name}.md"
    path.write_text("\n".join(lines) + "\n")
    (OUT / f"{a.name}.json").write_text(json.dumps({"rows": rows, "compare": cmp}, indent=1))
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
