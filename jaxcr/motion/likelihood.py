"""Segment membership probabilities (M-L eqs. 10-16) and the object mask.

* eqs. 10-12: p = N(e | 0, lambda I) for the prediction residual e (translation: x_i + b_j -
  x_{i+1}; homography: H_j x_i - x_{i+1}), so with rho = |e|^2 (eqs. 5, 9)
  p = exp(-rho / (2 lambda)). The normalising factor 1 / (2 pi lambda) is dropped so that
  p lies in [0, 1], which eq. 13's 1 - p requires (the constants are absorbed by kappa and by
  the threshold relative to the maximum, section 5.1).
* eqs. 13-14 (arm removal; the garbled cases are reconstructed from the text of section 4.4:
  "any motion that correlates with the arm movement before an object is touched is likely to
  belong to the arm"): frames without touch use (1 - p) / kappa, frames with touch use p.
  "In practice kappa_j^i can be any constant": kappa = 1.
* eqs. 15-16: the probability of segment S_j is the average over the used frames, kept as a
  running average (count and mean per segment) so that it works incrementally.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


def gaussian_likelihood(rho: Float[Array, "..."], lam: float) -> Float[Array, "..."]:
    """exp(-rho / (2 lambda)): eqs. 10-12 with Sigma = lambda I, rho in px^2, lambda in px^2."""
    return jnp.exp(-rho / (2.0 * lam))


def remove_arm(
    p: Float[Array, "..."], touch: Bool[Array, ""], kappa: float = 1.0
) -> Float[Array, "..."]:
    """Eq. 13: p where the object is touched, (1 - p) / kappa before the touch."""
    return jnp.where(touch, p, (1.0 - p) / kappa)


def running_average(
    mean: Float[Array, " k"],
    count: Float[Array, " k"],
    p: Float[Array, " k"],
    use: Bool[Array, " k"],
) -> tuple[Float[Array, " k"], Float[Array, " k"]]:
    """Eqs. 15-16 incrementally: mean_j <- mean_j + (p_j - mean_j) / n_j for the segments used
    in this frame (``use``), so after n frames mean_j = (1/n_j) sum_i p_j^i."""
    n = count + use
    upd = mean + (p - mean) / jnp.maximum(n, 1.0)
    return jnp.where(use, upd, mean), n


def probability_map(seg_prob: Float[Array, " k"], labels) -> Float[Array, "h w"]:
    """Paint the per-segment probabilities onto a label map."""
    return seg_prob[labels]


def threshold_map(prob: Float[Array, "h w"], fraction: float) -> Bool[Array, "h w"]:
    """Object mask: probability >= ``fraction`` x the map's maximum (section 5.1 picks 75%)."""
    return prob >= fraction * jnp.maximum(jnp.max(prob), 1e-12)
