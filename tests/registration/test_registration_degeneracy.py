"""Degeneracy-aware ICP (jaxcr.registration.icp.degeneracy_filter, scaled_coordinates) against
closed forms: the unobservable motions of a cylinder (rotation about its axis), a plane (two
in-plane shifts and the rotation about its normal) and a sphere (rotations about its
centre); no change on a surface that constrains every direction; unit invariance; and an
ICP whose dense term is given a known systematic error along a cylinder's free direction."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxcr.registration.icp import (
    CloudArrays,
    IcpConfig,
    Keypoints,
    degeneracy_filter,
    icp_jit,
    scaled_coordinates,
)
from jaxcr.registration.metrics import pose_error

RATIO = 0.01
_C0 = np.array([0.02, -0.01, 0.3])  # a point on the test cylinders' axis (camera frame)


def _normal_equations(p, n, r, w):
    """Point-to-plane normal equations in float64 numpy (independent of the JAX code):
    residual n.(p + omega x p + v - q) with value ``r`` at delta = 0, J = [n, p x n]."""
    J = np.concatenate([n, np.cross(p, n)], axis=1)
    return (J * w[:, None]).T @ J, (J * w[:, None]).T @ r


def _cylinder(
    rng,
    n=800,
    radius=0.05,
    height=0.13,
    axis_rot=(0.3, -0.2, 0.1),
    centre=tuple(_C0),
    span=1.3,
):
    """Points and outward normals on the side of a cylinder (azimuths within ``span`` rad of
    the camera-facing one) plus its top disc, in a camera frame; returns (points, normals,
    axis direction, a point on the axis)."""
    R = Rotation.from_rotvec(axis_rot).as_matrix()
    c0 = np.asarray(centre)
    k = int(0.75 * n)
    phi = rng.uniform(-span, span, k) + np.pi  # facing -z (towards the camera)
    z = rng.uniform(0, height, k)
    side = np.stack([radius * np.sin(phi), z - height / 2, radius * np.cos(phi)], -1)
    ns = np.stack([np.sin(phi), np.zeros(k), np.cos(phi)], -1)
    rr = radius * np.sqrt(rng.uniform(0, 1, n - k))
    th = rng.uniform(0, 2 * np.pi, n - k)
    top = np.stack([rr * np.sin(th), np.full(n - k, -height / 2), rr * np.cos(th)], -1)
    nt = np.tile([0.0, -1.0, 0.0], (n - k, 1))
    p = np.concatenate([side, top]) @ R.T + c0
    nn = np.concatenate([ns, nt]) @ R.T
    return p, nn, R @ np.array([0.0, 1.0, 0.0]), c0


def _screw(axis, c0):
    """delta = (v, omega) of a unit rotation about the line through c0 along ``axis``:
    p -> p + omega x (p - c0), i.e. v = -omega x c0."""
    return np.r_[-np.cross(axis, c0), axis]


# compiled once per point count and dtype (eagerly, each call compiled the filter's
# operations one by one at every new shape); the eager filter is checked against the compiled
# one in test_filter_is_unit_invariant_and_jit_equals_eager
_FILTER = jax.jit(degeneracy_filter, static_argnums=(4,))
_SCALED = jax.jit(scaled_coordinates)


def _filter64(H, g, p, w):
    with jax.enable_x64(True):
        Hf, gf, k = _FILTER(jnp.asarray(H), jnp.asarray(g), jnp.asarray(p), jnp.asarray(w), RATIO)
        return np.asarray(Hf), np.asarray(gf), int(k)


def test_scaled_coordinates_closed_form():
    # J delta == J' (A delta) with J' = [n, (p - c) x n / L] (c, L: weighted centroid and
    # RMS radius), for random deltas.
    rng = np.random.default_rng(0)
    p = rng.normal(0, 0.1, (50, 3)) + [0, 0, 0.5]
    n = rng.normal(0, 1, (50, 3))
    w = rng.uniform(0.1, 1.0, 50)
    c = w @ p / w.sum()
    L = np.sqrt(w @ np.sum((p - c) ** 2, 1) / w.sum())
    A = np.asarray(_SCALED(jnp.asarray(p, jnp.float32), jnp.asarray(w, jnp.float32)))
    J = np.concatenate([n, np.cross(p, n)], 1)
    Js = np.concatenate([n, np.cross(p - c, n) / L], 1)
    for _ in range(5):
        d = rng.normal(0, 1, 6)
        np.testing.assert_allclose(J @ d, Js @ (A @ d), rtol=1e-4, atol=1e-5)


def test_cylinder_loses_exactly_its_axis_rotation():
    rng = np.random.default_rng(1)
    p, n, axis, c0 = _cylinder(rng)
    w = rng.uniform(0.5, 1.0, len(p))
    r = rng.normal(0, 1e-3, len(p))
    H, g = _normal_equations(p, n, r, w)
    Hf, gf, k = _filter64(H, g, p, w)
    assert k == 1
    s = _screw(axis, c0)
    # the geometry is blind to the screw (closed form), and the filtered term has no
    # curvature and no gradient along it ...
    assert s @ H @ s < 1e-9 * np.trace(H)
    assert abs(s @ gf) < 1e-9 * np.linalg.norm(g) and np.linalg.norm(Hf @ s) < 1e-9 * np.trace(H)
    # ... while every delta with no screw component (orthogonal in the scaled metric) keeps
    # the original curvature and gradient.
    with jax.enable_x64(True):
        A = np.asarray(_SCALED(jnp.asarray(p), jnp.asarray(w)))
    u = A @ s / np.linalg.norm(A @ s)
    for _ in range(5):
        d = rng.normal(0, 1, 6)
        d = np.linalg.solve(A, A @ d - u * (u @ (A @ d)))
        np.testing.assert_allclose(d @ Hf @ d, d @ H @ d, rtol=1e-6)
        np.testing.assert_allclose(d @ gf, d @ g, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("shape, expected", [("plane", 3), ("sphere", 3), ("bumps", 0)])
def test_number_of_degenerate_directions(shape, expected):
    rng = np.random.default_rng(2)
    m = 900
    if shape == "plane":
        p = (
            np.c_[rng.uniform(-0.1, 0.1, (m, 2)), np.full(m, 0.4)]
            @ Rotation.from_rotvec([0.3, 0.2, 0]).as_matrix().T
        )
        n = np.tile(Rotation.from_rotvec([0.3, 0.2, 0]).apply([0, 0, -1.0]), (m, 1))
    elif shape == "sphere":
        d = rng.normal(0, 1, (m, 3))
        d[:, 2] = -np.abs(d[:, 2])
        n = d / np.linalg.norm(d, axis=1, keepdims=True)
        p = 0.06 * n + [0.01, 0.02, 0.4]
    else:  # a height field with bumps in both directions and a slope: nothing is free
        x, y = rng.uniform(-0.1, 0.1, (2, m))
        zf = 0.4 + 0.02 * np.sin(30 * x) + 0.02 * np.cos(25 * y)
        p = np.c_[x, y, zf]
        n = np.c_[0.6 * np.cos(30 * x), -0.5 * np.sin(25 * y), -np.ones(m)]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    w = np.ones(m)
    H, g = _normal_equations(p, n, rng.normal(0, 1e-3, m), w)
    Hf, gf, k = _filter64(H, g, p, w)
    assert k == expected
    if expected == 0:
        np.testing.assert_allclose(Hf, H, rtol=1e-9, atol=1e-12 * np.abs(H).max())
        np.testing.assert_allclose(gf, g, rtol=1e-9, atol=1e-12 * np.abs(g).max())


def test_filter_is_unit_invariant_and_jit_equals_eager():
    # The same cylinder in millimetres: same count of degenerate directions, and the same
    # Gauss-Newton step (translation x 1000, rotation unchanged).
    rng = np.random.default_rng(3)
    p, n, _, _ = _cylinder(rng, n=400)
    w = rng.uniform(0.5, 1.0, len(p))
    r = rng.normal(0, 1e-3, len(p))
    H, g = _normal_equations(p, n, r, w)
    Hk, gk = _normal_equations(p, n, np.zeros_like(r), w)
    Hk = Hk + 0.1 * np.eye(6) * np.trace(H) / 6  # a full-rank other term
    Hf, gf, k = _filter64(H, g, p, w)
    Hm, gm = _normal_equations(1000 * p, n, 1000 * r, w)
    Hfm, gfm, km = _filter64(Hm, gm, 1000 * p, w)
    S = np.diag([1000.0] * 3 + [1.0] * 3)  # delta_mm = S delta_m
    Si = np.linalg.inv(S)
    d_m = -np.linalg.solve(Hf + Hk, gf)
    d_mm = -np.linalg.solve(Hfm + Si.T @ Hk @ Si * 1e6, gfm)
    assert k == km == 1
    np.testing.assert_allclose(d_mm, S @ d_m, rtol=1e-6, atol=1e-9 * np.abs(d_mm).max())
    f = jax.jit(degeneracy_filter, static_argnums=(4,))
    args = [jnp.asarray(a, jnp.float32) for a in (H, g, p, w)]
    a = degeneracy_filter(*args, RATIO)
    b = f(*args, RATIO)
    # jit and eager are two float32 computations of the projector on the eigen-directions: a
    # rounding error there reaches every entry of P H P with the size of the largest, so the
    # bound is on max |jit - eager| / max |eager|, not entrywise (an entry 36x under the
    # largest moved by 4e-5 of itself on an SSE4.2 target, where rtol 1e-5 failed). Measured
    # over cylinder seeds 0-11 and four code generations (XLA's defaults; the tests' legacy
    # emitter; it with --xla_cpu_max_isa=SSE4_2; the tests' AVX level-0 flags, decisions T4):
    # at most 1.1e-6 (H) and 1.9e-6 (g), ~16 eps32; bound 2e-5, 10x that. A jit that computes
    # something else (another projector, the degenerate count) moves entries by O(max).
    for x, y in zip(a, b, strict=True):
        scale = float(np.max(np.abs(np.asarray(y))))
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=2e-5 * scale)


def _arrays(p, n, m=None):
    k = len(p)
    col = np.full((k, 3), 0.5, np.float32)
    return CloudArrays(
        jnp.asarray(p, jnp.float32),
        jnp.asarray(col),
        jnp.asarray(n, jnp.float32),
        jnp.ones(k, bool) if m is None else jnp.asarray(m),
    )


@pytest.fixture(scope="module")
def biased_cylinder():
    """Source / target clouds: two independent samples of the same whole cylinder (target <-
    source = a 2 deg rotation about the axis plus a 3 mm shift). The target's side points
    are 1.5 mm outside the true surface all around (no net push on the translation) and
    their normals tilted by 5 deg about the axis: a systematic model error whose
    point-to-plane residuals exert a torque about the axis, the one direction the geometry
    cannot observe."""
    rng = np.random.default_rng(5)
    p, n, axis, c0 = _cylinder(rng, n=2000, span=np.pi)
    ps, ns, _, _ = _cylinder(rng, n=2000, span=np.pi)
    Rt = Rotation.from_rotvec(np.deg2rad(2.0) * axis).as_matrix()
    T_true = np.eye(4)
    T_true[:3, :3] = Rt
    T_true[:3, 3] = c0 - Rt @ c0 + [0.003, 0.0, 0.0]
    Ti = np.linalg.inv(T_true)
    src_p = ps @ Ti[:3, :3].T + Ti[:3, 3]
    src_n = ns @ Ti[:3, :3].T
    side = np.abs(n @ axis) < 0.5
    tilt = Rotation.from_rotvec(np.deg2rad(5.0) * axis).as_matrix()
    tgt_n = np.where(side[:, None], n @ tilt.T, n)
    tgt_p = np.where(side[:, None], p + 0.0015 * n, p)
    # keypoints: 30 exact correspondences on the true side surface
    side_s = np.flatnonzero(np.abs(ns @ axis) < 0.5)
    idx = rng.choice(side_s, 30, replace=False)
    kp = Keypoints(
        jnp.asarray(src_p[idx], jnp.float32),
        jnp.asarray(ps[idx], jnp.float32),  # = T_true src_p[idx]
        jnp.ones(30, bool),
        jnp.float32(0.005),
    )
    return _arrays(src_p, src_n), _arrays(tgt_p, tgt_n), T_true, kp, axis


def _axis_angle_error(T, T_true, axis):
    E = T @ np.linalg.inv(T_true)
    return float(np.degrees(Rotation.from_matrix(E[:3, :3]).as_rotvec() @ axis))


def test_icp_degenerate_direction_comes_from_keypoints_not_biased_geometry(biased_cylinder):
    src, tgt, T_true, kp, axis = biased_cylinder
    base = dict(iterations=25, max_dist=0.02, min_dist=0.004, sigma_colour=1e3)
    T0 = jnp.eye(4, dtype=jnp.float32)
    plain = icp_jit(src, tgt, T0, IcpConfig(**base, keypoint_weight=0.3), kp)
    aware = icp_jit(
        src, tgt, T0, IcpConfig(**base, keypoint_weight=0.3, degeneracy_ratio=RATIO), kp
    )
    e_plain = _axis_angle_error(np.asarray(plain.T, np.float64), T_true, axis)
    e_aware = _axis_angle_error(np.asarray(aware.T, np.float64), T_true, axis)
    # the tilted normals drag the plain estimate about the axis; the degeneracy-aware one
    # takes that direction from the exact keypoints
    assert abs(e_plain) > 0.3, e_plain
    assert abs(e_aware) < 0.05, e_aware
    r, t = pose_error(np.asarray(aware.T, np.float64), T_true)
    # the observable directions carry the model error's own (small) share
    assert r < 0.15 and t < 1e-3, (r, t)


def test_icp_without_other_terms_keeps_the_seed_along_the_degenerate_direction(biased_cylinder):
    # Zhang et al.'s remapping: no keypoints, so the axis rotation stays at the seed (the
    # identity: -2 deg from the truth) while the observable directions are still solved.
    src, tgt, T_true, _, axis = biased_cylinder
    cfg = IcpConfig(
        iterations=25,
        max_dist=0.02,
        min_dist=0.004,
        sigma_colour=1e3,
        keypoint_weight=0.0,
        degeneracy_ratio=RATIO,
    )
    res = icp_jit(src, tgt, jnp.eye(4, dtype=jnp.float32), cfg)
    T = np.asarray(res.T, np.float64)
    R_axis = np.degrees(Rotation.from_matrix(T[:3, :3]).as_rotvec() @ axis)
    assert abs(R_axis) < 0.05, R_axis  # stayed at the seed's rotation about the axis
    assert abs(_axis_angle_error(T, T_true, axis) + 2.0) < 0.05
    # the rest is solved: the truth with its axis rotation undone, x -> x + R(-2 deg) shift
    # (closed form: T_true = x -> R(x - c0) + c0 + shift)
    T_exp = np.eye(4)
    T_exp[:3, 3] = T_true[:3, :3].T @ (T_true[:3, 3] - (np.eye(3) - T_true[:3, :3]) @ _C0)
    # (3 mm off at the seed; what remains is the tilted normals' share, as with keypoints)
    r, t = pose_error(T, T_exp)
    assert r < 0.25 and t < 1e-3, (r, t)
    assert float(res.fitness) > 0.7 and float(res.rmse) < 2e-3


def test_filter_vmap_equals_loop():
    rng = np.random.default_rng(7)
    batch = []
    for k in range(3):
        p, n, _, _ = _cylinder(rng, n=300, axis_rot=(0.2 * k, 0.1, -0.1 * k))
        w = rng.uniform(0.5, 1.0, len(p))
        H, g = _normal_equations(p, n, rng.normal(0, 1e-3, len(p)), w)
        batch.append([jnp.asarray(a, jnp.float32) for a in (H, g, p, w)])
    stacked = [jnp.stack(x) for x in zip(*batch, strict=True)]
    Hv, gv, kv = jax.vmap(lambda H, g, p, w: degeneracy_filter(H, g, p, w, RATIO))(*stacked)
    for i, args in enumerate(batch):
        Hl, gl, kl = degeneracy_filter(*args, RATIO)
        np.testing.assert_allclose(np.asarray(Hv[i]), np.asarray(Hl), rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(np.asarray(gv[i]), np.asarray(gl), rtol=1e-4, atol=1e-8)
        assert int(kv[i]) == int(kl) == 1
