"""CTR forward kinematics (TEST_CTR, float32, CPU), round 3 of issue 18: the working tree's
solvers against a reference revision's (default 31765ad, the tree before this round), loaded
from git into the same process and timed interleaved; a per-stage profile of both; accuracy
against the golden scipy references (tests/helpers/data/ctr_reference.json) and a fine-step
x64 reference.

    python experiments/kinematics/ctr_speed_r3.py [--ref 31765ad] [--cold-batch 64]
        [--batch 1024] [--repeats 7] [--out experiments/results/kinematics/ctr_speed_r3.md]

Times: compile = first call minus the median run (wall) and first-call CPU seconds minus one
run's (``time.process_time``, both cores summed: less sensitive to the other engineers' load
than wall time); runs: the median over interleaved repeats of wall and CPU seconds per q.
Writes the Markdown report and a .json beside it.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.benchmarks.ctr_reference import TEST_ROBOT, Tubes, random_q
from jaxcr.kinematics import ctr as ctr_now
from jaxcr.kinematics.newton import fd_jacobian

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.abspath(os.path.join(HERE, "..", ".."))
OUT = os.path.join(ROOT, "experiments", "results", "kinematics", "ctr_speed_r3.md")
FILES = ("ctr.py", "ctr_mechanics.py", "newton.py")


def load_reference(rev: str):
    """``jaxcr.kinematics.ctr`` (with its mechanics and solvers) as of git revision ``rev``,
    imported as the package ``ctr_ref_<rev>`` (the rest of jaxcr from the working tree)."""
    pkg = f"ctr_ref_{rev}"
    tmp = tempfile.mkdtemp(prefix="ctr_ref_")
    os.makedirs(os.path.join(tmp, pkg))
    open(os.path.join(tmp, pkg, "__init__.py"), "w").close()
    for name in FILES:
        src = subprocess.check_output(
            ["git", "show", f"{rev}:jaxcr/kinematics/{name}"], cwd=ROOT
        ).decode()
        for mod in ("ctr_mechanics", "newton"):
            src = src.replace(f"jaxcr.kinematics.{mod} ", f"{pkg}.{mod} ")
        with open(os.path.join(tmp, pkg, name), "w") as fh:
            fh.write(src)
    # the package from its folder (no sys.path edit): its submodules resolve through __path__
    spec = importlib.util.spec_from_file_location(
        pkg, os.path.join(tmp, pkg, "__init__.py"),
        submodule_search_locations=[os.path.join(tmp, pkg)],
    )  # fmt: skip
    sys.modules[pkg] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sys.modules[pkg])
    return importlib.import_module(f"{pkg}.ctr")


def _call(fn, *args):
    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0, time.process_time() - c0


def _golden_errors(mod, fwd):
    """Max tip error (mm) and max relative energy error over the golden cases of each kind."""
    with open(os.path.join(ROOT, "tests", "helpers", "data", "ctr_reference.json")) as fh:
        cases = json.load(fh)["cases"]
    out = {}
    for tt in (False, True):
        m = mod.make_test_ctr(transmission_torsion=tt)
        errs, den, oks = [], [], []
        for c in cases:
            if c["transmission_torsion"] != tt:
                continue
            r = fwd(m, jnp.asarray(c["q"], jnp.float32))
            errs.append(np.linalg.norm(np.asarray(r.centreline.p[-1], float) - c["tip"]) * 1e3)
            den.append(abs(float(r.energy) - c["energy"]) / abs(c["energy"]))
            oks.append(bool(r.ok))
        out[f"tt={tt}"] = {"n": len(errs), "max_tip_mm": float(max(errs)),
                           "max_rel_energy": float(max(den)), "all_ok": all(oks)}  # fmt: skip
    return out


def _fine_errors(mod, model, fwd_cold, warm, qs):
    """Tip error (mm) of float32 cold solves against the x64 solution on a 577-sample grid
    (warm-started from the float32 state; discretisation error of that grid ~7e-4 mm)."""
    res = fwd_cold(model, qs)
    with jax.enable_x64(True):
        fine = mod.make_test_ctr(dtype=jnp.float64, n_points=577)
        ref = warm(fine, jnp.asarray(np.asarray(qs), jnp.float64),
                   jnp.asarray(np.asarray(res.state), jnp.float64))  # fmt: skip
        tips_ref = np.asarray(ref.centreline.p[:, -1])
        ok_ref = np.asarray(ref.ok)
    d = np.linalg.norm(np.asarray(res.centreline.p[:, -1], float) - tips_ref, axis=-1) * 1e3
    return {"max_tip_mm": float(d[ok_ref].max()), "median_tip_mm": float(np.median(d[ok_ref])),
            "n": int(ok_ref.sum())}  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", default="31765ad", help="git revision of the reference solvers")
    ap.add_argument("--cold-batch", type=int, default=64)
    ap.add_argument("--batch", type=int, default=1024, help="warm batch")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--fine", type=int, default=64, help="q checked against the fine grid")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stages", action="store_true", help="also profile the stages")
    ap.add_argument("-o", "--out", default=OUT)
    args = ap.parse_args(argv)
    loads = [os.getloadavg()[0]]

    ref_mod = load_reference(args.ref)
    impls = {"reference": ref_mod, "current": ctr_now}
    models = {k: m.make_test_ctr() for k, m in impls.items()}
    rng = np.random.default_rng(args.seed)
    tubes = Tubes(TEST_ROBOT)
    qs_np = np.stack([random_q(rng, tubes) for _ in range(args.batch)])
    qs = jnp.asarray(qs_np, jnp.float32)
    cq = qs[: args.cold_batch]
    dq = rng.normal(0.0, 1.0, qs.shape) * np.r_[[0.0] * 3, [0.01] * 3]
    q_next = jnp.asarray(qs_np + dq, jnp.float32)  # every tube turned by ~0.6 deg: video rate

    cold = eqx.filter_jit(lambda m, q: jax.vmap(m.forward)(q))
    warm = eqx.filter_jit(lambda m, q, g: jax.vmap(m.forward)(q, g))
    one_cold = eqx.filter_jit(lambda m, q: m.forward(q))

    calls, compile_s, compile_cpu, outs = {}, {}, {}, {}

    def first(key, thunk, batch):
        out, wall, cpu = _call(thunk)
        _, wall2, cpu2 = _call(thunk)
        compile_s[key], compile_cpu[key] = wall - wall2, cpu - cpu2
        calls[key], outs[key] = (thunk, batch), out
        print(f"{key}: first call {wall:.1f} s ({cpu:.1f} s CPU)", flush=True)
        return out

    # states for the warm batch come from the reference's cold path (same branch for both)
    for name, m in models.items():
        first((name, "cold forward"), lambda m=m: cold(m, cq), args.cold_batch)
        loads.append(os.getloadavg()[0])
    m_ref = models["reference"]
    states = jnp.concatenate([
        cold(m_ref, qs[k : k + args.cold_batch]).state
        for k in range(0, args.batch - args.cold_batch + 1, args.cold_batch)
    ])  # fmt: skip
    nb = states.shape[0]
    for name, m in models.items():
        first((name, "warm forward"), lambda m=m: warm(m, q_next[:nb], states), nb)
    loads.append(os.getloadavg()[0])
    if args.stages:
        for name, m in models.items():
            _stages(name, m, cq, q_next[:nb], states, first)
    loads.append(os.getloadavg()[0])

    times = {k: ([], []) for k in calls}
    for _ in range(args.repeats):
        for k, (thunk, _) in calls.items():
            _, wall, cpu = _call(thunk)
            times[k][0].append(wall)
            times[k][1].append(cpu)
        loads.append(os.getloadavg()[0])

    rows = []
    for (name, stage), (wall, cpu) in times.items():
        b = calls[(name, stage)][1]
        rows.append({"impl": name, "stage": stage, "batch": b,
                     "compile_s": compile_s[(name, stage)],
                     "compile_cpu_s": compile_cpu[(name, stage)],
                     "median_batch_s": float(np.median(wall)),
                     "min_batch_s": float(np.min(wall)), "max_batch_s": float(np.max(wall)),
                     "per_q_ms": float(np.median(wall)) / b * 1e3,
                     "cpu_per_q_ms": float(np.median(cpu)) / b * 1e3})  # fmt: skip

    # agreement and accuracy
    a, b = outs[("reference", "cold forward")], outs[("current", "cold forward")]
    wa, wb = outs[("reference", "warm forward")], outs[("current", "warm forward")]

    def tipd(x, y):
        return np.linalg.norm(np.asarray(x.centreline.p[:, -1]) - np.asarray(y.centreline.p[:, -1]),
                              axis=-1) * 1e3  # fmt: skip

    agree = {
        "cold_max_tip_mm_current_vs_reference": float(tipd(a, b).max()),
        "cold_max_rel_energy": float(np.max(np.abs(np.asarray(a.energy) - np.asarray(b.energy))
                                            / np.abs(np.asarray(a.energy)))),
        "warm_max_tip_mm_current_vs_reference": float(tipd(wa, wb).max()),
        "ok_cold": {"reference": float(np.mean(a.ok)), "current": float(np.mean(b.ok))},
        "ok_warm": {"reference": float(np.mean(wa.ok)), "current": float(np.mean(wb.ok))},
        "warm_steps": {k: {"mean": float(np.mean(w.num_steps)), "max": int(np.max(w.num_steps)),
                           "hist": np.bincount(np.asarray(w.num_steps)).tolist()}
                       for k, w in (("reference", wa), ("current", wb))},
    }  # fmt: skip
    accuracy = {}
    for name, mod in impls.items():
        accuracy[name] = {
            "golden": _golden_errors(mod, one_cold),
            "fine_577_x64": _fine_errors(mod, models[name], cold, warm, qs[: args.fine]),
        }
        print(name, accuracy[name], flush=True)
    loads.append(os.getloadavg()[0])

    try:
        commit = subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT).decode()
        dirty = subprocess.check_output(
            ["git", "status", "--porcelain", "jaxcr"], cwd=ROOT
        ).decode()
    except Exception:  # noqa: BLE001
        commit, dirty = "unknown", ""
    cmd = "python experiments/kinematics/ctr_speed_r3.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    meta = {"commit": commit.strip() + (" + uncommitted jaxcr/ changes" if dirty else ""),
            "reference": args.ref, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": platform.platform(), "cpus": os.cpu_count(), "load_avg_1min": loads,
            "jax": jax.__version__, "command": cmd.strip()}  # fmt: skip
    text = _markdown(rows, agree, accuracy, meta)
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(text)
    with open(os.path.splitext(args.out)[0] + ".json", "w") as fh:
        json.dump({"rows": rows, "agreement": agree, "accuracy": accuracy, "meta": meta}, fh,
                  indent=2)  # fmt: skip
    return 0


def _stages(name, m, cq, qw, states, first):
    """Per-stage rows: one residual and one difference Jacobian on each grid, the warm
    solve, the result (centreline), the cold scan and multi-start."""
    nb, cb = qw.shape[0], cq.shape[0]
    for n_pts in sorted({m.n_points, m._coarse_points}):
        res = eqx.filter_jit(
            lambda m, q, x, n=n_pts: jax.vmap(lambda a, z: m._shooting(a, n)(z))(q, x)
        )
        fdj = eqx.filter_jit(
            lambda m, q, x, n=n_pts: jax.vmap(lambda a, z: fd_jacobian(m._shooting(a, n), z, 1e-3))(q, x)
        )  # fmt: skip
        # default arguments bind this iteration's functions (the repeats call the thunks later)
        first((name, f"residual ({n_pts} samples)"), lambda f=res: f(m, qw, states), nb)
        first((name, f"difference Jacobian ({n_pts} samples)"),
              lambda f=fdj: f(m, qw, states), nb)  # fmt: skip
    ws = eqx.filter_jit(lambda m, q, x: jax.vmap(m._warm_solve)(q, x))
    rs = eqx.filter_jit(lambda m, q, x: jax.vmap(lambda a, z: m._result(a, z, 0, True))(q, x))
    sc = eqx.filter_jit(lambda m, q: jax.vmap(m.initial_guesses)(q))
    ms = eqx.filter_jit(lambda m, q, g: jax.vmap(m._cold_solve)(q, g))
    first((name, "warm solve (no centreline)"), lambda: ws(m, qw, states), nb)
    first((name, "result (centreline)"), lambda: rs(m, qw, states), nb)
    g = first((name, "cold scan"), lambda: sc(m, cq), cb)
    first((name, "cold multi-start"), lambda: ms(m, cq, g), cb)


def _markdown(rows, agree, accuracy, meta):
    loads = meta["load_avg_1min"]
    lines = [
        "# CTR forward kinematics, issue 18 round 3: current vs reference, same process",
        "",
        f"- command: `{meta['command']}`",
        f"- commit {meta['commit']} (reference solvers: `git show {meta['reference']}:"
        "jaxcr/kinematics/{ctr,ctr_mechanics,newton}.py` loaded as a module), "
        f"{meta['date']}, {meta['machine']}, {meta['cpus']} CPUs, jax {meta['jax']}",
        f"- load average (1 min) during the run: {min(loads):.1f}-{max(loads):.1f} on 2 cores "
        "(shared machine: wall times are inflated by the other engineers' jobs; CPU seconds "
        "and the ratios between the two implementations, timed interleaved, are the figures "
        "to compare)",
        "",
        "| impl | stage | batch | compile wall (s) | compile CPU (s) | median batch (s) "
        "| min-max (s) | wall per q (ms) | CPU per q (ms) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['impl']} | {r['stage']} | {r['batch']} | {r['compile_s']:.1f} "
            f"| {r['compile_cpu_s']:.1f} | {r['median_batch_s']:.4f} "
            f"| {r['min_batch_s']:.4f}-{r['max_batch_s']:.4f} | {r['per_q_ms']:.4f} "
            f"| {r['cpu_per_q_ms']:.4f} |"
        )
    by = {(r["impl"], r["stage"]): r for r in rows}
    lines += ["", "| stage | reference / current (wall per q) | (CPU per q) | (compile CPU) |",
              "|---|---|---|---|"]  # fmt: skip
    for (impl, stage), c in by.items():
        if impl != "current" or ("reference", stage) not in by:
            continue
        p = by[("reference", stage)]
        lines.append(
            f"| {stage} | {p['per_q_ms'] / c['per_q_ms']:.2f}x "
            f"| {p['cpu_per_q_ms'] / c['cpu_per_q_ms']:.2f}x "
            f"| {p['compile_cpu_s'] / max(c['compile_cpu_s'], 1e-3):.2f}x |"
        )
    lines += ["", "Agreement (current vs reference, same q) and warm iterations:", ""]
    lines += [f"- {k}: {v}" for k, v in agree.items()]
    lines += ["", "Accuracy (float32 cold solves; golden = the scipy references of "
              "tests/kinematics/test_ctr.py; fine = x64 on 577 samples, warm from the float32 "
              "state):", "", "| impl | golden tt=False max tip (mm) | golden tt=True max tip (mm) "
              "| golden max rel. energy | all ok | fine max tip (mm) | fine median tip (mm) |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, acc in accuracy.items():
        g0, g1, f = acc["golden"]["tt=False"], acc["golden"]["tt=True"], acc["fine_577_x64"]
        lines.append(
            f"| {name} | {g0['max_tip_mm']:.2e} | {g1['max_tip_mm']:.2e} "
            f"| {max(g0['max_rel_energy'], g1['max_rel_energy']):.1e} "
            f"| {g0['all_ok'] and g1['all_ok']} | {f['max_tip_mm']:.2e} "
            f"| {f['median_tip_mm']:.2e} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
