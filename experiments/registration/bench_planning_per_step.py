"""Algorithm 1's planning time per step (issue 18, row "arc planning, per step": the paper
reports 20-31 ms per step; the pipeline reported 254-355 ms per route). Writes
experiments/results/registration/bench_planning_per_step.md (+ .json).

    python experiments/registration/bench_planning_per_step.py --tasks 1 2 --seed 5

Planner only (no rendering, no registration): for every route of the Task 1 / Task 2 scene
(development seed), the pipeline's ArmSpec and PlannerConfig, stepped until the route ends
with the scene's whole obstacle cloud plus points on the target's surface (a ring at the
object's radius, the most the sensing can add) as the sensed cloud and the object centre
known. ``PlanState.step_times`` (the same timer as Table I's T_mp) per step; medians and max,
the clearance check's compilation (``ArcPlanner.__init__``) apart. The machine is shared:
load recorded; there is no reference implementation in the same run (the planner is the only
one in the repository).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxcr.registration.pipeline import run_arm_spec
from jaxcr.registration.planning import ArcPlanner, PlannerConfig
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

OUT = Path(__file__).parent.parent / "results" / "registration"


def route(sim, run: dict) -> dict:
    spec = run_arm_spec(sim, run)
    cfg = PlannerConfig(
        direction=int(run["direction"]),
        delta_s=float(run["delta_s"]),
        view_radius=float(sim.cfg["view_radius"]),
    )
    t0 = time.perf_counter()
    planner = ArcPlanner(spec, cfg)
    compile_s = time.perf_counter() - t0
    ob = sim.cfg["object"]
    r = float(ob.get("radius", np.max(np.abs(ob.get("half", [0.05, 0.05])[:2]))))
    ang = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    target = np.stack([r * np.cos(ang), r * np.sin(ang), np.full_like(ang, spec.height)], 1)
    cloud = np.concatenate([sim.obstacles, target])
    status = "moving"
    while status == "moving" and len(planner.state.step_times) < 60:
        status = planner.step(cloud, np.zeros(2))
    return {
        "name": str(run["name"]),
        "status": status,
        "compile_s": compile_s,
        "step_ms": [1000 * t for t in planner.state.step_times],
        "total_ms": 1000 * planner.state.planning_time,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tasks", nargs="+", default=["1", "2"])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--scratch", default="/tmp/bench_planning")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args()
    load0 = os.getloadavg()
    rows = []
    for task in a.tasks:
        sim = RgbdSimulator(generate_task(Path(a.scratch) / f"task{task}", task, a.seed), a.seed)
        for run in sim.cfg["runs"]:
            rows.append({"task": task, **route(sim, run)})
    load1 = os.getloadavg()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    cmd = "python experiments/registration/bench_planning_per_step.py " + " ".join(sys.argv[1:])
    md = [
        "# Arc planning (Algorithm 1): time per step (issue 18)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs shared with other jobs; load average {load0[0]:.1f} at start, "
        f"{load1[0]:.1f} at end. Command: `{cmd}`. Paper: 20-31 ms per step.",
        "",
        "| task | route | steps | median ms/step | max ms/step | first step ms | total ms | compile s | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s = r["step_ms"]
        md.append(
            f"| {r['task']} | {r['name']} | {len(s)} | {np.median(s):.1f} | {max(s):.1f} | "
            f"{s[0]:.1f} | {r['total_ms']:.0f} | {r['compile_s']:.1f} | {r['status']} |"
        )
    allsteps = [t for r in rows for t in r["step_ms"]]
    md += [
        "",
        f"All steps: median {np.median(allsteps):.1f} ms, max {max(allsteps):.1f} ms "
        f"({len(allsteps)} steps).",
    ]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_planning_per_step.md").write_text("\n".join(md) + "\n")
    (out / "bench_planning_per_step.json").write_text(
        json.dumps(
            {"command": cmd, "commit": commit, "load": [load0, load1], "routes": rows}, indent=1
        )
    )
    print("\n".join(md))


if __name__ == "__main__":
    main()
