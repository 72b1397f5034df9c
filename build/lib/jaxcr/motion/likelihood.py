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

Integration (:func:`window_update`, :func:`object_probability`). The frames fall into two
windows, before the touch (where eq. 13 turns p into the arm-removal term 1 - p) and while
touching (p). Averaging both windows together (eq. 16 over all frames, ``"mixture"``) leaves
a background segment (p ~ 0) at the fraction of pre-touch frames and an arm segment (p ~ 1
throughout) at the fraction of touching frames, so the levels depend on when the touch
happens (with the touch at 40 % of the video: 0.4 and 0.6 against 1 for the object, which is
why the P-R optimal threshold sat at 0.9 of the maximum). The default (``"product"``) keeps
eq. 16 per window, mean_pre = <(1 - p)/kappa>, mean_touch = <p>, and combines the windows as
independent evidence for the object hypothesis "did not move like the end-effector before the
touch AND moves like it while touched": P = mean_pre x mean_touch, which is ~1 for the object
and ~0 for the arm (fails the first) and the background (fails the second) whatever the
touch time. Each window mean carries a prior of ``prior_frames`` pseudo-frames at 1/2 (a Beta
prior), so that a segment seen in one or two frames (a sliver left by occlusion) cannot reach
the map's maximum on a single lucky frame; 0 gives the plain averages.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

INTEGRATIONS = ("product", "mixture")


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


def window_update(
    sums: Float[Array, "2 k"],
    counts: Float[Array, "2 k"],
    q: Float[Array, " k"],
    use: Bool[Array, " k"],
    touch: Bool[Array, ""],
) -> tuple[Float[Array, "2 k"], Float[Array, "2 k"]]:
    """Add one frame's arm-removed probabilities ``q`` (:func:`remove_arm`: (1 - p) / kappa
    before the touch, p while touching) to the running sums of its window, row 0 before the
    touch and row 1 while touching, for the segments in ``use``; ``counts`` counts the frames
    per window and segment (eqs. 15-16, incremental)."""
    row = jnp.stack([~touch, touch]).astype(q.dtype)[:, None] * use.astype(q.dtype)[None]
    return sums + row * q[None], counts + row


def object_probability(
    sums: Float[Array, "2 k"],
    counts: Float[Array, "2 k"],
    integration: str = "product",
    prior_frames: float = 1.0,
) -> Float[Array, " k"]:
    """Integrated segment probability from :func:`window_update`'s sums (see the module
    docstring): ``"product"`` mean_pre x mean_touch, ``"mixture"`` the mean over all frames
    (eq. 16 with both windows pooled). Means are (sum + prior_frames / 2) /
    (count + prior_frames); with no frame and no prior a mean is 0."""
    if integration not in INTEGRATIONS:
        raise ValueError(f"integration must be one of {INTEGRATIONS}, got {integration!r}")

    def mean(s, n):
        den = n + prior_frames
        return jnp.where(den > 0, (s + 0.5 * prior_frames) / jnp.where(den > 0, den, 1.0), 0.0)

    if integration == "product":
        return mean(sums[0], counts[0]) * mean(sums[1], counts[1])
    return mean(sums.sum(0), counts.sum(0))


def probability_map(seg_prob: Float[Array, " k"], labels) -> Float[Array, "h w"]:
    """Paint the per-segment probabilities onto a label map."""
    return seg_prob[labels]


def threshold_map(prob: Float[Array, "h w"], fraction: float) -> Bool[Array, "h w"]:
    """Object mask: probability >= ``fraction`` x the map's maximum (section 5.1 picks 75%)."""
    return prob >= fraction * jnp.maximum(jnp.max(prob), 1e-12)
