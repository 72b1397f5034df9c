"""Contour extraction (Reiter et al. Sec. III-B.2): hull vs cv2.convexHull, Bresenham vs
cv2.line, Sobel vs cv2.Sobel, snapping vs brute force, concave pull-in, descriptor
histogram vs numpy.histogram."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxcr.eigen.contour import (
    bresenham,
    contour_points,
    convex_hull,
    densify_polygon,
    polyline_pixels,
    snap_to_nearest,
    sobel,
    sobel_edges,
    sobel_edges_batch,
)
from jaxcr.eigen.descriptor import (
    MIN_MARKER_PIXELS,
    Contours,
    angular_histogram,
    contour_histograms,
    mask_contours,
    mask_descriptors,
    stereo_descriptor,
)
from jaxcr.eigen.pipeline import StereoContours, stereo_histograms, view_centres
from jaxcr.errors import InputError


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 60))
def test_convex_hull_matches_cv2(seed, n):
    pts = np.random.default_rng(seed).integers(0, 50, (n, 2))
    ours = convex_hull(pts)
    ref = cv2.convexHull(pts.astype(np.int32)).reshape(-1, 2)
    # Same vertex set (cv2 drops collinear points too); orientation is a convention.
    assert {tuple(p) for p in ours} == {tuple(p) for p in ref}


@settings(max_examples=60, deadline=None)
@given(st.integers(-20, 20), st.integers(-20, 20), st.integers(-20, 20), st.integers(-20, 20))
def test_bresenham_matches_cv2_line(x0, y0, x1, y1):
    ours = bresenham(np.array([x0, y0]), np.array([x1, y1]))
    img = np.zeros((64, 64), np.uint8)
    cv2.line(img, (x0 + 30, y0 + 30), (x1 + 30, y1 + 30), 255, 1, cv2.LINE_8)
    ys, xs = np.nonzero(img)
    ref = {(x - 30, y - 30) for x, y in zip(xs, ys, strict=True)}
    got = {tuple(p) for p in ours}
    # Same count and endpoints; 8-connected; at most a few tie-broken pixels differ.
    assert len(got) == len(ref) == max(abs(x1 - x0), abs(y1 - y0)) + 1
    assert (x0, y0) in got and (x1, y1) in got
    steps = np.abs(np.diff(ours, axis=0))
    assert np.all(steps.max(axis=1) == 1)
    # Each pixel is a nearest pixel to the ideal line along the major axis (exact halves are
    # ties, broken differently by OpenCV, so the sets may differ there only).
    dx, dy = x1 - x0, y1 - y0
    for x, y in got:
        if abs(dx) >= abs(dy):
            assert abs(y - (y0 + dy * (x - x0) / dx if dx else y0)) <= 0.5 + 1e-9
        else:
            assert abs(x - (x0 + dx * (y - y0) / dy)) <= 0.5 + 1e-9
    for x, y in got ^ ref:
        if abs(dx) >= abs(dy):
            assert dx and np.isclose(abs(y - (y0 + dy * (x - x0) / dx)), 0.5)
        else:
            assert np.isclose(abs(x - (x0 + dx * (y - y0) / dy)), 0.5)


def test_sobel_matches_cv2():
    rng = np.random.default_rng(0)
    img = rng.random((24, 31)).astype(np.float32)
    gx, gy = sobel(jnp.asarray(img))
    np.testing.assert_allclose(np.asarray(gx), cv2.Sobel(img, cv2.CV_32F, 1, 0), atol=1e-5)
    np.testing.assert_allclose(np.asarray(gy), cv2.Sobel(img, cv2.CV_32F, 0, 1), atol=1e-5)
    # Differentiable; jit == eager.
    g = jax.grad(lambda x: sobel(x)[0].sum())(jnp.asarray(img))
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_array_equal(np.asarray(jax.jit(sobel)(img)[1]), np.asarray(gy))


def test_sobel_edges_batch_equals_loop():
    m = np.zeros((3, 20, 20), bool)
    m[0, 5:10, 5:12] = True
    m[1, 2:18, 9:11] = True
    m[2, 0:4, 0:4] = True
    out = np.asarray(sobel_edges_batch(jnp.asarray(m)))
    loop = np.stack([np.asarray(sobel_edges(jnp.asarray(x))) for x in m])
    np.testing.assert_array_equal(out, loop)
    # Inner border of a rectangle: the ring of labelled pixels touching the outside.
    ring = m[0] & ~cv2.erode(m[0].astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    np.testing.assert_array_equal(out[0], ring)


def test_snap_matches_brute_force():
    rng = np.random.default_rng(4)
    p = rng.random((700, 2)) * 50
    t = rng.integers(0, 50, (300, 2))
    got = snap_to_nearest(p, t, chunk=128)
    d_ref = np.sqrt(((p[:, None] - t[None]) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(np.linalg.norm(got - p, axis=1), d_ref, atol=1e-12)


def test_densify_spacing_and_vertices():
    v = np.array([[0, 0], [10, 0], [10, 7]])
    d = densify_polygon(v, 2.0)
    nxt = np.roll(d, -1, axis=0)
    assert np.linalg.norm(nxt - d, axis=1).max() <= 2.0 + 1e-12
    for q in v:
        assert np.any(np.all(d == q, axis=1))


def _banana(h=60, w=80):
    """A concave arc-shaped band (like a bent segment) as a binary image."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - 40, yy - 65)
    return (r > 35) & (r < 45) & (yy < 50)


def test_contour_follows_concave_side():
    m = _banana()
    pts = contour_points(m, spacing=2.0)
    outside = ~m[pts[:, 1], pts[:, 0]]
    hull_line = polyline_pixels(convex_hull(np.stack(np.nonzero(m)[::-1], 1)))
    hull_out = ~m[hull_line[:, 1], hull_line[:, 0]]
    # The hull chord across the concave side runs through unlabelled pixels (> 20 % of the
    # hull line); after snapping, only Bresenham fill between neighbouring snapped points
    # can leave the region, and never by more than the control spacing.
    assert hull_out.mean() > 0.2 and outside.mean() < 0.15
    dist_out = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 5)
    assert dist_out[pts[:, 1], pts[:, 0]].max() <= 1.5
    # Bresenham joins are 8-connected: every point has a neighbour in the set.
    s = {tuple(p) for p in pts}
    assert all(
        any((x + a, y + b) in s for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b) for x, y in s
    )
    assert len(contour_points(np.zeros((10, 10), bool))) == 0


def test_angular_histogram_matches_numpy():
    rng = np.random.default_rng(5)
    pts = rng.integers(0, 100, (400, 2)).astype(np.float32)
    c = np.array([47.3, 52.1], np.float32)
    valid = rng.random(400) > 0.2
    for nb in (72, 120, 360):
        h = np.asarray(
            angular_histogram(jnp.asarray(pts), jnp.asarray(valid), jnp.asarray(c), nb, False)
        )
        ang = np.mod(np.arctan2(pts[valid, 1] - c[1], pts[valid, 0] - c[0]), 2 * np.pi)
        ref, _ = np.histogram(ang, bins=nb, range=(0, 2 * np.pi))
        np.testing.assert_array_equal(h, ref)
        hn = angular_histogram(jnp.asarray(pts), jnp.asarray(valid), jnp.asarray(c), nb)
        np.testing.assert_allclose(np.asarray(hn), ref / ref.sum(), atol=1e-7)
    # vmap == loop, jit == eager.
    P = jnp.asarray(np.stack([pts, pts[::-1]]))
    V = jnp.asarray(np.stack([valid, valid[::-1]]))
    C = jnp.asarray(np.stack([c, c + 3]))
    f = jax.jit(jax.vmap(angular_histogram, in_axes=(0, 0, 0, None)), static_argnums=3)
    out = np.asarray(f(P, V, C, 120))
    for i in range(2):
        np.testing.assert_allclose(
            out[i], np.asarray(angular_histogram(P[i], V[i], C[i], 120)), atol=1e-7
        )
    assert stereo_descriptor(jnp.ones(3), jnp.zeros(3)).shape == (6,)


def test_mask_descriptors_flags_empty_frames():
    m = np.zeros((3, 60, 80), bool)
    m[0] = _banana()
    m[2, 5:8, 5:8] = True  # 9 pixels < MIN_MARKER_PIXELS
    H, ok = mask_descriptors(m, 72)
    assert MIN_MARKER_PIXELS > 9
    np.testing.assert_array_equal(ok, [True, False, False])
    assert H.shape == (3, 72) and np.isclose(H[0].sum(), 1.0) and not H[1:].any()


@pytest.mark.parametrize("nb", [72, 120])
def test_descriptor_changes_with_shape(nb):
    a = _banana()
    b = np.zeros_like(a)
    b[5:55, 30:40] = True
    H, ok = mask_descriptors(np.stack([a, b]), nb)
    assert ok.all() and np.abs(H[0] - H[1]).sum() > 0.3


def _np_hist(pts, centre, nb):
    ang = np.mod(np.arctan2(pts[:, 1] - centre[1], pts[:, 0] - centre[0]), 2 * np.pi)
    return np.histogram(ang, bins=nb, range=(0, 2 * np.pi))[0].astype(np.float64)


def _two_contours():
    m = np.zeros((2, 60, 80), bool)
    m[0] = _banana()
    m[1, 10:50, 30:42] = True
    return mask_contours(m)


def test_contour_histograms_fixed_and_region_centres_match_numpy():
    """centre=None uses each frame's region centroid; a given point is used for every
    frame. Reference: numpy histogram of the atan2 angles (exact counts)."""
    c = _two_contours()
    fixed = np.array([40.5, 31.0])
    H_reg = contour_histograms(c, 72, normalise=False)
    H_fix = contour_histograms(c, 72, normalise=False, centre=fixed)
    for i in range(2):
        np.testing.assert_array_equal(H_reg[i], _np_hist(c.points[i], c.centres[i], 72))
        np.testing.assert_array_equal(H_fix[i], _np_hist(c.points[i], fixed, 72))
    Hn = contour_histograms(c, 72, centre=fixed)
    np.testing.assert_allclose(Hn, H_fix / H_fix.sum(1, keepdims=True), atol=1e-7)
    with pytest.raises(InputError, match="centre"):
        contour_histograms(c, 72, centre=np.array([1.0, np.nan]))


def test_fixed_centre_confines_occlusion_to_its_bins():
    """Why the fixed centre (descriptor module docstring): removing the contour points of
    an occluded part changes, with a fixed centre, exactly the bins of the removed points
    (raw counts); with the region centroid the centre moves and other bins change too."""
    m = _banana()
    occ = m.copy()
    occ[:, 55:] = False  # an occluder hides the right end of the region
    c_full, c_occ = mask_contours(m[None]), mask_contours(occ[None])
    kept = {tuple(p) for p in c_occ.points[0]}
    # Points of the full contour that survive unchanged; the occluded contour adds its
    # new border along the cut, the full one loses the hidden part.
    removed = np.array([p for p in c_full.points[0] if tuple(p) not in kept])
    full_set = {tuple(p) for p in c_full.points[0]}
    added = np.array([p for p in c_occ.points[0] if tuple(p) not in full_set])
    fixed = c_full.centres[0]
    d_fix = (
        contour_histograms(c_full, 120, False, fixed)[0]
        - contour_histograms(c_occ, 120, False, fixed)[0]
    )
    np.testing.assert_array_equal(
        d_fix, _np_hist(removed, fixed, 120) - _np_hist(added, fixed, 120)
    )
    d_reg = contour_histograms(c_full, 120, False)[0] - contour_histograms(c_occ, 120, False)[0]
    touched = (_np_hist(removed, fixed, 120) + _np_hist(added, fixed, 120)) > 0
    assert np.abs(d_fix[~touched]).sum() == 0
    assert np.abs(d_reg[~touched]).sum() > 10  # the moved centroid re-bins untouched points


def test_view_centres_and_stereo_histograms():
    c = _two_contours()
    bad = Contours(
        [c.points[0], np.zeros((0, 2), np.int64)],
        c.centres,
        np.array([True, False]),
        c.marker_pixels,
    )
    sc = StereoContours(["a", "b"], (c, bad))
    vc = view_centres(sc)  # only frame 0 has markers in both views
    np.testing.assert_allclose(vc, np.stack([c.centres[0], c.centres[0]]))
    sc2 = StereoContours(["a", "b"], (c, c))
    np.testing.assert_allclose(view_centres(sc2), [c.centres.mean(0)] * 2)
    H, ok = stereo_histograms(sc2, 36, True, vc)
    np.testing.assert_allclose(H[:, :36], contour_histograms(c, 36, True, vc[0]), atol=0)
    np.testing.assert_array_equal(ok, [True, True])
    with pytest.raises(InputError, match="view centres"):
        stereo_histograms(sc2, 36, True, np.zeros(2))
    empty = StereoContours(
        ["a"],
        tuple(
            Contours([np.zeros((0, 2), np.int64)], np.zeros((1, 2)), np.zeros(1, bool), np.zeros(1))
            for _ in range(2)
        ),
    )
    with pytest.raises(InputError, match="no frame"):
        view_centres(empty)
