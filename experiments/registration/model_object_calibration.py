"""Issue 6: why the pose graph misses 2 mm on some scenes, and what calibrating the edge
covariances does (jaxcr.registration.pose_graph.calibrate_edges).

For each task and scene seed: build the model once with the pipeline (the graph -- ring
edges, closure, extra registrations, their ICP information -- is cached as a pickle), then
solve the same graph with different weightings and compare the worst camera pose error
(frame O = the last ring view, as model_object_tasks.md):

- chained (no global step), Algorithm 2 (the paper's), the pose graph with the stated ICP
  information (the previous default) and calibrated (the new default);
- diagnostics using the truth (not estimators): every edge's information rescaled so its
  own error has e^T Omega e = 6 ("oracle per-edge calibration"), the covariance model
  a Omega^-1 + floor fitted by maximum likelihood to the true edge errors ("oracle
  model"), ring edges only, and the seam edges (closure and extras across it) dropped;
- the loop test of the ring alone (closure against the chain) with calibrated covariances,
  the seam edges' errors against their stated sd.

    python experiments/registration/model_object_calibration.py [--tasks 1 2] [--seeds 0 1 2 3 4]
        [--cache DIR]

Writes experiments/results/registration/model_object_calibration.md.
"""

from __future__ import annotations

import argparse
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pose_graph import (
    GraphEdge,
    calibrate_edges,
    consistency_chi2,
    graph_linearisation,
    optimize_pose_graph,
)

OUT = Path(__file__).parent.parent / "results" / "registration"


def build(task, seed, cache):
    """The graph of one scene (pickled in ``cache``)."""
    path = Path(cache) / f"t{task}_s{seed}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    from jaxcr.registration.evaluation import truth_poses
    from jaxcr.registration.pipeline import PipelineConfig, build_model, graph_edges
    from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

    scene = generate_task(f"{cache}/scene_t{task}_s{seed}", task, seed)
    sim = RgbdSimulator(scene, seed=seed)
    result = build_model(sim, PipelineConfig(), seed=seed)
    m = len(result.ring)
    alle = [(k, (k + 1) % m, e) for k, e in enumerate(result.edges)] + result.extra
    ge = graph_edges(result, alle, "information")
    d = dict(
        m=m,
        truth=truth_poses(result),
        initial=result.alg2_result.initial,
        alg2=result.alg2_result.poses,
        edges=[(g.i, g.j, g.Z, g.info) for g in ge],
        n_ring=m,
        runs=len(result.runs),
    )
    path.write_bytes(pickle.dumps(d))
    return d


def _res(Ti, Tj, Z):
    E = np.linalg.inv(Tj) @ Ti @ np.linalg.inv(Z)
    return np.r_[E[:3, 3], Rotation.from_matrix(E[:3, :3]).as_rotvec()]


def _worst(P, truth):
    e = np.array([pose_error(a, b) for a, b in zip(P, truth, strict=True)])
    return float(e[:, 0].max()), 1000 * float(e[:, 1].max())


def _solve(d, infos, keep=None, calibrate=False):
    edges = [GraphEdge(i, j, Z, W) for (i, j, Z, _), W in zip(d["edges"], infos, strict=True)]
    if keep is not None:
        edges = [e for e, k in zip(edges, keep, strict=True) if k]
    return optimize_pose_graph(d["alg2"], edges, anchor=-1, calibrate=calibrate)


def _oracle_model(infos, errs):
    """ML fit of a Omega^-1 + diag(ft, fr) to the true edge errors (diagnostic only)."""
    Q = [np.linalg.inv(W) for W in infos]

    def nll(p):
        a, ft, fr = np.exp(p)
        s = 0.0
        for q, r in zip(Q, errs, strict=True):
            C = a * q + np.diag([ft] * 3 + [fr] * 3)
            s += np.linalg.slogdet(C)[1] + r @ np.linalg.solve(C, r)
        return s

    p = minimize(nll, np.log([10, 1e-8, 1e-6]), method="Nelder-Mead", options=dict(maxiter=3000)).x
    a, ft, fr = np.exp(p)
    return [np.linalg.inv(a * q + np.diag([ft] * 3 + [fr] * 3)) for q in Q]


def scene(task, seed, cache):
    d = build(task, seed, cache)
    T, m = d["truth"], d["m"]
    infos = [e[3] for e in d["edges"]]
    errs = [_res(T[i], T[j], Z) for (i, j, Z, _) in d["edges"]]
    chi2 = np.array([r @ W @ r for r, W in zip(errs, infos, strict=True)])
    rows = {"chained": _worst(d["initial"], T), "Algorithm 2": _worst(d["alg2"], T)}
    stated = _solve(d, infos)
    rows["pose graph, stated ICP information"] = _worst(stated.poses, T)
    _solve(d, infos, calibrate=True)  # compile
    t0 = time.perf_counter()
    cal = _solve(d, infos, calibrate=True)
    t_cal = time.perf_counter() - t0
    rows["pose graph, calibrated (default)"] = _worst(cal.poses, T)
    rows["[truth] per-edge information x 6 / e^T Omega e"] = _worst(
        _solve(d, [W * 6 / c for W, c in zip(infos, chi2, strict=True)]).poses, T
    )
    rows["[truth] a Omega^-1 + floor fitted to the true errors"] = _worst(
        _solve(d, _oracle_model(infos, errs)).poses, T
    )
    n = len(infos)
    rows["ring edges only, stated information"] = _worst(
        _solve(d, infos, keep=[k < m for k in range(n)]).poses, T
    )
    seam = [k for k, (i, j, _, _) in enumerate(d["edges"]) if i > j] if d["runs"] == 1 else []
    if seam:
        rows["[truth] seam edges dropped (closure + extras across it)"] = _worst(
            _solve(d, infos, keep=[k not in seam for k in range(n)]).poses, T
        )
    # loop test of the ring alone with the calibrated covariances
    edges = [GraphEdge(i, j, Z, W) for (i, j, Z, W) in d["edges"]]
    calib, c = calibrate_edges(stated.poses, edges, -1)
    loop, dof = consistency_chi2(cal.poses, calib[:m], -1)
    # View-shared errors: how much of the (calibrated) true errors of the edges at the
    # worst view one shift of that view's pose explains (~6 / (6 x edges) by chance). Such
    # an error moves the view consistently in all its edges: no cycle sees it.
    err_pose = [pose_error(a, b)[1] for a, b in zip(cal.poses, T, strict=True)]
    k = int(np.argmax(err_pose))
    rt, Jt = graph_linearisation(T, calib, -1)
    inc = [n for n, e in enumerate(calib) if k in (e.i, e.j)]
    Lw = [np.linalg.cholesky(calib[n].info) for n in inc]
    rw = np.concatenate([L.T @ rt[6 * n : 6 * n + 6] for L, n in zip(Lw, inc, strict=True)])
    Jw = np.concatenate(
        [L.T @ Jt[6 * n : 6 * n + 6, 6 * k : 6 * k + 6] for L, n in zip(Lw, inc, strict=True)]
    )
    delta = np.linalg.lstsq(Jw, -rw, rcond=None)[0]
    explained = 1 - np.sum((rw + Jw @ delta) ** 2) / np.sum(rw**2)
    lines = [
        f"## Task {task}, seed {seed}",
        "",
        f"{m} ring views, {n} edges ({n - m} extra). Calibration: a = {c.scale:.2f}, floor "
        f"{1000 * np.sqrt(c.floor_t):.3f} mm / {np.degrees(np.sqrt(c.floor_r)):.4f} deg "
        f"(redundancy {c.redundancy:.0f}); calibrated solve incl. the stated one "
        f"{1000 * t_cal:.0f} ms (warm). Edge errors against the truth: e^T Omega e median "
        f"{np.median(chi2):.0f} stated (chi^2_6 median 5.3). Loop test of the ring alone, "
        f"calibrated: chi^2 {loop:.1f} / {dof} dof, p = {chi2_dist.sf(loop, dof):.3f}. "
        f"Worst pose (calibrated): view {k}, {1000 * err_pose[k]:.2f} mm; one shift of that "
        f"view's pose by {1000 * np.linalg.norm(delta[:3]):.2f} mm explains "
        f"{100 * explained:.0f} % of the calibrated chi^2 of its {len(inc)} edges' true "
        f"errors ({100 / len(inc):.0f} % expected by chance).",
        "",
        "| global step | worst deg | worst mm |",
        "|---|---|---|",
        *[f"| {k} | {v[0]:.3f} | {v[1]:.2f} |" for k, v in rows.items()],
        "",
    ]
    for k in [m - 1, *seam[1:]] if seam else [m - 1]:
        i, j, _, W = d["edges"][k]
        sd = np.sqrt(np.diag(np.linalg.pinv(W)))
        lines.append(
            f"- edge {i} -> {j}{' (closure)' if k == m - 1 else ''}: error "
            f"{1000 * np.linalg.norm(errs[k][:3]):.2f} mm / "
            f"{np.degrees(np.linalg.norm(errs[k][3:])):.3f} deg; stated sd (max axis) "
            f"{1000 * sd[:3].max():.2f} mm / {np.degrees(sd[3:].max()):.3f} deg; e^T Omega e "
            f"{chi2[k]:.0f}"
        )
    return lines + [""], rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--tasks", nargs="+", default=["1", "2"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    ap.add_argument("--cache", default="/tmp/model_object_calibration")
    args = ap.parse_args()
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    load0 = os.getloadavg()[0]
    body, table = [], {}
    for task in args.tasks:
        for seed in args.seeds:
            lines, rows = scene(task, seed, args.cache)
            body += lines
            table[(task, seed)] = rows
            print("\n".join(lines), flush=True)
    keys = list(next(iter(table.values())).keys())
    head = "| global step | " + " | ".join(f"T{t} s{s}" for t, s in table) + " | mean | max |"
    summ = [head, "|---" * (len(table) + 3) + "|"]
    for k in keys:
        v = [table[ts][k][1] if k in table[ts] else np.nan for ts in table]
        summ.append(
            f"| {k} | "
            + " | ".join(f"{x:.2f}" for x in v)
            + f" | {np.nanmean(v):.2f} | {np.nanmax(v):.2f} |"
        )
    cmd = "python experiments/registration/model_object_calibration.py " + " ".join(sys.argv[1:])
    md = [
        "# Issue 6: pose-graph edge covariances, stated vs calibrated, against the truth",
        "",
        f"commit {commit}; command: `{cmd}`; load {load0:.1f} at start. Worst camera pose "
        "error (mm) over the ring, frame O = the last ring view. Rows marked [truth] use the "
        "ground truth and are diagnostics, not estimators. 'seam edges dropped' only for "
        "Task 1 (one route; nan for Task 2). The graphs come from the --cache folder "
        "(written by build_model on first use; the ones used here were written at d5b2258 "
        "in the same format, the registrations are unchanged since, and the end-to-end "
        "runs in model_object_tasks*.md reproduce the 'stated' and 'calibrated' rows to "
        "0.01 mm).",
        "",
        *summ,
        "",
        *body,
    ]
    (OUT / "model_object_calibration.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
