"""Issue 18, pairwise RGB-D registration, round 5: coarse-to-fine source sampling of the
projective ICP (``IcpConfig.coarse_stride``, :func:`jaxcr.registration.projective.
coarse_to_fine_icp`). Per pair, in one process, alternating pair by pair: the current
default (``PipelineConfig().register``, keypoint cache as in a run's forward chain) and the
same call with each ``--variants`` variant: coarse-to-fine ICP (``coarse_stride``,
``coarse_tol_factor``) and/or SIFT on the valid-depth box (``PipelineConfig.keypoint_crop``). Wall and process CPU ms, the
1-min load average, pose errors against the rendered truth for every variant. Writes
experiments/results/registration/<name>.md (+ .json).

    python experiments/registration/bench_speed_r5.py --seeds 0-4 --pairs 4 --variants s4x10,k16,s4x10+k16

Development seeds of Tasks 1 and 2 only (fresh seeds of fresh_seeds_reserved.md unused).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxcr.benchmarks import parse_seeds
from jaxcr.benchmarks.registration import forward_pairs, scene_sim
from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pipeline import PipelineConfig, capture_frame

OUT = Path(__file__).parent.parent / "results" / "registration"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0-4", help="development seeds, e.g. 0-4")
    ap.add_argument("--pairs", type=int, default=4, help="forward pairs per scene")
    ap.add_argument(
        "--variants",
        default="s4x10,k16,s4x10+k16",
        help="comma-separated variants of tokens joined by '+': sSTRIDE[xFACTOR] (IcpConfig "
        "coarse_stride, coarse_tol_factor), kMARGIN (PipelineConfig keypoint_crop; k- None), d (the "
        "default on another random draw of the source pixels: a noise reference)",
    )
    ap.add_argument("--scratch", default="/tmp/bench_speed_r5")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="speed_r5")
    a = ap.parse_args(argv)
    base = PipelineConfig()
    variants = {"now": base}
    redraw, alt = set(), {"now": False}
    for v in a.variants.split(","):
        cfg, desc = base, []
        for tok in v.split("+"):
            if tok.startswith("s"):  # sSTRIDE[xFACTOR]: coarse-to-fine ICP
                stride, _, factor = tok[1:].partition("x")
                icp = dataclasses.replace(
                    cfg.icp, coarse_stride=int(stride), coarse_tol_factor=float(factor or 1)
                )
                cfg = dataclasses.replace(cfg, icp=icp)
                desc.append(f"ICP stride {stride}, tol x{factor or 1}")
            elif tok == "k-":  # SIFT on the whole image (keypoint_crop None)
                cfg = dataclasses.replace(cfg, keypoint_crop=None)
                desc.append("SIFT whole image")
            elif tok.startswith("k"):  # kMARGIN: SIFT on the valid-depth box
                cfg = dataclasses.replace(cfg, keypoint_crop=int(tok[1:]))
                desc.append(f"SIFT crop {tok[1:]} px")
            elif tok == "d":  # another random draw of the 8192 source pixels: noise
                redraw.add(v)
                desc.append("now, another pixel sample (noise reference)")
            else:
                ap.error(f"unknown variant token {tok!r}")
        variants[" + ".join(desc)] = cfg
        alt[" + ".join(desc)] = v in redraw
    root = Path(a.scratch)
    pairs = []
    for task in ("1", "2"):
        for s in parse_seeds(a.seeds):
            sim = scene_sim(task, s, root)
            for k, (fa, fb, truth) in enumerate(forward_pairs(sim, s, a.pairs, 25.0, base)):
                # the same images with another random draw of the sampled source pixels
                fa2, fb2 = (
                    capture_frame(f.rgb, f.depth, sim.K, base, 1000 + s + k + j, f.label)
                    for j, f in enumerate((fa, fb))
                )
                pairs.append((f"task {task} seed {s} pair {k}", fa, fb, sim.K, truth, k, fa2, fb2))
    load0 = os.getloadavg()
    comp = {}
    _, fa, fb, K, truth, k, _, _ = pairs[0]
    for name, cfg in variants.items():
        t0 = time.perf_counter()
        cfg.register(fa, fb, K, truth, k)
        comp[name] = time.perf_counter() - t0
    wall = {n: [] for n in variants}
    cpu = {n: [] for n in variants}
    err = {n: [] for n in variants}
    loads = []
    names = list(variants)
    for i, (_label, fa1, fb1, K, truth, k, fa2, fb2) in enumerate(pairs):
        loads.append(os.getloadavg()[0])
        # alternate, so all variants see the same load; the order rotates pair by pair (the
        # first variant of a pair measured slower in a first run: warm caches favour later
        # ones)
        for name in names[i % len(names) :] + names[: i % len(names)]:
            cfg = variants[name]
            fa, fb = (fa2, fb2) if alt[name] else (fa1, fb1)
            # as in a run's forward chain: the target's features computed here, the
            # source's cached from the previous pair (a scene's first pair: both)
            fb.features.clear()
            if k == 0:
                fa.features.clear()
            c0, t0 = time.process_time(), time.perf_counter()
            res = cfg.register(fa, fb, K, truth, k)
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
            r, t = pose_error(res.T, truth)
            err[name].append((r, 1000 * t))
    load1 = os.getloadavg()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    dirty = [
        d
        for d in subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
        ).stdout.split("\n")
        if d
    ]
    cmd = "python experiments/registration/bench_speed_r5.py " + " ".join(
        sys.argv[1:] if argv is None else argv
    )
    now = np.array(wall["now"])
    md = [
        "# Registration speed, round 5: coarse-to-fine ICP, SIFT crop (issue 18)",
        "",
        f"commit {commit} (modified tracked files: {dirty or 'none'}), {platform.machine()}, "
        f"python {platform.python_version()}, {os.cpu_count()} CPUs shared with other "
        f"engineers' jobs; 1-min load average {load0[0]:.1f} at start, {load1[0]:.1f} at end "
        f"(per-pair min-max {min(loads):.1f}-{max(loads):.1f}). Command: `{cmd}`.",
        f"Development seeds {a.seeds} of Tasks 1 and 2, {len(pairs)} forward pairs (25 deg "
        "apart, 320x240, 8192 source pixels), the variants alternating pair by pair; "
        "compilation apart ("
        + ", ".join(f"{n} {v:.1f} s" for n, v in comp.items())
        + "). Features as in a run's forward chain (each pair computes its target's SIFT).",
        "",
        "| variant | median ms/pair | IQR ms | p90 ms | median CPU ms/pair | median per-pair "
        "ratio now / variant |",
        "|---|---|---|---|---|---|",
    ]
    for name in variants:
        t = 1000 * np.array(wall[name])
        c = 1000 * np.array(cpu[name])
        md.append(
            f"| {name} | {np.median(t):.1f} | {np.percentile(t, 25):.1f}-"
            f"{np.percentile(t, 75):.1f} | {np.percentile(t, 90):.1f} | {np.median(c):.1f} | "
            f"{np.median(now / np.array(wall[name])):.2f} |"
        )
    md += [
        "",
        "Pose error against the rendered truth (deg / mm), all pairs:",
        "",
        "| variant | rot median / p90 / max | trans median / p90 / max |",
        "|---|---|---|",
    ]
    for name in variants:
        e = np.array(err[name])
        md.append(
            f"| {name} | {np.median(e[:, 0]):.4f} / {np.percentile(e[:, 0], 90):.4f} / "
            f"{e[:, 0].max():.3f} | {np.median(e[:, 1]):.3f} / "
            f"{np.percentile(e[:, 1], 90):.3f} / {e[:, 1].max():.2f} |"
        )
    e0 = np.array(err["now"])
    md += ["", "Per-pair difference from now (variant - now), median / max |.|:", ""]
    for name in list(variants)[1:]:
        d = np.array(err[name]) - e0
        md.append(
            f"- {name}: rot {np.median(d[:, 0]):+.4f} / {np.abs(d[:, 0]).max():.4f} deg, "
            f"trans {np.median(d[:, 1]):+.3f} / {np.abs(d[:, 1]).max():.3f} mm"
        )
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(
        json.dumps(
            {
                "command": cmd,
                "commit": commit,
                "labels": [p[0] for p in pairs],
                "wall_s": wall,
                "cpu_s": cpu,
                "error_deg_mm": err,
                "compile_s": comp,
                "load": [load0[0], load1[0]],
                "pair_loads": loads,
            },
            indent=1,
            default=float,
        )
    )
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
