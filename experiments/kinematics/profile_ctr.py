"""Per-stage profile of the concentric-tube forward kinematics (TEST_CTR, float32, CPU): the
current solvers against the pre-issue-18 ones (:mod:`jaxcr.benchmarks.ctr_previous`), in the
same process, interleaved repeats.

Stages, each jitted and vmapped over the batch on its own (compile = first call - median run):
scan (``initial_guesses``), multi-start solve (``_cold_solve``), polish (``_warm_solve`` from
the chosen start), result (centreline), then the whole ``forward`` cold and warm
(guess = the cold solution's state, q moved by ~0.01 rad per tube: a video-rate step).
Agreement: the new cold solutions against the previous ones (tip distance, energy, ok).

    python experiments/kinematics/profile_ctr.py [--cold-batch 64] [--batch 1024] [--repeats 5]

writes experiments/results/kinematics/profile_ctr.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.benchmarks.ctr_previous import make_previous
from jaxcr.benchmarks.ctr_reference import TEST_ROBOT, Tubes, random_q
from jaxcr.kinematics.ctr import make_test_ctr

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "results", "kinematics", "profile_ctr.md")


def _stage_fns():
    scan = eqx.filter_jit(lambda m, q: jax.vmap(m.initial_guesses)(q))
    multi = eqx.filter_jit(lambda m, q, g: jax.vmap(m._cold_solve)(q, g))
    polish = eqx.filter_jit(lambda m, q, g: jax.vmap(m._warm_solve)(q, g))
    result = eqx.filter_jit(
        lambda m, q, x: jax.vmap(lambda qq, xx: m._result(qq, xx, 0, True))(q, x)
    )
    cold = eqx.filter_jit(lambda m, q: jax.vmap(m.forward)(q))
    warm = eqx.filter_jit(lambda m, q, g: jax.vmap(m.forward)(q, g))
    return scan, multi, polish, result, cold, warm


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cold-batch", type=int, default=64)
    ap.add_argument("--batch", type=int, default=1024, help="warm batch")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--skip-previous-cold",
        action="store_true",
        help="do not compile the previous whole cold forward (minutes)",
    )
    ap.add_argument("-o", "--out", default=OUT)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    tubes = Tubes(TEST_ROBOT)
    qs_np = np.stack([random_q(rng, tubes) for _ in range(args.batch)])
    qs = jnp.asarray(qs_np, jnp.float32)
    cq = qs[: args.cold_batch]
    dq = rng.normal(0.0, 1.0, qs.shape) * np.r_[[0.0] * 3, [0.01] * 3]
    q_next = jnp.asarray(qs_np + dq, jnp.float32)
    models = {"previous": make_previous(), "current": make_test_ctr()}
    scan, multi, polish, result, cold, warm = _stage_fns()
    loads = [os.getloadavg()[0]]

    calls = {}  # (impl, stage) -> (thunk, batch)
    compile_s = {}
    outs = {}

    def first(key, thunk, batch):
        t0 = time.perf_counter()
        out = jax.block_until_ready(thunk())
        t1 = time.perf_counter()
        s = time.perf_counter()
        jax.block_until_ready(thunk())
        compile_s[key] = (t1 - t0) - (time.perf_counter() - s)
        calls[key] = (thunk, batch)
        outs[key] = out
        print(f"{key}: first call {t1 - t0:.1f} s", flush=True)
        return out

    for name, m in models.items():
        g = first((name, "scan"), lambda m=m: scan(m, cq), args.cold_batch)
        x, res, en, _ = first((name, "multi-start"), lambda m=m, g=g: multi(m, cq, g),
                              args.cold_batch)  # fmt: skip
        best = jax.vmap(m._pick_branch)(res, en)
        xb = x[jnp.arange(args.cold_batch), best]
        xp = first((name, "polish"), lambda m=m, xb=xb: polish(m, cq, xb), args.cold_batch)[0]
        first((name, "result"), lambda m=m, xp=xp: result(m, cq, xp), args.cold_batch)
        if name == "previous" and args.skip_previous_cold:
            continue
        first((name, "cold forward"), lambda m=m: cold(m, cq), args.cold_batch)
        loads.append(os.getloadavg()[0])
    # warm: states of the whole batch from the current cold path (same branch for both)
    states = []
    for k in range(0, args.batch, args.cold_batch):
        chunk = qs[k : k + args.cold_batch]
        if chunk.shape[0] == args.cold_batch:
            states.append(cold(models["current"], chunk).state)
    states = jnp.concatenate(states)
    nb = states.shape[0]
    for name, m in models.items():
        first((name, "warm forward"), lambda m=m: warm(m, q_next[:nb], states), nb)
    loads.append(os.getloadavg()[0])

    times = {k: [] for k in calls}
    for _ in range(args.repeats):
        for k, (thunk, _) in calls.items():
            s = time.perf_counter()
            jax.block_until_ready(thunk())
            times[k].append(time.perf_counter() - s)
        loads.append(os.getloadavg()[0])

    rows = []
    for (name, stage), ts in times.items():
        b = calls[(name, stage)][1]
        med = float(np.median(ts))
        rows.append({"impl": name, "stage": stage, "batch": b,
                     "compile_s": compile_s[(name, stage)], "median_batch_s": med,
                     "min_batch_s": float(np.min(ts)), "max_batch_s": float(np.max(ts)),
                     "per_q_ms": med / b * 1e3})  # fmt: skip

    agree = {}
    if ("previous", "cold forward") in outs:
        a, b = outs[("previous", "cold forward")], outs[("current", "cold forward")]
        tip = np.linalg.norm(np.asarray(a.centreline.p[:, -1]) - np.asarray(b.centreline.p[:, -1]),
                             axis=-1) * 1e3  # fmt: skip
        de = np.abs(np.asarray(a.energy) - np.asarray(b.energy)) / np.abs(np.asarray(a.energy))
        agree = {"max_tip_mm": float(tip.max()), "median_tip_mm": float(np.median(tip)),
                 "n_tip_over_0.01mm": int(np.sum(tip > 0.01)),
                 "max_rel_energy": float(de.max()),
                 "ok_previous": float(np.mean(a.ok)), "ok_current": float(np.mean(b.ok))}  # fmt: skip
    wa, wb = outs[("previous", "warm forward")], outs[("current", "warm forward")]
    wtip = np.linalg.norm(np.asarray(wa.centreline.p[:, -1]) - np.asarray(wb.centreline.p[:, -1]),
                          axis=-1) * 1e3  # fmt: skip
    agree.update({"warm_max_tip_mm": float(wtip.max()),
                  "warm_ok_previous": float(np.mean(wa.ok)),
                  "warm_ok_current": float(np.mean(wb.ok)),
                  "warm_steps_mean_current": float(np.mean(wb.num_steps)),
                  "warm_steps_max_current": int(np.max(wb.num_steps)),
                  "warm_steps_mean_previous": float(np.mean(wa.num_steps))})  # fmt: skip
    try:
        commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=HERE).decode()
    except Exception:  # noqa: BLE001
        commit = "unknown"
    meta = {"commit": commit.strip(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": platform.platform(), "cpus": os.cpu_count(),
            "load_avg_1min": loads, "jax": jax.__version__,
            "command": "python experiments/kinematics/profile_ctr.py " + " ".join(argv or sys.argv[1:])}  # fmt: skip
    lines = [
        "# CTR forward kinematics: per-stage profile, previous vs current solvers",
        "",
        f"- command: `{meta['command']}`",
        f"- commit {meta['commit']}, {meta['date']}, {meta['machine']}, {meta['cpus']} CPUs, "
        f"jax {meta['jax']}",
        f"- load average (1 min) during the run: {min(loads):.1f}-{max(loads):.1f} on 2 cores "
        "(the machine is shared with 7 other engineers: absolute times are inflated several "
        "times; compare the two implementations, which ran interleaved in one process)",
        "- previous: residual scan on the 97-sample grid, optimistix LM (<= 20 iterations, "
        "jacfwd) from 6 starts, 5 fixed jacfwd-Newton iterations (polish and warm path)",
        "- current: scan and 8 fixed difference-Newton iterations per start on a 25-sample "
        "grid, chord polish / warm iterations on the 97-sample grid that stop at convergence",
        "",
        "| impl | stage | batch | compile (s) | median batch (s) | min-max (s) | per q (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['impl']} | {r['stage']} | {r['batch']} | {r['compile_s']:.1f} "
                     f"| {r['median_batch_s']:.4f} | {r['min_batch_s']:.4f}-{r['max_batch_s']:.4f} "
                     f"| {r['per_q_ms']:.3f} |")  # fmt: skip
    by = {(r["impl"], r["stage"]): r for r in rows}
    lines += ["", "| stage | previous / current (per q time) | previous / current (compile) |",
              "|---|---|---|"]  # fmt: skip
    for stage in ("scan", "multi-start", "polish", "result", "cold forward", "warm forward"):
        if ("previous", stage) in by and ("current", stage) in by:
            p, c = by[("previous", stage)], by[("current", stage)]
            lines.append(f"| {stage} | {p['per_q_ms'] / c['per_q_ms']:.1f}x "
                         f"| {p['compile_s'] / max(c['compile_s'], 1e-3):.1f}x |")  # fmt: skip
    lines += ["", "Agreement (current vs previous, same q):", ""]
    lines += [
        f"- {k}: {v:.3g}" if isinstance(v, float) else f"- {k}: {v}" for k, v in agree.items()
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(text)
    with open(os.path.splitext(args.out)[0] + ".json", "w") as fh:
        json.dump({"rows": rows, "agreement": agree, "meta": meta}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
