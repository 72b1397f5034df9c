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


def _srgb_to_linear(c):
    return jnp.where(c > 0.04045, ((jnp.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4, c / 12.92)


def _lab_f(t):
    # Cube root only on the positive branch (finite gradient at t = 0).
    return jnp.where(t > 0.008856, jnp.cbrt(jnp.maximum(t, 0.008856)), 7.787 * t + 16.0 / 116.0)


def _lab_channels(r, g, b):
    """CIELAB of separate sRGB channel arrays (channel-wise: a trailing axis of 3 is slow
    on CPU)."""
    r, g, b = _srgb_to_linear(r), _srgb_to_linear(g), _srgb_to_linear(b)
    M, W = _M_RGB_TO_XYZ, _WHITE_D65
    x = (M[0, 0] * r + M[0, 1] * g + M[0, 2] * b) / W[0]
    y = (M[1, 0] * r + M[1, 1] * g + M[1, 2] * b) / W[1]
    z = (M[2, 0] * r + M[2, 1] * g + M[2, 2] * b) / W[2]
    fx, fy, fz = _lab_f(x), _lab_f(y), _lab_f(z)
    L = jnp.where(y > 0.008856, 116.0 * fy - 16.0, 903.3 * y)
    return L, 500.0 * (fx - fy), 200.0 * (fy - fz)


_LIN_LUT = np.where(
    np.arange(256) / 255.0 > 0.04045,
    ((np.arange(256) / 255.0 + 0.055) / 1.055) ** 2.4,
    np.arange(256) / 255.0 / 12.92,
).astype(np.float32)


def _fast_lab(image):
    """CIELAB for labelling: channels quantised to 8 bits (the PNG input's precision) and
    linearised by table lookup, cube root as exp(log(t) / 3): XLA's pow and cbrt cost
    ~10x more on CPU. Within 0.05 Lab units of :func:`rgb_to_lab` on 8-bit colours."""
    lut = jnp.asarray(_LIN_LUT)
    q = jnp.clip(jnp.round(image * 255.0), 0, 255).astype(jnp.int32)
    r, g, b = lut[q[..., 0]], lut[q[..., 1]], lut[q[..., 2]]
    M, W = _M_RGB_TO_XYZ, _WHITE_D65
    x = (M[0, 0] * r + M[0, 1] * g + M[0, 2] * b) / W[0]
    y = (M[1, 0] * r + M[1, 1] * g + M[1, 2] * b) / W[1]
    z = (M[2, 0] * r + M[2, 1] * g + M[2, 2] * b) / W[2]

    def f(t):
        pos = t > 0.008856
        return jnp.where(
            pos, jnp.exp(jnp.log(jnp.where(pos, t, 1.0)) / 3.0), 7.787 * t + 16.0 / 116.0
        )

    fx, fy, fz = f(x), f(y), f(z)
    L = jnp.where(y > 0.008856, 116.0 * fy - 16.0, 903.3 * y)
    return L, 500.0 * (fx - fy), 200.0 * (fy - fz)


def rgb_to_lab(rgb: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """sRGB in [0, 1] -> CIELAB (L* in [0, 100], a*, b*), D65, as ``skimage.color.rgb2lab``."""
    rgb = jnp.asarray(rgb)
    return jnp.stack(_lab_channels(rgb[..., 0], rgb[..., 1], rgb[..., 2]), axis=-1)


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
    # every bad argument before the clustering (the work, and its compile)
    if marker_index is not None and not 0 <= marker_index < k:
        raise InputError(f"marker index must be in 0..{k - 1}, got {marker_index}")
    if marker_index is None and marker_rgb is None:
        raise InputError("give a marker colour or a marker cluster index")
    px = img.reshape(-1, 3)
    rng = np.random.default_rng(seed)
    if len(px) > max_pixels:
        px = px[rng.choice(len(px), max_pixels, replace=False)]
    ab = rgb_to_lab(jnp.asarray(px))[:, 1:]
    centres, _ = jax.jit(kmeans, static_argnums=(1, 3))(ab, k, jax.random.PRNGKey(seed), 30)
    if marker_index is not None:
        m = int(marker_index)
    else:
        ref = rgb_to_lab(jnp.asarray(marker_rgb, jnp.float32))[1:]
        m = int(jnp.argmin(jnp.sum((centres - ref) ** 2, axis=1)))
    return ColourModel(centres=centres, marker=jnp.asarray(m, jnp.int32))


def label_image(model: ColourModel, image: Float[Array, "*b h w 3"]) -> Bool[Array, "*b h w"]:
    """Marker pixels of an RGB frame (or any stack of frames): those whose nearest a*b*
    centre is the marker's (a tie with another centre counts as marker)."""
    _, a, b = _fast_lab(jnp.asarray(image))
    # Materialise a*, b* once: otherwise XLA fuses their (transcendental) computation into
    # each of the k distance terms and recomputes it k times (10x slower on CPU).
    a, b = jax.lax.optimization_barrier((a, b))
    c = model.centres
    d2 = [(a - c[j, 0]) ** 2 + (b - c[j, 1]) ** 2 for j in range(c.shape[0])]
    nearest = d2[0]
    for dj in d2[1:]:
        nearest = jnp.minimum(nearest, dj)
    d_marker = _select(d2, model.marker)
    # (A pairwise minimum chain instead of argmin: XLA's variadic argmin reduce is slow on CPU.)
    return d_marker <= nearest


def _select(values, index):
    out = values[0]
    for j, v in enumerate(values[1:], start=1):
        out = jnp.where(index == j, v, out)
    return out


#: Batched labelling (B, H, W, 3) -> (B, H, W) bool, compiled once per batch shape.
#: Labelling is per pixel, so the batch is just more leading axes (a ``jax.vmap`` of
#: :func:`label_image` gives the same masks but turns the table lookup into a batched
#: gather that is ~10x slower on CPU).
label_batch = jax.jit(label_image)
