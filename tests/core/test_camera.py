"""Camera projection tests against OpenCV, finite differences and loops.

Tolerances: against ``cv2.projectPoints`` 1e-6 px in x64 and the 1e-4 px contract in float32
(measured max 4e-5 px over 5000 points at 640x480; float32 eps 6e-8 relative on ~300 px values
gives ~2e-5 px per rounding).
"""

from __future__ import annotations

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from jaxcr.camera import (
    Camera,
    camera_from_arrays,
    monotonic_r2_limit,
    pixel_rays,
    project_points,
    project_xy,
    surface_points,
    undistort_normalized,
    unproject,
)
from tests.helpers.jitted import integrate_centreline  # compiled: input construction only

DIST = [-0.2, 0.05, 0.001, -0.002, 0.01]

# Compiled once per point count and dtype: called eagerly, project_points compiled each of its
# ~50 operations at every new shape (~480 small compilations in this module). Eager calls stay
# where eager is the point (jit == eager, project_xy == project_points), all on the (64, 3)
# float32 points, so their operations compile once.
PROJECT = eqx.filter_jit(project_points)


def make_camera(dist=DIST, size=(160, 120), eye=(0.1, -0.05, -0.3)):
    return Camera.look_at(eye, [0.0, 0.0, 0.05], [0.0, 0.0, 1.0], 300.0, size, fy=310.0, dist=dist)


def cv2_project(cam: Camera, P):
    T = np.asarray(cam.T_cam_robot, np.float64)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(
        np.asarray(P, np.float64),
        rvec,
        T[:3, 3],
        np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
    )
    return uv[:, 0]


def points(n=64, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * 0.03 + np.array([0.0, 0.0, 0.05])


def test_matches_opencv_x64():
    with jax.enable_x64(True):
        cam = make_camera()
        P = points()
        uv, valid = PROJECT(cam, jnp.asarray(P))
        assert uv.dtype == jnp.float64
        ref = cv2_project(cam, P)
        assert np.asarray(valid).sum() > 40
        np.testing.assert_allclose(np.asarray(uv), ref, atol=1e-6)


def test_matches_opencv_float32():
    cam = make_camera()
    P = points(seed=1)
    uv, valid = PROJECT(cam, jnp.asarray(P, jnp.float32))
    assert uv.dtype == jnp.float32
    ref = cv2_project(cam, P)
    v = np.asarray(valid)
    assert v.sum() > 40
    np.testing.assert_allclose(np.asarray(uv)[v], ref[v], atol=1e-4)


def test_skew_is_applied():
    # cv2.projectPoints ignores K[0, 1]; we honour it: u = fx x'' + s y'' + cx.
    cam = make_camera()
    K = np.asarray(cam.K, np.float64)
    K[0, 1] = 2.5
    skewed = camera_from_arrays(K, cam.dist, cam.T_cam_robot, 160, 120)
    P = jnp.asarray(points(seed=1), jnp.float32)
    uv0, _ = PROJECT(cam, P)
    uv1, _ = PROJECT(skewed, P)
    yd = (np.asarray(uv0[:, 1]) - K[1, 2]) / K[1, 1]
    np.testing.assert_allclose(np.asarray(uv1[:, 0] - uv0[:, 0]), 2.5 * yd, atol=2e-3)
    np.testing.assert_allclose(np.asarray(uv1[:, 1]), np.asarray(uv0[:, 1]), atol=1e-5)


def test_project_xy_matches_project_points():
    cam = make_camera()
    P = jnp.asarray(points(), jnp.float32)
    u, v, valid = project_xy(cam, P)
    uv, valid2 = project_points(cam, P)
    np.testing.assert_array_equal(np.asarray(u), np.asarray(uv[:, 0]))
    np.testing.assert_array_equal(np.asarray(v), np.asarray(uv[:, 1]))
    np.testing.assert_array_equal(np.asarray(valid), np.asarray(valid2))


def test_behind_camera_and_outside_image_masked_and_finite():
    cam = camera_from_arrays(
        np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]]), np.zeros(5), None, 100, 80
    )
    P = jnp.array(
        [
            [0.0, 0.0, 1.0],  # centre: valid
            [0.0, 0.0, -1.0],  # behind
            [0.0, 0.0, 0.0],  # on the camera plane
            [0.0, 0.0, 1e-9],  # nearer than near
            [1.0, 0.0, 1.0],  # u = 149.5: right of image
            [-0.4949, 0.0, 1.0],  # u = 0.01: valid
            [-0.5, 0.0, 1.0],  # u = -0.5: exactly the left edge: valid (OpenCV centres)
            [-0.5051, 0.0, 1.0],  # u = -1.01: outside
            [0.0, 0.399, 1.0],  # v = 79.4: valid
            [0.0, 0.4, 1.0],  # v = 79.5: outside (half-open)
            [1e6, -1e6, 1e-3],  # far off: clamped
        ]
    )
    uv, valid = PROJECT(cam, P)
    assert np.all(np.isfinite(np.asarray(uv)))
    np.testing.assert_array_equal(
        np.asarray(valid), [True, False, False, False, False, True, True, False, True, False, False]
    )
    assert np.all(np.asarray(uv[:, 0]) <= 200) and np.all(np.asarray(uv[:, 0]) >= -100)
    assert np.all(np.asarray(uv[:, 1]) <= 160) and np.all(np.asarray(uv[:, 1]) >= -80)
    # gradients stay finite for invalid points too
    g = jax.jit(jax.grad(lambda p: project_points(cam, p)[0].sum()))(P)
    assert np.all(np.isfinite(np.asarray(g)))


def test_strong_barrel_distortion_never_folds_into_image():
    # k1 < 0 alone: r_d = r (1 + k1 r^2) peaks at r^2 = -1/(3 k1) and folds back afterwards.
    cam = camera_from_arrays(
        np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]]), [-0.5, 0, 0, 0, 0], None, 100, 80
    )
    r2_lim = float(monotonic_r2_limit(cam))
    assert r2_lim <= 1.0 / 1.5 and r2_lim > 0.9 / 1.5
    # point at r = 1.6 (far outside the monotonic range): raw OpenCV maps it inside the image
    P = np.array([[1.6, 0.0, 1.0]])
    ref = cv2_project(cam, P)
    assert -0.5 <= ref[0, 0] < 99.5  # the fold-over we guard against
    uv, valid = PROJECT(cam, jnp.asarray(P, jnp.float32))
    assert not bool(valid[0])
    assert float(uv[0, 0]) > 99.5 or float(uv[0, 0]) < -0.5


def test_jit_equals_eager_and_single_trace():
    cam = make_camera()
    P = jnp.asarray(points(), jnp.float32)
    f = eqx.filter_jit(eqx.debug.assert_max_traces(project_points, max_traces=1))
    uv_j, valid_j = f(cam, P)
    uv_e, valid_e = project_points(cam, P)
    np.testing.assert_allclose(np.asarray(uv_j), np.asarray(uv_e), rtol=1e-6, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(valid_j), np.asarray(valid_e))
    cam2 = make_camera(eye=(0.0, 0.1, -0.25))
    f(cam2, P + 0.01)  # new values, same shapes: no retrace


@pytest.mark.parametrize("n", [1, 7, 64])
def test_shapes(n):
    cam = make_camera()
    uv, valid = PROJECT(cam, jnp.asarray(np.zeros((n, 3), np.float32) + [0.0, 0.0, 0.05]))
    assert uv.shape == (n, 2) and valid.shape == (n,) and valid.dtype == jnp.bool_


def test_vmap_over_cameras_and_point_sets_equals_loop():
    cams = [make_camera(eye=(0.1 * i, -0.05, -0.3)) for i in range(3)]
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *cams)
    P = np.asarray(points(), np.float32)
    # compiled vmaps (run eagerly, each compiled its operations one by one); the loop's
    # single calls are PROJECT's (64, 3) float32 program
    uv_v, valid_v = jax.jit(jax.vmap(project_points, in_axes=(0, None)))(stacked, P)
    for i, c in enumerate(cams):
        uv_l, valid_l = PROJECT(c, jnp.asarray(P))
        np.testing.assert_allclose(np.asarray(uv_v[i]), np.asarray(uv_l), rtol=1e-6, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(valid_v[i]), np.asarray(valid_l))
    Ps = np.stack([P, P * np.float32(1.1), P - np.float32(0.01)])
    uv_v, _ = jax.jit(jax.vmap(project_points, in_axes=(None, 0)))(cams[0], Ps)
    for i in range(3):
        np.testing.assert_allclose(
            np.asarray(uv_v[i]), np.asarray(PROJECT(cams[0], jnp.asarray(Ps[i]))[0]), rtol=1e-6,
            atol=1e-4,
        )  # fmt: skip


def test_grad_vs_finite_differences():
    with jax.enable_x64(True):
        cam = make_camera()
        P = jnp.asarray(points(8, seed=3))
        w = jnp.asarray(np.random.default_rng(4).normal(size=(8, 2)))

        @jax.jit
        def f(P, K, dist, T):
            c = Camera(K=K, dist=dist, T_cam_robot=T, width=cam.width, height=cam.height)
            return jnp.sum(project_points(c, P)[0] * w)

        args = (P, cam.K, cam.dist, cam.T_cam_robot)
        grads = jax.grad(f, argnums=(0, 1, 2, 3))(*args)
        eps = 1e-6
        for a, (arg, g) in enumerate(zip(args, grads, strict=True)):
            flat = np.asarray(arg).ravel()
            fd = np.zeros_like(flat)
            for i in range(flat.size):
                d = np.zeros_like(flat)
                d[i] = eps
                hi = list(args)
                lo = list(args)
                hi[a] = jnp.asarray((flat + d).reshape(arg.shape))
                lo[a] = jnp.asarray((flat - d).reshape(arg.shape))
                fd[i] = (f(*hi) - f(*lo)) / (2 * eps)
            np.testing.assert_allclose(
                np.asarray(g).ravel(), fd, rtol=1e-5, atol=1e-4 * max(1.0, np.abs(fd).max())
            )


def test_undistort_matches_opencv():
    with jax.enable_x64(True):
        cam = make_camera()
        uv, valid = PROJECT(cam, jnp.asarray(points(seed=5)))  # test_matches_opencv_x64's
        xy = undistort_normalized(cam, uv)
        ref = cv2.undistortPoints(
            np.asarray(uv)[:, None],
            np.asarray(cam.K),
            np.asarray(cam.dist),
            R=np.eye(3),
            P=np.eye(3),
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15),
        )[:, 0]
        np.testing.assert_allclose(np.asarray(xy), ref, atol=1e-10)


@eqx.filter_jit
def _round_trip(cam, uv, depth):
    P = unproject(cam, uv, depth)
    uv2, valid = project_points(cam, P)
    origin, d = pixel_rays(cam, uv)
    return P, uv2, valid, origin, d


_pixel = st.tuples(st.floats(0.0, 159.0), st.floats(0.0, 119.0), st.floats(0.05, 2.0))


@settings(max_examples=25, deadline=None, derandomize=True)
@given(samples=st.lists(_pixel, min_size=8, max_size=8))
def test_unproject_project_round_trip(samples):
    with jax.enable_x64(True):
        cam = make_camera(dist=[-0.1, 0.02, 0.001, -0.001, 0.0])
        arr = np.array(samples, np.float64)
        uv = jnp.asarray(arr[:, :2])
        P, uv2, valid, origin, d = _round_trip(cam, uv, jnp.asarray(arr[:, 2]))
        assert np.all(np.asarray(valid))
        np.testing.assert_allclose(np.asarray(uv2), arr[:, :2], atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=1), 1.0, atol=1e-12)
        along = np.asarray(P) - np.asarray(origin)
        np.testing.assert_allclose(np.cross(along, np.asarray(d)), 0.0, atol=1e-9)
        assert np.all(np.einsum("ij,ij->i", along, np.asarray(d)) > 0)
        np.testing.assert_allclose(np.asarray(P @ cam.R[2] + cam.t[2]), arr[:, 2], rtol=1e-12)


def test_look_at_geometry():
    cam = Camera.look_at([0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 100.0, (101, 81))
    np.testing.assert_allclose(np.asarray(cam.centre), [0, 0, -1], atol=1e-6)
    R = np.asarray(cam.R)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) > 0
    uv, valid = PROJECT(cam, jnp.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    np.testing.assert_allclose(np.asarray(uv[0]), [50.0, 40.0], atol=1e-4)  # target at centre
    assert float(uv[1, 1]) < 40.0  # +up appears higher in the image (smaller row)
    with pytest.raises(ValueError):
        Camera.look_at([0, 0, 0], [0, 0, 1], [0, 0, 1], 100.0, (10, 10))


def test_camera_from_arrays_dist_lengths():
    K = np.array([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]])
    assert camera_from_arrays(K, [0.1, 0.2, 0.0, 0.0], None, 20, 20).dist.shape == (5,)
    assert float(
        camera_from_arrays(K, [0.1, 0.2, 0, 0, 0.3, 0, 0, 0], None, 20, 20).dist[4]
    ) == pytest.approx(0.3)
    with pytest.raises(ValueError):
        camera_from_arrays(K, [0.1, 0.2, 0, 0, 0.3, 0.1, 0, 0], None, 20, 20)
    with pytest.raises(ValueError):
        camera_from_arrays(K, [0.1, 0.2, 0], None, 20, 20)


# compiled once per shape (the vmap == loop check is test_surface_points_jit_vmap_grad's)
SURFACE = jax.jit(surface_points, static_argnums=1)
R0 = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix().astype(np.float32)  # = so3_exp


def _centreline(kappa=20.0, n=16):
    # numpy inputs of the compiled integrate_centreline: no eager jnp op to compile
    s = np.linspace(0.0, 0.1, n, dtype=np.float32)
    u = np.tile(np.array([kappa, 0.0, 0.0], np.float32), (n - 1, 1))
    rho = np.linspace(1e-3, 0.5e-3, n, dtype=np.float32)
    return integrate_centreline(s, u, rho, R0=R0)


def test_surface_points_eq7_loop_reference():
    cl = _centreline()
    n_phi = 6
    S = np.asarray(SURFACE(cl, n_phi))
    assert S.shape == (16, n_phi, 3)
    p, R, rho = (np.asarray(a, np.float64) for a in (cl.p, cl.R, cl.rho))
    for i in range(16):
        for k in range(n_phi):
            phi = 2 * np.pi * k / n_phi
            Rz = np.array(
                [[np.cos(phi), -np.sin(phi), 0], [np.sin(phi), np.cos(phi), 0], [0, 0, 1]]
            )
            ref = p[i] + R[i] @ Rz @ np.array([rho[i], 0.0, 0.0])
            np.testing.assert_allclose(np.asarray(S[i, k]), ref, atol=1e-6)
    # every surface point is rho from the centreline, perpendicular to the tangent
    d = np.asarray(S) - p[:, None]
    np.testing.assert_allclose(
        np.linalg.norm(d, axis=-1), np.broadcast_to(rho[:, None], (16, n_phi)), rtol=1e-5
    )
    np.testing.assert_allclose(np.einsum("nkj,nj->nk", d, R[:, :, 2]), 0.0, atol=1e-8)


def test_surface_points_jit_vmap_grad():
    cls = [_centreline(k) for k in (0.0, 10.0, 30.0)]
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *cls)
    f = SURFACE
    Sv = jax.jit(jax.vmap(surface_points, in_axes=(0, None)), static_argnums=1)(stacked, 8)
    for i, c in enumerate(cls):
        np.testing.assert_allclose(np.asarray(Sv[i]), np.asarray(f(c, 8)), atol=1e-6)
        np.testing.assert_allclose(np.asarray(f(c, 8)), np.asarray(surface_points(c, 8)), atol=1e-6)
    with jax.enable_x64(True):
        c = _centreline().__class__(
            *(
                jnp.asarray(np.asarray(a, np.float64))
                for a in (cls[1].s, cls[1].p, cls[1].R, cls[1].u, cls[1].rho)
            )
        )
        g = jax.jit(jax.grad(
            lambda rho: surface_points(eqx.tree_at(lambda x: x.rho, c, rho), 5)[..., 0].sum()
        ))(c.rho)  # fmt: skip
        R = np.asarray(c.R)
        phi = 2 * np.pi * np.arange(5) / 5
        expected = (
            np.cos(phi)[None] * R[:, 0, 0][:, None] + np.sin(phi)[None] * R[:, 0, 1][:, None]
        ).sum(1)
        np.testing.assert_allclose(np.asarray(g), expected, atol=1e-12)
