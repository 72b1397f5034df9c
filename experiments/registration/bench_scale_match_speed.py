"""Issue 18 registration row, check for this round: time of ``PipelineConfig().register`` (the
pipeline default, ``photometric_scale_match=False``, whose code path is main's but for one
boolean test) against the same call with the scale-matched colour term on, alternating
call by call in one process, on development-seed pairs (a close pair at similar depths and a
far/near pair of :mod:`model_object_scale_match_edges`). Wall and process CPU medians after a
warm-up (compile) call; 1-min load average recorded.

    python experiments/registration/bench_scale_match_speed.py --seeds 0-1 --repeats 3
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
from model_object_scale_match_edges import camera  # sibling script

from jaxcr.benchmarks import parse_seeds
from jaxcr.registration.pipeline import PipelineConfig, capture_frame
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

OUT = Path(__file__).parent.parent / "results" / "registration"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0-1")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scratch", default="/tmp/bench_scale_match_speed")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args()
    cfgs = {
        "default": PipelineConfig(),
        "scale-matched": PipelineConfig(photometric_scale_match=True),
    }
    times = {k: ([], []) for k in cfgs}
    loads = [os.getloadavg()[0]]
    for task in ("1", "2"):
        for seed in parse_seeds(a.seeds):
            sim = RgbdSimulator(
                generate_task(Path(a.scratch) / f"t{task}s{seed}", task, seed), seed
            )
            target = np.array([0.0, 0.0, 0.08])
            for d0, d1, off in ((0.30, 0.30, 10.0), (0.60, 0.47, 12.0)):
                T0, T1 = (
                    camera(d0, 0.3 * seed, target),
                    camera(d1, 0.3 * seed + np.deg2rad(off), target),
                )
                fa, fb = (
                    capture_frame(*sim.capture(T), sim.K, cfgs["default"], seed, n)
                    for n, T in (("a", T0), ("b", T1))
                )
                prior = np.linalg.inv(T1) @ T0
                for cfg in cfgs.values():  # warm-up: compile, keypoint cache
                    cfg.register(fa, fb, sim.K, prior, seed)
                for _ in range(a.repeats):
                    for k, cfg in cfgs.items():
                        t0, c0 = time.perf_counter(), time.process_time()
                        cfg.register(fa, fb, sim.K, prior, seed)
                        times[k][0].append(time.perf_counter() - t0)
                        times[k][1].append(time.process_time() - c0)
            loads.append(os.getloadavg()[0])
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    md = [
        "# register_pair time with and without the scale-matched colour term",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}; "
        f"`python experiments/registration/bench_scale_match_speed.py --seeds {a.seeds} "
        f"--repeats {a.repeats}`; 1-min load average {min(loads):.1f}-{max(loads):.1f} "
        "(shared 2-core machine). Alternating call by call; medians over "
        f"{len(times['default'][0])} calls each (development seeds, Tasks 1 and 2).",
        "",
        "| variant | wall ms (median) | wall ms (IQR) | CPU ms (median) |",
        "|---|---|---|---|",
    ]
    for k, (w, c) in times.items():
        q1, q3 = np.percentile(w, [25, 75])
        md.append(
            f"| {k} | {1000 * np.median(w):.1f} | {1000 * q1:.1f}-{1000 * q3:.1f} | "
            f"{1000 * np.median(c):.1f} |"
        )
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "bench_scale_match_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
