"""Issue 17 item 10: the edges of a far view left out of the ring, raw or raw + denoised.

Development seeds only (fresh_seeds_reserved.md: 0-9). Each (task, seed) is built once with
the pipeline as it was before this change (``outside_far_mode="raw"``) and pickled
(``--record DIR``: ``res_t{task}_s{seed}.pkl``, (ModelResult, K)); then

1. every registration whose source is the run's first capture and more than
   ``far_source_ratio`` farther from the scene than its target (ring edges, gap edges and
   the outside-ring edges) is registered again from its pipeline estimate with the raw
   and with the denoised source points, and the error of each and of their equal-weight
   mean against the truth is recorded ('links');
2. the global stage (:func:`jaxcr.registration.pipeline.optimize_pose_graph_stage`) is run
   again on the recorded runs and Algorithm 2 result with ``outside_far_mode`` "raw" and
   "both", and every view's pose error after the global optimisation is recorded ('graph').

    python experiments/registration/model_object_outside_both.py --record /tmp/obj27/rec \
        --cases 1:0 1:1 1:2 1:3 1:4 1:5 1:6 1:7 1:8 1:9 --jsonl /tmp/obj27/ob.jsonl
    python experiments/registration/model_object_outside_both.py --jsonl /tmp/obj27/ob.jsonl \
        --report-only

Writes experiments/results/registration/model_object_outside_both.md (+ .json).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import pickle
import subprocess
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np  # noqa: E402

from jaxcr.registration.evaluation import view_errors  # noqa: E402
from jaxcr.registration.metrics import pose_error  # noqa: E402
from jaxcr.registration.pairwise import RegistrationFailed, median_depth  # noqa: E402
from jaxcr.registration.pipeline import (  # noqa: E402
    PipelineConfig,
    _capture,
    build_model,
    optimize_pose_graph_stage,
)
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "registration"
BEFORE = PipelineConfig(outside_far_mode="raw")


def recorded(task: str, seed: int, record: Path):
    """(ModelResult, K) of the pipeline before this change on (task, seed), built once."""
    f = record / f"res_t{task}_s{seed}.pkl"
    if f.exists():
        with open(f, "rb") as fh:
            return pickle.load(fh)
    scene = generate_task(record / f"scenes/task{task}_seed{seed}", task, seed)
    sim = RgbdSimulator(scene, seed=seed)
    res = build_model(sim, BEFORE, seed=seed)
    tmp = f.with_suffix(".tmp")
    with open(tmp, "wb") as fh:
        pickle.dump((res, np.asarray(sim.K)), fh)
    tmp.rename(f)
    return res, np.asarray(sim.K)


def chordal_mean(Ts: list[np.ndarray]) -> np.ndarray:
    """Equal-weight mean of poses: mean translation, the mean rotation matrix projected on
    SO(3) (SVD)."""
    R = np.mean([T[:3, :3] for T in Ts], axis=0)
    U, _, Vt = np.linalg.svd(R)
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    out[:3, 3] = np.mean([T[:3, 3] for T in Ts], axis=0)
    return out


def truth(res, nodes):
    anchor = _capture(res.runs, res.ring[-1]).T_true
    return [np.linalg.inv(anchor) @ _capture(res.runs, k).T_true for k in nodes]


def links(task: str, seed: int, res, K) -> list[dict]:
    cfg = BEFORE
    nodes = res.ring + res.outside
    m = len(res.ring)
    true = truth(res, nodes)
    ring_edges = [(k, (k + 1) % m, e) for k, e in enumerate(res.edges)]
    rows, seen = [], set()
    for n, (i, j, pair) in enumerate(ring_edges + list(res.extra) + list(res.outside_edges)):
        fa, fb = _capture(res.runs, nodes[i]).frame, _capture(res.runs, nodes[j]).frame
        if (
            pair.n_matches == 0
            or nodes[i][1] != 0
            or not median_depth(fa) > cfg.far_source_ratio * median_depth(fb)
            or (i, j) in seen
        ):
            continue
        seen.add((i, j))
        T_true = np.linalg.inv(true[j]) @ true[i]
        row = {"task": task, "seed": seed, "i": i, "j": j, "outside": i >= m}
        Ts = {}
        for name in ("plane", "raw"):
            try:
                p = dataclasses.replace(cfg, geometric_points=name).register(
                    fa, fb, K, pair.T, seed + 4000 + n, prior_gate=(3.0, 0.02)
                )
            except RegistrationFailed:
                continue
            Ts[name] = p.T
            row[name] = 1000 * pose_error(p.T, T_true)[1]
        if len(Ts) == 2:
            row["mean"] = 1000 * pose_error(chordal_mean(list(Ts.values())), T_true)[1]
        rows.append(row)
    return rows


def graph(task: str, seed: int, res, K) -> dict:
    row = {"task": task, "seed": seed}
    for mode in ("raw", "both"):
        t0 = time.process_time()
        r = optimize_pose_graph_stage(
            copy.copy(res), K, PipelineConfig(outside_far_mode=mode), seed=seed
        )
        v = view_errors(r, r.global_result.poses, r.outside_poses)
        row[mode] = {
            "trans_mm": [1000 * x["trans_m"] for x in v],
            "rot_deg": [x["rot_deg"] for x in v],
            "cpu_s": time.process_time() - t0,
        }
        row["ring_position"] = [x["ring_position"] for x in v]
        row["anchor"] = len(r.ring) - 1
    return row


def report(recs: list[dict], out: Path, cmd: str) -> None:
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    L = [r for r in recs if r["kind"] == "link"]
    G = sorted((r for r in recs if r["kind"] == "graph"), key=lambda r: (r["task"], r["seed"]))
    md = [
        "# Far views left out of the ring: raw or raw + denoised edges (issue 17 item 10)",
        "",
        f"commit {commit} (script), development seeds only; command: `{cmd}`.",
        "",
        "## 1. Registrations of a run's first capture to views nearer the object (depth ratio "
        "> far_source_ratio), from their pipeline estimates (error against the truth)",
        "",
        "| | n | mean mm | RMS mm | max mm |",
        "|---|---|---|---|---|",
    ]
    groups = [(t, o) for t in sorted({r["task"] for r in L}) for o in (False, True)]
    for t, o in groups:
        lab = f"task {t}, {'outside-ring view' if o else 'ring view'}"
        rows = [r for r in L if "mean" in r and r["task"] == t and r["outside"] == o]
        for k in ("raw", "plane", "mean"):
            v = np.array([r[k] for r in rows])
            if len(v):
                md.append(
                    f"| {lab}: {k} | {len(v)} | {v.mean():.2f} | "
                    f"{np.sqrt(np.mean(v**2)):.2f} | {v.max():.2f} |"
                )
    md += [
        "",
        "## 2. Every view after the global stage, outside_far_mode raw -> both",
        "",
        "| task | seed | views (outside) | worst mm raw -> both | outside views mm raw -> "
        "both | worst deg raw -> both | CPU s raw / both |",
        "|---|---|---|---|---|---|---|",
    ]
    diffs = []
    worst = {"raw": [], "both": []}
    for r in G:
        idx = [k for k, p in enumerate(r["ring_position"]) if p != r["anchor"]]
        out_idx = [k for k, p in enumerate(r["ring_position"]) if p is None]
        t = {m: np.array(r[m]["trans_mm"]) for m in ("raw", "both")}
        d = {m: np.array(r[m]["rot_deg"]) for m in ("raw", "both")}
        for m in t:
            worst[m].append(t[m][idx].max())
        diffs += list(t["both"][idx] - t["raw"][idx])
        o = " ; ".join(f"{t['raw'][k]:.2f} -> {t['both'][k]:.2f}" for k in out_idx)
        md.append(
            f"| {r['task']} | {r['seed']} | {len(idx) + 1} ({len(out_idx)}) | "
            f"{t['raw'][idx].max():.2f} -> {t['both'][idx].max():.2f} | {o} | "
            f"{d['raw'][idx].max():.3f} -> {d['both'][idx].max():.3f} | "
            f"{r['raw']['cpu_s']:.1f} / {r['both']['cpu_s']:.1f} |"
        )
    if G:
        diffs = np.array(diffs)
        for task in sorted({r["task"] for r in G}):
            w = {
                m: np.array([x for x, r in zip(worst[m], G, strict=True) if r["task"] == task])
                for m in worst
            }
            md.append("")
            md.append(
                f"Task {task}: worst view per run, mean {w['raw'].mean():.2f} -> "
                f"{w['both'].mean():.2f} mm, max {w['raw'].max():.2f} -> {w['both'].max():.2f} "
                f"mm over {len(w['raw'])} runs."
            )
        md.append(
            f"Every view (anchor excluded, {len(diffs)}): changed by more than 0.05 mm in "
            f"{int(np.sum(np.abs(diffs) > 0.05))}; largest increase {diffs.max():.2f} mm, "
            f"largest decrease {-diffs.min():.2f} mm."
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / "model_object_outside_both.md").write_text("\n".join(md) + "\n")
    (out / "model_object_outside_both.json").write_text(
        json.dumps({"command": cmd, "commit": commit, "records": recs}, indent=1)
    )
    print("\n".join(md))


def case_args(out: Path) -> argparse.Namespace:
    """The command line of this script and of the scripts that analyse its recorded runs:
    ``--record DIR`` (the pickled runs), ``--cases TASK:SEED ...``, ``--jsonl F`` (records,
    appended), ``--report-only``, ``--out DIR`` (default ``out``)."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--record", default="/tmp/model_object_outside_both")
    ap.add_argument("--cases", nargs="+", default=[f"1:{s}" for s in range(10)])
    ap.add_argument("--jsonl", required=True, help="records, appended (JSON lines)")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--out", default=str(out))
    return ap.parse_args()


def read_records(jsonl: Path) -> list[dict]:
    """The records of a ``--jsonl`` file (one JSON object per non-empty line)."""
    return [json.loads(x) for x in jsonl.read_text().splitlines() if x.strip()]


def main() -> None:
    a = case_args(OUT)
    jl = Path(a.jsonl)
    if not a.report_only:
        record = Path(a.record)
        record.mkdir(parents=True, exist_ok=True)
        for case in a.cases:
            task, seed = case.split(":")
            res, K = recorded(task, int(seed), record)
            rows = [{"kind": "link", **r} for r in links(task, int(seed), res, K)]
            rows.append({"kind": "graph", **graph(task, int(seed), res, K)})
            with open(jl, "a") as fh:
                for r in rows:
                    fh.write(json.dumps(r) + "\n")
            print(f"{case}: {len(rows) - 1} far links", flush=True)
        return
    recs = read_records(jl)
    cmd = (
        "python experiments/registration/model_object_outside_both.py --record REC --cases "
        "1:0 ... 1:9 2:0 ... 2:9 --jsonl J (several processes), then --jsonl J --report-only"
    )
    report(recs, Path(a.out), cmd)


if __name__ == "__main__":
    main()
