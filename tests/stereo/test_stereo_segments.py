"""Diameters (silhouette widths, cylinder method), segment identification, slope-angle
segmentation and the chroma key against closed forms and brute force."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera, project_points
from jaxcr.stereo.chroma import (
    KEY_COLOURS,
    chroma_alpha,
    chroma_score,
    key_projection,
    plate_alpha,
    plate_alpha_shadow_invariant,
)
from jaxcr.stereo.diameter import cylinder_diameters, profile_widths, view_weights
from jaxcr.stereo.segments import piecewise_constant, segment_backbone
from jaxcr.stereo.shadow import slope_angle_segments


def _tangent_edges(cam, P, t, r):
    """Exact silhouette edge pixels of the cylinder (axis point P, direction t, radius r)
    at P: the tangent planes through the camera centre, intersected with the plane through
    the camera centre, P and perpendicular to t... computed by sampling the circle."""
    C = np.asarray(cam.centre, np.float64)
    t = t / np.linalg.norm(t)
    a = np.cross(t, [0.3, 0.5, 0.8])
    a /= np.linalg.norm(a)
    b = np.cross(t, a)
    phi = np.linspace(0, 2 * np.pi, 20001)
    ring = P + r * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)
    uv, _ = project_points(cam, jnp.asarray(ring))
    uv = np.asarray(uv, np.float64)
    c_uv = np.asarray(project_points(cam, jnp.asarray(P[None]))[0][0], np.float64)
    c2, _ = project_points(cam, jnp.asarray((P + 1e-4 * t)[None]))
    du = np.asarray(c2[0], np.float64) - c_uv
    n = np.array([-du[1], du[0]]) / np.linalg.norm(du)
    # Extreme offsets of the ring's image along the normal, through lines parallel to the
    # projected axis; the silhouette edges of the cylinder are the envelopes of the rings.
    off = (uv - c_uv) @ n
    del C
    return c_uv, n, off.min(), off.max()


def test_cylinder_diameter_any_orientation():
    with jax.enable_x64(True):
        cam = Camera.look_at([0.0, -0.25, 0.1], [0.0, 0.0, 0.05], [0, 0, 1], 800.0, (640, 480))
        rng = np.random.default_rng(0)
        for _ in range(6):
            P = np.array([0.0, 0.0, 0.05]) + rng.normal(0, 0.02, 3)
            t = rng.normal(size=3)
            t /= np.linalg.norm(t)
            view = P - np.asarray(cam.centre)
            if abs(t @ view / np.linalg.norm(view)) > 0.9:
                continue
            c_uv, n, lo, hi = _tangent_edges(cam, P, t, 0.0012)
            d = cylinder_diameters(
                cam,
                jnp.asarray(P[None]),
                jnp.asarray(t[None]),
                jnp.asarray(c_uv[None]),
                jnp.asarray(n[None]),
                jnp.asarray([hi - lo]),
                jnp.asarray([(hi + lo) / 2]),
            )
            # The ring extremes approximate the cylinder's silhouette to second order in
            # r / distance.
            np.testing.assert_allclose(float(d[0]), 0.0024, rtol=2e-3)
            w = float(view_weights(cam, jnp.asarray(P[None]), jnp.asarray(t[None]))[0])
            assert 0 < w <= 1


def _stripe(width, angle, centre=(40.3, 30.7), shape=(64, 80), ss=16):
    """Anti-aliased stripe image (exact area coverage by supersampling)."""
    h, w = shape
    yy, xx = np.mgrid[0 : h * ss, 0 : w * ss]
    x = (xx + 0.5) / ss - 0.5
    y = (yy + 0.5) / ss - 0.5
    n = np.array([-np.sin(angle), np.cos(angle)])
    inside = np.abs((x - centre[0]) * n[0] + (y - centre[1]) * n[1]) <= width / 2
    return inside.reshape(h, ss, w, ss).mean(axis=(1, 3)), n


def test_profile_width_subpixel():
    key = np.array(KEY_COLOURS["green"])
    tube = np.array([0.35, 0.36, 0.37])
    for width, angle in itertools.product([3.3, 5.0, 7.6], [0.0, 0.4, 1.1]):
        cov, n = _stripe(width, angle)
        img = cov[..., None] * tube + (1 - cov[..., None]) * key
        im = jnp.asarray(img, jnp.float32)
        alpha = chroma_alpha(im, jnp.asarray(key, jnp.float32), 0.5, 0.8)
        kp = key_projection(im, jnp.asarray(key, jnp.float32))
        c = jnp.asarray([[40.3, 30.7]], jnp.float32)
        nn = jnp.asarray(n[None], jnp.float32)
        wl, off = profile_widths(alpha, c, nn, kp)
        assert abs(float(wl[0]) - width) < 0.05, (width, angle, float(wl[0]))
        assert abs(float(off[0])) < 0.05
        # Without the linear key projection: the alpha integral, good to ~0.5 px.
        wa, _ = profile_widths(alpha, c, nn)
        assert abs(float(wa[0]) - width) < 0.6


def test_chroma_scores_and_plate():
    key = jnp.asarray(KEY_COLOURS["green"], jnp.float32)
    s = chroma_score(
        jnp.asarray(
            [[KEY_COLOURS["green"], [0.05, 0.2, 0.07], [0.4, 0.4, 0.4], [0.6, 0.3, 0.3]]],
            jnp.float32,
        ),
        key,
    )
    s = np.asarray(s)[0]
    assert abs(s[0] - 1) < 1e-6 and s[1] > 0.8  # shadowed cloth stays key-like
    assert abs(s[2]) < 1e-3 and s[3] < 0  # grey and red are not
    a = np.asarray(
        chroma_alpha(
            jnp.asarray([[KEY_COLOURS["blue"], [0.4, 0.4, 0.4]]], jnp.float32),
            jnp.asarray(KEY_COLOURS["blue"], jnp.float32),
        )
    )
    np.testing.assert_allclose(a[0], [0.0, 1.0])
    img = jnp.zeros((2, 2, 3)).at[0, 0].set(0.5)
    np.testing.assert_allclose(np.asarray(plate_alpha(img, jnp.zeros((2, 2, 3)))), [[1, 0], [0, 0]])


def _brute_piecewise(y, k, min_len=3):
    n = len(y)
    best = (np.inf, None)
    for cuts in itertools.combinations(range(min_len, n - min_len + 1), k - 1):
        b = (0, *cuts, n)
        if any(b[i + 1] - b[i] < min_len for i in range(k)):
            continue
        e = sum(((y[b[i] : b[i + 1]] - y[b[i] : b[i + 1]].mean()) ** 2).sum() for i in range(k))
        if e < best[0]:
            best = (e, np.array(b[:-1]))
    return best


def test_piecewise_constant_vs_brute_force():
    rng = np.random.default_rng(2)
    y = np.r_[np.full(7, 2.4), np.full(6, 1.8), np.full(8, 1.2)] + rng.normal(0, 0.05, 21)
    for k in (1, 2, 3):
        starts, e = piecewise_constant(y, k)
        e_ref, st_ref = _brute_piecewise(y, k)
        np.testing.assert_allclose(e, e_ref, rtol=1e-9)
        np.testing.assert_array_equal(starts, st_ref)


def test_segment_backbone_steps():
    s = np.arange(0, 0.1, 5e-4)
    d = np.where(s < 0.04, 2.4e-3, np.where(s < 0.07, 1.8e-3, 1.2e-3))
    d = d + np.random.default_rng(0).normal(0, 3e-5, len(s))
    d[50] = 5e-3  # an outlier (e.g. the curl crossing the profile)
    seg = segment_backbone(s, d)
    assert len(seg["starts"]) == 3
    np.testing.assert_allclose(seg["boundaries_s"], [0.04, 0.07], atol=1e-3)
    np.testing.assert_allclose(seg["diameters"], [2.4e-3, 1.8e-3, 1.2e-3], rtol=0.01)
    seg2 = segment_backbone(s, d, n_segments=2)
    assert len(seg2["starts"]) == 2


def test_slope_angle_segments():
    # An L-shaped polyline (e.g. shadow along the floor, then the tube rising).
    a = np.stack([np.linspace(0, 30, 31), np.zeros(31)], 1)
    b = np.stack([np.full(30, 30.0), np.linspace(1, 30, 30)], 1)
    segs = slope_angle_segments(np.concatenate([a, b]), tolerance_deg=20, j=3)
    # Slopes that straddle the corner open short transitional segments (<= j points), as
    # in the report's Fig. 18; the two long ones are the two legs.
    long = [sg for sg in segs if len(sg) > 3]
    assert len(long) == 2
    assert abs(long[0][-1] - 30) <= 3 and abs(long[1][0] - 30) <= 3
    # Concatenation covers everything in order.
    np.testing.assert_array_equal(np.concatenate(segs), np.arange(61))
    # A larger tolerance merges a gentle bend; a smaller one splits it.
    t = np.linspace(0, np.radians(40), 60)
    arc = np.stack([np.sin(t), 1 - np.cos(t)], 1) * 50
    assert len(slope_angle_segments(arc, 60)) == 1
    assert len(slope_angle_segments(arc, 10)) > 1
    assert len(slope_angle_segments(np.stack([np.arange(20.0), np.zeros(20)], 1), 1)) == 1


def test_segment_backbone_ignores_a_widening_bump():
    # A curled tip touching the silhouette widens the profile locally; tubes only get
    # thinner towards the tip, so the bump is not a segment.
    s = np.arange(0, 0.065, 5e-4)
    d = np.where(s < 0.048, 2.4e-3, 1.8e-3)
    d = np.where((s > 0.042) & (s < 0.047), 3.0e-3, d)
    seg = segment_backbone(s, d)
    assert len(seg["starts"]) == 2
    np.testing.assert_allclose(seg["boundaries_s"], [0.048], atol=1e-3)


def test_shadow_invariant_plate():
    plate = jnp.asarray(np.tile(np.array(KEY_COLOURS["green"]), (1, 3, 1)), jnp.float32)
    img = plate.at[0, 1].multiply(0.45).at[0, 2].set(jnp.asarray([0.4, 0.4, 0.42]))
    a_plain = np.asarray(plate_alpha(img, plate))[0]
    a_inv = np.asarray(plate_alpha_shadow_invariant(img, plate))[0]
    np.testing.assert_allclose(a_plain, [0, 1, 1])  # the shadow counts as foreground
    np.testing.assert_allclose(a_inv, [0, 0, 1])  # not any more; the grey tube still does
