"""Zhang-Suen parallel thinning (Zhang & Suen 1984, "A fast parallel algorithm for thinning
digital patterns"), vectorised in JAX: every pixel of a sub-iteration is decided at once from
its 8 neighbours, and sub-iterations repeat in a ``lax.while_loop`` until nothing changes.

Neighbour names follow the paper (P1 is the pixel, P2 north, then clockwise)::

    P9 P2 P3
    P8 P1 P4
    P7 P6 P5

A foreground pixel is deleted in sub-iteration 1 when ``2 <= B <= 6``, ``A == 1``,
``P2 P4 P6 == 0`` and ``P4 P6 P8 == 0``; in sub-iteration 2 the last two become
``P2 P4 P8 == 0`` and ``P2 P6 P8 == 0``. ``B`` is the number of foreground neighbours and
``A`` the number of 0->1 transitions in the cyclic sequence P2, P3, ..., P9, P2. Pixels
outside the image count as background. This is the stereo report's thinning step (sec. 3.2.1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Int

__all__ = ["zhang_suen_thin", "zhang_suen_step"]

# (row, col) offsets of P2..P9.
_OFFSETS = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1))


def _neighbours(img: Int[Array, "h w"]) -> list[Int[Array, "h w"]]:
    """P2..P9 of every pixel (zero padding outside the image)."""
    h, w = img.shape
    pad = jnp.pad(img, 1)
    return [pad[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w] for dr, dc in _OFFSETS]


def _deletable(img: Int[Array, "h w"], first: bool) -> Bool[Array, "h w"]:
    p = _neighbours(img)
    p2, p3, p4, p5, p6, p7, p8, p9 = p
    b = sum(p)
    seq = p + [p2]
    a = sum((1 - seq[k]) * seq[k + 1] for k in range(8))
    if first:
        c1 = p2 * p4 * p6
        c2 = p4 * p6 * p8
    else:
        c1 = p2 * p4 * p8
        c2 = p2 * p6 * p8
    return (img == 1) & (b >= 2) & (b <= 6) & (a == 1) & (c1 == 0) & (c2 == 0)


def zhang_suen_step(img: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """One full Zhang-Suen iteration (sub-iteration 1 then 2) of a binary image."""
    x = img.astype(jnp.int32)
    x = jnp.where(_deletable(x, True), 0, x)
    x = jnp.where(_deletable(x, False), 0, x)
    return x.astype(bool)


@jax.jit
def zhang_suen_thin(mask: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """Thin a binary mask (H, W) to a one-pixel-wide 8-connected skeleton (Zhang-Suen).

    Iterates :func:`zhang_suen_step` until an iteration deletes nothing (at most H*W/2
    iterations, far fewer in practice: about half the largest stroke width). Single image;
    ``jax.vmap`` for a batch (the loop then runs until the slowest image converges).
    """

    def cond(state):
        _, changed = state
        return changed

    def body(state):
        x, _ = state
        y = zhang_suen_step(x)
        return y, jnp.any(y != x)

    out, _ = jax.lax.while_loop(cond, body, (mask.astype(bool), jnp.array(True)))
    return out
