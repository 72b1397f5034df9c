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


def rgb_to_lab(rgb: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """sRGB in [0, 1] to CIE L*a*b* (D65; L* in [0, 100]), as ``skimage.color.rgb2lab``.

    Inputs are clipped to [0, 1]. The cube root is taken of ``max(xyz, eps)`` only on the branch
    that uses it, so the gradient is finite at black.
    """
    rgb = jnp.clip(rgb, 0.0, 1.0)
    lin = jnp.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    M = jnp.asarray(_RGB2XYZ, rgb.dtype)
    xyz = (lin @ M.T) / jnp.asarray(_WHITE, rgb.dtype)
    f = jnp.where(xyz > _EPS, jnp.cbrt(jnp.maximum(xyz, _EPS)), 7.787 * xyz + 16.0 / 116.0)
    L = jnp.where(xyz[..., 1] > _EPS, 116.0 * f[..., 1] - 16.0, 903.3 * xyz[..., 1])
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return jnp.stack([L, a, b], axis=-1)
