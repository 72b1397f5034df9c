"""Tip-section length change (jaxcr.shape.stretch_tip_section / perturbed_centreline
``extension``) against closed forms and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcr.kinematics.cosserat import integrate_centreline
from jaxcr.shape import perturbed_centreline, stretch_tip_section, tip_section


def _arc(kappa: float, length: float, n: int, rho):
    s = jnp.linspace(0.0, length, n)
    u = jnp.zeros((n - 1, 3)).at[:, 0].set(kappa)
    return integrate_centreline(s, u, jnp.asarray(rho, jnp.float32))


def _arc_point(kappa: float, s: float) -> np.ndarray:
    """Closed form: bending about the body x axis from the origin along +z."""
    if kappa == 0:
        return np.array([0.0, 0.0, s])
    return np.array([0.0, -(1 - np.cos(kappa * s)) / kappa, np.sin(kappa * s) / kappa])


def test_tip_section_is_the_distal_run_of_the_tip_radius():
    rho = jnp.array([3.0, 3.0, 2.0, 1.0, 1.0, 2.0, 1.0, 1.0])  # a non-distal 1.0 run too
    np.testing.assert_array_equal(tip_section(rho), [0, 0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(tip_section(jnp.ones(5)), [1, 1, 1, 1])


def test_one_radius_arc_grows_to_the_closed_form_arc():
    kappa, length, delta = 12.0, 0.1, 0.004
    base = _arc(kappa, length, 65, np.full(65, 1e-3))
    cl = perturbed_centreline(base, jnp.zeros((2, 3)), extension=jnp.asarray(delta))
    np.testing.assert_allclose(float(cl.s[-1]), length + delta, rtol=1e-6)
    # the whole robot is the tip section: still one constant-curvature arc, now longer
    np.testing.assert_allclose(cl.p[-1], _arc_point(kappa, length + delta), atol=2e-6)


def test_only_the_tip_section_moves_and_zero_is_identity():
    n = 49
    rho = np.where(np.arange(n) < 30, 2e-3, 1e-3)
    base = _arc(8.0, 0.12, n, rho)
    c = jnp.array([[0.05, -0.02, 0.01], [0.0, 0.03, 0.0]])
    ref = perturbed_centreline(base, c)
    same = perturbed_centreline(base, c, extension=jnp.asarray(0.0))
    np.testing.assert_allclose(same.p, ref.p, atol=1e-7)
    cl = perturbed_centreline(base, c, extension=jnp.asarray(-0.003))
    np.testing.assert_allclose(cl.p[:30], ref.p[:30], atol=1e-7)  # before the tip section
    assert np.linalg.norm(np.asarray(cl.p[-1] - ref.p[-1])) > 2.5e-3
    np.testing.assert_allclose(float(cl.s[-1]), float(base.s[-1]) - 0.003, rtol=1e-5)


@pytest.mark.parametrize("kappa", [0.0, 10.0])  # straight tube: a singular point
def test_tip_gradient_matches_finite_differences(kappa):
    base = _arc(kappa, 0.1, 33, np.full(33, 1e-3))

    def tip(e):
        return perturbed_centreline(base, jnp.zeros((2, 2)), extension=e).p[-1]

    with jax.enable_x64(True):
        base64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), base)

        def tip64(e):
            return perturbed_centreline(base64, jnp.zeros((2, 2), jnp.float64), extension=e).p[-1]

        g = jax.jacfwd(tip64)(jnp.asarray(0.0, jnp.float64))
        h = 1e-6
        fd = (tip64(jnp.asarray(h)) - tip64(jnp.asarray(-h))) / (2 * h)
        np.testing.assert_allclose(g, fd, atol=1e-7)
        # the closed-form derivative: the arc's tangent at its end
        t = np.array([0.0, -np.sin(kappa * 0.1), np.cos(kappa * 0.1)])
        np.testing.assert_allclose(g, t, atol=1e-6)
    assert np.all(np.isfinite(jax.jacrev(tip)(jnp.asarray(0.0))))


def test_stretch_limits_shortening():
    s = jnp.linspace(0.0, 1.0, 11)
    rho = jnp.ones(11)
    out = stretch_tip_section(s, rho, jnp.asarray(-5.0))
    np.testing.assert_allclose(float(out[-1]), 0.1, rtol=1e-6)
    assert np.all(np.diff(np.asarray(out)) > 0)
