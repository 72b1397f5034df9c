"""Scale-out benchmark (issue 19): frames/s of ``jaxcr segment`` for 1 and 2 workers, local
(one process; two ``--shard`` processes) and Ray (``--executor ray --workers 1|2``), Ray's
overhead per task, the driver's per-record cost, and a scaling model for N workers checked
against the 1-2 worker runs.

    PYTHONPATH=. python experiments/scale/bench_scale.py [--frames 24] [--chunk 4]

writes experiments/results/scale/bench_scale.{md,json}. Every run is a fresh ``jaxcr``
process sharing one persistent compilation cache (filled by a warm-up run whose compile time is
reported apart), so the timed runs load the compiled refinement instead of compiling it.
The dataset is the 160x120 constant-curvature set of the scale-out tests
(tests/helpers/scale_data.py), the refinement the tests' short schedule (FAST_FLAGS).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _run(cmd: list[str], env: dict) -> dict:
    load0 = _load()
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode not in (0, 1):
        raise SystemExit(f"failed ({r.returncode}): {' '.join(cmd)}\n{r.stderr[-2000:]}")
    return {"wall_s": wall, "load_before": load0, "load_after": _load()}


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _startup(env: dict) -> float:
    """Seconds for a jaxcr process to start and import what segment imports (the fixed cost
    of each timed process, subtracted to get the frames' time)."""
    code = "import jaxcr.cli, jax, jaxcr.segmentation.refine, jaxcr.segmentation.batch"
    ts = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], env=env, check=True)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def ray_task_overhead(n_calls: int = 100) -> dict:
    """Round trip of a no-op actor call carrying a chunk's ids out and 4 records (~2 KB each)
    back, sequential (the driver's view), on a private 2-CPU Ray instance; and the instance's
    start and an actor's start."""
    import ray

    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    t_init = time.perf_counter() - t0

    @ray.remote
    class Echo:
        def process(self, ids):
            return {"records": [{"frame": i, "coeffs": [[0.0] * 64] * 4} for i in ids]}

    t0 = time.perf_counter()
    a = Echo.remote()
    ray.get(a.process.remote(["0"]))
    t_actor = time.perf_counter() - t0
    ids = ["000", "001", "002", "003"]
    ts = []
    for _ in range(n_calls):
        t0 = time.perf_counter()
        ray.get(a.process.remote(ids))
        ts.append(time.perf_counter() - t0)
    ray.shutdown()
    return {"init_s": t_init, "actor_start_s": t_actor,
            "task_roundtrip_ms_median": 1e3 * statistics.median(ts),
            "task_roundtrip_ms_p90": 1e3 * sorted(ts)[int(0.9 * len(ts))]}  # fmt: skip


def append_cost(folder: Path, n: int = 200) -> float:
    """Median ms per ``results.jsonl`` append (write + fsync) of a segment record: the
    driver's serial bookkeeping per frame."""
    from jaxcr.io.results import ResultsLog

    rec = json.loads((folder / "results.jsonl").read_text().splitlines()[0])
    path = folder.parent / "append_bench.jsonl"
    ts = []
    with ResultsLog(path) as log:
        for _ in range(n):
            t0 = time.perf_counter()
            log.append(rec)
            ts.append(time.perf_counter() - t0)
    path.unlink()
    return 1e3 * statistics.median(ts)


def frame_bytes(out: Path, n_frames: int) -> dict:
    files = [p for p in out.rglob("*") if p.is_file() and p.parent != out]
    return {"bytes_per_frame": sum(p.stat().st_size for p in files) / n_frames,
            "files_per_frame": len(files) / n_frames}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--chunk", type=int, default=4)
    ap.add_argument("--work", default="/tmp/jaxcr-bench-scale")
    ap.add_argument("--out", default=str(ROOT / "experiments/results/scale"))
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite the .md from the committed .json (no runs)")  # fmt: skip
    args = ap.parse_args()
    if args.report_only:
        res = json.loads((Path(args.out) / "bench_scale.json").read_text())
        (Path(args.out) / "bench_scale.md").write_text(report(res))
        return
    from tests.helpers.scale_data import FAST_FLAGS, make_segment_dataset

    work = Path(args.work)
    ds = work / f"ds{args.frames}"
    if not (ds / "dataset.json").exists():
        shutil.rmtree(ds, ignore_errors=True)
        make_segment_dataset(ds, args.frames)
    cache = work / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXCR_COMPILE_CACHE": "1",
           "JAXCR_CACHE_DIR": str(cache), "JAXCR_PROGRESS": "off",
           "PYTHONPATH": str(ROOT)}  # fmt: skip
    base = [sys.executable, "-m", "jaxcr", "segment", str(ds), *FAST_FLAGS, "--batch-size",
            str(args.chunk), "--no-overlays", "--quiet", "--overwrite"]  # fmt: skip
    res: dict = {"frames": args.frames, "chunk": args.chunk, "size": "160x120",
                 "flags": FAST_FLAGS, "machine": platform.machine(), "cpus": os.cpu_count(),
                 "python": platform.python_version()}  # fmt: skip
    try:
        import jax
        import ray

        res["versions"] = {"jax": jax.__version__, "ray": ray.__version__}
    except ImportError:
        res["versions"] = {}
    res["commit"] = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"],
                                   capture_output=True, text=True).stdout.strip()  # fmt: skip

    runs = {}
    o = work / "warm"
    runs["warmup_cold_compile"] = {**_run([*base, "-o", str(o)], env),
                                   "compile_s": _summary(o)["compile_s"]}  # fmt: skip
    res["startup_s"] = _startup(env)
    o = work / "local1"
    runs["local_1"] = {**_run([*base, "-o", str(o)], env), "summary": _summary(o)}
    res["append_ms"] = append_cost(o)
    res["output"] = frame_bytes(o, args.frames)
    # two local workers: two --shard processes at once into one folder
    o = work / "local2"
    shutil.rmtree(o, ignore_errors=True)
    load0, t0 = _load(), time.perf_counter()
    procs = [subprocess.Popen([*base, "-o", str(o), "--shard", f"{i}/2"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
             for i in range(2)]  # fmt: skip
    for p in procs:
        p.wait()
    runs["local_2_shards"] = {"wall_s": time.perf_counter() - t0, "load_before": load0,
                              "load_after": _load()}  # fmt: skip
    for w in (1, 2):
        o = work / f"ray{w}"
        r = _run([*base, "-o", str(o), "--executor", "ray", "--workers", str(w),
                  "--chunk", str(args.chunk)], env)  # fmt: skip
        runs[f"ray_{w}"] = {**r, "summary": _summary(o)}
    res["runs"] = runs
    res["ray_overhead"] = ray_task_overhead()
    res["load_end"] = _load()
    model(res)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_scale.json").write_text(json.dumps(res, indent=2) + "\n")
    (out / "bench_scale.md").write_text(report(res))
    print(report(res))


def model(res: dict) -> None:
    """Fit the scaling model's parameters from the 1-worker runs and predict the 2-worker
    walls (see the report's text)."""
    F, S = res["frames"], res["startup_s"]
    r = res["runs"]
    t_f = (r["local_1"]["wall_s"] - S) / F  # per frame, one worker, cache warm, all included
    ray1 = r["ray_1"]["summary"]["executor"]["wall_s"]
    # Ray's fixed cost: the run's wall minus the actors' share of the frames
    ray_fixed = r["ray_1"]["wall_s"] - S - F * t_f
    tasks = -(-F // res["chunk"])
    m = {"t_frame_s": t_f, "ray_fixed_s": ray_fixed, "ray1_executor_wall_s": ray1,
         "tasks": tasks}  # fmt: skip
    for w in (2,):
        m[f"pred_local_{w}_s"] = S + F * t_f / w
        m[f"pred_ray_{w}_s"] = S + ray_fixed + F * t_f / w
    m["meas_local_2_s"] = r["local_2_shards"]["wall_s"]
    m["meas_ray_2_s"] = r["ray_2"]["wall_s"]
    # driver-bound N: the driver spends (append + task round trip / chunk) per frame serially
    d = 1e-3 * (res["append_ms"] + res["ray_overhead"]["task_roundtrip_ms_median"] / res["chunk"])
    m["driver_s_per_frame"] = d
    m["n_driver_bound_cpu"] = t_f / d
    res["model"] = m


def report(res: dict) -> str:
    r, m, ov = res["runs"], res["model"], res["ray_overhead"]
    F = res["frames"]

    def fps(key):
        return F / r[key]["wall_s"]

    def loads(key):
        return f"{r[key]['load_before'][0]:.1f} -> {r[key]['load_after'][0]:.1f}"

    rows = [
        ("local, 1 worker", "local_1"),
        ("local, 2 workers (2 x --shard)", "local_2_shards"),
        ("Ray, 1 worker", "ray_1"),
        ("Ray, 2 workers", "ray_2"),
    ]
    lines = [
        "# Scale-out benchmark (issue 19)",
        "",
        "Command: `PYTHONPATH=. python experiments/scale/bench_scale.py --frames "
        f"{F} --chunk {res['chunk']}` (commit `{res['commit'][:10]}`, {res['cpus']} CPUs, "
        f"versions {res['versions']}).",
        "",
        "**The machine was loaded by other engineers' jobs** (1-min load average given per run, "
        "2 cores): absolute times are those of a shared, overloaded machine, and 2 workers "
        "compete with everyone else for the same 2 cores. Read the ratios and the fixed costs, "
        "not the absolute frame rates.",
        "",
        f"Job: `jaxcr segment` of {F} frames, 160x120, one camera, constant-curvature robot, "
        f"short refinement schedule (`{' '.join(res['flags'])}`), batch/chunk {res['chunk']}, "
        "no overlays. Each run is a fresh process; all share one persistent compilation cache "
        f"filled by a warm-up run (cold compile: {r['warmup_cold_compile']['compile_s']:.1f} s, "
        f"not in the timed runs). Process start + imports: {res['startup_s']:.1f} s (median of "
        "3), included in the walls below.",
        "",
        "| run | wall (s) | frames/s (end to end) | load 1-min |",
        "|---|---|---|---|",
    ]
    for name, key in rows:
        lines.append(f"| {name} | {r[key]['wall_s']:.1f} | {fps(key):.3f} | {loads(key)} |")
    lines += [
        "",
        "Ray's costs (same machine, same load):",
        "",
        f"- start of a private Ray instance (`ray.init`): {ov['init_s']:.1f} s; start of an "
        f"actor (process + first call): {ov['actor_start_s']:.2f} s; actors then import jaxcr "
        "and load the compiled refinement from the cache on their first chunk;",
        f"- **overhead per task** (round trip of a no-op actor call carrying 4 ids out and 4 "
        f"records back): median {ov['task_roundtrip_ms_median']:.1f} ms, p90 "
        f"{ov['task_roundtrip_ms_p90']:.1f} ms;",
        f"- the driver's append of one record to results.jsonl (write + fsync, local disk): "
        f"{res['append_ms']:.2f} ms;",
        f"- the Ray runs' fixed cost (wall minus start-up minus the frames at the 1-worker "
        f"local rate): {m['ray_fixed_s']:.1f} s;",
        *[
            f"- Ray, {w} worker(s), inside the run: executor wall {e['wall_s']:.1f} s x {w} "
            f"actors, of which {e['task_wall_s']:.1f} s inside the chunks; the rest, "
            f"{(e['wall_s'] * w - e['task_wall_s']) / e['tasks']:.2f} s per task over "
            f"{e['tasks']} tasks, is actor start, first cache load, scheduling and idle time;"
            for w, e in ((w, r[f"ray_{w}"]["summary"]["executor"]) for w in (1, 2))
        ],
        f"- output per frame: {res['output']['bytes_per_frame'] / 1e3:.1f} kB in "
        f"{res['output']['files_per_frame']:.1f} files (no overlays).",
        "",
        "## Scaling model",
        "",
        "For F frames on N workers with chunks of c frames:",
        "",
        "    T(N) = S + C_w + R + F * t_f / N           (workers busy)",
        "    T(N) >= S + R + F * (a + o / c)            (driver: serial per frame)",
        "",
        "- S: process start and imports; C_w: compile per worker (paid once per worker, in "
        "parallel, or a cache load when the persistent cache is warm and shared); R: Ray's "
        "fixed cost (instance/actors start; 0 locally);",
        "- t_f: per-frame time of one worker (refinement + reading the images + writing the "
        "frame's files), measured by the 1-worker local run;",
        "- a: the driver's append + fsync per record; o: Ray's round trip per task, of which "
        "the driver's share is serial; c: frames per task (`--chunk`).",
        "",
        f"Fitted from the 1-worker runs: t_f = {m['t_frame_s']:.3f} s per frame, R = "
        f"{m['ray_fixed_s']:.1f} s. Checked against the 2-worker runs:",
        "",
        "| run | predicted (s) | measured (s) |",
        "|---|---|---|",
        f"| local, 2 workers | {m['pred_local_2_s']:.1f} | {m['meas_local_2_s']:.1f} |",
        f"| Ray, 2 workers | {m['pred_ray_2_s']:.1f} | {m['meas_ray_2_s']:.1f} |",
        "",
        "The model assumes each worker has its own core/GPU. Here the 2 workers share 2 cores "
        "with the other engineers' jobs (load above), so the measured 2-worker walls are "
        "expected above the prediction by the factor the load takes away. The Ray runs show "
        "it directly: the time the actors spent inside their chunks, for the same frames, was "
        f"{r['ray_2']['summary']['executor']['task_wall_s']:.0f} s with 2 workers against "
        f"{r['ray_1']['summary']['executor']['task_wall_s']:.0f} s with 1 (x"
        f"{r['ray_2']['summary']['executor']['task_wall_s'] / r['ray_1']['summary']['executor']['task_wall_s']:.1f}"
        "; 1.0 if each worker had its own core): the second worker did not get a core of its "
        "own, so on this machine the check confirms the fixed costs (start-up, Ray's R) but "
        "cannot confirm the 1/N term; a node with free cores or GPUs is needed for that. The "
        "model's terms (fixed costs, per-frame cost, driver cost per frame) are what carries "
        "over to a GPU node.",
        "",
        "### Where the driver or the shared filesystem becomes the bottleneck",
        "",
        f"Upper bound on the driver's serial work: a + o/c = "
        f"{1e3 * m['driver_s_per_frame']:.2f} ms per frame (measured a and o, c = "
        f"{res['chunk']}), counting Ray's whole round trip o as driver time. Most of o is "
        "latency (scheduling, transfer, the loaded machine), which the 2 chunks in flight per "
        "actor hide, so this bound is pessimistic; the append a is truly serial. Workers "
        "deliver N / t_f frames/s, so the driver saturates at N* = t_f / (a + o/c): with this "
        f"CPU's t_f ({m['t_frame_s']:.2f} s) N* = {m['n_driver_bound_cpu']:.0f} workers. On "
        "GPUs t_f is far smaller: at ~0.1 s per frame (the package's CPU time per 640x480 "
        "frame, README) or an assumed 20 ms per frame on a GPU, the bound gives N* = "
        f"{0.1 / m['driver_s_per_frame']:.0f} and {0.02 / m['driver_s_per_frame']:.1f} "
        "workers at c = 4: small chunks are the first bottleneck. With `--chunk 64` the "
        "round-trip share falls 16-fold: N* = "
        f"{0.02 / (1e-3 * (res['append_ms'] + res['ray_overhead']['task_roundtrip_ms_median'] / 64)):.0f}"
        " GPU workers at 20 ms per frame, and the append (fsync) alone would allow t_f / a = "
        f"{0.02 / (1e-3 * res['append_ms']):.0f}. Rule: choose c so that o / c is a small "
        "fraction of t_f / N.",
        "",
        f"The shared filesystem: each frame writes {res['output']['files_per_frame']:.1f} "
        f"files ({res['output']['bytes_per_frame'] / 1e3:.1f} kB here; ~4x more with "
        "overlays, and 16x the pixels at 640x480), each a create + write + fsync + rename. An NFS "
        "server doing ~2000 such metadata operations/s (a typical order of magnitude; measure "
        "yours) serves 2000 / files-per-frame frames/s, so at 20 ms per GPU frame it saturates "
        f"near N = 2000 * 0.02 / {res['output']['files_per_frame']:.1f} = "
        f"{2000 * 0.02 / res['output']['files_per_frame']:.0f} GPU workers, before the "
        "driver at `--chunk 64`; bandwidth (MB/s) is not the limit at these file sizes. Past that, shard the "
        "output folders (one OUT per node with `--shard`) or drop products "
        "(`--no-overlays`).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
