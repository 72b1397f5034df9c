"""Issue 18, registration rows, round 3: pairwise RGB-D registration per pair and arc
planning per step, each against the implementation before issue 18 in the same process.
Writes experiments/results/registration/speed_r3.md (+ .json).

    python experiments/registration/bench_speed_r3.py --seeds 0-9 --pairs 4

Calls :func:`jaxcr.benchmarks.registration.run_registration_benchmark` and
:func:`run_planning_benchmark` (also ``jaxcr bench registration`` / ``jaxcr bench
planning`` for one seed) on the model-object development seeds (Tasks 1 and 2; the fresh
seeds of fresh_seeds_reserved.md are not used).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

from jaxcr.benchmarks import parse_seeds
from jaxcr.benchmarks.registration import run_planning_benchmark, run_registration_benchmark

OUT = Path(__file__).parent.parent / "results" / "registration"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0-9", help="development seeds, e.g. 0-9 or 0,3")
    ap.add_argument("--pairs", type=int, default=4, help="forward pairs per scene")
    ap.add_argument("--repeats", type=int, default=1, help="timings per pair and variant")
    ap.add_argument("--scratch", default="/tmp/bench_speed_r3")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    load0 = os.getloadavg()
    reg = run_registration_benchmark(
        seeds=seeds, frames=a.pairs, repeats=a.repeats, scratch=a.scratch + "/reg"
    )
    plan = run_planning_benchmark(seeds=seeds, scratch=a.scratch + "/plan")
    load1 = os.getloadavg()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    cmd = "python experiments/registration/bench_speed_r3.py " + " ".join(
        sys.argv[1:] if argv is None else argv
    )
    ms = lambda v: f"{1000 * v:.1f}"  # noqa: E731
    now, prev = np.array(reg["seconds_now"]), np.array(reg["seconds_previous"])
    pn, pp = np.array(plan["seconds_now"]), np.array(plan["seconds_previous"])
    md = [
        "# Registration speed, round 3 (issue 18: pairwise registration, arc planning)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs shared with 5 other engineers' jobs; load average "
        f"{load0[0]:.1f} at start, {load1[0]:.1f} at end (registration "
        f"{reg['load_start']:.1f} -> {reg['load_end']:.1f}, planning "
        f"{plan['load_start']:.1f} -> {plan['load_end']:.1f}). Command: `{cmd}`.",
        "Development seeds " + a.seeds + " of Tasks 1 and 2 (fresh seeds untouched). "
        "Absolute times are inflated by the load; the previous implementation ran in the "
        "same process, alternating pair by pair / route by route: read the ratios.",
        "",
        "## Pairwise RGB-D registration (`register_pair`, pipeline defaults)",
        "",
        f"{reg['pairs']} forward pairs (25 deg apart, 320x240, 8192 source pixels), "
        f"{a.repeats} timing(s) each; compilation apart (now {reg['compile_s']:.1f} s, "
        f"previous {reg['reference_compile_s']:.1f} s).",
        "",
        "| | median ms/pair | IQR ms | p90 ms | rot err median / p90 / max deg | trans err median / p90 / max mm |",
        "|---|---|---|---|---|---|",
    ]
    for name, t, pre in (("now", now, ""), ("previous (31765ad ICP)", prev, "previous_")):
        md.append(
            f"| {name} | {ms(np.median(t))} | {ms(np.percentile(t, 25))}-{ms(np.percentile(t, 75))} "
            f"| {ms(np.percentile(t, 90))} | {reg[pre + 'rot_deg_median']:.4f} / "
            f"{reg[pre + 'rot_deg_p90']:.4f} / {reg[pre + 'rot_deg_max']:.3f} | "
            f"{reg[pre + 'trans_mm_median']:.3f} / {reg[pre + 'trans_mm_p90']:.3f} / "
            f"{reg[pre + 'trans_mm_max']:.2f} |"
        )
    md += [
        "",
        f"Median of the per-pair ratios previous / now: {reg['median_ratio_per_pair']:.2f}x.",
        "",
        "## Arc planning (Algorithm 1), per step",
        "",
        f"{plan['routes']} routes, {plan['steps']} steps ({plan['steps_with_check']} of them "
        f"evaluate candidates; the others keep the arc without a check). Routes identical "
        f"(arcs, travelled arclengths, events, status): {plan['identical_routes']} of "
        f"{plan['routes']}. Paper: 20-31 ms per step.",
        "",
        "| | median ms/step (all) | median ms/step (steps with a check) | p90 ms | max ms/step |",
        "|---|---|---|---|---|",
        f"| now (k-d tree check) | {ms(plan['median_s'])} | "
        f"{ms(plan['median_s_steps_with_check'])} | {ms(np.percentile(pn, 90))} | {ms(plan['max_s'])} |",
        f"| previous (dense JAX check) | {ms(plan['reference_median_s'])} | "
        f"{ms(plan['reference_median_s_steps_with_check'])} | {ms(np.percentile(pp, 90))} | "
        f"{ms(plan['reference_max_s'])} |",
        "",
    ]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "speed_r3.md").write_text("\n".join(md) + "\n")
    for r in plan["rows"]:
        r["identical route"] = bool(r["identical route"])
    (out / "speed_r3.json").write_text(
        json.dumps(
            {"command": cmd, "commit": commit, "registration": reg, "planning": plan},
            indent=1,
            default=float,
        )
    )
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
