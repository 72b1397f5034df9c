"""Numbers for the report of a modelling run: Table I (images, Delta-s, planning time),
Fig. 13 statistics before/after Algorithm 2, pose errors against ground truth and the
model-to-truth surface distance."""

from __future__ import annotations

import numpy as np

from jaxcr.registration.clouds import Cloud, voxel_downsample
from jaxcr.registration.metrics import knn_mean_distance, neighbour_counts, pose_error
from jaxcr.registration.pipeline import ModelResult, _capture


def model_cloud(
    result: ModelResult, poses: list[np.ndarray], voxel: float = 0.002, with_views: bool = False
):
    """All ring clouds in frame O (each down-sampled to ``voxel`` first, then concatenated
    without merging, so overlaps that do not coincide stay visible to the Fig. 13 stats).
    The point order depends only on the views, not on ``poses``, so models built with
    different poses correspond point by point. With ``with_views`` also returns the ring
    position (n,) of each point's view."""
    parts = []
    for key, P in zip(result.ring, poses, strict=True):
        parts.append(voxel_downsample(_capture(result.runs, key).frame.cloud, voxel).transformed(P))
    cloud = Cloud(
        *(np.concatenate([getattr(p, k) for p in parts]) for k in ("points", "colours", "normals"))
    )
    if not with_views:
        return cloud
    return cloud, np.concatenate([np.full(len(p), j) for j, p in enumerate(parts)])


def truth_poses(result: ModelResult) -> list[np.ndarray]:
    """Ground-truth T_O,i (frame O = the last ring view, as for the estimates)."""
    anchor = _capture(result.runs, result.ring[-1]).T_true
    return [np.linalg.inv(anchor) @ _capture(result.runs, k).T_true for k in result.ring]


def seam_overlap(
    result: ModelResult, truth: list[np.ndarray], voxel: float = 0.002, radius: float = 0.004
) -> tuple[list[Cloud], np.ndarray]:
    """The loop-closure seam: the first and last ring views (each down-sampled to ``voxel``,
    camera frames) and a mask over their concatenated points of those within ``radius`` (m)
    of the other view under the true poses (a fixed point set for every set of poses).
    Before Algorithm 2 the whole loop drift sits between these two views; every other
    neighbour pair is as consistent as its pairwise registration."""
    from scipy.spatial import cKDTree

    views = [
        voxel_downsample(_capture(result.runs, result.ring[j]).frame.cloud, voxel) for j in (0, -1)
    ]
    a, b = (v.transformed(truth[j]).points for v, j in zip(views, (0, -1), strict=True))
    oa = cKDTree(b).query(a)[0] < radius
    ob = cKDTree(a).query(b)[0] < radius
    return views, np.concatenate([oa, ob])


def pose_errors(result: ModelResult, poses: list[np.ndarray]) -> dict:
    """Rotation (deg) / translation (m) errors of T_O,i against the truth expressed in the
    frame of the anchor view (O = the last ring view, paper eq. 1)."""
    anchor = _capture(result.runs, result.ring[-1]).T_true
    rot, tra = [], []
    for key, P in zip(result.ring, poses, strict=True):
        truth = np.linalg.inv(anchor) @ _capture(result.runs, key).T_true
        r, t = pose_error(P, truth)
        rot.append(r)
        tra.append(t)
    return {
        "rot_deg": rot,
        "trans_m": tra,
        "max_rot_deg": max(rot),
        "max_trans_m": max(tra),
        "mean_rot_deg": float(np.mean(rot)),
        "mean_trans_m": float(np.mean(tra)),
    }


def view_poses(result: ModelResult, ring_poses: list[np.ndarray]) -> list[dict]:
    """Pose T_O,i (4x4, camera i -> frame O = the last ring view) of every captured view,
    in run and capture order. Ring views take ``ring_poses`` (in ring order); a view left out
    of the ring (captured before the loop's closing view) is chained from the nearest ring
    view of its run through the run's forward registrations (T_{i+1 <- i}), so its error
    includes that chain's drift. Each entry: ``run`` (name), ``index``, ``ring_position``
    (None outside the ring), ``T`` and, when the scene records them, ``T_true`` (the true
    pose in the same frame O)."""
    pos = {k: j for j, k in enumerate(result.ring)}
    anchor = _capture(result.runs, result.ring[-1]).T_true
    out = []
    for r, log in enumerate(result.runs):
        members = [i for i in range(len(log.captures)) if (r, i) in pos]
        for i, cap in enumerate(log.captures):
            if (r, i) in pos:
                T = np.asarray(ring_poses[pos[(r, i)]], np.float64)
            elif members:
                j = min(members, key=lambda m: abs(m - i))
                T = np.asarray(ring_poses[pos[(r, j)]], np.float64)
                lo, hi = min(i, j), max(i, j)
                T_hi_lo = np.eye(4)  # T_{hi <- lo} from the forward pairs lo..hi-1
                for k in range(lo, hi):
                    T_hi_lo = np.asarray(log.pairs[k].T, np.float64) @ T_hi_lo
                T = T @ (T_hi_lo if i < j else np.linalg.inv(T_hi_lo))
            else:
                T = None  # no ring view in this run: nothing to chain from
            true = None
            if cap.T_true is not None and anchor is not None:
                true = np.linalg.inv(anchor) @ cap.T_true
            out.append(
                {
                    "run": log.name,
                    "index": i,
                    "ring_position": pos.get((r, i)),
                    "T": T,
                    "T_true": true,
                }
            )
    return out


def view_errors(result: ModelResult, ring_poses: list[np.ndarray]) -> list[dict]:
    """:func:`view_poses` with the rotation (deg) and translation (m) error of every view
    against the truth (NaN where either pose is missing)."""
    views = view_poses(result, ring_poses)
    for v in views:
        if v["T"] is None or v["T_true"] is None:
            v["rot_deg"], v["trans_m"] = float("nan"), float("nan")
        else:
            v["rot_deg"], v["trans_m"] = pose_error(v["T"], v["T_true"])
    return views


def statistics_points(
    result: ModelResult, max_points: int = 20000, seed: int = 0
) -> tuple[np.ndarray, tuple[list[Cloud], np.ndarray]]:
    """The points the Fig. 13 statistics are computed on, fixed for every set of poses:
    indices of at most ``max_points`` points of :func:`model_cloud` (a seeded random
    subset) and the loop seam (:func:`seam_overlap` under the true poses)."""
    n = len(model_cloud(result, truth_poses(result)).points)
    idx = np.arange(n)
    if n > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
    return idx, seam_overlap(result, truth_poses(result))


def model_statistics(
    sim,
    result: ModelResult,
    poses: list[np.ndarray],
    idx: np.ndarray,
    seam: tuple[list[Cloud], np.ndarray],
    k: int = 100,
    radius: float = 0.003,
) -> dict:
    """The Fig. 13 statistics (mean distance to the ``k`` nearest neighbours, number of
    neighbours within ``radius``; whole model ``model_cloud(...).points[idx]`` and the
    loop seam ``seam = seam_overlap(...)``), the pose errors and the model-to-truth
    surface distance of the model built with ``poses`` (T_O,i). The same ``idx`` and
    ``seam`` for every set of poses make the numbers differ only by the poses."""
    seam_views, seam_sel = seam
    anchor = _capture(result.runs, result.ring[-1]).T_true
    pts = model_cloud(result, poses).points[idx]
    knn = knn_mean_distance(pts, k)
    cnt = neighbour_counts(pts, radius)
    seam_pts = np.concatenate(
        [c.transformed(poses[j]).points for j, c in zip((0, -1), seam_views, strict=True)]
    )
    seam_knn = knn_mean_distance(seam_pts, k, seam_sel)
    seam_cnt = neighbour_counts(seam_pts, radius, seam_sel)
    world = pts @ anchor[:3, :3].T + anchor[:3, 3]
    sd = sim.surface_distance(world)
    return {
        "seam_knn_mean_mm": 1000 * float(np.mean(seam_knn)),
        "seam_neigh3mm_mean": float(np.mean(seam_cnt)),
        "pose": pose_errors(result, poses),
        "knn_mean_mm": 1000 * float(np.mean(knn)),
        "knn_median_mm": 1000 * float(np.median(knn)),
        "neigh3mm_mean": float(np.mean(cnt)),
        "neigh3mm_median": float(np.median(cnt)),
        "surface_mean_mm": 1000 * float(np.mean(sd)),
        "surface_median_mm": 1000 * float(np.median(sd)),
        "surface_p95_mm": 1000 * float(np.percentile(sd, 95)),
        "_knn": knn,
        "_cnt": cnt,
    }


def evaluate_result(
    sim,
    result: ModelResult,
    k: int = 100,
    radius: float = 0.003,
    max_points: int = 20000,
    seed: int = 0,
) -> dict:
    out: dict = {"runs": [], "notes": list(result.notes)}
    for r in result.runs:
        out["runs"].append(
            {
                "name": r.name,
                "images": len(r.captures),
                "delta_s_m": r.delta_s,
                "planning_ms": 1000 * r.planning_time,
                "status": r.status,
                "events": r.events,
                "pair_seconds": [p.seconds for p in r.pairs],
                "pair_fitness": [p.fitness for p in r.pairs],
                "pair_keypoint_seeded": [p.seeded_by_keypoints for p in r.pairs],
            }
        )
    g = result.global_result
    if g is None:
        return out
    # The same points (same views, same subset) for every set of poses, so the Fig. 13
    # numbers differ only by the poses; the true poses give the reference level (sensor
    # noise and sampling alone).
    truth = truth_poses(result)
    idx, seam = statistics_points(result, max_points, seed)
    tags = [("before", g.initial), ("after", g.poses), ("truth", truth)]
    a2 = result.alg2_result
    if a2 is not None and a2 is not g:
        # The pose graph is the final result: Algorithm 2 (the paper's) reported beside it.
        tags.insert(2, ("alg2", a2.poses))
    for tag, poses in tags:
        out[tag] = model_statistics(sim, result, poses, idx, seam, k, radius)
    # every captured view, ring or not (views before the loop's closing view are chained)
    out["views"] = {"before": view_errors(result, g.initial), "after": view_errors(result, g.poses)}
    left = [v for v in out["views"]["after"] if v["ring_position"] is None]
    out["outside_ring"] = {
        "views": len(left),
        "max_rot_deg": max((v["rot_deg"] for v in left), default=None),
        "max_trans_m": max((v["trans_m"] for v in left), default=None),
    }
    edge_err = []
    for j, e in enumerate(result.edges):
        a = _capture(result.runs, result.ring[j])
        b = _capture(result.runs, result.ring[(j + 1) % len(result.ring)])
        edge_err.append(pose_error(e.T, np.linalg.inv(b.T_true) @ a.T_true))
    out["edge_errors"] = {"rot_deg": [r for r, _ in edge_err], "trans_m": [t for _, t in edge_err]}
    out["global"] = {
        "method": "pose_graph" if result.pose_graph is not None else "alg2",
        "seconds": result.global_seconds,
        "refinements": g.n_refinements,
        "converged": g.converged,
        "views": len(result.ring),
        "alg2_seconds": result.alg2_seconds,
        "alg2_refinements": None if a2 is None else a2.n_refinements,
        "alg2_converged": None if a2 is None else a2.converged,
        "extra_edges": len(result.extra),
        "extra_pairs": [[int(i), int(j)] for i, j, _ in result.extra],
        "extra_seconds": result.extra_seconds,
    }
    extra_err = []
    for i, j, e in result.extra:
        extra_err.append(pose_error(e.T, np.linalg.inv(truth[j]) @ truth[i]))
    out["extra_edge_errors"] = {
        "rot_deg": [r for r, _ in extra_err],
        "trans_m": [t for _, t in extra_err],
    }
    out["merge"] = {k: v for k, v in result.merge.items() if k != "T_B_A"}
    return out
