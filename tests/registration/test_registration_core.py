"""Registration core (issue 6) against independent references: closed-form arcs, slow
loops, numpy/scipy re-implementations, known transforms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from jaxcr.errors import InputError
from jaxcr.io.ply import read_ply, write_ply
from jaxcr.registration.arm import (
    Arc,
    ArmLimit,
    ArmSpec,
    arc_points,
    arc_points_np,
    conform_sections,
    look_at_angles,
    tip_camera_pose,
)
from jaxcr.registration.clouds import Cloud, cloud_from_rgbd, pad_cloud, voxel_downsample
from jaxcr.registration.clustering import ClusterMap, euclidean_clusters
from jaxcr.registration.collision import arc_clearance, batch_clearance
from jaxcr.registration.global_opt import chain_poses, global_optimize
from jaxcr.registration.icp import CloudArrays, IcpConfig, icp_jit, no_keypoints
from jaxcr.registration.metrics import knn_mean_distance, neighbour_counts, pose_error
from jaxcr.registration.ransac import estimate_transform, ransac_kabsch, sample_valid


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------ arm / IK
def test_arc_points_closed_form_and_straight():
    start = jnp.array([0.1, -0.2, 0.3])
    s = jnp.linspace(0, 0.5, 7)
    k = 2.5
    got = np.asarray(arc_points(start, k, s))
    # circle centre on the left of the heading at distance 1/k
    c = np.array([0.1, -0.2]) + np.array([-np.sin(0.3), np.cos(0.3)]) / k
    ang = 0.3 - np.pi / 2 + k * np.asarray(s)
    ref = c + np.stack([np.cos(ang), np.sin(ang)], 1) / k
    np.testing.assert_allclose(got[:, :2], ref, atol=1e-6)
    straight = np.asarray(arc_points(start, 0.0, s))
    np.testing.assert_allclose(straight[:, 0], 0.1 + np.cos(0.3) * np.asarray(s), atol=1e-6)
    g = jax.grad(lambda kk: arc_points(start, kk, s)[-1, 0])(0.0)
    assert np.isfinite(g)
    jit = np.asarray(jax.jit(arc_points)(start, k, s))
    np.testing.assert_allclose(jit, got, atol=1e-6)


def test_arc_points_np_matches_jax():
    # The planner's numpy closed form against the JAX one (float64 closed form vs float32:
    # 1e-6 m / rad), curved, tiny and zero curvature, and the circle formula at kappa = 2.5.
    rng = np.random.default_rng(3)
    start = np.array([0.1, -0.2, 0.3])
    kap = np.array([2.5, -7.0, 1e-9, 0.0])
    s = np.sort(rng.uniform(0, 0.5, (4, 6)), axis=1)
    got = arc_points_np(start, kap, s)
    assert got.shape == (4, 6, 3)
    for b in range(4):
        ref = np.asarray(arc_points(jnp.asarray(start), kap[b], jnp.asarray(s[b])))
        np.testing.assert_allclose(got[b], ref, atol=1e-6)
    c = start[:2] + np.array([-np.sin(0.3), np.cos(0.3)]) / 2.5
    np.testing.assert_allclose(np.linalg.norm(got[0, :, :2] - c, axis=1), 1 / 2.5, atol=1e-12)
    np.testing.assert_allclose(Arc(tuple(start), 2.5, 0.4).state_at(s[0, 2]), got[0, 2])


def test_conform_sections_fk_lies_on_planned_arcs():
    spec = ArmSpec(3, 0.4, 0.01, 0.1, (-0.3, 0.05, 0.2))
    a1 = Arc(spec.base, 1.5, 0.5)  # longer than a section: split over two
    a2 = Arc(tuple(a1.end), -3.0, 0.3)
    kap, lens = conform_sections([a1, a2], [0.5, 0.2], spec)
    np.testing.assert_allclose(lens, [0.4, 0.1, 0.2])
    np.testing.assert_allclose(kap, [1.5, 1.5, -3.0])
    T, centre = tip_camera_pose(spec, kap, lens, 0.0, 0.0)
    tip = a2.state_at(0.2)
    np.testing.assert_allclose(T[:3, 3], [tip[0], tip[1], spec.height], atol=2e-5)
    np.testing.assert_allclose(T[:2, 2], [np.cos(tip[2]), np.sin(tip[2])], atol=2e-5)
    # every centreline sample lies on one of the two planned circles (closed form)
    pts = centre[:, :2]
    d1 = np.abs(
        np.linalg.norm(
            pts - (np.array(a1.start[:2]) + np.array([-np.sin(0.2), np.cos(0.2)]) / 1.5), axis=1
        )
        - 1 / 1.5
    )
    th = a1.end[2]
    d2 = np.abs(
        np.linalg.norm(pts - (a1.end[:2] - np.array([-np.sin(th), np.cos(th)]) / 3.0), axis=1)
        - 1 / 3.0
    )
    assert np.all(np.minimum(d1, d2) < 5e-5)
    np.testing.assert_allclose(centre[:, 2], spec.height, atol=1e-6)
    with pytest.raises(ArmLimit):
        conform_sections([a1, a2], [0.5, 0.3 + 0.4], spec)


def test_look_at_points_the_camera():
    spec = ArmSpec(2, 0.3, 0.01, 0.12, (0.0, 0.0, 0.4))
    kap, lens = conform_sections([Arc(spec.base, 2.0, 0.3)], [0.25], spec)
    T0, _ = tip_camera_pose(spec, kap, lens, 0.0, 0.0)
    T_tip = T0 @ np.diag([-1.0, -1.0, 1.0, 1.0])
    target = np.array([0.3, 0.4, 0.05])
    pan, tilt = look_at_angles(T_tip, target)
    T, _ = tip_camera_pose(spec, kap, lens, pan, tilt)
    v = target - T[:3, 3]
    np.testing.assert_allclose(T[:3, 2], v / np.linalg.norm(v), atol=1e-5)
    assert T[2, 1] < 0  # image rows run downwards in the world


# ------------------------------------------------------------------ collision
def _slow_clearance(start, kappa, length, cloud, height, n):
    # the arc in float64 numpy (arc_points_np: checked against arc_points above)
    s = np.linspace(0, 1, n) * length
    arc = arc_points_np(np.asarray(start, np.float64), np.array([kappa], np.float64), s[None])[0]
    best = np.inf
    for x, y, _ in arc:
        for p in cloud:
            best = min(best, float(np.linalg.norm(p - np.array([x, y, height]))))
    return best


def test_batch_clearance_matches_slow_loop_and_vmap():
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-0.3, 0.3, (40, 3)).astype(np.float32)
    mask = np.ones(48, bool)
    mask[40:] = False
    padded = np.zeros((48, 3), np.float32)
    padded[:40] = cloud
    starts = rng.uniform(-0.1, 0.1, (5, 3)).astype(np.float32)
    ks = rng.uniform(-5, 5, 5).astype(np.float32)
    ls = rng.uniform(0.05, 0.4, 5).astype(np.float32)
    got = np.asarray(batch_clearance(starts, ks, ls, padded, mask, jnp.float32(0.05)))
    for i in range(5):
        ref = _slow_clearance(starts[i], ks[i], ls[i], cloud, 0.05, 48)
        assert abs(got[i] - ref) < 1e-4  # float32 vs float64, m
        # the loop of single arcs compiled (one program; eager, its ops compiled one by one)
        one = float(jax.jit(arc_clearance)(starts[i], ks[i], ls[i], padded, mask, 0.05))
        assert abs(one - got[i]) < 1e-6
    empty = np.asarray(
        batch_clearance(starts, ks, ls, padded, np.zeros(48, bool), jnp.float32(0.0))
    )
    assert np.all(np.isinf(empty))


# ------------------------------------------------------------------ clouds / clustering
def test_cloud_from_plane_depth_has_plane_normals_and_errors():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    h, w = 48, 64
    v, u = np.mgrid[0:h, 0:w]
    n = np.array([0.2, -0.1, -1.0])
    n /= np.linalg.norm(n)
    # plane n.X = -0.5 : depth z with X = z * ((u-cx)/f, (v-cy)/f, 1)
    ray = np.stack([(u - 31.5) / 100, (v - 23.5) / 100, np.ones_like(u, float)], -1)
    z = -0.5 / (ray @ n)
    rgb = np.full((h, w, 3), 0.5)
    c = cloud_from_rgbd(rgb, z, K)
    np.testing.assert_allclose(c.points @ n, -0.5, atol=1e-9)
    np.testing.assert_allclose(c.normals, np.broadcast_to(n, c.normals.shape), atol=1e-6)
    with pytest.raises(InputError, match="no valid pixel"):
        cloud_from_rgbd(rgb, np.full((h, w), np.nan), K)
    with pytest.raises(InputError, match="RGB-D pair"):
        cloud_from_rgbd(rgb[:10], z, K)
    d = voxel_downsample(c, 0.05)
    assert 0 < len(d) < len(c)
    p, _, _, m = pad_cloud(d, len(d) + 5, np.random.default_rng(0))
    assert p.shape == (len(d) + 5, 3) and m.sum() == len(d)


def _slow_clusters(points, tol):
    n = len(points)
    label = -np.ones(n, int)
    k = 0
    for i in range(n):
        if label[i] >= 0:
            continue
        stack = [i]
        label[i] = k
        while stack:
            j = stack.pop()
            for l in range(n):
                if label[l] < 0 and np.linalg.norm(points[l] - points[j]) <= tol:
                    label[l] = k
                    stack.append(l)
        k += 1
    return sorted((np.flatnonzero(label == c) for c in range(k)), key=len, reverse=True)


def test_euclidean_clusters_match_slow_bfs_and_map_merges():
    rng = np.random.default_rng(1)
    pts = np.concatenate(
        [rng.normal(c, 0.01, (30, 3)) for c in ([0, 0, 0], [0.3, 0, 0], [0, 0.4, 0])]
    )
    got = euclidean_clusters(pts, 0.03)
    ref = _slow_clusters(pts, 0.03)
    assert sorted(map(tuple, map(sorted, got))) == sorted(map(tuple, map(sorted, ref)))
    m = ClusterMap(tolerance=0.03, voxel=0.001)
    assert m.add(pts[:30]) == 1
    assert m.add(pts[20:60]) == 1  # overlaps the first cluster (merged) + one new
    assert len(m.clusters) == 2


# ------------------------------------------------------------------ RANSAC / Kabsch
def test_ransac_recovers_transform_with_outliers():
    rng = np.random.default_rng(2)
    T = _T([0.2, -0.1, 0.3], [0.05, -0.02, 0.1])
    src = rng.uniform(-0.1, 0.1, (100, 3))
    tgt = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.0005, (100, 3))
    out = rng.random(100) < 0.4
    tgt[out] = rng.uniform(-0.2, 0.2, (out.sum(), 3))
    est, n = estimate_transform(src, tgt, seed=0, threshold=0.003)
    r, t = pose_error(est, T)
    assert r < 0.3 and t < 5e-4
    assert n >= 0.9 * (~out).sum()
    # compiled (run eagerly, its ~140 operations were compiled one by one)
    res = jax.jit(ransac_kabsch, static_argnums=5)(
        jnp.asarray(src, jnp.float32),
        jnp.asarray(tgt, jnp.float32),
        jnp.ones(100, bool),
        jax.random.PRNGKey(0),
        0.003,
        64,
    )
    assert np.all(np.asarray(res.inliers)[~out][:50].mean() > 0.9)
    # too few correspondences: no transform, never a garbage one
    assert estimate_transform(src[:2], tgt[:2])[0] is None
    bad, k = estimate_transform(src, rng.uniform(-1, 1, (100, 3)), threshold=0.001)
    assert bad is None


def test_ransac_sampling_is_uniform_over_the_valid_positions():
    """:func:`sample_valid` (RANSAC's minimal samples) draws only valid positions, each with
    probability 1 / n_valid: 30000 draws over 7 valid of 20 positions, counts within 5
    binomial standard deviations (sqrt(30000 p (1 - p)) = 61) of 30000 / 7 = 4286."""
    mask = np.zeros(20, bool)
    mask[[0, 3, 4, 9, 12, 17, 19]] = True
    sample = jax.jit(sample_valid, static_argnums=2)  # one program (eager: op by op)
    idx = np.asarray(sample(jax.random.PRNGKey(5), jnp.asarray(mask), (10000, 3)))
    assert idx.shape == (10000, 3)
    counts = np.bincount(idx.ravel(), minlength=20)
    assert counts[~mask].sum() == 0
    p = 1 / 7
    np.testing.assert_allclose(counts[mask], 30000 * p, atol=5 * np.sqrt(30000 * p * (1 - p)))


# ------------------------------------------------------------------ ICP
def _surface(rng, n=600):
    """A textured curved patch (saddle + bump) with analytic normals."""
    xy = rng.uniform(-0.06, 0.06, (n, 2))
    z = 0.3 + 8 * xy[:, 0] ** 2 - 5 * xy[:, 1] ** 2 + 0.01 * np.sin(60 * xy[:, 0])
    dzx = 16 * xy[:, 0] + 0.6 * np.cos(60 * xy[:, 0])
    dzy = -10 * xy[:, 1]
    nrm = np.stack([dzx, dzy, -np.ones(n)], 1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = 0.5 + 0.4 * np.stack(
        [np.sin(80 * xy[:, 0]), np.cos(70 * xy[:, 1]), np.sin(50 * (xy[:, 0] + xy[:, 1]))], 1
    )
    return np.concatenate([xy, z[:, None]], 1), col, nrm


def _arrays(p, c, n):
    return CloudArrays(
        jnp.asarray(p, jnp.float32),
        jnp.asarray(c, jnp.float32),
        jnp.asarray(n, jnp.float32),
        jnp.ones(len(p), bool),
    )


def _numpy_icp(src, tgt, T, cfg):
    """Slow float64 re-implementation of the same weighted ICP (scipy k-d tree)."""
    sp, sc, sn = src
    tp, tc, tn = tgt
    ratio = (cfg.min_dist / cfg.max_dist) ** (1 / max(cfg.iterations - 1, 1))
    tree = cKDTree(np.concatenate([tp, cfg.colour_scale * tc], 1))
    for k in range(cfg.iterations):
        radius = cfg.max_dist * ratio ** min(k, cfg.iterations - 1)
        ps = sp @ T[:3, :3].T + T[:3, 3]
        ns = sn @ T[:3, :3].T
        _, j = tree.query(np.concatenate([ps, cfg.colour_scale * sc], 1))
        q, nq, cq = tp[j], tn[j], tc[j]
        H = np.zeros((6, 6))
        g = np.zeros(6)
        for i in range(len(ps)):
            d = ps[i] - q[i]
            pl = d @ nq[i]
            nd = ns[i] @ nq[i]
            if d @ d >= radius**2 or nd <= 0.5:
                continue
            w = (
                np.exp(-(d @ d) / (2 * cfg.sigma_dist**2))
                * np.exp(-np.sum((sc[i] - cq[i]) ** 2) / (2 * cfg.sigma_colour**2))
                * nd
                * np.exp(-(pl**2) / (2 * cfg.sigma_plane**2))
            )
            J = np.concatenate([nq[i], np.cross(ps[i], nq[i])])
            H += w * np.outer(J, J)
            g += w * J * pl
            hp = np.array(
                [[0, -ps[i][2], ps[i][1]], [ps[i][2], 0, -ps[i][0]], [-ps[i][1], ps[i][0], 0]]
            )
            Jp = np.concatenate([np.eye(3), -hp], 1)
            H += cfg.point_weight * w * Jp.T @ Jp
            g += cfg.point_weight * w * Jp.T @ d
        scale = max(np.trace(H) / 6, 1e-12)
        delta = -np.linalg.solve(H + cfg.damping * scale * np.eye(6), g)
        T = _T(delta[3:], delta[:3]) @ T
    return T


@pytest.fixture(scope="module")
def icp_case():
    rng = np.random.default_rng(3)
    p, c, n = _surface(rng)
    T_true = _T([0.02, -0.015, 0.03], [0.004, -0.003, 0.002])
    Ti = np.linalg.inv(T_true)
    # the source is the surface seen in another frame: p_src = T_true^-1 p_tgt (+ resampling)
    p2, c2, n2 = _surface(rng)
    src = (p2 @ Ti[:3, :3].T + Ti[:3, 3], c2, n2 @ Ti[:3, :3].T)
    return src, (p, c, n), T_true


def _arrays64(p, c, n):
    return CloudArrays(
        jnp.asarray(p, jnp.float64),
        jnp.asarray(c, jnp.float64),
        jnp.asarray(n, jnp.float64),
        jnp.ones(len(p), bool),
    )


def test_icp_converges_and_matches_numpy_reference(icp_case):
    src, tgt, T_true = icp_case
    cfg = IcpConfig(iterations=15, keypoint_weight=0.0)
    res = icp_jit(_arrays(*src), _arrays(*tgt), jnp.eye(4), cfg, no_keypoints())
    T = np.asarray(res.T, np.float64)
    r, t = pose_error(T, T_true)
    assert r < 0.1 and t < 3e-4  # from a 2.3 deg / 5.4 mm perturbation
    assert float(res.fitness) > 0.8
    # Same algorithm as the float64 numpy reference, compared in float64 on the same inputs.
    # (Comparing the float32 run with it is not a test of the algorithm: the fixed point
    # depends on nearest-neighbour assignments, which float32 rounding of ~0.3 m coordinates
    # (3.6e-8 m) can flip; perturbing the source by 30 float32 ulps moved the float64
    # reference by up to 0.0028 deg / 9e-6 m here, and one AMD EPYC's float32 run differed by
    # 0.0235 deg. Float32 accuracy is checked against the truth above.)
    # Float64 error analysis: cond(H) of the 6x6 normal equations is 4.6e4 for this case, so
    # each solve is exact to ~cond * n * eps64 = 4.6e4 * 600 * 1.1e-16 = 3e-9 of its step;
    # 15 steps of at most 0.04 rad / 5.4 mm give < 2e-9 rad and < 3e-10 m. The rotation
    # metric itself (arccos of (trace - 1) / 2 in float64) resolves only sqrt(4 eps64) =
    # 2e-8 rad = 1.1e-6 deg, so the tolerances are 1e-5 deg and 1e-8 m.
    cfg6 = IcpConfig(iterations=6, keypoint_weight=0.0, point_weight=0.1)
    with jax.enable_x64(True):
        for c in (cfg, cfg6):
            T64 = icp_jit(
                _arrays64(*src), _arrays64(*tgt), jnp.eye(4, dtype=jnp.float64), c, no_keypoints()
            ).T
            assert T64.dtype == jnp.float64
            r2, t2 = pose_error(np.asarray(T64), _numpy_icp(src, tgt, np.eye(4), c))
            assert r2 < 1e-5 and t2 < 1e-8, (c.point_weight, r2, t2)
    # jit against eager, in float64: in float32 the two differently fused programs round
    # differently, and a ~1e-7 difference can flip a nearest-neighbour assignment and move the
    # pose by far more (3.4e-5 on one AMD EPYC against 1e-5 allowed before); in float64 the same
    # error analysis as above bounds the difference by ~3e-9 per step, so 2e-8 over the 6
    # steps of cfg6 (its float64 program is the one compiled above: no compile of its own).
    with jax.enable_x64(True):
        args64 = (_arrays64(*src), _arrays64(*tgt), jnp.eye(4, dtype=jnp.float64), cfg6)
        with jax.disable_jit():
            res2 = icp_jit(*args64, no_keypoints())
        res3 = icp_jit(*args64, no_keypoints())
        np.testing.assert_allclose(np.asarray(res2.T), np.asarray(res3.T), atol=2e-8)


def test_icp_vmap_equals_loop(icp_case):
    src, tgt, _ = icp_case
    # the float32 configuration of test_icp_converges_and_matches_numpy_reference: the loop's
    # calls load its program (run cache) instead of compiling one of their own
    cfg = IcpConfig(iterations=15, keypoint_weight=0.0)
    T0s = jnp.stack([jnp.eye(4), jnp.asarray(_T([0.01, 0, 0], [0.001, 0, 0]), jnp.float32)])
    from jaxcr.registration.icp import icp

    # the vmap compiled (run eagerly, its operations were compiled one by one)
    batched = jax.jit(jax.vmap(lambda T0: icp(_arrays(*src), _arrays(*tgt), T0, cfg).T))(T0s)
    for i in range(2):
        one = icp_jit(_arrays(*src), _arrays(*tgt), T0s[i], cfg, no_keypoints()).T
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(one), atol=1e-4)


# ------------------------------------------------------------------ global optimisation
def test_global_optimisation_spreads_loop_error():
    rng = np.random.default_rng(4)
    m = 8
    # true camera poses on a circle, looking at a shared textured blob
    truth = [
        _T(
            [0, 2 * np.pi * i / m, 0],
            [0.3 * np.sin(2 * np.pi * i / m), 0, -0.3 * np.cos(2 * np.pi * i / m)],
        )
        for i in range(m)
    ]
    world = rng.normal(0, 0.05, (3000, 3))
    clouds = []
    for T in truth:
        Ti = np.linalg.inv(T)
        local = world @ Ti[:3, :3].T + Ti[:3, 3]
        keep = local[:, 2] > -0.02 + local[:, 2].min() + 0.25  # a partial view
        pts = np.zeros((512, 3), np.float32)
        sel = local[keep][:512] if keep.sum() >= 100 else local[:512]
        pts[: len(sel)] = sel
        mask = np.zeros(512, bool)
        mask[: len(sel)] = True
        clouds.append((pts, mask))
    rel = []
    for i in range(m):
        j = (i + 1) % m
        R = np.linalg.inv(truth[j]) @ truth[i]
        # accumulated registration drift: the same small bias on every edge (0.5 deg, 1 mm)
        rel.append(_T([0.0, 0.0087, 0.0], [0.001, 0.0, 0.0]) @ R)
    g = global_optimize(clouds, rel, overlap_radius=0.02, n_samples=128)
    init = chain_poses(rel)
    np.testing.assert_allclose(g.initial[0], init[0])

    def err(poses):
        a = truth[m - 1]
        return max(
            pose_error(P, np.linalg.inv(a) @ T)[0] for P, T in zip(poses, truth, strict=True)
        )

    assert err(g.poses) < err(g.initial)
    np.testing.assert_allclose(g.poses[m - 1], np.eye(4), atol=1e-6)
    assert g.converged
    with pytest.raises(ValueError):
        global_optimize(clouds[:2], rel[:2])


# ------------------------------------------------------------------ metrics / PLY
def test_fig13_statistics_vs_brute_force(tmp_path):
    rng = np.random.default_rng(5)
    p = rng.uniform(0, 0.02, (200, 3))
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    ref_knn = np.sort(d, axis=1)[:, 1:11].mean(1)
    np.testing.assert_allclose(knn_mean_distance(p, 10), ref_knn, rtol=1e-10)
    np.testing.assert_array_equal(neighbour_counts(p, 0.003), (d <= 0.003).sum(1) - 1)
    c = rng.random((200, 3))
    n = rng.normal(size=(200, 3))
    write_ply(tmp_path / "m.ply", p, c, n)
    back = read_ply(tmp_path / "m.ply")
    np.testing.assert_allclose(back["x"], p[:, 0].astype(np.float32))
    np.testing.assert_allclose(back["nz"], n[:, 2].astype(np.float32))
    np.testing.assert_array_equal(back["red"], np.rint(c[:, 0] * 255).astype(np.uint8))
    (tmp_path / "bad.ply").write_text("hello")
    with pytest.raises(InputError):
        read_ply(tmp_path / "bad.ply")
    _ = Cloud(p, c, n).transformed(np.eye(4))
