"""Triangulation, epipolar geometry, monotone matching, and the plane / circular-arc fits
against OpenCV, brute force and closed forms."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxcr.camera import Camera
from jaxcr.stereo.correspondence import dtw_path_costs, dtw_path_costs_np, match_backbones
from jaxcr.stereo.fits import fit_arc, fit_plane, plane_angles
from jaxcr.stereo.triangulation import (
    essential_matrix,
    fundamental_matrix,
    sampson_distance,
    sampson_distance_np,
    triangulate_point,
    triangulate_points,
)


def _pair():
    c1 = Camera.look_at([0.25, 0.0, 0.1], [0.0, 0.0, 0.04], [0, 0, 1], 800.0, (640, 480))
    c2 = Camera.look_at([0.0, 0.25, 0.12], [0.0, 0.0, 0.04], [0, 0, 1], 800.0, (640, 480))
    return c1, c2


def _helix(n=80):
    t = np.linspace(0, 3.0, n)
    return np.stack([0.02 * np.cos(t), 0.02 * np.sin(t), 0.01 + 0.02 * t], 1)


def _norm_coords(cam, X):
    T = np.asarray(cam.T_cam_robot, np.float64)
    P = X @ T[:3, :3].T + T[:3, 3]
    return P[:, :2] / P[:, 2:]


def test_triangulation_matches_cv2():
    c1, c2 = _pair()
    X = _helix(40)
    x1, x2 = _norm_coords(c1, X), _norm_coords(c2, X)
    rng = np.random.default_rng(0)
    x1n = x1 + rng.normal(0, 5e-4, x1.shape)
    x2n = x2 + rng.normal(0, 5e-4, x2.shape)
    P1 = np.asarray(c1.T_cam_robot, np.float64)[:3]
    P2 = np.asarray(c2.T_cam_robot, np.float64)[:3]
    ref = cv2.triangulatePoints(P1, P2, x1n.T.copy(), x2n.T.copy())
    ref = (ref[:3] / ref[3]).T
    with jax.enable_x64(True):
        ours = np.asarray(
            triangulate_points(jnp.asarray(P1), jnp.asarray(P2), jnp.asarray(x1n), jnp.asarray(x2n))
        )
    np.testing.assert_allclose(ours, ref, atol=1e-9)
    # Exact data: exact points (float32 default path within 5 um).
    ours32 = np.asarray(
        triangulate_points(
            jnp.asarray(P1, jnp.float32),
            jnp.asarray(P2, jnp.float32),
            jnp.asarray(x1, jnp.float32),
            jnp.asarray(x2, jnp.float32),
        )
    )
    np.testing.assert_allclose(ours32, X, atol=5e-6)


def test_triangulation_vmap_loop_jit_and_gradient():
    c1, c2 = _pair()
    X = _helix(8)
    x1 = jnp.asarray(_norm_coords(c1, X), jnp.float32)
    x2 = jnp.asarray(_norm_coords(c2, X), jnp.float32)
    P1 = jnp.asarray(np.asarray(c1.T_cam_robot)[:3], jnp.float32)
    P2 = jnp.asarray(np.asarray(c2.T_cam_robot)[:3], jnp.float32)
    batched = triangulate_points(P1, P2, x1, x2)
    # the loop's single points and the x64 gradient below compiled (eagerly, op by op: ~70
    # small compilations); the eager batch is checked against the compiled one
    one = jax.jit(triangulate_point)
    loop = np.stack([np.asarray(one(P1, P2, x1[k], x2[k])) for k in range(8)])
    # two float32 programs of one formula (compiled differently: fusion, FMA contraction on the
    # host CPU); each is within 5e-6 of the exact point (test_triangulation_matches_cv2's
    # float32 bound), so they are within 1e-5 of each other
    np.testing.assert_allclose(batched, loop, atol=1e-5)
    np.testing.assert_allclose(jax.jit(triangulate_points)(P1, P2, x1, x2), batched, atol=1e-5)
    with jax.enable_x64(True):

        def f(a):
            return triangulate_point(
                jnp.asarray(P1, jnp.float64),
                jnp.asarray(P2, jnp.float64),
                a,
                jnp.asarray(x2[0], jnp.float64),
            )[0]  # noqa: E731

        a0 = np.asarray(x1[0], np.float64)
        g = jax.jit(jax.grad(f))(a0)
        fj = jax.jit(f)
        h = 1e-7
        fd = np.array([(fj(a0 + h * e) - fj(a0 - h * e)) / (2 * h) for e in np.eye(2)])
        np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-8)


def test_epipolar_matrices():
    c1, c2 = _pair()
    X = _helix(20)
    x1, x2 = _norm_coords(c1, X), _norm_coords(c2, X)
    E = np.asarray(
        essential_matrix(
            jnp.asarray(c1.T_cam_robot, jnp.float32), jnp.asarray(c2.T_cam_robot, jnp.float32)
        ),
        np.float64,
    )
    h1 = np.c_[x1, np.ones(20)]
    h2 = np.c_[x2, np.ones(20)]
    assert np.abs(np.einsum("ij,jk,ik->i", h2, E, h1)).max() < 1e-5
    F = np.asarray(fundamental_matrix(c1.K, c2.K, c1.T_cam_robot, c2.T_cam_robot), np.float64)
    u1 = h1 @ np.asarray(c1.K, np.float64).T
    u2 = h2 @ np.asarray(c2.K, np.float64).T
    Fcv, _ = cv2.findFundamentalMat(u1[:, :2], u2[:, :2], cv2.FM_8POINT)
    np.testing.assert_allclose(
        F / np.linalg.norm(F) * np.sign(F[2, 2]),
        Fcv / np.linalg.norm(Fcv) * np.sign(Fcv[2, 2]),
        atol=1e-3,
    )
    # Sampson distance: zero on true pairs, equals the numpy version, = the point-line
    # distance for an offset along the epiline normal in one image only (first order).
    S = np.asarray(sampson_distance(jnp.asarray(E), jnp.asarray(x1), jnp.asarray(x2)))
    np.testing.assert_allclose(S, sampson_distance_np(E, x1, x2), atol=1e-6)
    assert np.abs(np.diag(S)).max() < 1e-5


def _slow_dtw(c):
    n, m = c.shape
    D = np.full((n, m), np.inf)
    for i in range(n):
        for j in range(m):
            if i == 0 and j == 0:
                D[i, j] = c[0, 0]
                continue
            best = min(
                D[i - 1, j - 1] if i and j else np.inf,
                D[i - 1, j] if i else np.inf,
                D[i, j - 1] if j else np.inf,
            )
            D[i, j] = c[i, j] + best
    return D


def test_dtw_against_slow_loop():
    c = np.random.default_rng(1).random((17, 23))
    ref = _slow_dtw(c)
    D, K = dtw_path_costs(jnp.asarray(c, jnp.float32))
    Dn, Kn = dtw_path_costs_np(c)
    np.testing.assert_allclose(Dn, ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(D), ref, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(K), Kn)


def test_match_backbones_recovers_curve():
    c1, c2 = _pair()
    X = _helix(200)
    x1 = _norm_coords(c1, X)[::2]  # different sampling in the two views
    x2 = _norm_coords(c2, X)[::3]
    E = np.asarray(
        essential_matrix(
            jnp.asarray(c1.T_cam_robot, jnp.float32), jnp.asarray(c2.T_cam_robot, jnp.float32)
        ),
        np.float64,
    )
    y1, y2, q = match_backbones(E, x1, x2, cap=0.02)
    P1 = np.asarray(c1.T_cam_robot, np.float64)[:3]
    P2 = np.asarray(c2.T_cam_robot, np.float64)[:3]
    Y = cv2.triangulatePoints(P1, P2, y1.T.copy(), y2.T.copy())
    Y = (Y[:3] / Y[3]).T
    # Every triangulated point lies on the helix (dense truth) within 0.1 mm.
    Xd = _helix(4000)
    d = np.min(np.linalg.norm(Y[:, None] - Xd[None], axis=2), axis=1)
    assert np.percentile(d, 95) < 1e-4
    assert len(y1) >= max(len(x1), len(x2))
    # Arclength interpolation between well-conditioned matches stays on the curve too.
    z1, z2, _ = match_backbones(E, x1, x2, cap=0.02, min_quality=0.25)
    Z = cv2.triangulatePoints(P1, P2, z1.T.copy(), z2.T.copy())
    Z = (Z[:3] / Z[3]).T
    dz = np.min(np.linalg.norm(Z[:, None] - Xd[None], axis=2), axis=1)
    assert np.percentile(dz, 95) < 3e-4


# ----------------------------------------------------------------------------- fits


def _arc(R, sweep, n, rot, offset, noise=0.0, seed=0):
    t = np.linspace(0, sweep, n)
    P = np.stack([R * np.cos(t), R * np.sin(t), np.zeros(n)], 1) @ rot.T + offset
    return P + np.random.default_rng(seed).normal(0, noise, P.shape)


def _rot(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("R,sweep", [(0.03, 1.2), (0.008, 4.2), (0.2, 0.15)])
def test_arc_fit_closed_form(R, sweep):
    rot = _rot(3)
    P = _arc(R, sweep, 60, rot, np.array([0.01, -0.02, 0.03]))
    with jax.enable_x64(True):
        r = fit_arc(jnp.asarray(P))
        np.testing.assert_allclose(float(r["curvature"]), 1 / R, rtol=1e-6)
        np.testing.assert_allclose(float(r["arc_length"]), R * sweep, rtol=1e-6)
        n = np.asarray(r["normal"])
        assert abs(abs(n @ rot[:, 2]) - 1) < 1e-9
    r32 = fit_arc(jnp.asarray(P, jnp.float32))
    np.testing.assert_allclose(float(r32["curvature"]), 1 / R, rtol=2e-3)


# The arc tests use 60 points throughout (float32 and float64): fit_arc compiles once per
# shape and dtype, so the shapes are shared instead of one compile per test.
def test_arc_fit_noise_straight_padding_jit():
    rot = _rot(4)
    P = _arc(0.03, 1.0, 60, rot, np.zeros(3), noise=2e-5)
    r = fit_arc(jnp.asarray(P, jnp.float32))
    assert abs(float(r["curvature"]) * 0.03 - 1) < 0.02
    # Straight line: zero curvature, the line's length, no NaN; gradient finite.
    L = np.c_[np.zeros(60), np.zeros(60), np.linspace(0, 0.03, 60)]
    r = fit_arc(jnp.asarray(L, jnp.float32))
    assert float(r["curvature"]) < 1e-3 and abs(float(r["arc_length"]) - 0.03) < 1e-6
    g = jax.grad(lambda x: fit_arc(x)["curvature"])(
        jnp.asarray(L + 1e-4 * np.random.default_rng(0).normal(size=L.shape), jnp.float32)
    )
    assert np.all(np.isfinite(np.asarray(g)))
    # Zero-weight padding does not change the result.
    pad = np.concatenate([P, np.repeat(P[-1:], 20, 0)])
    w = np.r_[np.ones(60), np.zeros(20)]
    rp = fit_arc(jnp.asarray(pad, jnp.float32), jnp.asarray(w, jnp.float32))
    r0 = fit_arc(jnp.asarray(P, jnp.float32))
    np.testing.assert_allclose(float(rp["curvature"]), float(r0["curvature"]), rtol=1e-4)
    np.testing.assert_allclose(float(rp["arc_length"]), float(r0["arc_length"]), rtol=1e-4)


def test_arc_fit_gradient_vs_fd_and_vmap():
    rot = _rot(5)
    with jax.enable_x64(True):
        P = jnp.asarray(_arc(0.03, 1.0, 60, rot, np.zeros(3), noise=1e-4))
        f = lambda x: fit_arc(x)["curvature"]  # noqa: E731
        g = np.asarray(jax.grad(f)(P))
        h = 1e-8
        for idx in [(0, 0), (7, 2), (59, 1)]:  # both ends and an interior point
            e = np.zeros(P.shape)
            e[idx] = h
            fd = (f(P + e) - f(P - e)) / (2 * h)
            np.testing.assert_allclose(g[idx], fd, rtol=1e-3, atol=1e-3)
    Ps = jnp.asarray(
        np.stack([_arc(0.02 + 0.01 * k, 1.0, 60, _rot(k), np.zeros(3)) for k in range(3)]),
        jnp.float32,
    )
    batched = jax.vmap(fit_arc)(Ps)
    for k in range(3):
        np.testing.assert_allclose(batched["curvature"][k], fit_arc(Ps[k])["curvature"], rtol=1e-5)

    @eqx.debug.assert_max_traces(max_traces=1)
    def f2(x):
        return fit_arc(x)["curvature"]

    j = jax.jit(f2)
    for k in range(3):
        j(Ps[k])


@settings(max_examples=20, deadline=None)
@given(st.floats(0, np.pi), st.floats(-np.pi, np.pi))
def test_plane_angles_property(theta, phi):
    n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    a = np.asarray(plane_angles(jnp.asarray(n, jnp.float32)), np.float64)
    ref = np.degrees(np.arccos(np.clip(np.abs([n[2], n[1], n[0]]), 0, 1)))
    np.testing.assert_allclose(a, ref, atol=0.05)
    # Direction cosines: cos^2 sum to one.
    np.testing.assert_allclose(np.sum(np.cos(np.radians(a)) ** 2), 1.0, atol=1e-4)


def test_plane_fit_closed_form():
    rot = _rot(6)
    P = _arc(0.03, 1.5, 50, rot, np.array([0.0, 0.01, 0.0]))
    c, n = fit_plane(jnp.asarray(P, jnp.float32))
    assert abs(abs(float(np.asarray(n) @ rot[:, 2])) - 1) < 1e-5
    np.testing.assert_allclose(np.asarray(c), P.mean(0), atol=1e-7)
