"""Colour segmentation of the marker discs (Reiter et al. Sec. III-B.1).

One frame is clustered by k-means (k = 5 by default) on its CIELAB a*b* chromaticity; the
cluster of the lime markers is picked once (nearest to a reference colour, or by index) and
every later pixel is labelled by its nearest cluster centre. Labelling a batch of frames is
one jitted, vmapped function (:func:`label_batch`).

Colours: RGB images are float in [0, 1], sRGB-encoded (what PNG files hold); CIELAB uses the
D65 white point (the convention of ``skimage.color.rgb2lab``), a* and b* in their usual units
(about -128..127).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.errors import InputError

#: Default reference marker colour (lime green, sRGB in [0, 1]).
LIME_RGB = (0.55, 0.85, 0.12)

_M_RGB_TO_XYZ = np.array(
    [
        [0.412453, 0.357580, 0.180423],
        [0.212671, 0.715160, 0.072169],
        [0.019334, 0.119193, 0.950227],
    ]
)
_WHITE_D65 = np.array([0.95047, 1.0, 1.08883])


def rgb_to_lab(rgb: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """sRGB in [0, 1] -> CIELAB (L* in [0, 100], a*, b*), D65, as ``skimage.color.rgb2lab``."""
    rgb = jnp.asarray(rgb)
    lin = jnp.where(
        rgb > 0.04045, ((jnp.maximum(rgb, 0.04045) + 0.055) / 1.055) ** 2.4, rgb / 12.92
    )
    xyz = lin @ jnp.asarray(_M_RGB_TO_XYZ.T, lin.dtype)
    t = xyz / jnp.asarray(_WHITE_D65, lin.dtype)
    eps = 0.008856
    # Cube root only on the positive branch (finite gradient at t = 0).
    f = jnp.where(t > eps, jnp.cbrt(jnp.maximum(t, eps)), 7.787 * t + 16.0 / 116.0)
    L = jnp.where(t[..., 1] > eps, 116.0 * f[..., 1] - 16.0, 903.3 * t[..., 1])
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return jnp.stack([L, a, b], axis=-1)


def kmeans(
    x: Float[Array, "n d"], k: int, key: Array, iterations: int = 30
) -> tuple[Float[Array, "k d"], Int[Array, " n"]]:
    """Lloyd's k-means with k-means++ seeding, a fixed number of iterations (jit-able).

    Returns the centres (k, d) and each point's label (n,). Empty clusters keep their
    previous centre. Deterministic for a given ``key``.
    """
    x = jnp.asarray(x)
    n = x.shape[0]
    keys = jax.random.split(key, k)
    first = jax.random.randint(keys[0], (), 0, n)
    centres = jnp.zeros((k, x.shape[1]), x.dtype).at[0].set(x[first])

    def seed_step(i, c):
        d2 = jnp.min(
            jnp.where(
                (jnp.arange(k) < i)[None, :],
                jnp.sum((x[:, None, :] - c[None, :, :]) ** 2, -1),
                jnp.inf,
            ),
            axis=1,
        )
        p = d2 / jnp.maximum(jnp.sum(d2), 1e-30)
        j = jax.random.choice(keys[i], n, p=p)
        return c.at[i].set(x[j])

    centres = jax.lax.fori_loop(1, k, seed_step, centres)

    def assign(c):
        d2 = jnp.sum(x**2, 1)[:, None] - 2.0 * x @ c.T + jnp.sum(c**2, 1)[None, :]
        return jnp.argmin(d2, axis=1)

    def lloyd(_, c):
        lab = assign(c)
        onehot = jax.nn.one_hot(lab, k, dtype=x.dtype)
        cnt = onehot.sum(0)
        s = onehot.T @ x
        return jnp.where(cnt[:, None] > 0, s / jnp.maximum(cnt, 1.0)[:, None], c)

    centres = jax.lax.fori_loop(0, iterations, lloyd, centres)
    return centres, assign(centres)


class ColourModel(eqx.Module):
    """Cluster centres in a*b* (k, 2) and the index of the marker cluster."""

    centres: Float[Array, "k 2"]
    marker: Int[Array, ""]


def fit_colour_model(
    image: np.ndarray,
    k: int = 5,
    marker_rgb: tuple[float, float, float] | None = LIME_RGB,
    marker_index: int | None = None,
    seed: int = 0,
    max_pixels: int = 60_000,
) -> ColourModel:
    """Cluster one RGB frame (H, W, 3) in a*b* and choose the marker cluster.

    The marker cluster is ``marker_index`` if given, else the centre nearest (in a*b*) to
    ``marker_rgb``. At most ``max_pixels`` pixels (a fixed random subset) are clustered.
    """
    img = np.asarray(image, np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"colour model needs an RGB image (H, W, 3), got shape {img.shape}")
    if not 2 <= k <= 64:
        raise InputError(f"number of colour clusters must be in 2..64, got {k}", field="k")
    px = img.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    if len(px) > max_pixels:
        px = px[rng.choice(len(px), max_pixels, replace=False)]
    ab = rgb_to_lab(jnp.asarray(px))[:, 1:]
    centres, _ = jax.jit(kmeans, static_argnums=(1, 3))(ab, k, jax.random.PRNGKey(seed), 30)
    if marker_index is not None:
        if not 0 <= marker_index < k:
            raise InputError(f"marker index must be in 0..{k - 1}, got {marker_index}")
        m = int(marker_index)
    else:
        if marker_rgb is None:
            raise InputError("give a marker colour or a marker cluster index")
        ref = rgb_to_lab(jnp.asarray(marker_rgb, jnp.float32))[1:]
        m = int(jnp.argmin(jnp.sum((centres - ref) ** 2, axis=1)))
    return ColourModel(centres=centres, marker=jnp.asarray(m, jnp.int32))


def label_image(model: ColourModel, image: Float[Array, "h w 3"]) -> Bool[Array, "h w"]:
    """Marker pixels of one RGB frame: those whose nearest a*b* centre is the marker's."""
    ab = rgb_to_lab(image)[..., 1:]
    d2 = jnp.sum((ab[..., None, :] - model.centres) ** 2, axis=-1)
    return jnp.argmin(d2, axis=-1) == model.marker


#: Batched labelling (B, H, W, 3) -> (B, H, W) bool, compiled once per image shape.
label_batch = jax.jit(jax.vmap(label_image, in_axes=(None, 0)))
