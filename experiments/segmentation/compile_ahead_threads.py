"""Where the CPU of a first ``jaxcr segment`` process runs with the programs compiled side by
side (docs/decisions.md S30): per thread, independent of the machine's load.

Runs ``jaxcr segment DATASET`` in this process with an empty cache folder and records
``time.thread_time`` (the CPU of one thread) of the main thread at each stage and of each pool
worker over the XLA compilation it waits for, the process CPU over each compilation's span,
and at the end every OS thread's CPU (``/proc/self/task``). XLA:CPU compiles in threads of
its own (the pool's workers only wait for them), so the compile CPU shows up there.

Run (from the repository root)::

    PYTHONPATH=$PWD python experiments/segmentation/compile_ahead_threads.py DATASET \
        [--work /tmp/compile_ahead_threads] [--name NAME] [-- segment options]

Writes experiments/results/segmentation/NAME.md and .json.
"""

from __future__ import annotations

import time

T0, C0, M0 = time.perf_counter(), time.process_time(), time.thread_time()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
from pathlib import Path  # noqa: E402

RESULTS = Path(__file__).resolve().parents[2] / "experiments" / "results" / "segmentation"


def _threads() -> list[tuple[str, float]]:
    """(name, CPU s) of every thread of this process, largest first (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = []
    for tid in os.listdir("/proc/self/task"):
        try:
            stat = open(f"/proc/self/task/{tid}/stat").read().rsplit(")", 1)[1].split()
            name = open(f"/proc/self/task/{tid}/comm").read().strip()
        except OSError:
            continue
        out.append((f"{name}[{tid}]", (int(stat[11]) + int(stat[12])) / tick))
    return sorted(out, key=lambda x: -x[1])


def main() -> int:
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--work", default="/tmp/compile_ahead_threads")
    ap.add_argument("--name", default="compile_ahead_threads")
    a = ap.parse_args(argv[:cut])
    extra = argv[cut + 1 :]
    work = Path(a.work)
    shutil.rmtree(work, ignore_errors=True)
    os.environ["JAXCR_CACHE_DIR"] = str(work / "cache")
    os.environ.pop("JAXCR_COMPILE_CACHE", None)
    load0 = os.getloadavg()[0]
    from jaxcr.cli import main as cli_main
    from jaxcr.io import exported

    tasks: list[dict] = []
    lock = threading.Lock()
    real_start = exported._start_compile
    real_ahead = exported.compile_ahead
    marks: dict = {}

    def start_compile(pool, memo_key, call, leaves, out_tree, out_box):
        name = getattr(call, "__name__", "?")
        rec = {"program": name, "main_cpu_at_submit": time.thread_time() - M0}

        class Timed:  # wraps the pool so that the worker's own CPU is measured
            def submit(self, fn):
                def run():
                    t, c, w = time.thread_time(), time.process_time(), time.perf_counter()
                    out = fn()
                    rec.update(worker_cpu=time.thread_time() - t,
                               process_cpu=time.process_time() - c,
                               wall=time.perf_counter() - w,
                               thread=threading.current_thread().name)  # fmt: skip
                    return out

                return pool.submit(run)

        with lock:
            tasks.append(rec)
        return real_start(Timed(), memo_key, call, leaves, out_tree, out_box)

    from contextlib import contextmanager

    @contextmanager
    def ahead(*args, **kw):
        marks["dry_start"] = time.thread_time() - M0
        with real_ahead(*args, **kw):
            yield
            marks["dry_end"] = time.thread_time() - M0
            marks["dry_end_wall"] = time.perf_counter() - T0
        marks["wait_end"] = time.thread_time() - M0
        marks["wait_end_wall"] = time.perf_counter() - T0

    exported._start_compile = start_compile
    exported.compile_ahead = ahead
    code = cli_main(["segment", a.dataset, "-o", str(work / "out"), "--overwrite", "--quiet",
                     "--no-overlays", *extra])  # fmt: skip
    res = {
        "command": " ".join(
            ["python", "experiments/segmentation/compile_ahead_threads.py", *argv]
        ),  # fmt: skip
        "exit": code,
        "load_before": load0,
        "load_after": os.getloadavg()[0],
        "process_wall": time.perf_counter() - T0,
        "process_cpu": time.process_time() - C0,
        "main_cpu": time.thread_time() - M0,
        "marks": marks,
        "tasks": tasks,
    }
    res["threads"] = _threads()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{a.name}.json").write_text(json.dumps(res, indent=1) + "\n")
    lines = [
        "# First `jaxcr segment` process, CPU per thread (S30)",
        "",
        f"Reproduce: `PYTHONPATH=$PWD {res['command']}`; load {load0:.1f} -> "
        f"{res['load_after']:.1f}.",
        "",
        f"Process: {res['process_wall']:.1f} s wall, {res['process_cpu']:.1f} s CPU; main thread "
        f"{res['main_cpu']:.1f} s CPU (dry run {marks.get('dry_start', 0):.1f} -> "
        f"{marks.get('dry_end', 0):.1f} s of its CPU, the pool done at "
        f"{marks.get('wait_end_wall', 0):.1f} s wall).",
        "",
        "| program | queued at main-thread CPU s | worker's own CPU s | process CPU over its "
        "span s | wall s | worker |",
        "|---|---|---|---|---|---|",
    ]
    for t in tasks:
        lines.append(f"| `{t['program']}` | {t['main_cpu_at_submit']:.2f} | "
                     f"{t.get('worker_cpu', float('nan')):.2f} | "
                     f"{t.get('process_cpu', float('nan')):.2f} | {t.get('wall', float('nan')):.1f} "
                     f"| {t.get('thread', '?')} |")  # fmt: skip
    lines += ["", "OS threads by CPU s (name: CPU):", "",
              ", ".join(f"{n}: {c:.1f}" for n, c in res["threads"][:8])]  # fmt: skip
    (RESULTS / f"{a.name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
