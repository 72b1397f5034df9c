"""jaxcr.segmentation.metrics: IoU (Watson eq. 8), adjusted IoU, tip and mean centreline errors."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr.segmentation.metrics import (
    adjusted_iou,
    iou,
    mean_centreline_error,
    resample_by_arclength,
    tip_error,
    tip_error_components,
)


def test_iou_against_numpy():
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.random((20, 30)) < 0.3
        b = rng.random((20, 30)) < 0.4
        ref = (a & b).sum() / (a | b).sum()
        np.testing.assert_allclose(float(iou(jnp.asarray(a), jnp.asarray(b))), ref, rtol=1e-6)
    z = jnp.zeros((4, 4), bool)
    assert float(iou(z, z)) == 1.0
    assert float(iou(z.at[0, 0].set(True), z)) == 0.0


def test_adjusted_iou_excludes_occluded_predictions():
    pred = np.zeros((10, 10), bool)
    pred[2:8, 2:8] = True
    occ = np.zeros((10, 10), bool)
    occ[2:8, 5:8] = True
    truth = pred & ~occ  # visible part only
    assert float(iou(jnp.asarray(pred), jnp.asarray(truth))) == 0.5
    assert float(adjusted_iou(jnp.asarray(pred), jnp.asarray(truth), jnp.asarray(occ))) == 1.0


def test_centreline_errors_closed_form():
    s = np.linspace(0, 0.1, 51)
    a = np.stack([np.zeros_like(s), np.zeros_like(s), s], 1)
    b = a + np.array([0.002, 0.0, 0.0])  # parallel line 2 mm away
    assert abs(float(mean_centreline_error(jnp.asarray(a), jnp.asarray(b))) - 0.002) < 1e-7
    assert abs(float(tip_error(jnp.asarray(a), jnp.asarray(b))) - 0.002) < 1e-7
    # differently sampled copy of the same arc: zero error
    t = np.linspace(0, np.pi / 2, 200)
    arc = np.stack([0.05 * (1 - np.cos(t)), 0 * t, 0.05 * np.sin(t)], 1)
    t2 = np.linspace(0, np.pi / 2, 37)
    arc2 = np.stack([0.05 * (1 - np.cos(t2)), 0 * t2, 0.05 * np.sin(t2)], 1)
    assert float(mean_centreline_error(jnp.asarray(arc), jnp.asarray(arc2))) < 5e-5


def test_resample_by_arclength():
    p = jnp.array([[0.0, 0, 0], [0, 0, 1], [0, 1, 1]])
    q = resample_by_arclength(p, jnp.array([0.0, 0.5, 1.5, 2.0]))
    np.testing.assert_allclose(q, [[0, 0, 0], [0, 0, 0.5], [0, 0.5, 1], [0, 1, 1]], atol=1e-6)


def test_vmap_equals_loop():
    rng = np.random.default_rng(1)
    a = jnp.asarray(rng.random((4, 10, 12)) < 0.5)
    b = jnp.asarray(rng.random((4, 10, 12)) < 0.5)
    v = jax.jit(jax.vmap(iou))(a, b)
    np.testing.assert_allclose(v, [float(iou(x, y)) for x, y in zip(a, b, strict=True)])


def test_tip_error_components_against_projection():
    """Lateral/depth split of the tip error: against scipy's rotation of the error vector into
    the camera frame (tolerance 1e-6 m, float32), and lateral^2 + depth^2 == tip^2."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for _ in range(5):
        R = Rotation.random(random_state=rng).as_matrix()
        a = rng.normal(size=(7, 3)) * 0.05
        b = a + rng.normal(size=(7, 3)) * 0.004
        d = R @ (a[-1] - b[-1])
        lat, dep = tip_error_components(jnp.asarray(a), jnp.asarray(b), jnp.asarray(R))
        np.testing.assert_allclose(float(lat), np.hypot(d[0], d[1]), atol=1e-6)
        np.testing.assert_allclose(float(dep), abs(d[2]), atol=1e-6)
        tip = float(tip_error(jnp.asarray(a), jnp.asarray(b)))
        np.testing.assert_allclose(float(lat) ** 2 + float(dep) ** 2, tip**2, rtol=1e-4)
    # an error purely along the optical axis is all depth
    a = np.zeros((3, 3))
    b = a.copy()
    b[-1] = [0.0, 0.0, 0.003]
    lat, dep = tip_error_components(jnp.asarray(a), jnp.asarray(b), jnp.eye(3))
    assert float(lat) == 0.0 and abs(float(dep) - 0.003) < 1e-9
