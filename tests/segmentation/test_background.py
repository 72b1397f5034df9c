"""jaxcr.segmentation.background: colour conversions vs colorsys/scikit-image, masks, per-pixel GMM."""

import colorsys

import jax
import jax.numpy as jnp
import numpy as np
from skimage.color import rgb2lab

from jaxcr.segmentation.background import (
    HSVRange,
    background_model_mask,
    colour_mask,
    fit_background_model,
    lab_mask,
    no_mask,
    rgb_to_hsv,
    rgb_to_lab,
)


def test_rgb_to_hsv_matches_colorsys():
    x = np.random.default_rng(0).random((200, 3)).astype(np.float32)
    x[:3] = [[0.5, 0.5, 0.5], [0, 0, 0], [1, 0, 0]]  # grey, black, pure red
    ref = np.array([colorsys.rgb_to_hsv(*r) for r in x])
    ref[:, 0] *= 360
    np.testing.assert_allclose(np.asarray(rgb_to_hsv(jnp.asarray(x))), ref, atol=1e-4)


def test_rgb_to_lab_matches_skimage():
    x = np.random.default_rng(1).random((1, 100, 3)).astype(np.float32)
    np.testing.assert_allclose(np.asarray(rgb_to_lab(jnp.asarray(x))), rgb2lab(x), atol=2e-3)


def test_colour_mask_grey_robot_red_tissue():
    img = np.zeros((4, 4, 3), np.float32)
    img[:] = [0.7, 0.2, 0.2]  # saturated tissue
    img[1:3, 1:3] = [0.5, 0.5, 0.52]  # grey metal
    bg, ip = colour_mask(jnp.asarray(img))
    assert np.asarray(bg).sum() == 12 and not np.asarray(bg)[1:3, 1:3].any()
    np.testing.assert_allclose(np.asarray(ip)[0, 0], 0.0)
    np.testing.assert_allclose(np.asarray(ip)[1, 1], img[1, 1])
    # custom wrap-around hue range keeps the reds instead
    bg2, _ = colour_mask(jnp.asarray(img), ranges=(HSVRange(h_lo=340, h_hi=20, s_lo=0.5),))
    assert np.asarray(bg2)[1:3, 1:3].all() and not np.asarray(bg2)[0, 0]
    bl, _ = lab_mask(jnp.asarray(img))
    np.testing.assert_array_equal(np.asarray(bl), np.asarray(bg))
    bn, ipn = no_mask(jnp.asarray(img))
    assert not np.asarray(bn).any() and np.allclose(ipn, img)


def test_gmm_one_component_is_mean_and_variance():
    rng = np.random.default_rng(2)
    ims = rng.normal(0.5, 0.1, (8, 5, 6, 3)).astype(np.float32)
    m = fit_background_model(jnp.asarray(ims), 1, min_std=0.0)
    np.testing.assert_allclose(np.asarray(m.means)[:, :, 0], ims.mean(0), atol=1e-5)
    np.testing.assert_allclose(np.asarray(m.variances)[:, :, 0], ims.var(0), atol=1e-5)


def test_gmm_two_components_and_mask():
    rng = np.random.default_rng(3)
    # a flickering background pixel: half the images dark, half bright
    ims = np.where((np.arange(10) % 2 == 0)[:, None, None, None], 0.2, 0.8) + rng.normal(
        0, 0.01, (10, 4, 4, 3)
    )
    ims = ims.astype(np.float32)
    m = fit_background_model(jnp.asarray(ims), 2, iterations=20)
    mu = np.sort(np.asarray(m.means)[0, 0, :, 0])
    np.testing.assert_allclose(mu, [0.2, 0.8], atol=0.02)
    test = np.full((4, 4, 3), 0.8, np.float32)
    test[0, 0] = [0.5, 0.5, 0.5]  # neither mode: robot
    bg, _ = background_model_mask(m, jnp.asarray(test))
    bg = np.asarray(bg)
    assert not bg[0, 0] and bg.sum() == 15


def test_jit_and_vmap():
    imgs = jnp.asarray(np.random.default_rng(4).random((3, 8, 8, 3)).astype(np.float32))
    b, i = jax.jit(jax.vmap(colour_mask))(imgs)
    for k in range(3):
        bk, ik = colour_mask(imgs[k])
        np.testing.assert_array_equal(np.asarray(b[k]), np.asarray(bk))
        np.testing.assert_allclose(np.asarray(i[k]), np.asarray(ik))
