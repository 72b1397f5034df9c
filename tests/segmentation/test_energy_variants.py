"""jaxcr.segmentation.energy variants: residual_variance, chan_vese_energy's ``var`` override and the robust
term's envelope gradient, vs dense numpy definitions on a hard mask; RefineConfig.data_var validation."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.camera import Camera
from jaxcr.errors import InputError
from jaxcr.segmentation.energy import Weights, chan_vese_energy, residual_variance
from jaxcr.segmentation.refine import RefineConfig
from jaxcr.segmentation.silhouette import project_tube

# compiled (one program each per shape, shared with test_energy through the run's compilation
# cache), not op by op: the inputs of the terms under test
from tests.helpers.jitted import (
    integrate_centreline,
    prepare_region_data,
    rasterise_dense,
    select_band,
)

W, H = 96, 72


def _scene():
    n = 33
    s = jnp.linspace(0.0, 0.12, n)
    u = jnp.tile(jnp.array([8.0, 3.0, 0.0]), (n - 1, 1))
    R0 = jnp.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    cl = integrate_centreline(s, u, jnp.full(n, 4e-3), jnp.array([-0.05, 0.0, 0.0]), R0)
    cam = Camera.look_at([0, 0, -0.3], [0, 0, 0], [0, -1, 0], fx=120.0, size=(W, H))
    return cl, cam


def _image(seed):
    rng = np.random.default_rng(seed)
    return rng.random((H, W, 3)).astype(np.float32), rng.random((H, W)) < 0.3


def _band_pixels(d, band):
    in_band = np.zeros(d.grid.n_tiles, bool)
    in_band[np.asarray(band.tiles)] = True
    tiles = np.broadcast_to(in_band[:, None], (d.grid.n_tiles, d.grid.n_pix))
    return np.asarray(d.grid.from_tiles(jnp.asarray(tiles)))


@pytest.mark.parametrize("local", [False, True])
def test_residual_variance_matches_dense_definition(local):
    """(sum_R |I - mu_in|^2 + sum_Rc |I - mu_out|^2) / (|R| + |Rc|) over non-background pixels
    (Rc within the band when local), hard mask (tau -> 0), rtol 1e-3 in float32; areas within
    half a pixel."""
    cl, cam = _scene()
    img, bg = _image(11)
    tube = project_tube(cam, cl)
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, 40, 8)
    _, t = chan_vese_energy(tube, band, d, 0.0, Weights(), 1e-4, 300.0, local)
    mask = np.asarray(rasterise_dense(tube, H, W))
    x = img.astype(np.float64)
    R = mask & ~bg
    Rc = ~mask & ~bg
    if local:
        Rc &= _band_pixels(d, band)
    e = ((x[R] - x[R].mean(0)) ** 2).sum() + ((x[Rc] - x[Rc].mean(0)) ** 2).sum()
    ref = e / (R.sum() + Rc.sum())
    np.testing.assert_allclose(float(residual_variance(t)), ref, rtol=1e-3)
    # a pixel centre within ~1e-4 px of the boundary is partly inside at tau = 1e-4
    np.testing.assert_allclose(float(t["area_in"]), R.sum(), atol=0.5)
    np.testing.assert_allclose(float(t["area_out"]), Rc.sum(), atol=0.5)


def test_var_override_scales_data_terms_only():
    """J(var=v) = g3 reg + g4 pen / A + (J(None) - g3 reg - g4 pen / A) * var_image / v, and
    var=var_image reproduces the default (rtol 1e-5)."""
    cl, cam = _scene()
    img, bg = _image(12)
    tube = project_tube(cam, cl)
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, 40, 8)
    wts, area, reg = Weights(), 300.0, 0.25
    J0, t = chan_vese_energy(tube, band, d, reg, wts, 0.7, area, True)
    var_img = float(d.total_s2 / d.total_w)
    rest = wts.g_reg * reg + wts.g_pen * float(t["e_pen"]) / area
    J1, _ = chan_vese_energy(tube, band, d, reg, wts, 0.7, area, True, 0.0, jnp.asarray(var_img))
    np.testing.assert_allclose(float(J1), float(J0), rtol=1e-5)
    v = 0.01
    Jv, _ = chan_vese_energy(tube, band, d, reg, wts, 0.7, area, True, 0.0, jnp.asarray(v))
    np.testing.assert_allclose(float(Jv), rest + (float(J0) - rest) * var_img / v, rtol=1e-4)


def test_data_var_config_validation():
    assert RefineConfig(data_var="residual").data_var == "residual"
    with pytest.raises(InputError):
        RefineConfig(data_var="global")


def test_robust_envelope_gradient_is_per_pixel_welsch_cost():
    """With envelope=True, d e_in / d soft at a band pixel is w_i c^2 (1 - exp(-|I_i - mu|^2 /
    c^2)) with mu the two-step reweighted mean of a slow numpy loop (every tile in the band,
    hard mask; atol 1e-5 of c^2); the value equals the exact variant's (rtol 1e-6); the
    exact gradient differs (it also flows through mu)."""
    import jax

    from jaxcr.segmentation.energy import region_terms
    from tests.helpers.jitted import band_margin

    cl, cam = _scene()
    img, bg = _image(13)
    tube = project_tube(cam, cl)
    d = prepare_region_data(jnp.asarray(img), jnp.asarray(bg), 0, 8)
    band = select_band(tube, d.grid, d.grid.n_tiles, 32)
    hard = (band_margin(tube, d.grid, band) > 0).astype(jnp.float32)

    def e_in(soft, env):
        return region_terms(soft, band, d, robust=1.0, envelope=env).e_in

    g_env = np.asarray(jax.grad(e_in)(hard, True))
    g_ex = np.asarray(jax.grad(e_in)(hard, False))
    np.testing.assert_allclose(float(e_in(hard, True)), float(e_in(hard, False)), rtol=1e-6)
    # numpy reference in the band's pixel order (centred colours, as RegionData)
    bw, _, x = (np.asarray(a, np.float64) for a in d.gather(band.tiles))
    ins = np.asarray(hard, bool) & (bw > 0)
    c2 = float(d.total_s2) / float(d.total_w)
    mu = x[ins].mean(0)
    for _ in range(2):
        wr = np.exp(-((x[ins] - mu) ** 2).sum(-1) / c2)
        mu = (wr[:, None] * x[ins]).sum(0) / wr.sum()
    ref = bw * c2 * (1.0 - np.exp(-((x - mu) ** 2).sum(-1) / c2))
    np.testing.assert_allclose(g_env, ref, atol=1e-5 * c2)
    assert np.abs(g_ex - ref).max() > 1e-3 * c2
