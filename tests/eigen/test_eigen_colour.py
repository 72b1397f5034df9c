"""Colour segmentation (Reiter et al. Sec. III-B.1): CIELAB conversion vs scikit-image,
k-means vs cv2.kmeans, batch labelling (jit == eager, vmap == loop), bad input."""

from __future__ import annotations

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.color import rgb2lab

from jaxcr.eigen.colour import (
    LIME_RGB,
    ColourModel,
    fit_colour_model,
    kmeans,
    label_batch,
    label_image,
    rgb_to_lab,
)
from jaxcr.errors import InputError


def test_rgb_to_lab_matches_skimage():
    rng = np.random.default_rng(0)
    rgb = rng.random((500, 3)).astype(np.float32)
    rgb[:5] = [[0, 0, 0], [1, 1, 1], [0.01, 0.02, 0.03], [0.5, 0.5, 0.5], list(LIME_RGB)]
    ours = np.asarray(rgb_to_lab(jnp.asarray(rgb)))
    ref = rgb2lab(rgb[None].astype(np.float64))[0]
    # float32 vs float64 and the 0.008856 / 903.3 constants: within 0.02 Lab units.
    np.testing.assert_allclose(ours, ref, atol=2e-2)


def test_rgb_to_lab_grad_finite_at_black():
    g = jax.jit(jax.grad(lambda x: rgb_to_lab(x).sum()))(jnp.zeros(3))  # compiled: one program
    assert np.all(np.isfinite(np.asarray(g)))


def _blobs(rng, n=300):
    centres = np.array([[-40.0, 50.0], [30.0, 20.0], [0.0, 0.0], [45.0, -30.0]])
    x = np.concatenate([c + rng.normal(0, 2.0, (n, 2)) for c in centres])
    return x.astype(np.float32), centres


def test_kmeans_matches_cv2_on_separated_clusters():
    rng = np.random.default_rng(1)
    x, true_c = _blobs(rng)
    c, lab = jax.jit(kmeans, static_argnums=(1, 3))(jnp.asarray(x), 4, jax.random.PRNGKey(0), 30)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    _, cv_lab, cv_c = cv2.kmeans(x, 4, None, crit, 5, cv2.KMEANS_PP_CENTERS)
    ours = np.asarray(c)[np.lexsort(np.asarray(c).T)]
    ref = cv_c[np.lexsort(cv_c.T)]
    np.testing.assert_allclose(ours, ref, atol=1e-3)
    # Same partition (up to relabelling).
    m = {}
    for a, b in zip(np.asarray(lab), cv_lab.ravel(), strict=True):
        m.setdefault(int(a), set()).add(int(b))
    assert all(len(v) == 1 for v in m.values()) and len(m) == 4


def test_kmeans_deterministic_per_key():
    rng = np.random.default_rng(2)
    x, _ = _blobs(rng, 100)
    run = jax.jit(kmeans, static_argnums=(1, 3))  # one program (eagerly: op by op)
    a = run(jnp.asarray(x), 4, jax.random.PRNGKey(3), 10)[0]
    b = run(jnp.asarray(x), 4, jax.random.PRNGKey(3), 10)[0]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.fixture(scope="module")
def scene():
    """A 72x96 image: red-pink noise background with two lime squares and a grey bar."""
    rng = np.random.default_rng(0)
    img = np.empty((72, 96, 3), np.float32)
    img[:] = [0.65, 0.25, 0.25]
    img += rng.normal(0, 0.03, img.shape).astype(np.float32)
    img[10:30, 20:35] = [0.45, 0.8, 0.1]
    img[40:55, 60:80] = [0.42, 0.78, 0.08]
    img[60:66, 5:90] = [0.6, 0.6, 0.62]
    truth = np.zeros((72, 96), bool)
    truth[10:30, 20:35] = True
    truth[40:55, 60:80] = True
    return np.clip(img, 0, 1), truth


def test_fit_and_label_recovers_markers(scene):
    img, truth = scene
    model = fit_colour_model(img, k=3, seed=0)
    mask = np.asarray(label_image(model, jnp.asarray(img)))
    np.testing.assert_array_equal(mask, truth)
    # By index: the same cluster.
    by_index = fit_colour_model(img, k=3, seed=0, marker_index=int(model.marker))
    assert int(by_index.marker) == int(model.marker)


def test_label_batch_jit_vmap_equal_loop(scene):
    img, _ = scene
    model = fit_colour_model(img, k=3, seed=0)
    batch = np.stack([img, img[::-1], np.ascontiguousarray(img[:, ::-1])])
    out = np.asarray(label_batch(model, jnp.asarray(batch)))
    loop = np.stack([np.asarray(label_image(model, jnp.asarray(b))) for b in batch])
    np.testing.assert_array_equal(out, loop)
    # the vmap compiled (eagerly, its operations compiled one by one); the loop above stays
    # eager (jit == eager)
    vm = eqx.filter_jit(jax.vmap(label_image, in_axes=(None, 0)))(model, jnp.asarray(batch))
    np.testing.assert_array_equal(out, np.asarray(vm))
    # One trace for many frames of one shape.
    f = eqx.filter_jit(eqx.debug.assert_max_traces(label_image, max_traces=1))
    for b in batch:
        f(model, jnp.asarray(b))


def test_wrong_colour_gives_empty_mask(scene):
    img, _ = scene
    model = fit_colour_model(img, k=3, seed=0)
    no_marker = img.copy()
    no_marker[10:30, 20:35] = [0.65, 0.25, 0.25]
    no_marker[40:55, 60:80] = [0.65, 0.25, 0.25]
    assert not np.asarray(label_image(model, jnp.asarray(no_marker))).any()


def test_bad_input():
    with pytest.raises(InputError, match="RGB image"):
        fit_colour_model(np.zeros((8, 8)))
    with pytest.raises(InputError, match="clusters"):
        fit_colour_model(np.zeros((8, 8, 3)), k=1)
    with pytest.raises(InputError, match="marker index"):
        fit_colour_model(np.random.default_rng(0).random((8, 8, 3)), k=3, marker_index=5)
    assert isinstance(ColourModel(jnp.zeros((2, 2)), jnp.asarray(0)), ColourModel)
