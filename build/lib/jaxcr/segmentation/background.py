"""Background subtraction I' = I o M(I, theta) (Watson et al. Sec. II-A).

Pluggable, each variant returns ``(B, I')``: ``B`` (h, w) bool is True on background pixels
(excluded from the data terms of eq. 5 and penalised under the projection), ``I' = I * ~B``.

* :func:`colour_mask` — a colour mask removing colours unlikely for a robot (the paper's
  choice). Default ranges (:data:`ROBOT_HSV`) describe *metallic / grey / white* tubes, which is
  what continuum robots are made of (nitinol, stainless steel, PTFE/PEEK sheaths): low
  saturation at any hue and any brightness above near-black. Strongly saturated colours
  (tissue reds, blood, green drapes, blue gloves) are background. These numbers come from
  the physics of the materials (grey metals reflect nearly equally in R, G, B; specular
  highlights are the colour of the light), not from any scene generator. Pass your own
  :class:`HSVRange` boxes (or Lab chroma limits with :func:`lab_mask`) for coloured robots.
* :func:`fit_background_model` / :func:`background_model_mask` — a per-pixel Gaussian mixture
  learned from robot-free background images (a JAX counterpart of Zivkovic's MOG/MOG2 for a
  static camera); pixels explained by the model are background.
* :func:`no_mask` — no background subtraction (B empty).

All functions are pure JAX on RGB float images in [0, 1] (h, w, 3), jit- and vmap-able.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float
from jaxcr.colour import rgb_to_lab  # noqa: F401  (re-exported: part of this module's API)


class HSVRange(eqx.Module):
    """An HSV box of robot colours. Hue in degrees [0, 360) (wraps when ``h_lo > h_hi``),
    saturation and value in [0, 1]."""

    h_lo: float = 0.0
    h_hi: float = 360.0
    s_lo: float = 0.0
    s_hi: float = 1.0
    v_lo: float = 0.0
    v_hi: float = 1.0


#: Robot colours by default: greys/metals/whites (saturation <= 0.30) not near-black.
ROBOT_HSV: tuple[HSVRange, ...] = (HSVRange(s_hi=0.30, v_lo=0.06),)


def rgb_to_hsv(image: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """RGB in [0, 1] to HSV with hue in degrees [0, 360), S and V in [0, 1] (as
    ``colorsys.rgb_to_hsv`` scaled by 360 for hue)."""
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    v = jnp.max(image, axis=-1)
    mn = jnp.min(image, axis=-1)
    c = v - mn
    has_c = c > 0
    cs = jnp.where(has_c, c, 1.0)
    s = jnp.where(v > 0, c / jnp.where(v > 0, v, 1.0), 0.0)
    h = jnp.where(
        v == r,
        jnp.mod((g - b) / cs, 6.0),
        jnp.where(v == g, (b - r) / cs + 2.0, (r - g) / cs + 4.0),
    )
    h = jnp.where(has_c, h * 60.0, 0.0)
    return jnp.stack([h, s, v], axis=-1)


def subtract(image: Float[Array, "h w 3"], background: Bool[Array, "h w"]) -> Float[Array, "h w 3"]:
    """I' = I o M with M = not B (the Hadamard product of Watson et al.)."""
    return image * (~background)[..., None].astype(image.dtype)


def colour_mask(
    image: Float[Array, "h w 3"], *, ranges: tuple[HSVRange, ...] = ROBOT_HSV
) -> tuple[Bool[Array, "h w"], Float[Array, "h w 3"]]:
    """Colour mask: pixels whose HSV colour lies in none of the robot ``ranges`` are background.

    Parameters
    ----------
    image : float array (h, w, 3)
        RGB in [0, 1].
    ranges : tuple[HSVRange, ...]
        HSV boxes of robot colours (hue in degrees, saturation and value in [0, 1]); the
        default :data:`ROBOT_HSV` takes greys, metals and whites (saturation <= 0.3) that are
        not near-black.

    Returns
    -------
    background : bool array (h, w)
        B: True where the pixel is background (in no range).
    image : float array (h, w, 3)
        I' = I o M with M = not B: the image with the background set to 0 (Watson et al.).

    Examples
    --------
    >>> import jax.numpy as jnp
    >>> import jaxcr as jcr
    >>> rgb = jnp.array([[[0.6, 0.6, 0.6], [0.1, 0.7, 0.2]]])  # grey (robot), green
    >>> background, masked = jcr.colour_mask(rgb)
    >>> background.tolist()
    [[False, True]]
    >>> masked[0, 1].tolist()
    [0.0, 0.0, 0.0]
    """
    hsv = rgb_to_hsv(image)
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    robot = jnp.zeros(h.shape, bool)
    for r in ranges:
        in_h = jnp.where(
            r.h_lo <= r.h_hi, (h >= r.h_lo) & (h <= r.h_hi), (h >= r.h_lo) | (h <= r.h_hi)
        )
        robot = robot | (in_h & (s >= r.s_lo) & (s <= r.s_hi) & (v >= r.v_lo) & (v <= r.v_hi))
    bg = ~robot
    return bg, subtract(image, bg)


def lab_mask(
    image: Float[Array, "h w 3"],
    max_chroma: float = 25.0,
    min_lightness: float = 5.0,
    centre_ab: tuple[float, float] = (0.0, 0.0),
) -> tuple[Bool[Array, "h w"], Float[Array, "h w 3"]]:
    """Lab colour mask: robot colours lie within ``max_chroma`` of ``centre_ab`` in the (a*, b*)
    plane (default: near-grey) with L* >= ``min_lightness``; the rest is background.

    Returns ``(B, I')``.
    """
    lab = rgb_to_lab(image)
    da = lab[..., 1] - centre_ab[0]
    db = lab[..., 2] - centre_ab[1]
    robot = (da * da + db * db <= max_chroma**2) & (lab[..., 0] >= min_lightness)
    bg = ~robot
    return bg, subtract(image, bg)


def no_mask(image: Float[Array, "h w 3"]) -> tuple[Bool[Array, "h w"], Float[Array, "h w 3"]]:
    """No background subtraction: B is empty and I' = I."""
    return jnp.zeros(image.shape[:2], bool), image


class BackgroundModel(eqx.Module):
    """Per-pixel Gaussian mixture of background colours (diagonal covariances).

    Attributes:
        weights: (h, w, k) mixture weights (sum to 1 per pixel).
        means: (h, w, k, 3) RGB means.
        variances: (h, w, k, 3) per-channel variances (floored at ``min_var``).
    """

    weights: Float[Array, "h w k"]
    means: Float[Array, "h w k 3"]
    variances: Float[Array, "h w k 3"]


def fit_background_model(
    images: Float[Array, "n h w 3"],
    n_components: int = 1,
    iterations: int = 10,
    min_std: float = 0.03,
) -> BackgroundModel:
    """Fit a per-pixel Gaussian mixture to robot-free images by EM (fixed iterations).

    With one component this is the per-pixel mean and variance. ``min_std`` (colour units)
    floors the standard deviation, covering sensor noise when only a few images exist.
    Components are initialised from evenly spaced images.
    """
    n = images.shape[0]
    k = min(n_components, n)
    x = jnp.moveaxis(images, 0, 2)  # (h, w, n, 3)
    min_var = min_std**2
    init_idx = jnp.linspace(0, n - 1, k).round().astype(jnp.int32)
    mu = x[:, :, init_idx]  # (h, w, k, 3)
    var = jnp.maximum(jnp.var(x, axis=2, keepdims=True), min_var) * jnp.ones_like(mu)
    wts = jnp.full(x.shape[:2] + (k,), 1.0 / k, x.dtype)

    def em(_, state):
        wts, mu, var = state
        d = x[:, :, :, None, :] - mu[:, :, None]  # (h, w, n, k, 3)
        logp = -0.5 * jnp.sum(d * d / var[:, :, None] + jnp.log(2 * jnp.pi * var[:, :, None]), -1)
        logp = logp + jnp.log(wts)[:, :, None]
        resp = jax.nn.softmax(logp, axis=-1)  # (h, w, n, k)
        nk = jnp.sum(resp, axis=2) + 1e-6  # (h, w, k)
        mu = jnp.einsum("hwnk,hwnc->hwkc", resp, x) / nk[..., None]
        d = x[:, :, :, None, :] - mu[:, :, None]
        var = jnp.einsum("hwnk,hwnkc->hwkc", resp, d * d) / nk[..., None]
        return nk / n, mu, jnp.maximum(var, min_var)

    if k > 1:
        wts, mu, var = jax.lax.fori_loop(0, iterations, em, (wts, mu, var))
    else:
        mu = jnp.mean(x, axis=2, keepdims=True)
        var = jnp.maximum(jnp.var(x, axis=2, keepdims=True), min_var)
    return BackgroundModel(weights=wts, means=mu, variances=var)


def background_model_mask(
    model: BackgroundModel, image: Float[Array, "h w 3"], threshold: float = 3.0
) -> tuple[Bool[Array, "h w"], Float[Array, "h w 3"]]:
    """Pixels within ``threshold`` standard deviations (Mahalanobis, per component) of a
    background component with weight >= 0.05 are background. Returns ``(B, I')``."""
    d = image[:, :, None, :] - model.means
    m2 = jnp.sum(d * d / model.variances, axis=-1)  # (h, w, k)
    # chi-square with 3 dof: threshold on the per-channel-normalised distance
    close = (m2 <= 3.0 * threshold**2) & (model.weights >= 0.05)
    bg = jnp.any(close, axis=-1)
    return bg, subtract(image, bg)
