"""Tests of the denoised back-projection (clouds.plane_points) and of the photometric
term evaluated at separate (denoised) source positions (projective photo_points)."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.registration.clouds import (
    depth_scaled_window,
    organised_cloud,
    plane_points,
    plane_points_scaled,
)
from jaxcr.registration.icp import DEFAULT_ICP, CloudArrays
from jaxcr.registration.projective import depth_image, projective_icp, projective_icp_jit

K = np.array([[120.0, 0, 47.5], [0, 120.0, 35.5], [0, 0, 1]])
H, W = 72, 96


def _plane_depth(n, d):
    """Depth (H, W) of the plane n . p = d seen by K (closed form: z = d / (n . r))."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d / (r @ n), r


def test_plane_points_exact_on_noise_free_plane():
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    z, r = _plane_depth(n, -0.3)
    P, _, N, ok = organised_cloud(np.full((H, W, 3), 0.5), z, K)
    Pd = plane_points(P, N, ok)
    ref = r * z[..., None]
    np.testing.assert_allclose(Pd[ok], ref[ok], atol=1e-9)
    # rays are kept: the point stays on its pixel
    np.testing.assert_allclose(
        Pd[ok][:, :2] / Pd[ok][:, 2:], ref[ok][:, :2] / ref[ok][:, 2:], atol=1e-12
    )


def test_plane_points_reduces_noise_and_is_unbiased():
    rng = np.random.default_rng(0)
    n = np.array([0.2, 0.1, -1.0])
    n /= np.linalg.norm(n)
    z, r = _plane_depth(n, -0.3)
    sigma = 1.2e-3
    zn = z + rng.normal(0, sigma, z.shape)
    P, _, N, ok = organised_cloud(np.full((H, W, 3), 0.5), zn, K)
    Pd = plane_points(P, N, ok)
    # signed distance to the true plane, inner pixels (full windows)
    inner = ok.copy()
    inner[:6], inner[-6:], inner[:, :6], inner[:, -6:] = False, False, False, False
    dist_raw = P[inner] @ n + 0.3
    dist = Pd[inner] @ n + 0.3
    assert np.std(dist) < 0.35 * np.std(dist_raw)  # ~1/7 expected for a 7x7 window
    assert abs(np.mean(dist)) < 4 * np.std(dist) / np.sqrt(inner.sum() / 49)


def test_plane_points_sphere_sagitta_and_invalid():
    # sphere of radius R at distance c: the plane fit errs by at most ~ s^2 / (8 R) inward
    R, c = 0.05, 0.25
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    a = np.sum(r * r, -1)
    b = -2 * c * r[..., 2]
    disc = b * b - 4 * a * (c * c - R * R)
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)
    z = t  # r has z = 1
    P, _, N, ok = organised_cloud(np.full((H, W, 3), 0.5), z, K)
    Pd = plane_points(P, N, ok)
    cen = np.array([0, 0, c])
    err = np.linalg.norm(Pd[ok] - cen, axis=1) - R
    s = 7 * c / K[0, 0]  # window footprint (m)
    centre_ok = ok & (np.linalg.norm(P - cen, axis=-1) < R) & (N[..., 2] < -0.7)
    err_c = np.linalg.norm(Pd[centre_ok] - cen, axis=1) - R
    assert np.all(np.abs(err_c) < s * s / (8 * R) * 2 + 1e-9)
    assert np.all(np.abs(err) < 0.01 + 1e-9)
    assert np.all(Pd[~ok] == 0)


def test_depth_scaled_window_closed_form():
    # nearest odd integer to footprint * f / z, clipped to [3, 7]; invalid depths -> 7
    z = np.array([0.05, 0.2, 0.3, 0.45, 0.6, 0.9, 2.0, np.nan, 0.0])
    f, s = 304.0, 0.007
    got = depth_scaled_window(z, f, s)
    odd = np.arange(1, 41, 2)
    for zi, wi in zip(z, got, strict=True):
        if not (np.isfinite(zi) and zi > 0):
            assert wi == 7
            continue
        x = s * f / zi
        assert wi == np.clip(odd[np.argmin(np.abs(odd - x))], 3, 7), (zi, x, wi)
    assert got.dtype.kind == "i"


def test_plane_points_scaled_matches_slow_loop():
    # a noisy tilted plane spanning 0.25-0.45 m: windows of 7, 5 and 3 px; every checked
    # pixel's point is the plane through its own window's mean (explicit loop) with its
    # normal, met along its ray: z = (n . m) / (n . r)
    rng = np.random.default_rng(3)
    n = np.array([0.38, 0.0, -1.0])
    n /= np.linalg.norm(n)
    z, r = _plane_depth(n, -0.33)
    zn = z + rng.normal(0, 1e-3, z.shape)
    P, _, N, ok = organised_cloud(np.full((H, W, 3), 0.5), zn, K)
    f, s = 120.0, 0.016
    Pd = plane_points_scaled(P, N, ok, f, s)
    win = depth_scaled_window(P[..., 2], f, s)
    assert len(np.unique(win[ok])) >= 2
    for y, x in zip(rng.integers(8, H - 8, 40), rng.integers(8, W - 8, 40), strict=True):
        w = int(win[y, x])
        h = w // 2
        patch = P[y - h : y + h + 1, x - h : x + h + 1][ok[y - h : y + h + 1, x - h : x + h + 1]]
        m = patch.mean(0)
        ray = P[y, x] / P[y, x, 2]
        zz = N[y, x] @ m / (N[y, x] @ ray)
        np.testing.assert_allclose(Pd[y, x], ray * zz, rtol=0, atol=1e-9)


def test_plane_points_scaled_smaller_crease_error_at_depth():
    # a convex 90-degree roof (faces at 45 degrees) 0.6 m away, noise free: a window of
    # footprint s centred on the crease sees depths z0 + |x|, |x| <= s/2, so the plane
    # through their mean errs by up to ~s/4 (the fixed 7 px: s = 35 mm; 15 mm footprint at
    # 0.6 m and f = 120 px: a 3 px window, s = 15 mm)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rx = (u - K[0, 2]) / K[0, 0]
    z = 0.6 / (1 - np.abs(rx))
    P, _, N, ok = organised_cloud(np.full((H, W, 3), 0.5), z, K)
    e7 = np.abs(plane_points(P, N, ok)[..., 2] - z)[ok]
    es = np.abs(plane_points_scaled(P, N, ok, 120.0, 0.015)[..., 2] - z)[ok]
    assert e7.max() <= 0.035 / 4 and es.max() <= 0.015 / 4
    assert es.max() < 0.5 * e7.max() and es.mean() < 0.5 * e7.mean()


def _textured_plane(rng, T):
    """Source and target organised views of a textured fronto-parallel plane at 0.3 m:
    the target camera at T (target <- source)."""

    def view(T_cam):  # T_cam: plane frame -> camera; plane z = 0 in plane frame
        Rm, t = T_cam[:3, :3], T_cam[:3, 3]
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        dp = d @ Rm  # direction in plane frame
        o = -Rm.T @ t
        s = -o[2] / dp[..., 2]
        X = o + s[..., None] * dp
        x, y = X[..., 0], X[..., 1]
        col = np.stack(
            [0.5 + 0.2 * np.sin(90 * x + 2 * k) + 0.2 * np.cos(70 * y + k) for k in range(3)], -1
        )
        return np.clip(col, 0, 1), s * d[..., 2]

    return view


def test_photo_points_equal_points_gives_same_result():
    """photo_points = the source points reproduces the default (same expression)."""
    rng = np.random.default_rng(1)
    T0 = np.eye(4)
    T0[:3, 3] = [0, 0, 0.3]
    view = _textured_plane(rng, None)
    rgb_s, z_s = view(T0)
    T1 = T0.copy()
    T1[:3, 3] += [0.004, 0.0, 0.0]
    rgb_t, z_t = view(T1)
    Ps, Cs, Ns, oks = organised_cloud(rgb_s, z_s, K)
    Pt, Ct, Nt, okt = organised_cloud(rgb_t, z_t, K)
    idx = np.flatnonzero(oks.ravel())[::7]
    src = CloudArrays(
        jnp.asarray(Ps.reshape(-1, 3)[idx], jnp.float32),
        jnp.asarray(Cs.reshape(-1, 3)[idx], jnp.float32),
        jnp.asarray(Ns.reshape(-1, 3)[idx], jnp.float32),
        jnp.ones(len(idx), bool),
    )
    si, ti = depth_image(Ps, Cs, Ns, oks, K), depth_image(Pt, Ct, Nt, okt, K)
    kw = dict(window=0, src_image=si, photometric="chromaticity")
    a = projective_icp_jit(src, ti, jnp.eye(4), DEFAULT_ICP, None, **kw)
    b = projective_icp_jit(src, ti, jnp.eye(4), DEFAULT_ICP, None, **kw, photo_points=src.points)
    np.testing.assert_allclose(np.asarray(a.T), np.asarray(b.T), atol=1e-6)
    # truth: target <- source = translation by +0.004 in x (plane points shift +x)
    np.testing.assert_allclose(np.asarray(a.T[:3, 3]), [0.004, 0, 0], atol=3e-4)
    # jit == eager with photo_points
    c = projective_icp(src, ti, jnp.eye(4), DEFAULT_ICP, None, **kw, photo_points=src.points)
    np.testing.assert_allclose(np.asarray(c.T), np.asarray(b.T), atol=2e-5)


def test_keypoint_noise_balance_matches_slow_loop():
    """normal_equations with keypoint_balance="noise": dense point-to-plane term plus each
    keypoint's across-ray residual weighted by exp(-r^2 / 2 sk^2) * s_g^2 / (sk / 3)^2,
    against an explicit float64 loop."""
    from jaxcr.registration.icp import IcpConfig, Keypoints, normal_equations

    rng = np.random.default_rng(3)
    n, k = 40, 7
    ps = rng.normal(0, 0.05, (n, 3)) + [0, 0, 0.3]
    nq = rng.normal(0, 1, (n, 3))
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    q = ps + rng.normal(0, 0.002, (n, 3))
    pl = np.sum((ps - q) * nq, 1)
    w = rng.random(n)
    ks = rng.normal(0, 0.05, (k, 3)) + [0, 0, 0.3]
    kt = ks + rng.normal(0, 0.002, (k, 3))
    mask = np.arange(k) < 6
    sk = 0.004
    cfg = IcpConfig(keypoint_weight=0.7, keypoint_balance="noise")
    f = jnp.float32
    kp = Keypoints(jnp.asarray(ks, f), jnp.asarray(kt, f), jnp.asarray(mask), f(sk))
    data = tuple(jnp.asarray(x, f) for x in (ps, q, nq, w, pl))
    H, g = normal_equations(jnp.eye(4), *data, cfg, kp)
    Hr, gr = np.zeros((6, 6)), np.zeros(6)
    for i in range(n):
        J = np.r_[nq[i], np.cross(ps[i], nq[i])]
        Hr += w[i] * np.outer(J, J)
        gr += w[i] * J * pl[i]
    s_g2 = np.sum(w * pl**2) / np.sum(w)
    for i in range(k):
        if not mask[i]:
            continue
        r = ks[i] - kt[i]
        wk = np.exp(-(r @ r) / (2 * sk**2)) * 0.7 * s_g2 / (sk / 3) ** 2
        ray = kt[i] / np.linalg.norm(kt[i])
        P = np.eye(3) - np.outer(ray, ray)
        x, y, z = ks[i]
        J = P @ np.c_[np.eye(3), -np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])]
        Hr += wk * J.T @ J
        gr += wk * J.T @ (P @ r)
    np.testing.assert_allclose(np.asarray(H), Hr, rtol=2e-4, atol=1e-6 * np.abs(Hr).max())
    np.testing.assert_allclose(np.asarray(g), gr, rtol=2e-4, atol=1e-5 * np.abs(gr).max())
    with pytest.raises(ValueError, match="keypoint_balance"):
        normal_equations(jnp.eye(4), *data, IcpConfig(keypoint_balance="x"), kp)
