"""Foreground (robot) alpha from a chroma-key background and from a background plate.

Chroma key (stereo report sec. 3.1.2): a pixel belongs to the background when its colour
lies close to the key colour's hue with enough saturation. The score is brightness
invariant, so the tube's shadow on the cloth (darker, same hue) stays background, while the
metal tube, even with a green cast from reflected cloth, has low saturation and is kept::

    c      = rgb - mean(rgb)                    (chroma vector, removes grey)
    along  = c . k_hat / (max(rgb) + eps)       (saturation towards the key hue)
    across = |c - (c . k_hat) k_hat| / (max(rgb) + eps)
    score  = (along - across) / score(key)      (1 for the key colour, <= 0 for grey)

``alpha = clip((tol_hi - score) / (tol_hi - tol_lo), 0, 1)``: 1 on the robot, 0 on the cloth,
fractional on anti-aliased edge pixels (used for sub-pixel widths by
:mod:`jaxcr.stereo.diameter`). ``tolerance`` is the report's chroma tolerance: the score
below which a pixel counts as foreground.

Background plate (for real rigs where tubes are dark metal with a green cast and a pure
colour key fails): ``alpha = clip((|I - B| - lo) / (hi - lo), 0, 1)`` with the empty-scene
image ``B``. Shadows differ from the plate and are segmented with the tube; they are removed
afterwards (:mod:`jaxcr.stereo.shadow`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float

__all__ = [
    "KEY_COLOURS",
    "chroma_score",
    "chroma_alpha",
    "key_projection",
    "chroma_alpha_and_projection",
    "plate_alpha",
    "plate_alpha_shadow_invariant",
]

KEY_COLOURS = {"green": (0.15, 0.62, 0.22), "blue": (0.12, 0.25, 0.70)}
_EPS = 1e-3


def _to_float(image: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """uint8 images -> float32 in [0, 1]; float images unchanged."""
    if image.dtype == jnp.uint8:
        return image.astype(jnp.float32) * jnp.float32(1.0 / 255.0)
    return image


def _key_hat(key_rgb, dtype) -> Float[Array, "3"]:
    key = jnp.asarray(key_rgb, dtype)
    kc = key - jnp.mean(key)
    return kc / jnp.linalg.norm(kc)


def _channels_score(r, g, b, k_hat):
    """Raw key score from separate channel arrays (elementwise only: XLA fuses it into one
    loop; a ``(..., 3) @ (3,)`` contraction was ~10x slower on CPU)."""
    m = (r + g + b) * (1.0 / 3.0)
    cr, cg, cb = r - m, g - m, b - m
    along = cr * k_hat[0] + cg * k_hat[1] + cb * k_hat[2]
    pr, pg, pb = cr - along * k_hat[0], cg - along * k_hat[1], cb - along * k_hat[2]
    across = jnp.sqrt(pr * pr + pg * pg + pb * pb + 1e-12)
    bright = jnp.maximum(jnp.maximum(r, g), b) + _EPS
    return (along - across) / bright, along


def _raw_score(rgb: Float[Array, "... 3"], k_hat: Float[Array, "3"]) -> Float[Array, "..."]:
    return _channels_score(rgb[..., 0], rgb[..., 1], rgb[..., 2], k_hat)[0]


def chroma_score(image: Float[Array, "h w 3"], key_rgb: Float[Array, "3"]) -> Float[Array, "h w"]:
    """Key-likeness of every pixel (1 = the key colour, <= 0 = grey or another hue).

    ``image`` RGB in [0, 1] (or uint8); ``key_rgb`` the cloth colour (need not be exact:
    only its hue direction matters, and the normalisation by its own score)."""
    image = _to_float(image)
    k_hat = _key_hat(key_rgb, image.dtype)
    key = jnp.asarray(key_rgb, image.dtype)
    return _raw_score(image, k_hat) / _raw_score(key, k_hat)


@jax.jit
def chroma_alpha(
    image: Float[Array, "h w 3"],
    key_rgb: Float[Array, "3"],
    tol_lo: float = 0.25,
    tol_hi: float = 0.55,
) -> Float[Array, "h w"]:
    """Foreground alpha in [0, 1] from the chroma key (see module docstring)."""
    s = chroma_score(image, key_rgb)
    return jnp.clip((tol_hi - s) / (tol_hi - tol_lo), 0.0, 1.0)


@jax.jit
def key_projection(image: Float[Array, "h w 3"], key_rgb: Float[Array, "3"]) -> Float[Array, "h w"]:
    """``(rgb - mean(rgb)) . k_hat``: linear in RGB, hence linear in the coverage of an
    edge pixel that mixes tube and cloth (used for sub-pixel widths)."""
    image = _to_float(image)
    k_hat = _key_hat(key_rgb, image.dtype)
    return _channels_score(image[..., 0], image[..., 1], image[..., 2], k_hat)[1]


@jax.jit
def chroma_alpha_and_projection(
    image: Float[Array, "h w 3"],
    key_rgb: Float[Array, "3"],
    tol_lo: float = 0.25,
    tol_hi: float = 0.55,
) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """:func:`chroma_alpha` and :func:`key_projection` in one pass over the image
    (uint8 or float RGB)."""
    image = _to_float(image)
    k_hat = _key_hat(key_rgb, image.dtype)
    key = jnp.asarray(key_rgb, image.dtype)
    raw, along = _channels_score(image[..., 0], image[..., 1], image[..., 2], k_hat)
    s = raw / _raw_score(key, k_hat)
    return jnp.clip((tol_hi - s) / (tol_hi - tol_lo), 0.0, 1.0), along


@jax.jit
def plate_alpha(
    image: Float[Array, "h w 3"],
    plate: Float[Array, "h w 3"],
    lo: float = 0.06,
    hi: float = 0.15,
) -> Float[Array, "h w"]:
    """Foreground alpha from the colour distance to a background plate (empty scene)."""
    image, plate = _to_float(image), _to_float(plate)
    d = jnp.sqrt(jnp.sum((image - plate) ** 2, axis=-1) + 1e-12)
    return jnp.clip((d - lo) / (hi - lo), 0.0, 1.0)


@jax.jit
def plate_alpha_shadow_invariant(
    image: Float[Array, "h w 3"],
    plate: Float[Array, "h w 3"],
    lo: float = 0.06,
    hi: float = 0.15,
    min_gain: float = 0.25,
) -> Float[Array, "h w"]:
    """Background-plate alpha that ignores shadows: a shadow darkens the plate without
    changing its colour, ``I ~ g B`` with a gain ``g`` in ``[min_gain, 1]``, so the
    distance is taken to the best-scaled plate ``g B`` (``g = I.B / B.B`` clipped)."""
    image, plate = _to_float(image), _to_float(plate)
    g = jnp.sum(image * plate, axis=-1) / jnp.maximum(jnp.sum(plate * plate, axis=-1), 1e-9)
    g = jnp.clip(g, min_gain, 1.0)[..., None]
    d = jnp.sqrt(jnp.sum((image - g * plate) ** 2, axis=-1) + 1e-12)
    return jnp.clip((d - lo) / (hi - lo), 0.0, 1.0)
