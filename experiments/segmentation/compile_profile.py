"""Where a ``jaxcr segment`` process spends its time, per compiled program (issue 18,
compilation row): import, then for every program JAX traces, lowers or compiles (or loads
from the persistent cache) the wall and process-CPU seconds of each of the three stages,
and what is left (running the frames, reading and writing files, Python glue).

Each process is ``jaxcr segment DATASET -o OUT --overwrite --quiet --no-overlays [extra]``
run in a child of this script with ``JAXCR_CACHE_DIR=CACHE``; the driver runs it with an empty
cache (first process) and again with the filled cache (second process), records the 1-min
load before each, and writes a Markdown table.

Stages come from JAX's monitoring events (``/jax/core/compile/jaxpr_trace_duration``,
``..._to_mlir_module_duration``, ``backend_compile_duration``; their ``fun_name``), CPU from
``time.process_time`` at the start (scalar event) and end (span event) of each stage, so the
CPU column includes XLA's compile threads and anything else the process ran in that span.

``DATASET`` = ``demo`` profiles ``jaxcr demo -o OUT [extra]`` instead (synth, segment and
evaluate in one process; the summary figures are its segment step's).

Run (from the repository root)::

    PYTHONPATH=$PWD python experiments/segmentation/compile_profile.py DATASET \
        [--work /tmp/jaxcr_compile_profile] [--name compile_profile] [-- extra segment options]

Writes experiments/results/segmentation/NAME.md and .json.
"""

from __future__ import annotations

import time

T_START = time.perf_counter()
C_START = time.process_time()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "experiments" / "results" / "segmentation"
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "backend",
}


def child(dataset: str, out: str, extra: list[str]) -> dict:
    import jax.monitoring as monitoring

    wall: dict = defaultdict(float)
    cpu: dict = defaultdict(float)
    count: dict = defaultdict(int)
    started: dict = defaultdict(list)

    def on_start(event: str, value: float, **kw) -> None:
        if event in EVENTS:
            started[event].append(time.process_time())

    def on_span(event: str, start: float, end: float, **kw) -> None:
        if event in EVENTS and started[event]:
            key = (EVENTS[event], str(kw.get("fun_name", "?")))
            wall[key] += end - start
            cpu[key] += time.process_time() - started[event].pop()
            count[key] += 1

    monitoring.register_scalar_listener(on_start)
    monitoring.register_event_time_span_listener(on_span)
    t_jax, c_jax = time.perf_counter(), time.process_time()
    from jaxcr.cli import main as cli_main

    t_cli, c_cli = time.perf_counter(), time.process_time()
    if dataset == "demo":  # `jaxcr demo -o OUT [extra]` (synth + segment + evaluate)
        shutil.rmtree(out, ignore_errors=True)
        argv = ["demo", "-o", out, *extra]
    else:
        argv = ["segment", dataset, "-o", out, "--overwrite", "--quiet", "--no-overlays", *extra]
    rc = cli_main(argv)
    t_end, c_end = time.perf_counter(), time.process_time()
    seg = Path(out) / ("segment" if dataset == "demo" else "")
    summary = json.loads((seg / "summary.json").read_text())
    programs: dict = defaultdict(dict)
    for (stage, name), w in wall.items():
        programs[name][stage] = [round(w, 3), round(cpu[(stage, name)], 3), count[(stage, name)]]
    return {
        "rc": rc,
        "import_jax": [round(t_jax - T_START, 3), round(c_jax - C_START, 3)],
        "import_jaxcr": [round(t_cli - t_jax, 3), round(c_cli - c_jax, 3)],
        "segment_call": [round(t_end - t_cli, 3), round(c_end - c_cli, 3)],
        "process": [round(t_end - T_START, 3), round(c_end - C_START, 3)],
        "programs": programs,
        "summary_compile_s": summary.get("compile_s"),
        "summary_run_s": summary.get("run_s"),
    }


def _table(r: dict, top: int) -> list[str]:
    rows = []
    for name, st in r["programs"].items():
        tot_w = sum(v[0] for v in st.values())
        tot_c = sum(v[1] for v in st.values())
        rows.append((tot_c, tot_w, name, st))
    rows.sort(reverse=True)

    def cell(st, k):
        return f"{st[k][0]:.2f} / {st[k][1]:.2f}" if k in st else "-"

    lines = ["| program | trace wall / CPU s | lower | backend (XLA or cache load) | total CPU s |",
             "|---|---|---|---|---|"]  # fmt: skip
    for tot_c, _tot_w, name, st in rows[:top]:
        lines.append(f"| `{name}` | {cell(st, 'trace')} | {cell(st, 'lower')} | "
                     f"{cell(st, 'backend')} | {tot_c:.2f} |")  # fmt: skip
    rest = rows[top:]
    if rest:
        lines.append(f"| {len(rest)} others | | | | {sum(x[0] for x in rest):.2f} |")
    sums = {k: [0.0, 0.0] for k in ("trace", "lower", "backend")}
    for _, _, _, st in rows:
        for k, v in st.items():
            sums[k][0] += v[0]
            sums[k][1] += v[1]
    comp_w = sum(v[0] for v in sums.values())
    comp_c = sum(v[1] for v in sums.values())
    seg = r["segment_call"]
    lines += [
        "",
        "| process part | wall s | CPU s |",
        "|---|---|---|",
        f"| import jax | {r['import_jax'][0]:.2f} | {r['import_jax'][1]:.2f} |",
        f"| import jaxcr.cli | {r['import_jaxcr'][0]:.2f} | {r['import_jaxcr'][1]:.2f} |",
        *(f"| {k} (all {len(rows)} programs) | {v[0]:.2f} | {v[1]:.2f} |" for k, v in sums.items()),
        f"| rest of the command (segment's frames run {r['summary_run_s']:.2f} s wall, file I/O, export "
        f"serialisation, glue) | {seg[0] - comp_w:.2f} | {seg[1] - comp_c:.2f} |",
        f"| **process** | **{r['process'][0]:.2f}** | **{r['process'][1]:.2f}** |",
        "",
        f"summary.json compile_s {r['summary_compile_s']:.2f}, run_s {r['summary_run_s']:.2f}; "
        f"load before {r['load_before']:.2f}",
    ]
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--work", default="/tmp/jaxcr_compile_profile")
    ap.add_argument("--name", default="compile_profile")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    a = ap.parse_args(argv[:cut])
    a.extra = argv[cut + 1 :]  # segment's (or demo's) own options, after "--"
    work = Path(a.work)
    if a.child:
        print("RESULT " + json.dumps(child(a.dataset, str(work / "out"), a.extra)), flush=True)
        return 0
    cache = work / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAXCR_PROGRESS="0", JAXCR_CACHE_DIR=str(cache))
    env.pop("JAXCR_COMPILE_CACHE", None)
    res = {"command": " ".join(["python", *sys.argv]), "runs": {}}
    for run in ("first", "second"):
        load = os.getloadavg()[0]
        p = subprocess.run(
            [sys.executable, __file__, a.dataset, "--work", str(work), "--child",
             *(["--", *a.extra] if a.extra else [])],
            env=env, capture_output=True, text=True,
        )  # fmt: skip
        line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
        if p.returncode != 0 or not line:
            raise SystemExit(f"child failed ({p.returncode}): {p.stderr[-2000:]}")
        r = json.loads(line[0][7:])
        r["load_before"] = load
        res["runs"][run] = r
    res["load_after"] = os.getloadavg()[0]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.json").write_text(json.dumps(res, indent=1) + "\n")
    lines = [
        "# Where a `jaxcr segment` process spends its time, per program",
        "",
        f"Reproduce: `PYTHONPATH=$PWD {res['command']}` (2-core CPU shared with other jobs).",
        "",
    ]
    for run, title in (("first", "First process (empty cache)"),
                       ("second", "Second process (filled cache)")):  # fmt: skip
        lines += [f"## {title}", "", *_table(res["runs"][run], a.top), ""]
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
