"""Where a tracked frame's fixed cost goes inside its compiled program: an XLA op profile
(issue 18, refinement rows, "Floors"; engineer track30b).

``profile_tracking.py`` measures the fixed cost of a tracked frame as the same frame with a
step budget of 0 (package-default warm schedule, started from the previous answer). This
script runs exactly that call (frame 1 of ``make_scene(frames, seed, smooth=True)`` from frame
0's cold answer, :func:`refine_frame_jit`'s program ``_refine_frame_jit``) ``--repeats`` times
under ``jax.profiler`` and sums the XLA:CPU thunk events (one per fusion, custom call, copy,
loop...) by their *self* time (a while/conditional thunk's own time without its body's
thunks). Each thunk is named after its instruction in the optimised HLO, whose metadata give
the Python stack that emitted it (the module's stack-frame tables), read as its jaxcr
functions (the stage: the outermost two below ``_refine_frame_body``; and the innermost).
Reported per stage, per function and per thunk: ms per call (a thunk's self time summed over
its runs in a call, median over the calls: thread time, the median dropping descheduled
calls), runs per call, and the process CPU ms of the whole call beside it.

``--budget N`` (issue 18, engineer track31) profiles the same call with N steps per solve
(the warm schedule's 30: the tracked frame itself) and adds two tables of the thunks inside
the solver loop, by the Optimistix function that emitted them (``quasi_newton`` step: the
linearised evaluation at every step; ``filter_cond``: the accepted branch, whose gradient is
the transpose of that linearisation) and by jaxcr function: a thunk's runs per call count its
evaluations (all steps) or accepted steps.

Run: ``PYTHONPATH=$PWD python experiments/segmentation/profile_fixed_ops.py [--size 640x480]
[--repeats 20] [--budget 30] [--tag NAME] [--save OUT.npz]`` (writes ``experiments/results/segmentation/
profile_fixed_ops<tag>.md`` and ``.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import re
import tempfile
import time
from collections import defaultdict
from functools import cache
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax._src.profiler import ProfileData

import jaxcr.benchmarks.segment as bs
import jaxcr.segmentation.refine as rf
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.refine import RefineConfig, refine_frame_jit

OUT = Path(__file__).resolve().parents[1] / "results" / "segmentation"
_INSTR = re.compile(r"^\s*(?:ROOT )?%?([\w.\-]+) = .*?metadata=\{[^}]*stack_frame_id=(\d+)")


def _stacks(hlo: str) -> dict[str, tuple[tuple[str, str, int], ...]]:
    """Per optimised-HLO instruction, its Python stack (innermost first) as ``(file,
    function, line)``, from the module's FileNames / FunctionNames / FileLocations /
    StackFrames tables (a frame's ``parent_frame_id`` is the parent's id + 1; 0 = none)."""
    tables = {k: {} for k in ("FileNames", "FunctionNames", "FileLocations", "StackFrames")}
    sec, instr = None, {}
    for line in hlo.splitlines():
        if line in tables:
            sec = line
            continue
        m = re.match(r"^(\d+) (.*)$", line)
        if sec and m:
            tables[sec][int(m.group(1))] = m.group(2)
            continue
        sec = None
        m = _INSTR.match(line)
        if m:
            instr[m.group(1)] = int(m.group(2))
    files = {i: v.strip('"') for i, v in tables["FileNames"].items()}
    funcs = {i: v.strip('"') for i, v in tables["FunctionNames"].items()}
    locs, frames = {}, {}
    for i, v in tables["FileLocations"].items():
        d = dict(re.findall(r"(\w+)=(\d+)", v))
        locs[i] = (files[int(d["file_name_id"])], funcs[int(d["function_name_id"])],
                   int(d["line"]))  # fmt: skip
    for i, v in tables["StackFrames"].items():
        d = dict(re.findall(r"(\w+)=(\d+)", v))
        frames[i] = (int(d["file_location_id"]), int(d["parent_frame_id"]) - 1)

    @cache
    def chain(f):
        out, seen = [], set()
        while f in frames and f not in seen:
            seen.add(f)
            loc, f = frames[f]
            out.append(locs[loc])
        return tuple(out)

    return {n: chain(f) for n, f in instr.items()}


def _jaxcr_path(stack) -> tuple[str, str]:
    """(stage, innermost): the jaxcr functions of a stack below ``_refine_frame_body``,
    outermost two as the stage, the innermost jaxcr function with its line."""
    names = []
    for path, fn, line in stack:  # innermost first
        if "/jaxcr/" not in path:
            continue
        if fn in ("_refine_frame_body", "refine_frame", "_refine_frame_jit"):
            break
        item = f"{Path(path).stem}.{fn}"
        if not names or names[-1][0] != item:
            names.append((item, line))
    if not names:
        return "(refine_frame_body itself / no jaxcr frame)", "-"
    outer = [n for n, _ in reversed(names)]
    return " > ".join(outer[:2]), f"{names[0][0]}:{names[0][1]}"


def _solver_path(stack) -> str:
    """Which part of a BFGS step emitted an instruction, from the Optimistix functions of its
    stack: the objective's value and linearisation (``jax.linearize`` at every step, accepted
    or not), its gradient (the transpose of that linearisation, in the branch of an accepted
    step, Optimistix's ``filter_cond``), or the solver's own work (line search, Hessian update,
    descent, stopping test); "-" outside the solver loop."""
    names = [f"{Path(p).stem}.{fn}" for p, fn, _ in stack if "/optimistix/" in p]
    if not names:
        return "-"
    if any(n.endswith("NoneAux.__call__") for n in names):
        if any(n.endswith("filter_cond") for n in names):
            return "objective: gradient (transpose; accepted steps)"
        return "objective: value + linearisation (every step)"
    return "BFGS bookkeeping (line search, Hessian update, descent, stop test)"


def _self_times(events) -> dict[str, list[tuple[int, float]]]:
    """Self time (ns) of each thunk event on one thread line: its duration minus its nested
    events' (a while thunk contains its body's thunks), as (start, self time) pairs."""
    ev = sorted(
        ((e.start_ns, e.duration_ns, e.name) for e in events
         if not e.name.startswith(("ThreadpoolListener", "end: "))),
        key=lambda t: (t[0], -t[1]),
    )  # fmt: skip
    out = defaultdict(list)
    stack = []  # [end, name, start, self]
    for s, d, n in ev:
        while stack and s >= stack[-1][0]:
            _, nm, s0, st = stack.pop()
            out[nm].append((s0, st))
        if stack:
            stack[-1][3] -= d
        stack.append([s + d, n, s, d])
    for _, nm, s0, st in stack:
        out[nm].append((s0, st))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--tag", default="")
    ap.add_argument("--save", default=None, help="write the call's outputs to this .npz")
    ap.add_argument(
        "--budget",
        type=int,
        default=0,
        help="step budget per solve (0: the fixed cost; the warm schedule's is 30)",
    )
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    bs.W, bs.H = w, h
    load0 = os.getloadavg()[0]
    base, cam, fr = bs.make_scene(args.frames, seed=args.seed, smooth=True)
    ims = [colour_mask(jnp.asarray(f["img"])) for f in fr]
    cold = refine_frame_jit(base, cam, ims[0][1], ims[0][0], RefineConfig())
    warm = RefineConfig().warm()
    zero = dataclasses.replace(warm, steps=(args.budget,) * len(warm.steps))
    config, steps = rf._traced_apart(zero, base.p.dtype)  # steps: every traced setting
    call_args = (
        base, (cam,), (ims[1][1],), (ims[1][0],), config, cold.coeffs, jnp.asarray(True),
        cold.camera_correction, None, steps,
    )  # fmt: skip
    compiled = rf._refine_frame_jit.lower(*call_args).compile()
    hlo = compiled.compiled.as_text()
    if os.environ.get("PROFILE_FIXED_OPS_HLO"):
        Path(os.environ["PROFILE_FIXED_OPS_HLO"]).write_text(hlo)
    stacks = _stacks(hlo)
    where = {n: _jaxcr_path(st) for n, st in stacks.items()}
    solver_of = {n: _solver_path(st) for n, st in stacks.items()}

    def call():
        return jax.block_until_ready(compiled(*call_args))

    out = call()
    n_steps = int(out.num_steps)
    if args.save:
        leaves = jax.tree.leaves(out)
        np.savez(args.save, *[np.asarray(x) for x in leaves])
    cpu, wall = [], []
    for _ in range(args.repeats):  # the call alone, not profiled
        c0, t0 = time.process_time(), time.perf_counter()
        call()
        cpu.append(1e3 * (time.process_time() - c0))
        wall.append(1e3 * (time.perf_counter() - t0))
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp)
        pc0 = time.process_time()
        for _ in range(args.repeats):
            call()
        prof_cpu = 1e3 * (time.process_time() - pc0) / args.repeats
        jax.profiler.stop_trace()
        (pb,) = glob.glob(f"{tmp}/**/*.xplane.pb", recursive=True)
        pd = ProfileData.from_file(pb)
    thunks = defaultdict(list)
    for plane in pd.planes:
        if plane.name != "/host:CPU":
            continue
        for line in plane.lines:
            if line.name == "python":
                continue
            for name, st in _self_times(list(line.events)).items():
                if name in where:
                    thunks[name] += st
    # a thunk's time per call: its runs sorted by start time and cut into the calls (the calls
    # are sequential), summed per call, median over the calls (drops the calls during which
    # the thread was descheduled, common at loads above the core count)
    per = {}
    for n, v in thunks.items():
        k = len(v) // args.repeats
        st = np.asarray([t for _, t in sorted(v)][: k * args.repeats]).reshape(args.repeats, k)
        per[n] = (float(np.median(st.sum(axis=1))) / 1e6, len(v) / args.repeats)
    total = sum(ms for ms, _ in per.values())
    by_fn = defaultdict(lambda: [0.0, 0.0])
    by_inner = defaultdict(lambda: [0.0, 0.0])
    by_solver = defaultdict(lambda: [0.0, 0.0])
    by_step_fn = defaultdict(lambda: [0.0, 0.0])  # innermost jaxcr function, in the loop
    for n, (ms, k) in per.items():
        tables = [(by_fn, where[n][0]), (by_inner, where[n][1].split(":")[0])]
        tables.append((by_solver, solver_of[n]))
        if solver_of[n] != "-":
            tables.append((by_step_fn, where[n][1].split(":")[0] + " | " + solver_of[n]))
        for table, key in tables:
            table[key][0] += ms
            table[key][1] += k
    load1 = os.getloadavg()[0]
    meta = bs._meta()
    cmd = (
        "PYTHONPATH=$PWD python experiments/segmentation/profile_fixed_ops.py "
        f"--size {args.size} --repeats {args.repeats}"
        + (f" --budget {args.budget}" if args.budget else "")
        + (f" --seed {args.seed}" if args.seed != 1 else "")
        + (f" --tag {args.tag}" if args.tag else "")
    )
    res = {
        "cpu_ms_median": float(np.median(cpu)),
        "wall_ms_median": float(np.median(wall)),
        "cpu_ms_profiled": prof_cpu,
        "thunk_ms_total": total,
        "by_stage": {k: v for k, v in sorted(by_fn.items(), key=lambda t: -t[1][0])},
        "by_innermost": {k: v for k, v in sorted(by_inner.items(), key=lambda t: -t[1][0])},
        "by_thunk": {
            n: {"ms": ms, "count": k, "where": where[n]}
            for n, (ms, k) in sorted(per.items(), key=lambda t: -t[1][0])
        },
        "hlo_instructions_with_source": len(where),
        "num_steps": n_steps,
        "by_solver": {k: v for k, v in sorted(by_solver.items(), key=lambda t: -t[1][0])},
        "in_solver_by_innermost": {
            k: v for k, v in sorted(by_step_fn.items(), key=lambda t: -t[1][0])
        },
    }
    stem = f"profile_fixed_ops{args.tag}"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps({"command": cmd, "results": res, "meta": meta}, indent=1)
    )
    lines = [
        (
            f"# Op profile of a tracked frame's fixed cost, {w}x{h} (step budget 0, warm schedule)"
            if not args.budget
            else f"# Op profile of a tracked frame, {w}x{h} (step budget {args.budget} per solve, "
            "warm schedule): the BFGS steps"
        ),
        "",
        f"Command: `{cmd}`",
        "",
        f"The call alone: **{res['cpu_ms_median']:.1f} CPU ms**, {res['wall_ms_median']:.1f} ms "
        f"wall (medians of {args.repeats}); under the profiler {prof_cpu:.1f} CPU ms per call; "
        f"XLA thunks' self time {total:.1f} ms per call (thread time; the rest of the call is "
        "dispatch, argument handling and the profiler's own cost).",
        "",
        "## By stage (the outermost two jaxcr functions below `_refine_frame_body`)",
        "",
        "| stage | ms per call | share of thunk time | thunks per call |",
        "|---|---|---|---|",
    ]
    for fn, (ms, k) in list(res["by_stage"].items())[: args.top]:
        lines.append(f"| `{fn}` | {ms:.2f} | {100 * ms / total:.1f} % | {k:.0f} |")
    lines += [
        "",
        "## By innermost jaxcr function",
        "",
        "| function | ms per call | share of thunk time | thunks per call |",
        "|---|---|---|---|",
    ]
    for fn, (ms, k) in list(res["by_innermost"].items())[: args.top]:
        lines.append(f"| `{fn}` | {ms:.2f} | {100 * ms / total:.1f} % | {k:.0f} |")
    if args.budget:
        lines += [
            "",
            f"## Inside the solver loop ({n_steps} steps in the call: two solves of up to "
            f"{args.budget}), by Optimistix function",
            "",
            "| Optimistix path | ms per call | ms per step | thunks per call |",
            "|---|---|---|---|",
        ]
        for fn, (ms, k) in list(res["by_solver"].items())[: args.top]:
            lines.append(f"| `{fn}` | {ms:.2f} | {ms / max(n_steps, 1):.3f} | {k:.0f} |")
        lines += [
            "",
            "## Inside the solver loop, by innermost jaxcr function and Optimistix path",
            "",
            "| function \\| solver path | ms per call | ms per step | thunks per call |",
            "|---|---|---|---|",
        ]
        for fn, (ms, k) in list(res["in_solver_by_innermost"].items())[: args.top]:
            lines.append(f"| `{fn}` | {ms:.2f} | {ms / max(n_steps, 1):.3f} | {k:.0f} |")
    lines += [
        "",
        "## Largest thunks",
        "",
        "| thunk (optimised HLO instruction) | ms per call | runs per call | source |",
        "|---|---|---|---|",
    ]
    for n, r in list(res["by_thunk"].items())[: args.top]:
        lines.append(
            f"| `{n}` | {r['ms']:.3f} | {r['count']:.0f} | `{r['where'][0]}` / `{r['where'][1]}` |"
        )
    lines += [
        "",
        f"1-min load before/after: {load0:.1f} / {load1:.1f} on {os.cpu_count()} cores.",
    ]
    print(bs.write_markdown(OUT / f"{stem}.md", lines, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
