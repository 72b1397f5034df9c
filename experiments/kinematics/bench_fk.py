"""Forward-kinematics throughput of the concentric-tube model (TEST_CTR), against the scipy
reference model of tests/helpers/ctr_reference.py.

    python experiments/kinematics/bench_fk.py [--batch 1024] [--cold-batch 256] [--repeats 5]

Measures, for jit(vmap(forward)) over a batch of seeded random joint vectors:
* cold start (guess=None: residual scan + Optimistix Levenberg-Marquardt from 6 starts, least
  energy, Newton polish);
* warm start (guess = the solution state of a nearby q, i.e. tracking a trajectory; fixed
  Newton iterations);
compile time separately, then the median and spread over repeats (block_until_ready).
The scipy reference (solve_ivp DOP853 + root, one start from the JAX state's twist) is timed
per configuration on a few q and reported with the ratio. Also the max tip difference to the
reference on those q. Prints a Markdown table and writes experiments/results/kinematics/bench_fk.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix
import scipy

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "tests", "helpers"))
from ctr_reference import TEST_ROBOT, Tubes, random_q, solve_all  # noqa: E402

from jaxcr.kinematics.ctr import make_test_ctr  # noqa: E402


def _timeit(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return np.array(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1024, help="warm-start batch size")
    ap.add_argument("--cold-batch", type=int, default=256, help="cold-start batch size")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--n-reference", type=int, default=3, help="q timed with scipy")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "-o", "--out", default=os.path.join(HERE, "..", "results", "kinematics", "bench_fk.md")
    )
    args = ap.parse_args(argv)

    model = make_test_ctr()
    tubes = Tubes(TEST_ROBOT)
    rng = np.random.default_rng(args.seed)
    qs_np = np.stack([random_q(rng, tubes) for _ in range(args.batch)])
    qs = jnp.asarray(qs_np, jnp.float32)
    cold_qs = qs[: args.cold_batch]

    cold = eqx.filter_jit(lambda m, q: jax.vmap(m.forward)(q))
    warm = eqx.filter_jit(lambda m, q, g: jax.vmap(m.forward)(q, g))

    t0 = time.perf_counter()
    jax.block_until_ready(cold(model, cold_qs))
    first_cold = time.perf_counter() - t0
    t_cold = _timeit(lambda: cold(model, cold_qs), max(1, args.repeats // 2))
    compile_cold = first_cold - float(np.median(t_cold))  # first call = compile + one run
    solved = cold(model, cold_qs)
    ok_cold = float(jnp.mean(solved.ok))

    # warm: states for the whole batch (cold, in chunks of the cold batch), then a nearby q
    states = []
    for k in range(0, args.batch, args.cold_batch):
        chunk = qs[k : k + args.cold_batch]
        if chunk.shape[0] != args.cold_batch:
            chunk = jnp.concatenate([chunk, qs[: args.cold_batch - chunk.shape[0]]])
        states.append(cold(model, chunk).state)
    states = jnp.concatenate(states)[: args.batch]
    dq = jnp.asarray(rng.normal(0.0, 1.0, qs.shape) * np.r_[[0.0] * 3, [0.01] * 3], jnp.float32)
    q_next = qs + dq  # rotate every tube by ~0.6 deg: a video-rate step
    t0 = time.perf_counter()
    jax.block_until_ready(warm(model, q_next, states))
    first_warm = time.perf_counter() - t0
    t_warm = _timeit(lambda: warm(model, q_next, states), args.repeats)
    compile_warm = first_warm - float(np.median(t_warm))
    w = warm(model, q_next, states)
    ok_warm = float(jnp.mean(w.ok))
    steps_warm = float(jnp.mean(w.num_steps))

    # scipy reference per configuration (one shooting start at the JAX solution's twist)
    ref_times, tip_err = [], []
    r = solved
    for k in range(args.n_reference):
        q = qs[k]
        _, uz = model.twist_profile(q, r.state[k])
        m0 = np.asarray(uz[0], float) * tubes.GJ
        t0 = time.perf_counter()
        found = solve_all(tubes, np.asarray(q, float), [m0], rtol=1e-8, atol=1e-10)
        ref_times.append(time.perf_counter() - t0)
        tip_err.append(np.linalg.norm(found[0]["tip"] - np.asarray(r.centreline.p[k, -1])) * 1e3)
    ref_per_q = float(np.median(ref_times))

    per_cold = np.median(t_cold) / args.cold_batch
    per_warm = np.median(t_warm) / args.batch
    try:
        commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=HERE).decode()
    except Exception:  # noqa: BLE001
        commit = "unknown"
    load = os.getloadavg()
    lines = [
        "# CTR forward-kinematics throughput (TEST_CTR, float32, CPU)",
        "",
        f"- command: `python experiments/kinematics/bench_fk.py --batch {args.batch} "
        f"--cold-batch {args.cold_batch} --repeats {args.repeats}`",
        f"- commit {commit.strip()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        f"- machine: {platform.platform()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, load average {load[0]:.1f} (shared machine: "
        "timings are inflated by other jobs)",
        f"- versions: jax {jax.__version__}, equinox {eqx.__version__}, optimistix "
        f"{optimistix.__version__}, numpy {np.__version__}, scipy {scipy.__version__}",
        f"- model: n_points {model.n_points}, scan {model.scan_points}^2 tip angles, "
        f"{model.n_starts} optimistix LM starts x <= {model.cold_steps} iterations + "
        f"{model.warm_steps} Newton iterations (cold), {model.warm_steps} fixed Newton "
        "iterations (warm); steps shared among pieces in proportion to their lengths",
        "",
        "| path | batch | compile (s) | median batch time (s) | spread (min-max) | per q (ms) "
        "| vs scipy per q | ok |",
        "|---|---|---|---|---|---|---|---|",
        f"| cold (guess=None) | {args.cold_batch} | {compile_cold:.1f} | {np.median(t_cold):.3f} "
        f"| {t_cold.min():.3f}-{t_cold.max():.3f} | {per_cold * 1e3:.2f} "
        f"| {ref_per_q / per_cold:.0f}x faster | {ok_cold:.3f} |",
        f"| warm (guess=state, dalpha~0.01 rad) | {args.batch} | {compile_warm:.1f} "
        f"| {np.median(t_warm):.3f} | {t_warm.min():.3f}-{t_warm.max():.3f} "
        f"| {per_warm * 1e3:.3f} | {ref_per_q / per_warm:.0f}x faster | {ok_warm:.3f} |",
        "",
        f"- scipy reference (solve_ivp DOP853 rtol 1e-8, root hybr, one start at the solution's "
        f"twist, i.e. no branch search): median {ref_per_q * 1e3:.0f} ms per configuration over "
        f"{args.n_reference} q ({', '.join(f'{t * 1e3:.0f}' for t in ref_times)} ms)",
        f"- max tip difference JAX (float32, N={model.n_points}) vs scipy on those q: "
        f"{max(tip_err):.2e} mm",
        f"- warm start: mean {steps_warm:.1f} Newton iterations until converged "
        f"(cost is {model.warm_steps} fixed iterations)",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)  # "-o x.md": dirname is ""
    with open(args.out, "w") as fh:
        fh.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
