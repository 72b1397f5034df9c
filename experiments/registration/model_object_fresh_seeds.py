"""Object-modelling pose errors on fresh seeds (issue 17 item 10). Writes
experiments/results/registration/model_object_fresh_seeds.md (+ .json).

    python experiments/registration/model_object_fresh_seeds.py --seeds 300-304 --tasks 2

The seeds (scene and sensor-noise seed, as experiments/registration/model_object_tasks.py --seed) were
reserved before development (experiments/results/segmentation/fresh_seeds_reserved.md: 300-305;
development 5-9) and are run once with the pipeline defaults (pose graph, calibrated edge
weights). For every run: the worst and median camera pose error after global optimisation
over all views (ring views and those left out of the ring; since 2026-12-02 the latter are
nodes of the pose graph, ``PipelineConfig.outside_links``, before that chained from the
nearest ring view), in frame O = the last ring view, with the view that is worst.

    python experiments/registration/model_object_fresh_seeds.py --seeds 320-325 --tasks 1 2 \
        --name model_object_fresh_seeds_320_325

``--set FIELD=VALUE`` overrides a PipelineConfig field (Python literal; ``icp.FIELD`` a field of
its IcpConfig), for before/after comparisons on the development seeds (fresh seeds run with
the defaults):

    python experiments/registration/model_object_fresh_seeds.py --seeds 0-9 --tasks 1 \
        --set photometric_scale_match=False --name dev_before

Records are appended to --log (JSON lines) as each run completes, so a stopped run resumes;
the report is written from the completed records and says how many there are.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np  # noqa: E402

from jaxcr.registration.evaluation import evaluate_result  # noqa: E402
from jaxcr.registration.pipeline import PipelineConfig, build_model  # noqa: E402
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "registration"
GOAL_MM, GOAL_DEG = 2.0, 1.0  # issue 6's done-when targets


def run_one(
    task: str, seed: int, scratch: Path, overrides: dict | None = None, capture_frames: int = 1
) -> dict:
    scene = generate_task(scratch / f"task{task}_seed{seed}", task, seed)
    sim = RgbdSimulator(scene, seed=seed, capture_frames=capture_frames)
    t0 = time.perf_counter()
    cfg = dataclasses.replace(PipelineConfig(), **(overrides or {}))
    result = build_model(sim, cfg, seed=seed)
    wall = time.perf_counter() - t0
    rec = {
        "task": task,
        "seed": seed,
        "wall_s": wall,
        "notes": list(result.notes),
        "capture_frames": capture_frames,
    }
    if result.global_result is None:
        rec["status"] = "no global result"
        return rec
    ev = evaluate_result(sim, result, seed=seed)
    views = []
    for b, a in zip(ev["views"]["before"], ev["views"]["after"], strict=True):
        views.append(
            {
                "run": a["run"],
                "index": a["index"],
                "ring_position": a["ring_position"],
                "rot_deg": a["rot_deg"],
                "trans_mm": 1000 * a["trans_m"],
                "rot_before_deg": b["rot_deg"],
                "trans_before_mm": 1000 * b["trans_m"],
            }
        )
    # the anchor (frame O) has zero error by construction: statistics over the others
    others = [v for v in views if v["ring_position"] != len(result.ring) - 1]
    t = np.array([v["trans_mm"] for v in others])
    r = np.array([v["rot_deg"] for v in others])
    w = others[int(np.argmax(t))]
    rec.update(
        status="ok",
        views=views,
        n_views=len(views),
        n_outside_ring=sum(v["ring_position"] is None for v in views),
        worst_trans_mm=float(t.max()),
        worst_view=f"run {w['run']} capture {w['index']} (ring position {w['ring_position']})",
        median_trans_mm=float(np.median(t)),
        worst_rot_deg=float(r.max()),
        median_rot_deg=float(np.median(r)),
        worst_trans_before_mm=float(max(v["trans_before_mm"] for v in others)),
        outside_worst_trans_mm=max(
            (v["trans_mm"] for v in views if v["ring_position"] is None), default=None
        ),
        alg2_worst_trans_mm=1000 * float(ev["alg2"]["pose"]["max_trans_m"])
        if "alg2" in ev
        else None,
    )
    return rec


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="300-304", help="first-last (inclusive)")
    ap.add_argument("--tasks", nargs="+", default=["2", "1"])
    ap.add_argument("--scratch", default="/tmp/model_object_fresh")
    ap.add_argument("--log", default=None, help="JSON lines (default: SCRATCH/records.jsonl)")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument(
        "--name", default="model_object_fresh_seeds", help="report file stem (.md, .json)"
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a PipelineConfig field (Python literal); repeatable",
    )
    ap.add_argument(
        "--capture-frames",
        type=int,
        default=1,
        help="depth frames averaged per capture (RgbdSimulator capture_frames; 1 = the "
        "paper's single frame, the default)",
    )
    a = ap.parse_args()
    overrides = {}
    icp_overrides = {}
    for item in a.set:
        key, _, val = item.partition("=")
        try:
            value = ast.literal_eval(val)
        except (ValueError, SyntaxError):
            value = val
        if key.startswith("icp."):  # a field of PipelineConfig.icp (IcpConfig)
            if key[4:] not in {f.name for f in dataclasses.fields(PipelineConfig().icp)}:
                ap.error(f"--set: IcpConfig has no field {key[4:]!r}")
            icp_overrides[key[4:]] = value
            continue
        if key not in {f.name for f in dataclasses.fields(PipelineConfig)}:
            ap.error(f"--set: PipelineConfig has no field {key!r}")
        overrides[key] = value
    if icp_overrides:
        overrides["icp"] = dataclasses.replace(PipelineConfig().icp, **icp_overrides)
    s0, s1 = (int(v) for v in a.seeds.split("-"))
    scratch = Path(a.scratch)
    scratch.mkdir(parents=True, exist_ok=True)
    log = Path(a.log) if a.log else scratch / "records.jsonl"
    done = {}
    if log.exists():
        for line in log.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[(r["task"], r["seed"])] = r
    load0 = os.getloadavg()
    if not a.report_only:
        for seed in range(s0, s1 + 1):
            for task in a.tasks:
                if (task, seed) in done:
                    continue
                r = run_one(task, seed, scratch, overrides, a.capture_frames)
                with open(log, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
                done[(task, seed)] = r
                print(
                    f"task {task} seed {seed}: {r['status']} worst "
                    f"{r.get('worst_trans_mm', float('nan')):.2f} mm ({r['wall_s']:.0f} s)",
                    flush=True,
                )
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    cmd = "python experiments/registration/model_object_fresh_seeds.py " + " ".join(sys.argv[1:])
    md = [
        "# Object modelling on fresh seeds (issue 17 item 10)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}; command: "
        f"`{cmd}`; load average at start {load0[0]:.1f}."
        + (f" PipelineConfig overrides: {a.set}." if overrides else "")
        + f" Depth frames per capture: {a.capture_frames}.",
        "",
        f"Seeds {s0}-{s1} reserved before development (fresh_seeds_reserved.md; development "
        "seeds 0-9, see that file). Pipeline defaults (pose graph, calibrated edge "
        "weights). Errors of every view's camera pose after global optimisation against the "
        "truth, in frame O = the last ring view (the anchor, error 0 by construction, is left "
        "out of the statistics); views outside the ring are pose-graph nodes with registrations to "
        "several ring views (PipelineConfig.outside_links; 'outside mm' = their worst). "
        f"Goal (issue 6): <= {GOAL_DEG:g} deg and <= {GOAL_MM:g} mm. Previous audit on fresh "
        "seeds: worst 2.06 mm (task 2, view 0); seeds 320-325: 10 of 12 runs, worst 2.30 mm (task 1 seed 324, ring position 0).",
        "",
        "| task | seed | views (outside ring) | worst mm (view) | median mm | worst deg | median deg | outside mm | chained worst mm | Alg. 2 worst mm | goal met | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    recs = [done[k] for k in sorted(done, key=lambda k: (k[0], k[1])) if s0 <= k[1] <= s1]
    for r in recs:
        if r["status"] != "ok":
            md.append(
                f"| {r['task']} | {r['seed']} | {r['status']}: {'; '.join(r['notes'])} | | | | | | | | no | {r['wall_s']:.0f} |"
            )
            continue
        met = r["worst_trans_mm"] <= GOAL_MM and r["worst_rot_deg"] <= GOAL_DEG
        a2 = "" if r["alg2_worst_trans_mm"] is None else f"{r['alg2_worst_trans_mm']:.2f}"
        o = r.get("outside_worst_trans_mm")
        ow = "" if o is None else f"{o:.2f}"
        md.append(
            f"| {r['task']} | {r['seed']} | {r['n_views']} ({r['n_outside_ring']}) | "
            f"{r['worst_trans_mm']:.2f} ({r['worst_view']}) | {r['median_trans_mm']:.2f} | "
            f"{r['worst_rot_deg']:.3f} | {r['median_rot_deg']:.3f} | {ow} | "
            f"{r['worst_trans_before_mm']:.2f} | {a2} | {'yes' if met else 'NO'} | {r['wall_s']:.0f} |"
        )
    ok = [r for r in recs if r["status"] == "ok"]
    if ok:
        worst = max(ok, key=lambda r: r["worst_trans_mm"])
        md += [
            "",
            f"{len(recs)} runs completed ({len(ok)} with a closed loop). Worst view over all: "
            f"{worst['worst_trans_mm']:.2f} mm (task {worst['task']} seed {worst['seed']}, "
            f"{worst['worst_view']}); median over runs of the per-run median "
            f"{np.median([r['median_trans_mm'] for r in ok]):.2f} mm; goal met in "
            f"{sum(r['worst_trans_mm'] <= GOAL_MM and r['worst_rot_deg'] <= GOAL_DEG for r in ok)}"
            f" of {len(ok)} runs.",
        ]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(
        json.dumps({"command": cmd, "commit": commit, "runs": recs}, indent=1)
    )
    print("\n".join(md))


if __name__ == "__main__":
    main()
