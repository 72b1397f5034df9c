"""Forward-kinematics throughput of the concentric-tube model (TEST_CTR), against the scipy
reference model :mod:`jaxcr.benchmarks.ctr_reference`.

Measures, for jit(vmap(forward)) over a batch of seeded random joint vectors:

* cold start (guess=None: residual scan and fixed difference-Newton iterations from 6 starts
  on a coarse grid, least energy, chord polish on the full grid);
* warm start (guess = the solution state of a nearby q, i.e. tracking a trajectory; chord
  iterations on the coarse grid that stop at convergence, one chord step on the full grid);

compile time separately, then the median and spread over repeats (block_until_ready).
The previous implementation (:mod:`jaxcr.benchmarks.ctr_previous`: optimistix LM cold path,
5 fixed jacfwd-Newton iterations warm) is timed in the same run, interleaved, with the tip
distance between the two, with ``previous=True`` (``jaxcr bench fk --previous``; its cold
path compiles for minutes).
The load average is recorded before and after (the machine may be shared).
The scipy reference (solve_ivp DOP853 + root, one start from the JAX state's twist) is timed
per configuration on a few q and reported with the ratio, with the max tip difference to the
reference on those q.

Run it with ``jaxcr bench fk`` (installed package) or
``python experiments/kinematics/bench_fk.py`` (writes experiments/results/kinematics/bench_fk.md).
"""

from __future__ import annotations

import os
import platform
import subprocess
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix
import scipy

from jaxcr.benchmarks.ctr_previous import make_previous
from jaxcr.benchmarks.ctr_reference import TEST_ROBOT, Tubes, random_q, solve_all
from jaxcr.kinematics.ctr import make_test_ctr


def _timeit(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return np.array(times)


def _timed_first(fn):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


def _previous_rows(cold, warm, cold_qs, q_next, states, repeats, cur_cold, cur_warm):
    """Time the pre-issue-18 solvers on the same inputs (rows + agreement with the current)."""
    prev = make_previous()
    out_c, first_c = _timed_first(lambda: cold(prev, cold_qs))
    t_c = _timeit(lambda: cold(prev, cold_qs), max(1, repeats // 2))
    out_w, first_w = _timed_first(lambda: warm(prev, q_next, states))
    t_w = _timeit(lambda: warm(prev, q_next, states), repeats)

    def tipd(a, b):
        d = np.asarray(a.centreline.p[:, -1]) - np.asarray(b.centreline.p[:, -1])
        return float(np.max(np.linalg.norm(d, axis=-1)) * 1e3)

    rows = [
        {
            "path": "previous cold (optimistix LM, 97-sample scan)",
            "batch": int(cold_qs.shape[0]),
            "compile_s": first_c - float(np.median(t_c)),
            "median_batch_s": float(np.median(t_c)),
            "per_q_ms": float(np.median(t_c)) / cold_qs.shape[0] * 1e3,
            "ok": float(jnp.mean(out_c.ok)),
        },
        {
            "path": "previous warm (5 fixed jacfwd-Newton)",
            "batch": int(q_next.shape[0]),
            "compile_s": first_w - float(np.median(t_w)),
            "median_batch_s": float(np.median(t_w)),
            "per_q_ms": float(np.median(t_w)) / q_next.shape[0] * 1e3,
            "ok": float(jnp.mean(out_w.ok)),
        },
    ]
    agree = {
        "max_tip_mm_cold_vs_previous": tipd(out_c, cur_cold),
        "max_tip_mm_warm_vs_previous": tipd(out_w, cur_warm),
        "max_rel_energy_cold_vs_previous": float(
            np.max(
                np.abs(np.asarray(out_c.energy) - np.asarray(cur_cold.energy))
                / np.abs(np.asarray(out_c.energy))
            )
        ),  # fmt: skip
    }
    return rows, agree, t_c.tolist(), t_w.tolist()


def run_fk_benchmark(
    batch: int = 1024,
    cold_batch: int = 256,
    repeats: int = 5,
    n_reference: int = 3,
    seed: int = 0,
    previous: bool = False,
) -> dict:
    """Run the benchmark (see the module docstring).

    Parameters
    ----------
    batch : int
        Warm-start batch size (joint vectors).
    cold_batch : int
        Cold-start batch size, at most ``batch`` (clipped).
    repeats : int
        Timed repetitions of the warm batch (the cold batch: ``max(1, repeats // 2)``).
    n_reference : int
        Configurations solved with the scipy reference (0: none).
    seed : int
        Seed of the random joint vectors.
    previous : bool
        Also time the pre-issue-18 solvers (:mod:`jaxcr.benchmarks.ctr_previous`) on the
        same q (their cold path compiles for minutes).

    Returns
    -------
    dict
        ``name``, ``unit`` ("q"), ``median_s`` / ``compile_s`` (warm start, per q / whole batch),
        ``reference`` and ``reference_median_s`` (per q), ``rows`` (cold and warm), and the raw
        numbers (``t_cold``, ``t_warm`` in s per batch, ``ref_times``, ``tip_err_mm``, ...).
    """
    cold_batch = min(cold_batch, batch)
    load_before = os.getloadavg()
    model = make_test_ctr()
    tubes = Tubes(TEST_ROBOT)
    rng = np.random.default_rng(seed)
    qs_np = np.stack([random_q(rng, tubes) for _ in range(batch)])
    qs = jnp.asarray(qs_np, jnp.float32)
    cold_qs = qs[:cold_batch]

    cold = eqx.filter_jit(lambda m, q: jax.vmap(m.forward)(q))
    warm = eqx.filter_jit(lambda m, q, g: jax.vmap(m.forward)(q, g))

    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(cold(model, cold_qs))
    first_cold, first_cold_cpu = time.perf_counter() - t0, time.process_time() - c0
    c0 = time.process_time()
    t_cold = _timeit(lambda: cold(model, cold_qs), max(1, repeats // 2))
    run_cold_cpu = (time.process_time() - c0) / len(t_cold)
    compile_cold = first_cold - float(np.median(t_cold))  # first call = compile + one run
    # CPU seconds of the compile (first call's CPU time minus one run's): on a shared machine
    # the wall-clock compile time grows with the load, this much less
    compile_cold_cpu = first_cold_cpu - run_cold_cpu
    solved = cold(model, cold_qs)
    ok_cold = float(jnp.mean(solved.ok))

    # warm: states for the whole batch (cold, in chunks of the cold batch), then a nearby q
    states = []
    for k in range(0, batch, cold_batch):
        chunk = qs[k : k + cold_batch]
        if chunk.shape[0] != cold_batch:
            chunk = jnp.concatenate([chunk, qs[: cold_batch - chunk.shape[0]]])
        states.append(cold(model, chunk).state)
    states = jnp.concatenate(states)[:batch]
    dq = jnp.asarray(rng.normal(0.0, 1.0, qs.shape) * np.r_[[0.0] * 3, [0.01] * 3], jnp.float32)
    q_next = qs + dq  # rotate every tube by ~0.6 deg: a video-rate step
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(warm(model, q_next, states))
    first_warm, first_warm_cpu = time.perf_counter() - t0, time.process_time() - c0
    c0 = time.process_time()
    t_warm = _timeit(lambda: warm(model, q_next, states), repeats)
    compile_warm_cpu = first_warm_cpu - (time.process_time() - c0) / len(t_warm)
    compile_warm = first_warm - float(np.median(t_warm))
    w = warm(model, q_next, states)
    ok_warm = float(jnp.mean(w.ok))
    steps_warm = float(jnp.mean(w.num_steps))

    # scipy reference per configuration (one shooting start at the JAX solution's twist)
    ref_times, tip_err = [], []
    r = solved
    for k in range(min(n_reference, cold_batch)):
        q = qs[k]
        _, uz = model.twist_profile(q, r.state[k])
        m0 = np.asarray(uz[0], float) * tubes.GJ
        t0 = time.perf_counter()
        found = solve_all(tubes, np.asarray(q, float), [m0], rtol=1e-8, atol=1e-10)
        ref_times.append(time.perf_counter() - t0)
        tip_err.append(np.linalg.norm(found[0]["tip"] - np.asarray(r.centreline.p[k, -1])) * 1e3)
    ref_per_q = float(np.median(ref_times)) if ref_times else None

    per_cold = float(np.median(t_cold)) / cold_batch
    per_warm = float(np.median(t_warm)) / batch
    prev_rows, agree, prev_t_cold, prev_t_warm = [], {}, [], []
    if previous:
        prev_rows, agree, prev_t_cold, prev_t_warm = _previous_rows(
            cold, warm, cold_qs, q_next, states, repeats, solved[:cold_batch], w
        )
    load_after = os.getloadavg()
    return {
        "name": "CTR forward kinematics (TEST_CTR, float32, CPU), warm start",
        "unit": "q",
        "median_s": per_warm,
        "compile_s": compile_warm,
        "reference": "scipy solve_ivp DOP853 + root, one start" if ref_times else None,
        "reference_median_s": ref_per_q,
        "batch": batch,
        "cold_batch": cold_batch,
        "repeats": repeats,
        "ok_cold": ok_cold,
        "ok_warm": ok_warm,
        "warm_newton_steps_mean": steps_warm,
        "max_tip_difference_mm": max(tip_err) if tip_err else None,
        "load_avg_before": list(load_before),
        "load_avg_after": list(load_after),
        **agree,
        "notes": "Shared 2-core machine: absolute times are inflated by the load average "
        "recorded here; the previous/current ratios come from the same process.",
        "rows": [
            {
                "path": "cold (guess=None)",
                "batch": cold_batch,
                "compile_s": compile_cold,
                "compile_cpu_s": compile_cold_cpu,
                "median_batch_s": float(np.median(t_cold)),
                "per_q_ms": per_cold * 1e3,
                "ok": ok_cold,
            },
            {
                "path": "warm (guess=state)",
                "batch": batch,
                "compile_s": compile_warm,
                "compile_cpu_s": compile_warm_cpu,
                "median_batch_s": float(np.median(t_warm)),
                "per_q_ms": per_warm * 1e3,
                "ok": ok_warm,
            },
            *prev_rows,
        ],
        "prev_t_cold": prev_t_cold,
        "prev_t_warm": prev_t_warm,
        "t_cold": t_cold.tolist(),
        "t_warm": t_warm.tolist(),
        "compile_cold_s": compile_cold,
        "compile_cold_cpu_s": compile_cold_cpu,
        "compile_warm_cpu_s": compile_warm_cpu,
        "ref_times": ref_times,
        "tip_err_mm": tip_err,
        "model": {
            "n_points": model.n_points,
            "scan_points": model.scan_points,
            "n_starts": model.n_starts,
            "scan_n_points": model.scan_n_points,
            "cold_steps": model.cold_steps,
            "warm_steps": model.warm_steps,
        },
    }


def markdown(res: dict, command: str) -> str:
    """The report of experiments/kinematics/bench_fk.py for a :func:`run_fk_benchmark` result."""
    m = res["model"]
    t_cold, t_warm = np.asarray(res["t_cold"]), np.asarray(res["t_warm"])
    per_cold = float(np.median(t_cold)) / res["cold_batch"]
    per_warm = float(np.median(t_warm)) / res["batch"]
    ref_per_q, ref_times = res["reference_median_s"], res["ref_times"]
    try:
        commit = subprocess.check_output(
            ["git", "rev-parse", "--short", "HEAD"], cwd=os.path.dirname(os.path.abspath(__file__))
        ).decode()
    except Exception:  # noqa: BLE001
        commit = "unknown"
    load = res.get("load_avg_before") or os.getloadavg()
    load_after = res.get("load_avg_after") or load

    def vs(per):
        return f"{ref_per_q / per:.0f}x faster" if ref_per_q else "n/a"

    lines = [
        "# CTR forward-kinematics throughput (TEST_CTR, float32, CPU)",
        "",
        f"- command: `{command}`",
        f"- commit {commit.strip()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- machine: {platform.platform()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, load average {load[0]:.1f} before, "
        f"{load_after[0]:.1f} after (shared machine: timings are inflated by other jobs; "
        "compare ratios within the run)",
        f"- versions: jax {jax.__version__}, equinox {eqx.__version__}, optimistix "
        f"{optimistix.__version__}, numpy {np.__version__}, scipy {scipy.__version__}",
        f"- model: n_points {m['n_points']}, scan {m['scan_points']}^2 tip angles on a "
        f"{m['scan_n_points']}-sample grid, {m['n_starts']} starts x {m['cold_steps']} "
        "difference-Newton iterations on that grid + chord polish (cold); chord iterations "
        f"on that grid that stop at convergence, at most {m['warm_steps']}, then one chord "
        "step on the full grid (warm); steps shared among pieces in proportion to their "
        "lengths; angles integrated as (cos, sin) pairs",
        "",
        "| path | batch | compile (s) | compile CPU (s) | median batch time (s) | spread (min-max) "
        "| per q (ms) | vs scipy per q | ok |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| cold (guess=None) | {res['cold_batch']} | {res['compile_cold_s']:.1f} "
        f"| {res['compile_cold_cpu_s']:.1f} "
        f"| {np.median(t_cold):.3f} | {t_cold.min():.3f}-{t_cold.max():.3f} "
        f"| {per_cold * 1e3:.2f} | {vs(per_cold)} | {res['ok_cold']:.3f} |",
        f"| warm (guess=state, dalpha~0.01 rad) | {res['batch']} | {res['compile_s']:.1f} "
        f"| {res['compile_warm_cpu_s']:.1f} "
        f"| {np.median(t_warm):.3f} | {t_warm.min():.3f}-{t_warm.max():.3f} "
        f"| {per_warm * 1e3:.3f} | {vs(per_warm)} | {res['ok_warm']:.3f} |",
        "",
    ]
    if ref_times:
        lines += [
            f"- scipy reference (solve_ivp DOP853 rtol 1e-8, root hybr, one start at the "
            f"solution's twist, i.e. no branch search): median {ref_per_q * 1e3:.0f} ms per "
            f"configuration over {len(ref_times)} q "
            f"({', '.join(f'{t * 1e3:.0f}' for t in ref_times)} ms)",
            f"- max tip difference JAX (float32, N={m['n_points']}) vs scipy on those q: "
            f"{res['max_tip_difference_mm']:.2e} mm",
        ]
    prev = res["rows"][2:]
    if prev:
        cur = {"cold": res["rows"][0], "warm": res["rows"][1]}
        lines += ["", "Previous solvers (same q, same process, interleaved):", "",
                  "| path | batch | compile (s) | median batch (s) | per q (ms) | ok "
                  "| current is faster by | compiles faster by |",
                  "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for row, key in zip(prev, ("cold", "warm"), strict=True):
            c = cur[key]
            lines.append(
                f"| {row['path']} | {row['batch']} | {row['compile_s']:.1f} "
                f"| {row['median_batch_s']:.3f} | {row['per_q_ms']:.3f} | {row['ok']:.3f} "
                f"| {row['per_q_ms'] / c['per_q_ms']:.1f}x "
                f"| {row['compile_s'] / max(c['compile_s'], 1e-3):.1f}x |"
            )
        lines += [
            "",
            f"- max tip distance current vs previous: cold "
            f"{res['max_tip_mm_cold_vs_previous']:.2e} mm, warm "
            f"{res['max_tip_mm_warm_vs_previous']:.2e} mm; max relative energy difference "
            f"(cold) {res['max_rel_energy_cold_vs_previous']:.2e}",
        ]
    lines += [
        f"- warm start: mean {res['warm_newton_steps_mean']:.1f} chord iterations until "
        f"converged (at most {m['warm_steps']}; the loop stops when every member of the "
        "batch has converged)",
        "",
    ]
    return "\n".join(lines)
