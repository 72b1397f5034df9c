"""jaxcr.colour.rgb_to_lab against scikit-image, the previous matmul + cbrt implementation, and
finite differences; singular points (black, the branch points of sRGB and of CIELAB's f)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.color import rgb2lab

from jaxcr import colour
from jaxcr.colour import rgb_to_lab

# float32 noise floor: a* = 500 (f(x) - f(y)) with f ~ 1, so one float32 ulp of f is 6e-5 Lab
# units; both implementations are within 1e-4 of float64 scikit-image, so 2e-4 between them.
ATOL32 = 2e-4
# skimage's linear L* segment is 116 * 7.787 y = 903.292 y, ours (and the previous code) the
# CIE constant 903.3 y: at most 0.008 * 0.008856 = 7.1e-5 apart, for y <= 0.008856 only.
L_LINEAR_GAP = 7.2e-5
# jit (fused, XLA may contract a * b + c to an FMA) vs eager (op by op) in float32: f may differ
# by one ulp (6e-8), i.e. 500 * 1.2e-7 = 6e-5 in a*.
JIT_ATOL = 1e-4

# Compiled once per shape and dtype (called eagerly, rgb_to_lab compiled each of its ~20
# operations at every new shape and dtype: ~310 small compilations in this module); eager calls
# stay where eager is the point (test_jit_equals_eager_and_batch_shapes).
_JIT = jax.jit(rgb_to_lab)


def _old_rgb_to_lab(rgb):
    """The implementation before this change (matmul over the colour axis, cube root), in
    numpy in the input's dtype (float32 stays float32: numpy 2 keeps Python scalars weak)."""
    rgb = np.clip(rgb, 0.0, 1.0)
    lin = np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    M = np.asarray(colour._RGB2XYZ, rgb.dtype)
    xyz = (lin @ M.T) / np.asarray(colour._WHITE, rgb.dtype)
    eps = colour._EPS
    f = np.where(xyz > eps, np.cbrt(np.maximum(xyz, eps)), 7.787 * xyz + 16.0 / 116.0)
    L = np.where(xyz[..., 1] > eps, 116.0 * f[..., 1] - 16.0, 903.3 * xyz[..., 1])
    out = np.stack([L, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)
    assert out.dtype == rgb.dtype
    return out


def _colours() -> np.ndarray:
    """8-bit grid (step 5 levels), random colours, and values at the branch points: sRGB's
    0.04045 and grey levels whose Y sits at CIELAB's 0.008856, each +- a few ulp."""
    v = np.arange(0, 256, 5) / 255.0
    grid = np.stack(np.meshgrid(v, v, v, indexing="ij"), -1).reshape(-1, 3)
    rnd = np.random.default_rng(0).random((4000, 3))
    # grey with Y = 0.008856: linear value 0.008856 (row sums of M are ~white) -> sRGB.
    g_eps = 1.055 * 0.008856 ** (1 / 2.4) - 0.055
    edges = []
    for c in (0.04045, g_eps, 0.0, 1.0):
        for d in (-3e-7, -1e-7, 0.0, 1e-7, 3e-7):
            edges.append(np.full(3, c + d))
            edges.append(np.array([c + d, 0.3, 0.7]))
    return np.clip(np.concatenate([grid, rnd, np.array(edges)]), 0.0, 1.0)


COLOURS = _colours()


def test_float32_matches_skimage_and_previous():
    x = COLOURS.astype(np.float32)
    ours = np.asarray(_JIT(jnp.asarray(x)))
    assert ours.dtype == np.float32
    np.testing.assert_allclose(ours, rgb2lab(x.astype(np.float64)), atol=ATOL32, rtol=0)
    np.testing.assert_allclose(ours, _old_rgb_to_lab(x), atol=ATOL32)


def test_float64_matches_skimage_and_previous():
    with jax.enable_x64(True):
        x = jnp.asarray(COLOURS, jnp.float64)
        ours = np.asarray(_JIT(x))
        old = _old_rgb_to_lab(COLOURS)
    assert ours.dtype == np.float64
    ref = rgb2lab(COLOURS)
    # CIELAB with skimage's constants (0.008856, 7.787) jumps by 3.3e-7 in f at the branch
    # point, i.e. 1.7e-4 in a*: colours whose X, Y or Z is within 1e-9 of it may land on
    # either side (one-ulp differences in pow vs exp/log), so they get that tolerance.
    lin = np.where(COLOURS > 0.04045, ((COLOURS + 0.055) / 1.055) ** 2.4, COLOURS / 12.92)
    xyz = lin @ np.asarray(colour._RGB2XYZ).T / np.asarray(colour._WHITE)
    near = np.any(np.abs(xyz - colour._EPS) < 1e-9, axis=-1)
    assert 0 < near.sum() < 20
    far = ~near
    np.testing.assert_allclose(ours[far], old[far], atol=1e-9, rtol=0)
    np.testing.assert_allclose(ours[near], old[near], atol=2e-4, rtol=0)
    np.testing.assert_allclose(ours[far, 1:], ref[far, 1:], atol=1e-9, rtol=0)
    np.testing.assert_allclose(ours[:, 1:], ref[:, 1:], atol=2e-4, rtol=0)
    np.testing.assert_allclose(ours[:, 0], ref[:, 0], atol=L_LINEAR_GAP, rtol=0)
    # Away from the linear L* segment, L* is the same formula as skimage's.
    y = far & (ref[:, 0] > 8.0 + 1e-3)  # L* = 8 at Y = 0.008856
    np.testing.assert_allclose(ours[y, 0], ref[y, 0], atol=1e-9, rtol=0)


def test_jit_equals_eager_and_batch_shapes():
    x = jnp.asarray(COLOURS[:1200].reshape(2, 20, 30, 3), jnp.float32)
    eager = np.asarray(rgb_to_lab(x))
    assert eager.shape == x.shape
    np.testing.assert_allclose(np.asarray(_JIT(x)), eager, atol=JIT_ATOL, rtol=0)
    # the loop of single pixels and the vmap compiled (one program each)
    looped = np.stack([np.asarray(_JIT(p)) for p in np.asarray(x).reshape(-1, 3)])
    np.testing.assert_allclose(eager.reshape(-1, 3), looped, atol=JIT_ATOL, rtol=0)
    vm = np.asarray(jax.jit(jax.vmap(rgb_to_lab))(np.asarray(x).reshape(-1, 3)))
    np.testing.assert_allclose(vm, looped, atol=JIT_ATOL, rtol=0)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16, jnp.float32])
def test_dtype_follows_input(dtype):
    # the traced output type (eval_shape: the same function, nothing compiled)
    assert jax.eval_shape(rgb_to_lab, jax.ShapeDtypeStruct((4, 3), dtype)).dtype == dtype


def test_exact_at_black_white_and_clipped():
    # _JIT's single-pixel program (test_jit_equals_eager_and_batch_shapes' loop)
    lab = lambda rgb: np.asarray(_JIT(np.asarray(rgb, np.float32)))  # noqa: E731
    np.testing.assert_array_equal(lab(np.zeros(3)), np.zeros(3))
    np.testing.assert_array_equal(lab([-0.5, -1.0, 0.0]), np.zeros(3))
    np.testing.assert_array_equal(lab([1.5, 2.0, 1.0]), lab(np.ones(3)))
    np.testing.assert_allclose(lab(np.ones(3)), rgb2lab(np.ones(3)), atol=1e-4)


def test_lab_f_linear_segment_and_branch_point():
    eps = colour._EPS
    # one compiled program (the points padded to one shape)
    t = np.asarray([0.0, 1e-4, 0.5 * eps, eps, eps, np.nextafter(np.float32(eps), 1)], np.float32)
    f = np.asarray(jax.jit(colour._lab_f)(t))
    # float32 reference of the same a*t + b; compiled, XLA may contract it into one fused
    # multiply-add (host-CPU dependent), which rounds once instead of twice: at most 1 ulp
    # apart, i.e. a relative 2**-23; bound 2 ulp
    np.testing.assert_allclose(f[:4], 7.787 * t[:4] + 16 / 116, rtol=2 * 2.0**-23, atol=0)
    # The CIE constants make f continuous at eps to ~1e-6 (not exactly: 0.008856, 7.787).
    lo, hi = f[4:]
    assert abs(float(hi) - float(lo)) < 2e-6


def test_cube_root_within_two_ulp():
    with jax.enable_x64(True):
        t = np.geomspace(colour._EPS, 1.2, 20001)
        exact = np.cbrt(t.astype(np.float32).astype(np.float64))
    got = np.asarray(jax.jit(colour._cbrt_pos)(t.astype(np.float32)), np.float64)
    ulp = np.spacing(exact.astype(np.float32)).astype(np.float64)
    assert np.max(np.abs(got - exact) / ulp) <= 2.0


def test_gradients_finite_at_singular_points():
    g_eps = 1.055 * 0.008856 ** (1 / 2.4) - 0.055
    pts = jnp.asarray(
        [
            [0.0, 0.0, 0.0],
            [0.04045, 0.04045, 0.04045],
            [g_eps, g_eps, g_eps],
            [1.0, 1.0, 1.0],
            [0.0, 0.5, 1.0],
            [-0.2, 1.3, 0.5],
        ],
        jnp.float32,
    )
    jac = jax.jit(jax.vmap(jax.jacrev(rgb_to_lab)))(pts)
    assert np.all(np.isfinite(np.asarray(jac)))


def test_gradient_matches_finite_differences():
    # Interior points on both branches of sRGB and of f (dark: Y < 0.008856), away from kinks.
    pts = np.array([[0.02, 0.03, 0.01], [0.2, 0.6, 0.9], [0.7, 0.1, 0.3], [0.05, 0.5, 0.02]])
    with jax.enable_x64(True):
        jac = jax.jit(jax.jacrev(rgb_to_lab))
        h = 1e-6
        for p in pts:
            num = np.stack(
                [
                    (np.asarray(_JIT(p + h * e)) - np.asarray(_JIT(p - h * e))) / (2 * h)
                    for e in np.eye(3)
                ],
                -1,
            )
            p = jnp.asarray(p, jnp.float64)
            np.testing.assert_allclose(np.asarray(jac(p)), num, rtol=1e-6, atol=1e-6)
