"""Compilation cost of the ``jaxcr stereo`` command's own process (issue 18, the stereo
compilation row): wall clock, process CPU, number of XLA compilations and seconds per
program, for a first process with an empty compilation cache, a second process with the
cache the first one filled, and a process with the cache off.

Usage::

    python experiments/stereo/stereo_compile.py [--work DIR] [--frames 8] [--size 640x480]
        [--repeats 1] [--tag NAME] [--tree DIR ...] [--modes first,second,off]

``jaxcr stereo synth -o WORK/data --frames F --size WxH --seed 0`` writes the dataset once;
then, for each ``--tree`` (a jaxcr source tree, e.g. a ``git archive`` of an older commit;
default: the tree this script is imported from) and each repeat, interleaved, three
``jaxcr stereo WORK/data -o ...`` processes: ``first`` (``JAXCR_CACHE_DIR`` a new empty
folder), ``second`` (the same folder again) and ``off`` (``JAXCR_COMPILE_CACHE=0``). Each child
runs ``jaxcr.cli.main`` with JAX's compile loggers captured: per program the tracing, lowering
and XLA seconds (the XLA span is a compilation or, on a persistent-cache hit, the load of the
stored executable). Wall and CPU (user + system of the child, all threads) come from
``os.wait4``. The results are compared between trees (largest differences of backbone
points, segment curvatures and plane angles, tip pixels). Writes
``experiments/results/stereo/stereo_compile_<tag>.md`` and ``.json``; ``--report JSON``
rewrites the report from an earlier run's JSON and output folders without running again.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

_RX = {
    "xla": re.compile(r"Finished XLA compilation of (\S+) in ([0-9.e-]+) sec"),
    "trace": re.compile(r"Finished tracing \+ transforming (\S+) for pjit in ([0-9.e-]+) sec"),
    "trace2": re.compile(r"Finished tracing (\S+) for jit in ([0-9.e-]+) sec"),
    "lower": re.compile(r"Finished jaxpr to MLIR module conversion (\S+) in ([0-9.e-]+) sec"),
    "hit": re.compile(r"Persistent compilation cache hit for '(\S+)'"),
}


class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.events: list[tuple[str, str, float]] = []

    def emit(self, rec):
        msg = rec.getMessage()
        for kind, rx in _RX.items():
            m = rx.search(msg)
            if m:
                secs = float(m.group(2)) if kind != "hit" else 0.0
                self.events.append(("trace" if kind == "trace2" else kind, m.group(1), secs))


def _child(out_json: str, argv: list[str]) -> int:
    h = _Collect()
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.pjit",
                 "jax._src.compiler"):  # fmt: skip
        lg = logging.getLogger(name)
        lg.setLevel(logging.DEBUG)
        lg.addHandler(h)
        lg.propagate = False
    t0 = time.perf_counter()
    from jaxcr.cli import main

    rc = main(argv)
    Path(out_json).write_text(
        json.dumps({"rc": rc, "wall_in": time.perf_counter() - t0, "events": h.events})
    )
    return 0


def _run(tree: str, work: Path, label: str, cache: Path | None, data: Path) -> dict:
    out = work / f"out_{label}"
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=tree, JAXCR_PROGRESS="off")
    if cache is None:
        env["JAXCR_COMPILE_CACHE"] = "0"
    else:
        env["JAXCR_CACHE_DIR"] = str(cache)
        env.pop("JAXCR_COMPILE_CACHE", None)
    ev = work / f"events_{label}.json"
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [
            sys.executable,
            os.path.abspath(__file__),
            "--child",
            str(ev),
            "--",
            "stereo",
            str(data),
            "-o",
            str(out),
        ],  # fmt: skip
        env=env,
        cwd=work,
    )
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    rec = json.loads(ev.read_text())
    by = {}
    for kind, name, secs in rec["events"]:
        d = by.setdefault(name, {"trace": 0.0, "lower": 0.0, "xla": 0.0, "n": 0, "hits": 0})
        if kind == "xla":
            d["n"] += 1
        if kind == "hit":
            d["hits"] += 1
        else:
            d[kind] += secs
    recs = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    ok = [r["ok"] for r in recs]
    # per-pair CPU of the pipeline's stages (reconstruct_pair's timings), frames after the
    # first (in a second process: nothing left to compile; a run-time check of the buckets)
    pair_cpu = [sum(r["timings"]["cpu"].values()) for r in recs[1:] if r.get("timings")]
    return {
        "label": label,
        "status": status,
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "load": load,
        "n_xla": sum(d["n"] for d in by.values()),
        "n_hits": sum(d["hits"] for d in by.values()),
        "xla_s": sum(d["xla"] for d in by.values()),
        "trace_s": sum(d["trace"] for d in by.values()),
        "lower_s": sum(d["lower"] for d in by.values()),
        "programs": by,
        "pair_cpu_ms": 1e3 * float(np.median(pair_cpu)) if pair_cpu else float("nan"),
        "frames_ok": int(sum(ok)),
        "frames": len(ok),
        "out": str(out),
    }


def _frame_diffs(out: str, ref: str) -> dict[str, float]:
    """Largest differences between two runs' frames: backbone points (m), segment
    curvatures (1/m), plane angles (deg), tip pixels (px); inf where shapes differ."""
    d = {"p_m": 0.0, "kappa_1pm": 0.0, "angle_deg": 0.0, "tip_px": 0.0}
    for f in sorted(Path(ref, "frames").glob("*.json")):
        a, b = json.loads(f.read_text()), json.loads(Path(out, "frames", f.name).read_text())
        pa, pb = (np.load(Path(x, "frames", f.stem + ".npz"))["p"] for x in (ref, out))
        if pa.shape != pb.shape or len(a["segments"]) != len(b["segments"]):
            return {k: float("inf") for k in d}
        d["p_m"] = max(d["p_m"], float(np.max(np.abs(pa - pb))))
        for sa, sb in zip(a["segments"], b["segments"], strict=True):
            d["kappa_1pm"] = max(d["kappa_1pm"], abs(sa["curvature_1pm"] - sb["curvature_1pm"]))
            for k in ("phi_xy_deg", "phi_zx_deg", "phi_yz_deg"):
                d["angle_deg"] = max(d["angle_deg"], abs(sa[k] - sb[k]))
        va, vb = (list(x["views"].values()) if isinstance(x["views"], dict) else x["views"]
                  for x in (a, b))  # fmt: skip
        for x, y in zip(va, vb, strict=True):
            t = np.abs(np.asarray(x["tip_px"], float) - np.asarray(y["tip_px"], float))
            d["tip_px"] = max(d["tip_px"], float(t.max()))
    return d


def main() -> int:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        return _child(sys.argv[2], sys.argv[4:])
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="/tmp/stereo_compile")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--tag", default="head")
    ap.add_argument("--tree", action="append", default=None,
                    help="jaxcr source tree(s) to measure, interleaved (default: this one)")  # fmt: skip
    ap.add_argument("--modes", default="first,second,off")
    ap.add_argument("--report", default=None,
                    help="rewrite the report from this JSON (and its runs' output folders)")  # fmt: skip
    args = ap.parse_args()
    here = str(Path(__file__).resolve().parents[2])
    trees = args.tree or [here]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    data = work / f"data_{args.size}_{args.frames}"
    if not (data / "stereo.json").exists():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "jaxcr",
                "stereo",
                "synth",
                "-o",
                str(data),
                "--frames",
                str(args.frames),
                "--size",
                args.size,
                "--seed",
                "0",
            ],  # fmt: skip
            check=True,
            env=dict(os.environ, PYTHONPATH=here, JAXCR_COMPILE_CACHE="0"),
        )
    rows = json.loads(Path(args.report).read_text())["rows"] if args.report else []
    for rep in range(0 if args.report else args.repeats):
        for ti, tree in enumerate(trees):
            cache = work / f"cache_t{ti}_r{rep}"
            shutil.rmtree(cache, ignore_errors=True)
            for mode in args.modes.split(","):
                label = f"t{ti}_r{rep}_{mode}"
                print(f"{label} ...", flush=True)
                r = _run(tree, work, label, None if mode == "off" else cache, data)
                r.update(tree=tree, tree_index=ti, rep=rep, mode=mode)
                rows.append(r)
                print(f"  wall {r['wall_s']:.1f} s cpu {r['cpu_s']:.1f} s xla {r['n_xla']}"
                      f" ({r['xla_s']:.1f} s, {r['n_hits']} cache hits) load {r['load']:.1f}",
                      flush=True)  # fmt: skip
    # Same results across trees (first process of repeat 0 of each tree against tree 0's).
    firsts = [r for r in rows if r["rep"] == 0 and r["mode"] == rows[0]["mode"]]
    diffs = {r["tree_index"]: _frame_diffs(r["out"], firsts[0]["out"]) for r in firsts[1:]}
    commit = subprocess.run(["git", "log", "-1", "--format=%h"], capture_output=True,
                            text=True, cwd=here).stdout.strip()  # fmt: skip
    res = Path(here) / "experiments/results/stereo"
    (res / f"stereo_compile_{args.tag}.json").write_text(
        json.dumps({"rows": rows, "diffs": diffs, "trees": trees}, indent=1)
    )
    argv = sys.argv[1:]
    if args.report:  # the command that measured, not the rewrite
        i = argv.index("--report")
        argv = argv[:i] + argv[i + 2 :]
    cmd = "python experiments/stereo/stereo_compile.py " + " ".join(argv)
    lines = [
        "# `jaxcr stereo`: compilation in the command's own process (issue 18)",
        "",
        f"Command: `{cmd}`  ",
        f"commit {commit} (of the script's tree); jax {__import__('jax').__version__};"
        f" Python {sys.version.split()[0]}; {platform.machine()}; {os.cpu_count()} logical CPUs"
        f" (shared machine). Dataset: `jaxcr stereo synth --frames {args.frames} --size"
        f" {args.size} --seed 0`. Trees: "
        + ", ".join(f"t{i} = `{t}`" for i, t in enumerate(trees))
        + ".",
        "",
        "CPU = user + system seconds of the whole child process (all threads); XLA = seconds"
        " in XLA compilations or, on a persistent-cache hit, executable loads; trace/lower ="
        " JAX's tracing and StableHLO lowering spans; load = 1-min load average at the start;"
        " pair CPU ms = median over frames 2..N of the summed stage CPU times"
        " (`results.jsonl` timings; in a second process a run-time figure).",
        "",
        "| run | load | wall s | CPU s | XLA programs | cache hits | XLA s | trace s | lower s"
        " | frames ok | pair CPU ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['load']:.1f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} |"
            f" {r['n_xla']} | {r['n_hits']} | {r['xla_s']:.1f} | {r['trace_s']:.1f} |"
            f" {r['lower_s']:.1f} | {r['frames_ok']}/{r['frames']} | {r['pair_cpu_ms']:.0f} |"
        )
    for k, v in diffs.items():
        lines += ["", f"Results of t{k} against t0 (largest difference over all frames and"
                  f" segments): backbone points {v['p_m']:.3g} m, curvatures"
                  f" {v['kappa_1pm']:.3g} 1/m, plane angles {v['angle_deg']:.3g} deg, tip pixels"
                  f" {v['tip_px']:.3g} px."]  # fmt: skip
    for r in rows:
        if r["rep"] == 0 and r["mode"] == "off":
            # the cache-off process: with the cache on, the programs jaxcr stereo calls
            # through jaxcr.io.exported.cached_call all compile under the name "call"
            progs = sorted(r["programs"].items(), key=lambda kv: -kv[1]["xla"])
            lines += [
                "",
                f"### Programs of {r['label']} (XLA seconds, descending; compilations n;"
                " cache off, so every program keeps its name)",
                "",
                "| program | n | XLA s | trace s | lower s |",
                "|---|---|---|---|---|",
            ]
            for name, d in progs:
                if d["n"]:
                    lines.append(f"| `{name}` | {d['n']} | {d['xla']:.2f} | {d['trace']:.2f} |"
                                 f" {d['lower']:.2f} |")  # fmt: skip
    (res / f"stereo_compile_{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
