"""jaxcr.segmentation.energy: Chan-Vese terms of Watson eq. 5/6 vs a dense numpy evaluation, pyramid vs
OpenCV, gradient vs finite differences (x64)."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera
from jaxcr.segmentation.energy import Weights, chan_vese_energy, downsample, region_terms
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.silhouette import project_tube

# compiled (one program each per shape, shared with the other segmentation modules through
# the run's compilation cache), not op by op: the inputs of the terms under test
from tests.helpers.energy_x64 import energy_value_and_grad, smooth_scene
from tests.helpers.jitted import (
    band_margin,
    integrate_centreline,
    prepare_region_data,
    rasterise_dense,
    select_band,
)

W, H = 96, 72


def _scene(dtype=jnp.float32):
    n = 33
    s = jnp.linspace(0.0, 0.12, n, dtype=dtype)
    u = jnp.tile(jnp.array([8.0, 3.0, 0.0], dtype), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype)
    cl = integrate_centreline(
        s, u, jnp.full(n, 4e-3, dtype), jnp.array([-0.05, 0.0, 0.0], dtype), R0
    )
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=120.0, size=(W, H))
    return cl, cam


def _image(seed=0):
    rng = np.random.default_rng(seed)
    img = rng.random((H, W, 3)).astype(np.float32)
    bg = rng.random((H, W)) < 0.3
    return img, bg


def _dense_terms(mask, img, bg):
    """Watson eq. 5/6 data and penalty terms on a hard mask, straight from the definition."""
    R = mask & ~bg
    Rc = ~mask & ~bg
    mu_in = img[R].mean(0)
    mu_out = img[Rc].mean(0)
    e_in = ((img[R] - mu_in) ** 2).sum()
    e_out = ((img[Rc] - mu_out) ** 2).sum()
    return e_in, e_out, (mask & bg).sum()


def test_region_terms_match_dense_definition():
    cl, cam = _scene()
    img, bg = _image()
    img_p = img * ~bg[..., None]  # I' = I o M
    tube = project_tube(cam, cl)
    mask = np.asarray(rasterise_dense(tube, H, W))
    assert 50 < mask.sum() < 0.5 * H * W
    d = prepare_region_data(jnp.asarray(img_p), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, 40, 8)
    m = band_margin(tube, d.grid, band)
    t = region_terms((m > 0).astype(jnp.float32), band, d)
    e_in, e_out, pen = _dense_terms(mask, img_p.astype(np.float64), bg)
    np.testing.assert_allclose(float(t.e_in), e_in, rtol=2e-4)
    np.testing.assert_allclose(float(t.e_out), e_out, rtol=2e-4)
    assert float(t.e_pen) == pen


def test_local_out_region_is_band():
    cl, cam = _scene()
    img, bg = _image(1)
    tube = project_tube(cam, cl)
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, 40, 8)
    m = band_margin(tube, d.grid, band)
    t = region_terms((m > 0).astype(jnp.float32), band, d, local=True)
    # dense reference: R^c restricted to the band tiles
    in_band = np.zeros(d.grid.n_tiles, bool)
    in_band[np.asarray(band.tiles)] = True
    band_img = np.asarray(
        d.grid.from_tiles(jnp.broadcast_to(jnp.asarray(in_band)[:, None], (d.grid.n_tiles, 64)))
    )
    mask = np.asarray(rasterise_dense(tube, H, W))
    Rc = ~mask & ~bg & band_img
    e_out = ((img[Rc] - img[Rc].mean(0)) ** 2).sum()
    np.testing.assert_allclose(float(t.e_out), e_out, rtol=2e-4)


def test_downsample_matches_cv2_area():
    img, _ = _image(2)
    w = jnp.ones((H, W))
    out, w2, b2 = downsample(jnp.asarray(img), w, jnp.zeros((H, W)))
    ref = cv2.resize(img, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(np.asarray(out), ref, atol=1e-5)
    np.testing.assert_allclose(np.asarray(w2), 1.0)


def test_pixel_units_consistent_across_levels():
    """Level-1 area of a region is counted in full-resolution pixels (4 per level-1 pixel)."""
    img, bg = _image(3)
    d0 = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    d1 = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 1, 8)
    np.testing.assert_allclose(float(d1.total_w) * d1.pix_area, float(d0.total_w), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(d1.centre), np.asarray(d0.centre), atol=1e-5)


def _assert_grad_matches_fd(scene, reg_weight, local=False, robust=0.0, eps=1e-5):
    """jax.grad of J(c) = energy_x64.band_energy(scene, c, ...) at a random (2, 3) point vs
    central differences (rtol 1e-4, x64), and not trivially flat.

    One compiled value-and-gradient program (tests/helpers/energy_x64.py, shared with
    test_least_squares) gives both the gradient and the values of the differences; jit ==
    eager is checked in test_jit_equals_eager_and_vmap_equals_loop."""
    # numpy points (float64): the compiled program is the only XLA code the loop runs
    c0 = np.random.default_rng(5).normal(0, 0.05, (2, 3))
    w = np.float64(reg_weight)

    def J(c):
        return energy_value_and_grad(scene, c, w, local, robust)

    g = np.asarray(J(c0)[1])
    fd = np.zeros_like(g)
    for i in range(2):
        for j in range(3):
            e = np.zeros((2, 3))
            e[i, j] = eps
            fd[i, j] = (float(J(c0 + e)[0]) - float(J(c0 - e)[0])) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-7)
    assert np.abs(g).max() > 1e-4


def test_energy_gradient_vs_finite_differences():
    with jax.enable_x64(True):
        # the 8 / 3 1/m arc of _scene, a smooth image, 10 background columns; regulariser
        # sum(c**2) with weight 1
        _assert_grad_matches_fd(smooth_scene([8.0, 3.0, 0.0]), 1.0)


def test_jit_equals_eager_and_vmap_equals_loop():
    cl, cam = _scene()
    img, bg = _image(6)
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    tube0 = project_tube(cam, cl)
    band = select_band(tube0, d.grid, 40, 8)

    def J(c):
        t = project_tube(cam, perturbed_centreline(cl, c))
        return chan_vese_energy(t, band, d, 0.0, Weights(), 0.7, 300.0)[0]

    cs = jnp.asarray(np.random.default_rng(7).normal(0, 0.05, (3, 2, 3)), jnp.float32)
    eager = np.array([float(J(c)) for c in cs])
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(J))(cs)), eager, rtol=1e-5)


def _robust_dense(mask, img, bg, k):
    """Slow reference of the robust inside term (region_terms docstring) on a hard mask."""
    w = (~bg).astype(np.float64)
    x = img.reshape(-1, 3).astype(np.float64)
    ww = w.ravel()
    centre = (ww[:, None] * x).sum(0) / ww.sum()
    xc = x - centre
    c2 = k * k * (ww * (xc * xc).sum(1)).sum() / ww.sum()
    inside = mask.ravel() & (ww > 0)
    pts = xc[inside]
    mu = pts.mean(0)
    for _ in range(2):
        wr = np.exp(-((pts - mu) ** 2).sum(1) / c2)
        mu = (wr[:, None] * pts).sum(0) / wr.sum()
    r2 = ((pts - mu) ** 2).sum(1)
    return float((c2 * (1 - np.exp(-r2 / c2))).sum())


def test_robust_inside_term_matches_reference_and_limits():
    """Robust (Welsch) inside term vs a slow numpy loop of its definition (every tile in the
    band, so no whole-tile approximation; rtol 1e-3 in float32); with a huge scale it tends
    to the quadratic eq. 6 term (rtol 1e-3); an occluder painted over part of R costs less
    with the robust term than with the quadratic one (relative to the clean image)."""
    cl, cam = _scene()
    img, bg = _image()
    img_p = img * ~bg[..., None]
    tube = project_tube(cam, cl)
    mask = np.asarray(rasterise_dense(tube, H, W))
    d = prepare_region_data(jnp.asarray(img_p), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, d.grid.n_tiles, 32)
    m = band_margin(tube, d.grid, band)
    hard = (m > 0).astype(jnp.float32)
    t = region_terms(hard, band, d, robust=1.0)
    np.testing.assert_allclose(float(t.e_in), _robust_dense(mask, img_p, bg, 1.0), rtol=1e-3)
    t_big = region_terms(hard, band, d, robust=1e3)
    t_q = region_terms(hard, band, d)
    np.testing.assert_allclose(float(t_big.e_in), float(t_q.e_in), rtol=1e-3)
    # occluder: a quarter of the robot's pixels painted black
    occ = img_p.copy()
    ys, xs = np.nonzero(mask)
    sel = slice(0, len(ys) // 4)
    occ[ys[sel], xs[sel]] = 0.0
    d2 = prepare_region_data(jnp.asarray(occ), jnp.asarray(bg), 0, 8)
    dq = float(region_terms(hard, band, d2).e_in) - float(t_q.e_in)
    dr = float(region_terms(hard, band, d2, robust=1.0).e_in) - float(t.e_in)
    assert dr < 0.5 * dq, (dr, dq)


def test_robust_energy_gradient_vs_finite_differences():
    with jax.enable_x64(True):
        # no background, local mu_out, Welsch scale 1, no regulariser
        scene = smooth_scene([8.0, 3.0, 0.0], background_cols=0)
        _assert_grad_matches_fd(scene, 0.0, local=True, robust=1.0)
