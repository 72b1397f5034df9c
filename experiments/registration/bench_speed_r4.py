"""Issue 18, pairwise RGB-D registration, round 4: the per-frame keypoint cache
(:func:`jaxcr.registration.pairwise.frame_features`). Per pair, in one process, alternating
pair by pair: the current path (cached features, as in a run's chain of forward
registrations), the same path without the cache, and the implementation before issue 18
(31765ad ICP, no cache). Writes experiments/results/registration/speed_r4.md (+ .json).

    python experiments/registration/bench_speed_r4.py --seeds 0-9 --pairs 4

Development seeds of Tasks 1 and 2 only (fresh seeds of fresh_seeds_reserved.md unused).
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
from jaxcr.benchmarks.registration import run_registration_benchmark

OUT = Path(__file__).parent.parent / "results" / "registration"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0-9", help="development seeds, e.g. 0-9 or 0,3")
    ap.add_argument("--pairs", type=int, default=4, help="forward pairs per scene")
    ap.add_argument("--repeats", type=int, default=1, help="timings per pair and variant")
    ap.add_argument("--scratch", default="/tmp/bench_speed_r4")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="speed_r4", help="output file stem")
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    reg = run_registration_benchmark(
        seeds=parse_seeds(a.seeds),
        frames=a.pairs,
        repeats=a.repeats,
        scratch=a.scratch,
        uncached_reference=True,
    )
    load1 = os.getloadavg()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    ).stdout.split("\n")
    cmd = "python experiments/registration/bench_speed_r4.py " + " ".join(
        sys.argv[1:] if argv is None else argv
    )
    ms = lambda v: f"{1000 * v:.1f}"  # noqa: E731
    now, unc, prev = (
        np.array(reg[k]) for k in ("seconds_now", "seconds_uncached", "seconds_previous")
    )
    md = [
        "# Registration speed, round 4 (issue 18: pairwise RGB-D registration)",
        "",
        f"commit {commit} (modified tracked files: {[d for d in dirty if d] or 'none'}), "
        f"{platform.machine()}, python {platform.python_version()}, {os.cpu_count()} CPUs "
        f"shared with other engineers' jobs; load average {load0[0]:.1f} at start, "
        f"{load1[0]:.1f} at end. Command: `{cmd}`.",
        f"Development seeds {a.seeds} of Tasks 1 and 2 (fresh seeds untouched), "
        f"{reg['pairs']} forward pairs (25 deg apart, 320x240, 8192 source pixels), "
        f"{a.repeats} timing(s) each per variant, the three variants alternating pair by "
        f"pair; compilation apart (now {reg['compile_s']:.1f} s, previous "
        f"{reg['reference_compile_s']:.1f} s).",
        "",
        "- **now**: `PipelineConfig().register` with the per-frame keypoint cache, as in a "
        "run's chain of forward registrations (the source's features were computed when it "
        "was the previous pair's target; each pair computes its target's; a scene's first "
        "pair both).",
        "- **uncached**: the same call with the features computed at every registration "
        "(before this round).",
        "- **previous**: before issue 18 (31765ad projective ICP, no cache).",
        "",
        "| | median ms/pair | IQR ms | p90 ms | median CPU ms/pair (process, all threads) |",
        "|---|---|---|---|---|",
    ]
    cpu = reg["cpu_median_s"]
    for name, key, t in (
        ("now", "now", now),
        ("uncached", "uncached", unc),
        ("previous (31765ad)", "previous", prev),
    ):
        md.append(
            f"| {name} | {ms(np.median(t))} | {ms(np.percentile(t, 25))}-"
            f"{ms(np.percentile(t, 75))} | {ms(np.percentile(t, 90))} | {ms(cpu[key])} |"
        )
    md += [
        "",
        f"Median per-pair ratios: uncached / now {reg['cache_ratio_per_pair']:.2f}x, "
        f"previous / now {reg['median_ratio_per_pair']:.2f}x. Pose of the cached path equal "
        f"to the uncached one (exactly): {reg['uncached_pose_identical']} pairs.",
        "",
        "Pose error against the rendered truth (deg / mm):",
        "",
        "| | rot median / p90 / max | trans median / p90 / max |",
        "|---|---|---|",
    ]
    for name, pre in (("now", ""), ("previous", "previous_")):
        md.append(
            f"| {name} | {reg[pre + 'rot_deg_median']:.4f} / {reg[pre + 'rot_deg_p90']:.4f} / "
            f"{reg[pre + 'rot_deg_max']:.3f} | {reg[pre + 'trans_mm_median']:.3f} / "
            f"{reg[pre + 'trans_mm_p90']:.3f} / {reg[pre + 'trans_mm_max']:.2f} |"
        )
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(
        json.dumps({"command": cmd, "commit": commit, "registration": reg}, indent=1, default=float)
    )
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
