"""Sandwich covariance of a registration (jaxcr.registration.covariance, decision R3) against
independent references: explicit leave-one-cluster-out refits of a linear least-squares
problem (numpy), and the Monte-Carlo scatter of projective ICP estimates on a small
synthetic surface with independent and with tile-correlated depth noise."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.registration.clouds import organised_cloud
from jaxcr.registration.covariance import (
    keypoint_rows,
    projective_sandwich_information,
    projective_sandwich_information_jit,
    sandwich,
)
from jaxcr.registration.icp import CloudArrays, IcpConfig, Keypoints, no_keypoints, normal_equations
from jaxcr.registration.pipeline import PipelineConfig
from jaxcr.registration.projective import (
    depth_image,
    projective_icp_jit,
    projective_information_jit,
)

W, H = 96, 72
F = 90.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
CFG = IcpConfig(iterations=20, max_dist=0.01, min_dist=0.006, sigma_plane=0.01)


def test_sandwich_is_the_leave_one_cluster_out_jackknife():
    # Linear least squares y = X b + e in clusters: with leave_out the sandwich covariance
    # is exactly sum_c (b_(c) - b)(b_(c) - b)^T, b_(c) the fit without cluster c (explicit
    # refits); without it, the textbook CR0 form H^-1 (sum_c X_c^T e_c e_c^T X_c) H^-1.
    rng = np.random.default_rng(3)
    n, g = 240, 30
    X = rng.standard_normal((n, 6)) * np.array([1, 2, 0.5, 1, 3, 1])
    y = X @ rng.standard_normal(6) + rng.standard_normal(n)
    c = rng.integers(0, g, n)
    b = np.linalg.lstsq(X, y, rcond=None)[0]
    e = y - X @ b
    Hm = X.T @ X
    # ICP sign convention: residual r = -e at the estimate, score X^T r per cluster
    S = np.stack([X[c == k].T @ -e[c == k] for k in range(g)])
    Hc = np.stack([X[c == k].T @ X[c == k] for k in range(g)])
    info, cov = sandwich(jnp.asarray(Hm), jnp.asarray(S), jnp.asarray(Hc))
    ref = np.zeros((6, 6))
    for k in range(g):
        bk = np.linalg.lstsq(X[c != k], y[c != k], rcond=None)[0]
        ref += np.outer(bk - b, bk - b)
    np.testing.assert_allclose(np.asarray(cov), ref, rtol=2e-3, atol=1e-4 * np.abs(ref).max())
    np.testing.assert_allclose(
        np.asarray(info) @ np.asarray(cov), np.eye(6), atol=2e-3
    )  # information = covariance^-1 (H invertible)
    _, cov0 = sandwich(jnp.asarray(Hm), jnp.asarray(S), jnp.asarray(Hc), leave_out=False)
    Hi = np.linalg.inv(Hm)
    np.testing.assert_allclose(
        np.asarray(cov0), Hi @ (S.T @ S) @ Hi, rtol=2e-3, atol=1e-4 * np.abs(ref).max()
    )


def _surface(X, Y):
    return 0.5 + 0.02 * np.sin(12 * X + 1.0) + 0.015 * np.cos(15 * Y) + 0.1 * X


@pytest.fixture(scope="module")
def surface():
    """Noise-free target view of a bumpy height field and 1536 points on it (source camera =
    target camera), their source pixels and 8 x 8-pixel tile ids."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    a, b = (u - K[0, 2]) / F, (v - K[1, 2]) / F
    z = np.full_like(a, 0.5)
    for _ in range(60):  # ray casting by fixed-point iteration (a contraction here)
        z = _surface(z * a, z * b)
    P, C, N, ok = organised_cloud(np.full((H, W, 3), 0.5), z, K, normal_window=3, normal_step=1)
    tgt = depth_image(P, C, N, ok, K)
    rng = np.random.default_rng(0)
    n = 1536
    X, Y = rng.uniform(-0.11, 0.11, n), rng.uniform(-0.08, 0.08, n)
    pts = np.stack([X, Y, _surface(X, Y)], -1)
    nrm = np.stack(
        [0.24 * np.cos(12 * X + 1.0) + 0.1, -0.225 * np.sin(15 * Y), -np.ones_like(X)], -1
    )
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    up, vp = F * X / pts[:, 2] + K[0, 2], F * Y / pts[:, 2] + K[1, 2]
    tiles = np.unique(np.floor(vp / 8) * 100 + np.floor(up / 8), return_inverse=True)[1]
    return dict(tgt=tgt, pts=pts, nrm=nrm, tiles=tiles)


def _source(s, e):
    """The points with depth errors ``e`` (m) along their viewing rays."""
    p = s["pts"] * (1 + e / s["pts"][:, 2])[:, None]
    n = len(p)
    return CloudArrays(
        jnp.asarray(p, jnp.float32),
        jnp.full((n, 3), 0.5, jnp.float32),
        jnp.asarray(s["nrm"], jnp.float32),
        jnp.ones(n, bool),
    )


def _twist(T):
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def test_independent_residuals_give_the_usual_information(surface):
    # One pixel per tile, independent depth noise of one variance: the sandwich is the
    # usual H / s^2 (projective_information) up to the scatter of a variance estimate
    # from ~1500 residuals (a few per cent; the bound leaves room for the weights).
    e = 0.001 * np.random.default_rng(1).standard_normal(len(surface["pts"]))
    src = _source(surface, e)
    res = projective_icp_jit(src, surface["tgt"], jnp.eye(4), CFG, window=0)
    info_h, _ = projective_information_jit(res.T, src, surface["tgt"], CFG, window=0)
    info_s, _ = projective_sandwich_information_jit(res.T, src, surface["tgt"], CFG, tile=1)
    ih, is_ = np.asarray(info_h, np.float64), np.asarray(info_s, np.float64)
    ratio = np.linalg.eigvals(np.linalg.solve(ih, is_)).real
    assert 0.7 < ratio.min() and ratio.max() < 1.4, ratio


@pytest.mark.parametrize("correlated", [False, True])
def test_covariance_matches_monte_carlo_scatter_of_icp(surface, correlated):
    # 100 noise draws, each registered from the true pose (identity). Reference: the
    # scatter of the estimates. Independent noise (1 mm): the sandwich and H / s^2 both
    # agree with it. Noise shared by each 8 x 8-pixel tile (0.2 mm) plus 0.3 mm per
    # pixel: H / s^2 is ~13x too confident, the tile sandwich agrees. Bounds: the Monte-
    # Carlo trace of 3 variances from 100 draws has a relative standard error of ~10-15 %,
    # and the sandwich itself is ~10 % low (iid) to ~10 % high (jackknife) here.
    n = len(surface["pts"])
    errs, cov_s, cov_h = [], [], []
    for d in range(100):
        r = np.random.default_rng(100 + d)
        if correlated:
            g = surface["tiles"].max() + 1
            e = 0.0002 * r.standard_normal(g)[surface["tiles"]] + 0.0003 * r.standard_normal(n)
        else:
            e = 0.001 * r.standard_normal(n)
        src = _source(surface, e)
        res = projective_icp_jit(src, surface["tgt"], jnp.eye(4), CFG, window=0)
        errs.append(_twist(np.asarray(res.T, np.float64)))
        _, c = projective_sandwich_information_jit(res.T, src, surface["tgt"], CFG, tile=8)
        cov_s.append(np.asarray(c, np.float64))
        ih, _ = projective_information_jit(res.T, src, surface["tgt"], CFG, window=0)
        cov_h.append(np.linalg.inv(np.asarray(ih, np.float64)))
    mc = np.cov(np.array(errs).T)
    cs, ch = np.mean(cov_s, 0), np.mean(cov_h, 0)
    for blk in (slice(0, 3), slice(3, 6)):
        ts = np.trace(cs[blk, blk]) / np.trace(mc[blk, blk])
        th = np.trace(ch[blk, blk]) / np.trace(mc[blk, blk])
        assert 0.6 < ts < 1.6, (blk, ts)
        if correlated:
            assert th < 0.25, (blk, th)
        else:
            assert 0.6 < th < 1.6, (blk, th)


@pytest.mark.slow  # eager: ~30 s of op-by-op dispatch on a loaded 2-core machine
def test_jit_equals_eager_and_options_are_checked(surface):
    src = _source(surface, 0.001 * np.random.default_rng(2).standard_normal(len(surface["pts"])))
    a = projective_sandwich_information(jnp.eye(4), src, surface["tgt"], CFG)
    b = projective_sandwich_information_jit(jnp.eye(4), src, surface["tgt"], CFG)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-3, atol=1e-6)
    cfg = PipelineConfig()
    assert (cfg.edge_information, cfg.information_tile) == ("sandwich", 1)  # decision R3
    from jaxcr.registration.pairwise import register_pair

    with pytest.raises(ValueError, match="information must be 'hessian' or 'sandwich'"):
        register_pair(None, None, K, information="bootstrap")


@pytest.mark.parametrize("balance", ["noise", "fraction"])
def test_keypoint_rows_sum_to_the_icp_keypoint_term(balance):
    # Reference: the keypoint term of normal_equations, as H and g with keypoints minus
    # H and g without them (the same dense matches).
    rng = np.random.default_rng(5)
    n, k = 50, 12
    ps = rng.normal([0, 0, 0.5], 0.05, (n, 3))
    nq = rng.normal(size=(n, 3))
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    q = ps + 0.002 * rng.standard_normal((n, 3))
    w = rng.uniform(0.2, 1.0, n)
    pl = np.sum((ps - q) * nq, 1)
    src = rng.normal([0, 0, 0.5], 0.05, (k, 3))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix()
    T[:3, 3] = [0.003, -0.002, 0.001]
    tgt = src @ T[:3, :3].T + T[:3, 3] + 0.002 * rng.standard_normal((k, 3))
    mask = np.arange(k) < 9
    kp = Keypoints(*(jnp.asarray(x, jnp.float32) for x in (src, tgt)), jnp.asarray(mask))
    cfg = IcpConfig(keypoint_weight=1.0, keypoint_balance=balance)
    args = [jnp.asarray(x, jnp.float32) for x in (T, ps, q, nq, w, pl)]
    H1, g1 = normal_equations(*args, cfg, kp)
    H0, g0 = normal_equations(*args, cfg, no_keypoints())
    bal = np.sum(w * pl**2) / np.sum(w) if balance == "noise" else np.sum(w)
    s, h = keypoint_rows(jnp.asarray(T, jnp.float32), kp, jnp.float32(bal), cfg)
    s, h = np.asarray(s), np.asarray(h)
    assert np.all(s[~mask] == 0) and np.all(h[~mask] == 0)
    Hk, gk = np.asarray(H1 - H0), np.asarray(g1 - g0)
    np.testing.assert_allclose(h.sum(0), Hk, rtol=1e-3, atol=1e-4 * np.abs(Hk).max())
    np.testing.assert_allclose(s.sum(0), gk, rtol=1e-3, atol=1e-3 * np.abs(gk).max())
