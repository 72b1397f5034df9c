"""Issue 6 additions against independent references: the robust keypoint scale (closed
form for Gaussian noise), the ICP keypoint term (slow float64 loop), the Fig. 13 statistics
on a query subset (brute force), the seam overlap and true poses of the evaluation (brute
force on a hand-built result), and Open3D's point-to-plane ICP as an outside reference for
our ICP when the optional [bench] extra is installed."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.registration.clouds import Cloud, voxel_downsample
from jaxcr.registration.evaluation import model_cloud, seam_overlap, truth_poses
from jaxcr.registration.icp import CloudArrays, IcpConfig, Keypoints, icp_jit
from jaxcr.registration.metrics import knn_mean_distance, neighbour_counts, pose_error
from jaxcr.registration.pairwise import Frame, keypoint_scale
from jaxcr.registration.pipeline import Capture, ModelResult, RunLog


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------ keypoint scale
def test_keypoint_scale_is_three_sigma_of_gaussian_noise():
    rng = np.random.default_rng(0)
    T = _T([0.1, -0.2, 0.05], [0.02, 0.01, -0.03])
    ka = rng.uniform(-0.05, 0.05, (4000, 3)) + [0, 0, 0.3]
    sigma = 4e-4
    kb = ka @ T[:3, :3].T + T[:3, 3] + rng.normal(0, sigma, ka.shape)
    # closed form: the across-ray residual is 2-D Gaussian, its norm Rayleigh(sigma)
    assert keypoint_scale(ka, kb, T, upper=0.01) == pytest.approx(3 * sigma, rel=0.05)
    # the cap, the floor and no keypoints
    assert keypoint_scale(ka, kb, T, upper=5e-4) == 5e-4
    assert keypoint_scale(ka, ka @ T[:3, :3].T + T[:3, 3], T, upper=0.01) == 1e-4
    assert keypoint_scale(ka[:0], kb[:0], T, upper=0.005) == 0.005
    # noise along the target rays does not count (the term ignores keypoint depth)
    ray = kb / np.linalg.norm(kb, axis=1, keepdims=True)
    along = kb + ray * rng.normal(0, 0.01, (len(kb), 1))
    assert keypoint_scale(ka, along, T, upper=0.01) == pytest.approx(3 * sigma, rel=0.08)


# ------------------------------------------------------------------ ICP keypoint term
def _plane_patch(rng, n=400):
    """Two textured planes at a crease (geometry alone leaves a sliding direction)."""
    a = rng.uniform(-0.04, 0.04, (n, 2))
    p1 = np.stack([a[: n // 2, 0], a[: n // 2, 1], 0.3 + 0.0 * a[: n // 2, 0]], 1)
    p2 = np.stack([0.04 + 0.0 * a[n // 2 :, 0], a[n // 2 :, 1], 0.3 + a[n // 2 :, 0]], 1)
    p = np.concatenate([p1, p2])
    nrm = np.concatenate([np.tile([0, 0, -1.0], (n // 2, 1)), np.tile([-1.0, 0, 0], (n // 2, 1))])
    col = 0.5 + 0.4 * np.sin(np.stack([90 * p[:, 1], 70 * p[:, 0], 50 * p[:, 2]], 1))
    return p, col, nrm


def _numpy_icp_kp(src, tgt, kp, scale, T, cfg):
    """Slow float64 loop of the weighted ICP with the keypoint term (icp_step docstring)."""
    from scipy.spatial import cKDTree

    sp, sc, sn = src
    tp, tc, tn = tgt
    ratio = (cfg.min_dist / cfg.max_dist) ** (1 / max(cfg.iterations - 1, 1))
    tree = cKDTree(np.concatenate([tp, cfg.colour_scale * tc], 1))

    def hat(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    for k in range(cfg.iterations):
        radius = cfg.max_dist * ratio ** min(k, cfg.iterations - 1)
        ps = sp @ T[:3, :3].T + T[:3, 3]
        ns = sn @ T[:3, :3].T
        _, j = tree.query(np.concatenate([ps, cfg.colour_scale * sc], 1))
        H = np.zeros((6, 6))
        g = np.zeros(6)
        wsum = 0.0
        for i in range(len(ps)):
            q, nq, cq = tp[j[i]], tn[j[i]], tc[j[i]]
            d = ps[i] - q
            pl = d @ nq
            nd = ns[i] @ nq
            if d @ d >= radius**2 or nd <= 0.5:
                continue
            w = (
                np.exp(-(d @ d) / (2 * cfg.sigma_dist**2))
                * np.exp(-np.sum((sc[i] - cq) ** 2) / (2 * cfg.sigma_colour**2))
                * nd
                * np.exp(-(pl**2) / (2 * cfg.sigma_plane**2))
            )
            wsum += w
            J = np.concatenate([nq, np.cross(ps[i], nq)])
            H += w * np.outer(J, J)
            g += w * J * pl
        ks = kp[0] @ T[:3, :3].T + T[:3, 3]
        wk_total = cfg.keypoint_weight * wsum / len(ks)
        for s, t in zip(ks, kp[1], strict=True):
            r = s - t
            wk = wk_total * np.exp(-(r @ r) / (2 * scale**2))
            ray = t / np.linalg.norm(t)
            P = np.eye(3) - np.outer(ray, ray)
            J = P @ np.concatenate([np.eye(3), -hat(s)], 1)
            H += wk * J.T @ J
            g += wk * J.T @ (P @ r)
        sc6 = max(np.trace(H) / 6, 1e-12)
        delta = -np.linalg.solve(H + cfg.damping * sc6 * np.eye(6), g)
        T = _T(delta[3:], delta[:3]) @ T
    return T


def test_icp_keypoint_term_with_scale_matches_slow_loop():
    rng = np.random.default_rng(1)
    p, c, n = _plane_patch(rng)
    T_true = _T([0.01, 0.02, -0.015], [0.002, 0.004, -0.001])
    Ti = np.linalg.inv(T_true)
    p2, c2, n2 = _plane_patch(rng)
    src = (p2 @ Ti[:3, :3].T + Ti[:3, 3], c2, n2 @ Ti[:3, :3].T)
    # 12 exact keypoints (texture) and 3 gross outliers that the robust scale must ignore
    kt = p[rng.choice(len(p), 15, replace=False)]
    ks = kt @ Ti[:3, :3].T + Ti[:3, 3]
    kt = kt.copy()
    kt[:3] += 0.004
    scale = 0.001

    def arr(x, y, z):
        return CloudArrays(
            jnp.asarray(x, jnp.float32),
            jnp.asarray(y, jnp.float32),
            jnp.asarray(z, jnp.float32),
            jnp.ones(len(x), bool),
        )

    kp = Keypoints(
        jnp.asarray(ks, jnp.float32),
        jnp.asarray(kt, jnp.float32),
        jnp.ones(15, bool),
        jnp.float32(scale),
    )
    cfg = IcpConfig(iterations=12, keypoint_weight=1.0)
    T = np.asarray(icp_jit(arr(*src), arr(p, c, n), jnp.eye(4), cfg, kp).T, np.float64)
    ref = _numpy_icp_kp(src, (p, c, n), (ks, kt), scale, np.eye(4), cfg)
    r, t = pose_error(T, ref)
    assert r < 0.02 and t < 5e-5  # float32 JAX vs float64 loop (deg, m)
    r, t = pose_error(T, T_true)
    assert r < 0.1 and t < 3e-4  # recovered despite the sliding direction and outliers


# ------------------------------------------------------------------ Fig. 13 on a subset
def test_fig13_statistics_on_query_subset_vs_brute_force():
    rng = np.random.default_rng(2)
    p = rng.uniform(0, 0.02, (150, 3))
    idx = np.array([3, 7, 40, 149])
    d = np.linalg.norm(p[idx, None] - p[None], axis=-1)
    ref = np.sort(d, axis=1)[:, 1:9].mean(1)
    np.testing.assert_allclose(knn_mean_distance(p, 8, idx), ref, rtol=1e-10)
    np.testing.assert_array_equal(neighbour_counts(p, 0.004, idx), (d <= 0.004).sum(1) - 1)


# ------------------------------------------------------------------ evaluation helpers
def _fake_result(rng):
    """Three views of one planar grid (camera frames), true poses and a ring."""
    g = np.stack(np.meshgrid(np.arange(0, 0.04, 0.002), np.arange(0, 0.04, 0.002)), -1)
    world = np.concatenate([g.reshape(-1, 2), np.zeros((g.size // 2, 1))], 1)
    truths = [_T([0, 0, 0.1 * i], [0.01 * i, 0.0, 0.3]) for i in range(3)]
    caps = []
    for i, T in enumerate(truths):
        Ti = np.linalg.inv(T)
        keep = world[:, 0] >= 0.01 * i  # partial, overlapping views
        pts = world[keep] @ Ti[:3, :3].T + Ti[:3, 3]
        cl = Cloud(pts, np.full_like(pts, 0.5), np.tile(Ti[:3, 2], (len(pts), 1)))
        fr = Frame(np.zeros((2, 2, 3)), np.zeros((2, 2)), cl, None, f"v{i}")
        caps.append(Capture("r", i, fr, T, T, np.zeros((2, 3))))
    run = RunLog("r", 1, 0.1)
    run.captures = caps
    return ModelResult([run], [(0, 0), (0, 1), (0, 2)], [], None, 0.0, {}, []), truths


def test_truth_poses_seam_overlap_and_model_views_vs_brute_force():
    res, truths = _fake_result(np.random.default_rng(3))
    tp = truth_poses(res)
    for P, T in zip(tp, truths, strict=True):
        np.testing.assert_allclose(P, np.linalg.inv(truths[-1]) @ T, atol=1e-12)
    views, sel = seam_overlap(res, tp, voxel=0.002, radius=0.0015)
    a = voxel_downsample(res.runs[0].captures[0].frame.cloud, 0.002).transformed(tp[0]).points
    b = voxel_downsample(res.runs[0].captures[2].frame.cloud, 0.002).transformed(tp[2]).points
    da = np.linalg.norm(a[:, None] - b[None], axis=-1).min(1)
    db = np.linalg.norm(b[:, None] - a[None], axis=-1).min(1)
    np.testing.assert_array_equal(sel, np.concatenate([da < 0.0015, db < 0.0015]))
    assert 0 < sel.sum() < len(sel)  # views 0 and 2 overlap on part of the grid
    cloud, vid = model_cloud(res, tp, voxel=0.002, with_views=True)
    assert len(cloud) == len(vid)
    assert np.bincount(vid)[0] == len(views[0]) and np.bincount(vid)[2] == len(views[1])
    # point order does not depend on the poses (before/after/truth correspond point by point)
    other, vid2 = model_cloud(res, [np.eye(4)] * 3, voxel=0.002, with_views=True)
    np.testing.assert_array_equal(vid, vid2)
    np.testing.assert_allclose(
        cloud.points[vid == 1], other.points[vid2 == 1] @ tp[1][:3, :3].T + tp[1][:3, 3], atol=1e-12
    )


# ------------------------------------------------------------------ Open3D reference
def test_icp_agrees_with_open3d_point_to_plane():
    o3d = pytest.importorskip("open3d", exc_type=ImportError)
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.06, 0.06, (800, 2))
    z = 0.3 + 8 * xy[:, 0] ** 2 - 5 * xy[:, 1] ** 2
    p = np.concatenate([xy, z[:, None]], 1)
    n = np.stack([16 * xy[:, 0], -10 * xy[:, 1], -np.ones(len(xy))], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    T_true = _T([0.02, -0.015, 0.03], [0.004, -0.003, 0.002])
    Ti = np.linalg.inv(T_true)
    src = (p @ Ti[:3, :3].T + Ti[:3, 3], n @ Ti[:3, :3].T)
    col = np.full_like(p, 0.5)
    cfg = IcpConfig(iterations=20, keypoint_weight=0.0, sigma_colour=1e3)

    def arr(x, y):
        return CloudArrays(
            jnp.asarray(x, jnp.float32),
            jnp.asarray(col, jnp.float32),
            jnp.asarray(y, jnp.float32),
            jnp.ones(len(x), bool),
        )

    ours = np.asarray(icp_jit(arr(*src), arr(p, n), jnp.eye(4), cfg).T, np.float64)
    s, t = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
    s.points, s.normals = o3d.utility.Vector3dVector(src[0]), o3d.utility.Vector3dVector(src[1])
    t.points, t.normals = o3d.utility.Vector3dVector(p), o3d.utility.Vector3dVector(n)
    reg = o3d.pipelines.registration
    T_o3d = reg.registration_icp(
        s,
        t,
        0.02,
        np.eye(4),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=50),
    ).transformation
    r, tt = pose_error(ours, np.asarray(T_o3d))
    assert r < 0.02 and tt < 5e-5  # same points: both reach the exact alignment
    assert pose_error(ours, T_true)[0] < 0.02
