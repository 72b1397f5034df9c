"""Weighted SE(3) pose graph (jaxcr.registration.pose_graph) and the registration
information (jaxcr.registration.projective.projective_information), against independent
references: exact recovery of a noise-free graph, a float64 scipy least-squares solve of
the same cost with scipy's rotations, the closed-form weighted mean of two conflicting
measurements, a slow per-point loop with finite-difference Jacobians."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from jaxcr.registration.clouds import organised_cloud
from jaxcr.registration.icp import CloudArrays, IcpConfig
from jaxcr.registration.pose_graph import (
    GraphEdge,
    edge_residual,
    edge_residuals_jit,
    graph_cost,
    inverted_edge,
    optimize_pose_graph,
    point_information,
    solve_pose_graph_jit,
)
from jaxcr.registration.projective import depth_image, projective_information


def _T(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _ring(m=10, radius=0.3):
    """Cameras on a circle looking at its centre, frame O = the last camera."""
    out = []
    for k in range(m):
        a = 2 * np.pi * k / m
        out.append(_T([0, -a, 0], [radius * np.sin(a), 0.02 * np.cos(3 * a), -radius * np.cos(a)]))
    A = np.linalg.inv(out[-1])
    return [A @ P for P in out]


def _edges(truth, gaps, rng=None, noise=(0.0, 0.0), info=None):
    m = len(truth)
    out = []
    for gap in gaps:
        for i in range(m):
            j = (i + gap) % m
            Z = np.linalg.inv(truth[j]) @ truth[i]
            if rng is not None:
                Z = _T(rng.normal(0, noise[1], 3), rng.normal(0, noise[0], 3)) @ Z
            W = np.eye(6) if info is None else info(i, j)
            out.append(GraphEdge(i, j, Z, W))
    return out


def _np_residual(Ti, Tj, Z):
    E = np.linalg.inv(Tj) @ Ti @ np.linalg.inv(Z)
    return np.r_[E[:3, 3], Rotation.from_matrix(E[:3, :3]).as_rotvec()]


def _reference(initial, edges, anchor):
    """float64 scipy least squares of the same cost, poses parametrised as right
    perturbations (rotation vector, translation) of the initial poses."""
    m = len(initial)
    free = [k for k in range(m) if k != anchor % m]
    L = [np.linalg.cholesky(e.info + 1e-12 * np.eye(6)) for e in edges]

    def poses(x):
        P = [p.copy() for p in initial]
        for n, k in enumerate(free):
            d = x[6 * n : 6 * n + 6]
            P[k] = initial[k] @ _T(d[3:], d[:3])
        return P

    def fun(x):
        P = poses(x)
        return np.concatenate(
            [Lk.T @ _np_residual(P[e.i], P[e.j], e.Z) for e, Lk in zip(edges, L, strict=True)]
        )

    sol = least_squares(fun, np.zeros(6 * len(free)), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return poses(sol.x)


def _close(A, B, rot=1e-5, tra=1e-6):
    for P, Q in zip(A, B, strict=True):
        E = np.linalg.inv(Q) @ P
        assert np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()) < rot
        assert np.linalg.norm(P[:3, 3] - Q[:3, 3]) < tra, (P[:3, 3], Q[:3, 3])


def test_noise_free_graph_is_recovered_exactly():
    truth = _ring(8)  # 16 edges: the same compiled shape as the scipy reference test
    rng = np.random.default_rng(0)
    init = [P @ _T(rng.normal(0, 0.03, 3), rng.normal(0, 0.02, 3)) for P in truth]
    init[-1] = truth[-1]
    res = optimize_pose_graph(init, _edges(truth, (1, 3)))
    _close(res.poses, truth, rot=2e-6, tra=2e-6)
    assert res.cost_final < 1e-9 < res.cost_initial


def test_noisy_weighted_graph_matches_scipy_float64_reference():
    truth = _ring(8)
    rng = np.random.default_rng(1)

    def info(i, j):
        A = rng.normal(size=(6, 6))
        return A @ A.T + np.diag([4e6, 4e6, 4e6, 1e5, 1e5, 1e5])

    edges = _edges(truth, (1, 3), rng, noise=(0.002, 0.004), info=info)
    init = [P @ _T(rng.normal(0, 0.01, 3), rng.normal(0, 0.005, 3)) for P in truth]
    init[2] = truth[2]
    res = optimize_pose_graph(init, edges, anchor=2)
    ref = _reference(init, edges, anchor=2)
    # float32 solve vs float64 reference (poses ~0.3 m from O)
    _close(res.poses, ref, rot=2e-5, tra=3e-6)
    _close([res.poses[2]], [init[2]], rot=1e-7, tra=1e-7)  # the anchor does not move


def test_weights_give_the_closed_form_weighted_mean():
    # Two poses, the anchor at O and two translation-only measurements of the other one,
    # rotation pinned (t_E = t_1 - R_1 t_Z couples a rotation to the translations): the
    # solution is their information-weighted mean.
    t1, t2 = np.array([0.1, 0.0, 0.02]), np.array([0.104, -0.002, 0.02])
    W1 = np.diag([1e6, 4e6, 1e6, 1e12, 1e12, 1e12])
    W2 = np.diag([3e6, 1e6, 1e6, 1e12, 1e12, 1e12])
    # Z = T_{0 <- 1} = T_O,1 with T_O,0 = I
    edges = [GraphEdge(1, 0, _T([0, 0, 0], t1), W1), GraphEdge(1, 0, _T([0, 0, 0], t2), W2)]
    res = optimize_pose_graph([np.eye(4), np.eye(4)], edges, anchor=0)
    w1, w2 = np.diag(W1)[:3], np.diag(W2)[:3]
    np.testing.assert_allclose(res.poses[1][:3, 3], (w1 * t1 + w2 * t2) / (w1 + w2), atol=5e-8)
    np.testing.assert_allclose(res.poses[1][:3, :3], np.eye(3), atol=1e-7)
    # Down-weighting an edge moves the answer to the other one.
    weak = [edges[0], GraphEdge(1, 0, edges[1].Z, W2 * 1e-6)]
    res = optimize_pose_graph([np.eye(4), np.eye(4)], weak, anchor=0)
    np.testing.assert_allclose(res.poses[1][:3, 3], t1, atol=5e-8)


def test_jit_equals_eager_and_residual_matches_numpy():
    # The shapes optimize_pose_graph solves a ring of 8 with (16 poses, 32 edges: padding
    # poses held fixed, padding edges with zero information; iterations=10): the program of
    # the tests above (run cache), not one of its own.
    truth = _ring(8)
    rng = np.random.default_rng(2)
    # one loop: 48 residuals, 42 free parameters, so the minimum is ~6/48 of the cost at
    # the truth (c1 < 0.5 c0 below)
    edges = _edges(truth, (1,), rng, noise=(0.001, 0.002))
    poses = np.tile(np.eye(4), (16, 1, 1))
    poses[:8] = np.stack(truth)
    src, tgt = np.zeros(32, np.int32), np.zeros(32, np.int32)
    Z, info = np.tile(np.eye(4), (32, 1, 1)), np.zeros((32, 6, 6))
    for k, e in enumerate(edges):
        src[k], tgt[k], Z[k], info[k] = e.i, e.j, e.Z, e.info
    args = (
        jnp.asarray(poses, jnp.float32),
        jnp.asarray(src),
        jnp.asarray(tgt),
        jnp.asarray(Z, jnp.float32),
        jnp.asarray(info, jnp.float32),
        jnp.int32(7),
    )
    # The solver's jit == eager is covered through its pieces (an eager Gauss-Newton solve
    # costs ~15 s of op-by-op dispatch): the cost eager vs jit, the vmapped residual vs a
    # numpy loop; the jitted solve itself is checked against scipy above.
    c_eager = graph_cost(*args[:5])
    c_jit = jax.jit(graph_cost)(*args[:5])
    np.testing.assert_allclose(float(c_eager), float(c_jit), rtol=1e-5)
    # 16 edges: the shape the robust rounds below evaluate (one small program)
    i, j, Zs = args[1][:16], args[2][:16], args[3][:16]
    r = np.asarray(edge_residuals_jit(args[0][i], args[0][j], Zs))
    for k, e in enumerate(edges):
        np.testing.assert_allclose(r[k], _np_residual(truth[e.i], truth[e.j], e.Z), atol=2e-6)
    ref = sum(
        _np_residual(truth[e.i], truth[e.j], e.Z)
        @ e.info
        @ _np_residual(truth[e.i], truth[e.j], e.Z)
        for e in edges
    )
    np.testing.assert_allclose(float(c_jit), ref, rtol=1e-3)
    P, c0, c1, _ = solve_pose_graph_jit(*args, iterations=10, n_poses=jnp.int32(8))
    assert float(c1) < 0.5 * float(c0)
    # the padding poses (index >= n_poses) are held fixed
    np.testing.assert_array_equal(np.asarray(P)[8:], np.asarray(args[0])[8:])


def test_residual_gradient_is_finite_at_zero_error():
    T = jnp.asarray(_ring(4)[1], jnp.float32)
    g = jax.jit(jax.jacfwd(lambda d: edge_residual(T @ jnp.eye(4).at[:3, 3].set(d), T, T)))(
        jnp.zeros(3)
    )
    assert np.all(np.isfinite(np.asarray(g)))


def test_inverted_edge_has_the_same_cost():
    rng = np.random.default_rng(3)
    Z = _T(rng.normal(0, 0.5, 3), rng.normal(0, 0.2, 3))
    A = rng.normal(size=(6, 6))
    info = A @ A.T
    Zi, info_i = inverted_edge(Z, info)
    np.testing.assert_allclose(Zi, np.linalg.inv(Z), atol=1e-12)
    for _ in range(5):
        Ti, Tj = _T(rng.normal(0, 1e-3, 3), rng.normal(0, 1e-3, 3)) @ Z, np.eye(4)
        Ti = np.linalg.inv(Tj) @ Ti  # predicted T_{j <- i} = Ti
        r1, r2 = _np_residual(Ti, Tj, Z), _np_residual(Tj, Ti, Zi)
        np.testing.assert_allclose(r1 @ info @ r1, r2 @ info_i @ r2, rtol=2e-3)


def test_point_information_matches_slow_loop():
    p = np.random.default_rng(4).normal(size=(40, 3))

    def hat(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    ref = np.mean(
        [np.hstack([np.eye(3), -hat(q)]).T @ np.hstack([np.eye(3), -hat(q)]) for q in p], 0
    )
    np.testing.assert_allclose(point_information(p), ref, atol=1e-12)


def test_degenerate_graphs_fail_clearly():
    truth = _ring(5)
    edges = _edges(truth, (1,))
    with pytest.raises(ValueError, match="no edge"):
        optimize_pose_graph(truth + [np.eye(4)], edges)
    with pytest.raises(ValueError, match="PSD"):
        optimize_pose_graph(truth, [edges[0]._replace(info=-np.eye(6))] + edges[1:])
    with pytest.raises(ValueError, match="non-finite"):
        optimize_pose_graph(truth, [edges[0]._replace(Z=np.full((4, 4), np.nan))] + edges[1:])
    with pytest.raises(ValueError, match="joins"):
        optimize_pose_graph(truth, [GraphEdge(0, 7, np.eye(4), np.eye(6))] + edges)
    with pytest.raises(ValueError, match=">= 2"):
        optimize_pose_graph([np.eye(4)], edges)
    with pytest.raises(ValueError):
        point_information(np.zeros((0, 3)))


W, H, F = 64, 48, 60.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def _height(X, Y):
    return 0.5 + 0.02 * np.sin(12 * X + 1.0) + 0.015 * np.cos(15 * Y) + 0.1 * X


def test_projective_information_matches_slow_finite_difference_loop():
    # Target: an organised view of a bumpy height field; source: points of the same surface
    # displaced by a small known motion. Plain weighted point-to-plane objective (no
    # degeneracy split, keypoints or colour term) so the reference is a direct loop.
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    a, b = (u - K[0, 2]) / F, (v - K[1, 2]) / F
    z = np.full_like(a, 0.5)
    for _ in range(60):
        z = _height(z * a, z * b)
    rgb = np.full((H, W, 3), 0.5)
    P, C, N, ok = organised_cloud(rgb, z, K, normal_window=3, normal_step=1)
    tgt = depth_image(P, C, N, ok, K)
    rng = np.random.default_rng(5)
    X, Y = rng.uniform(-0.15, 0.15, 400), rng.uniform(-0.1, 0.1, 400)
    pts = np.stack([X, Y, _height(X, Y)], -1)
    nrm = np.stack([0.24 * np.cos(12 * X + 1.0) + 0.1, -0.225 * np.sin(15 * Y), -np.ones(400)], -1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    T = _T([0.002, -0.001, 0.003], [0.001, 0.0005, -0.001])  # estimate: target <- source
    src = CloudArrays(
        jnp.asarray(pts, jnp.float32),
        jnp.full((400, 3), 0.5, jnp.float32),
        jnp.asarray(nrm, jnp.float32),
        jnp.ones(400, bool),
    )
    cfg = IcpConfig(min_dist=0.01, keypoint_weight=0.0)
    info, s = projective_information(jnp.asarray(T, jnp.float32), src, tgt, cfg)

    def residuals(delta):
        D = _T(delta[3:], delta[:3])  # left perturbation [exp(w), v] T, target frame
        M = D @ T
        ps, ns = pts @ M[:3, :3].T + M[:3, 3], nrm @ M[:3, :3].T
        out = []
        for p, n in zip(ps, ns, strict=True):
            iu = int(np.round(K[0, 0] * p[0] / p[2] + K[0, 2]))
            iv = int(np.round(K[1, 1] * p[1] / p[2] + K[1, 2]))
            if not (0 <= iu < W and 0 <= iv < H and ok[iv, iu]):
                out.append((0.0, 0.0))
                continue
            q, nq = P[iv, iu], N[iv, iu]
            d = p - q
            pl = float(d @ nq)
            if d @ d >= cfg.min_dist**2 or n @ nq <= 0.5:
                out.append((0.0, pl))
                continue
            w = (
                np.exp(-(d @ d) / (2 * cfg.sigma_dist**2))
                * (n @ nq)
                * np.exp(-(pl**2) / (2 * cfg.sigma_plane**2))
            )
            out.append((w, pl))
        return np.array(out)

    base = residuals(np.zeros(6))
    w, r0 = base[:, 0], base[:, 1]
    eps = 1e-6
    J = np.stack(
        [(residuals(eps * e)[:, 1] - residuals(-eps * e)[:, 1]) / (2 * eps) for e in np.eye(6)],
        1,
    )  # matches held fixed by the small step (same pixels)
    Href = (J * w[:, None]).T @ J
    s2 = np.sum(w * r0**2) / np.sum(w)
    assert (w > 0).sum() > 200
    np.testing.assert_allclose(float(s) ** 2, s2, rtol=2e-3)
    np.testing.assert_allclose(
        np.asarray(info), Href / s2, rtol=5e-3, atol=1e-3 * np.abs(Href / s2).max()
    )


# --- pipeline glue: the graph's edges and the extra registrations (stub frames) -------

from types import SimpleNamespace  # noqa: E402

from jaxcr.registration import pipeline  # noqa: E402
from jaxcr.registration.global_opt import GlobalResult  # noqa: E402
from jaxcr.registration.pairwise import PairResult, RegistrationFailed  # noqa: E402


def _stub_result(truth, route_pairs=()):
    """A ModelResult whose ring views are stub frames (a few camera-frame points) on one
    route, with exact ring edges and Algorithm 2 poses = the truth."""
    m = len(truth)
    rng = np.random.default_rng(6)
    caps = []
    for k in range(m):
        pts = rng.normal([0, 0, 0.4], 0.05, (30, 3)).astype(np.float32)
        arrays = SimpleNamespace(points=pts, mask=np.ones(30, bool))
        caps.append(SimpleNamespace(frame=SimpleNamespace(arrays=arrays, label=str(k))))
    pairs = [
        PairResult(np.linalg.inv(truth[k + 1]) @ truth[k], 10, 10, True, 0.9, 1e-3, 0.1)
        for k in range(m - 1)
    ]
    runs = [SimpleNamespace(captures=caps, pairs=pairs, name="1")]
    ring = [(0, k) for k in range(m)]
    edges = [
        PairResult(
            np.linalg.inv(truth[(k + 1) % m]) @ truth[k],
            10,
            10,
            True,
            0.9,
            1e-3,
            0.1,
            np.diag([1e6, 1e6, 1e6, 1e4, 1e4, 1e4]) * (k + 1),
        )
        for k in range(m)
    ]
    g = GlobalResult(truth, truth, 1, True)
    return pipeline.ModelResult(runs, ring, edges, g, 0.0, {}, [], g, 0.0)


def test_graph_edges_weights():
    truth = _ring(6)
    res = _stub_result(truth)
    m = len(truth)
    ring = [(k, (k + 1) % m, e) for k, e in enumerate(res.edges)]
    nominal = PairResult(res.edges[0].T, 0, 0, False, 0.0, float("nan"), 0.0)
    no_info = PairResult(res.edges[1].T, 5, 5, True, 0.8, 1e-3, 0.1)
    g = pipeline.graph_edges(res, ring + [(0, 1, nominal), (1, 2, no_info)], "information")
    for k in range(m):
        np.testing.assert_allclose(g[k].info, res.edges[k].information, rtol=1e-12, atol=1e-6)
    # float32 round-off: a slightly negative eigenvalue is clipped, not a failed solve
    bad = res.edges[0].information.copy()
    bad[5, 5] = -1e-3
    odd = PairResult(res.edges[0].T, 10, 10, True, 0.9, 1e-3, 0.1, bad)
    (ge,) = pipeline.graph_edges(res, [(0, 1, odd)], "information")
    assert np.linalg.eigvalsh(ge.info).min() >= -1e-9
    np.testing.assert_allclose(ge.info[:5, :5], bad[:5, :5], rtol=1e-12, atol=1e-6)
    ref = np.median([np.trace(e.information) for e in res.edges])
    f0 = np.asarray(res.runs[0].captures[1].frame.arrays.points, np.float64)
    T = no_info.T
    expect = point_information(f0 @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(g[-1].info, expect * ref / np.trace(expect), rtol=1e-9)
    assert np.trace(g[-2].info) == pytest.approx(ref / 100.0)  # nominal kinematics edge
    gp = pipeline.graph_edges(res, ring, "points")
    p0 = np.asarray(res.runs[0].captures[0].frame.arrays.points, np.float64)
    T0 = res.edges[0].T
    np.testing.assert_allclose(gp[0].info, point_information(p0 @ T0[:3, :3].T + T0[:3, 3]))
    with pytest.raises(ValueError, match="weights"):
        pipeline.graph_edges(res, ring, "uniform")


def test_extra_edges_gate_and_skip(monkeypatch):
    truth = _ring(8)
    res = _stub_result(truth)
    calls = []

    def fake_register(src, tgt, K, prior=None, **kw):
        i, j = int(src.label), int(tgt.label)
        calls.append((i, j))
        if (i, j) == (7, 1):
            raise RegistrationFailed("no overlap")
        T = np.linalg.inv(truth[j]) @ truth[i]
        if (i, j) == (2, 4):  # a false match, 5 deg off the Algorithm 2 poses
            T = _T([0, np.deg2rad(5.0), 0], [0, 0, 0]) @ T
        np.testing.assert_allclose(prior, np.linalg.inv(truth[j]) @ truth[i], atol=1e-9)
        return PairResult(T, 10, 10, True, 0.9, 1e-3, 0.1, np.eye(6))

    monkeypatch.setattr(pipeline, "register_pair", fake_register)
    cfg = pipeline.PipelineConfig(extra_gaps=(2,))
    out = pipeline.extra_edges(res, np.eye(3), cfg)
    assert calls == [(i, (i + 2) % 8) for i in range(8)]
    assert [(i, j) for i, j, _ in out] == [(i, (i + 2) % 8) for i in range(8) if i not in (2, 7)]
    for i, j, p in out:
        np.testing.assert_allclose(p.T, np.linalg.inv(truth[j]) @ truth[i], atol=1e-9)
    # The routes' own forward registrations off the ring are used without re-registering.
    res.ring = [(0, 0), (0, 2), (0, 1), (0, 3), (0, 4), (0, 5), (0, 6), (0, 7)]
    calls.clear()
    out = pipeline.extra_edges(res, np.eye(3), pipeline.PipelineConfig(extra_gaps=()))
    assert calls == []
    assert {(i, j) for i, j, _ in out} == {(0, 2), (1, 3)}


def test_robust_rounds_downweight_an_outlier_edge():
    from jaxcr.registration.pose_graph import robust_weights

    truth = _ring(8)
    rng = np.random.default_rng(7)
    edges = _edges(truth, (1, 2), rng, noise=(0.0005, 0.001), info=lambda i, j: np.eye(6) * 1e6)
    k = 3  # one registration 3 deg / 20 mm wrong
    edges[k] = edges[k]._replace(Z=_T([0, 0.05, 0], [0.02, 0, 0]) @ edges[k].Z)
    plain = optimize_pose_graph(truth, edges)
    robust = optimize_pose_graph(truth, edges, robust_rounds=4)

    def worst(P):
        return max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(P, truth, strict=True))

    assert worst(plain.poses) > 3e-3
    assert worst(robust.poses) < 0.25 * worst(plain.poses)
    # weights: 1 at zero residual, 1/2 at chi2 = c^2 s^2, monotone
    # (median 5.348 = the chi^2_6 median: unit scale)
    w = robust_weights(np.array([0.0, 5.348, 5.348, 5.348 * 2.3849**2, 1e9]))
    np.testing.assert_allclose(w[1], 1.0 / (1.0 + 5.348 / 2.3849**2), rtol=1e-4)
    np.testing.assert_allclose(w[[0, 3]], [1.0, 1.0 / (1.0 + 5.348)], rtol=1e-4)
    assert w[4] < 1e-6
