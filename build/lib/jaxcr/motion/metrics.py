"""Segmentation quality (M-L section 5): precision and recall (eqs. 17-18), P-R curves over a
threshold with the optimal point closest to (1, 1), the L2 distance (eq. 19), the Tanimoto
distance (eq. 20), and a Kolmogorov-Smirnov comparison of two methods' distances."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float


def precision_recall(pred: Bool[Array, "h w"], truth: Bool[Array, "h w"]) -> tuple[Array, Array]:
    """Pr = tp / (tp + fp), Re = tp / (tp + fn) (eqs. 17-18). An empty prediction has
    precision 1 (no false positives); an empty truth has recall 1."""
    tp = jnp.sum(pred & truth)
    fp = jnp.sum(pred & ~truth)
    fn = jnp.sum(~pred & truth)
    pr = jnp.where(tp + fp > 0, tp / jnp.maximum(tp + fp, 1), 1.0)
    re = jnp.where(tp + fn > 0, tp / jnp.maximum(tp + fn, 1), 1.0)
    return pr, re


@jax.jit
def pr_curve(score: Float[Array, "h w"], truth: Bool[Array, "h w"], thresholds: Float[Array, " t"]):
    """Precision and recall of ``score >= t`` for every threshold t: two (t,) arrays."""
    return jax.vmap(lambda t: precision_recall(score >= t, truth))(thresholds)


def optimal_threshold(thresholds, precision, recall) -> tuple[int, float]:
    """Index and value of the threshold whose (Pr, Re) is closest to (1, 1)."""
    d = np.hypot(1.0 - np.asarray(precision), 1.0 - np.asarray(recall))
    k = int(np.argmin(d))
    return k, float(np.asarray(thresholds)[k])


def l2_distance(a: Bool[Array, "h w"], b: Bool[Array, "h w"]) -> Array:
    """Eq. 19: (1 / (N K)) sqrt(sum |a - b|^2) for binary images of N x K pixels."""
    n = a.shape[0] * a.shape[1]
    return jnp.sqrt(jnp.sum((a.astype(jnp.float32) - b.astype(jnp.float32)) ** 2)) / n


def tanimoto_distance(a: Bool[Array, "h w"], b: Bool[Array, "h w"]) -> Array:
    """Eq. 20: 1 - |a AND b| / |a OR b| (0 when both are empty)."""
    inter = jnp.sum(a & b)
    union = jnp.sum(a | b)
    return jnp.where(union > 0, 1.0 - inter / jnp.maximum(union, 1), 0.0)


def ks_compare(ours, theirs) -> dict:
    """Compare per-video distances (lower is better) of two methods.

    Returns the two-sample KS statistic and p-value for the one-sided alternative "our
    distances are stochastically smaller" (scipy.stats.ks_2samp, alternative='greater'), the
    probability that a random video of ours beats a random video of theirs
    (P(ours < theirs) + P(tie)/2), and, for paired lists, the fraction of videos we win.
    """
    from scipy import stats  # scipy: only needed for this report

    a, b = np.asarray(ours, float), np.asarray(theirs, float)
    res = stats.ks_2samp(a, b, alternative="greater")
    diff = a[:, None] - b[None, :]
    p_win = float(np.mean(diff < 0) + 0.5 * np.mean(diff == 0))
    out = {
        "ks_statistic": float(res.statistic),
        "ks_pvalue": float(res.pvalue),
        "p_random_win": p_win,
    }
    if a.shape == b.shape:
        out["fraction_won"] = float(np.mean(a < b))
    return out
