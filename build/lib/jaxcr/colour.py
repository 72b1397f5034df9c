"""Colour-space conversions shared by the segmentation methods (pure JAX)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcr._types import Array, Float

_EPS = 0.008856
# sRGB (linear) -> XYZ and the D65 white point, as scikit-image's rgb2lab.
_RGB2XYZ = (
    (0.412453, 0.357580, 0.180423),
    (0.212671, 0.715160, 0.072169),
    (0.019334, 0.119193, 0.950227),
)
_WHITE = (0.95047, 1.0, 1.08883)


def _cbrt_pos(t: Float[Array, "..."]) -> Float[Array, "..."]:
    """Cube root of ``t >= _EPS`` as ``exp(log(t) / 3)`` refined by one Newton step.

    XLA's ``cbrt`` (and ``pow``) cost several times ``exp`` + ``log`` on CPU. The Newton step
    ``y <- (2 y + t / y^2) / 3`` squares the relative error of the exp/log estimate (a few
    ulp), so the result is within ~1 ulp of the true cube root; its derivative at the fixed
    point is the exact ``1 / (3 y^2)``.
    """
    y = jnp.exp(jnp.log(t) * (1.0 / 3.0))
    return (2.0 * y + t / (y * y)) * (1.0 / 3.0)


def _lab_f(t: Float[Array, "..."]) -> Float[Array, "..."]:
    """CIELAB's f(t): cube root above ``_EPS``, linear segment ``7.787 t + 16/116`` below.

    Double where: the cube root only sees ``t > _EPS`` (1 elsewhere), so values and
    gradients are finite at ``t = 0`` (black) and across the branch point.
    """
    pos = t > _EPS
    return jnp.where(pos, _cbrt_pos(jnp.where(pos, t, 1.0)), 7.787 * t + 16.0 / 116.0)


def _srgb_to_linear(c: Float[Array, "..."]) -> Float[Array, "..."]:
    """Inverse sRGB companding of one channel in [0, 1] (IEC 61966-2-1).

    The power ``((c + 0.055) / 1.055) ** 2.4`` is taken as ``exp(2.4 log(.))`` of an argument
    >= 0.055 / 1.055 on the branch that uses it (1 elsewhere), so it is finite everywhere.
    """
    pos = c > 0.04045
    u = (jnp.where(pos, c, 1.0) + 0.055) * (1.0 / 1.055)
    return jnp.where(pos, jnp.exp(2.4 * jnp.log(u)), c * (1.0 / 12.92))


def rgb_to_lab(rgb: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """sRGB in [0, 1] to CIE L*a*b* (D65; L* in [0, 100]), as ``skimage.color.rgb2lab``.

    Inputs are clipped to [0, 1]; the result has the input's floating dtype. The cube root is
    taken only on the branch that uses it, so the gradient is finite at black. Computed
    channel by channel (three scalar-weighted sums instead of a matmul over the trailing
    colour axis, powers via exp/log): ~4x faster on CPU than ``cbrt`` and ``@``, and within
    1e-4 Lab units of both (tests/core/test_colour.py).
    """
    rgb = jnp.clip(rgb, 0.0, 1.0)
    r = _srgb_to_linear(rgb[..., 0])
    g = _srgb_to_linear(rgb[..., 1])
    b = _srgb_to_linear(rgb[..., 2])
    M, W = _RGB2XYZ, _WHITE
    # Same operation order as skimage (M @ rgb, then / white): same side of the f branch point.
    x = (M[0][0] * r + M[0][1] * g + M[0][2] * b) / W[0]
    y = (M[1][0] * r + M[1][1] * g + M[1][2] * b) / W[1]
    z = (M[2][0] * r + M[2][1] * g + M[2][2] * b) / W[2]
    fx, fy, fz = _lab_f(x), _lab_f(y), _lab_f(z)
    L = jnp.where(y > _EPS, 116.0 * fy - 16.0, 903.3 * y)
    return jnp.stack([L, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)
