"""Parallel thinning of binary masks in JAX with 256-entry neighbourhood lookup tables.

Zhang & Suen (1984), "A fast parallel algorithm for thinning digital patterns" (the stereo
report's thinning step, sec. 3.2.1), and, as a second table set, Guo & Hall (1989),
"Parallel thinning with two-subiteration algorithms" (algorithm A1).

Both are two-sub-iteration parallel algorithms: in each sub-iteration every foreground pixel
is deleted or kept from its 8 neighbours alone, all at once. The 8 neighbours are packed
into one 8-bit code per pixel (a handful of shifted ``uint8`` ORs), and a 256-entry boolean
table per sub-iteration says whether a pixel with that neighbourhood is deleted; the
sub-iterations repeat in a ``lax.while_loop`` until an iteration deletes nothing.
Pixels outside the image count as background.

Neighbour names follow Zhang & Suen (P1 is the pixel, P2 north, then clockwise), and bit
``k - 2`` of the code is ``P_k``::

    P9 P2 P3
    P8 P1 P4
    P7 P6 P5

Zhang-Suen (built from the rule in :func:`zhang_suen_tables`): a foreground pixel is
deleted in sub-iteration 1 when ``2 <= B <= 6``, ``A == 1``, ``P2 P4 P6 == 0`` and
``P4 P6 P8 == 0``; in sub-iteration 2 the last two become ``P2 P4 P8 == 0`` and
``P2 P6 P8 == 0``. ``B`` is the number of foreground neighbours and ``A`` the number of
0->1 transitions in the cyclic sequence P2, P3, ..., P9, P2. This equals a literal
per-pixel loop of the paper exactly (tests).

scikit-image's ``skeletonize`` (2-D) is a different Zhang-Suen-based table: it also deletes
pixels whose neighbours stay 8-connected although the paper's ``A`` is 2 (the inner pixel
of a staircase corner, e.g. only P2 and P4 set), and it keeps some that the paper deletes;
its skeletons are one pixel thinner on diagonal runs and differ in ~2 % of the pixels and at
stroke ends (measured in ``experiments/stereo/stereo_bench.py``). scikit-image's ``thin`` is
Guo-Hall A1; :func:`guo_hall_thin` (tables built from the paper's conditions G1-G3 in
:func:`guo_hall_tables`) equals it exactly (tests).

Fast path (:func:`zhang_suen_thin`): the same rule bit-parallel. Each row is packed into
``uint32`` words (32 pixels per word, bit ``j`` of word ``i`` = column ``32 i + j``); the
eight neighbour planes are row shifts and carried bit shifts of the words, and the rule is
evaluated as Boolean logic on whole words: ``2 <= B <= 6`` is "at least two neighbours set
and at least two clear", ``A == 1`` is "exactly one 0->1 transition", each counted with
two accumulator words (``two |= one & b; one |= b``). It equals the table lookup
(:func:`lut_thin` with :func:`zhang_suen_tables`) exactly (tests) and is a few times faster.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import UInt8, UInt32

from jaxcr._types import Array, Bool

__all__ = [
    "neighbour_codes",
    "zhang_suen_tables",
    "guo_hall_tables",
    "lut_thin",
    "zhang_suen_thin",
    "zhang_suen_thin_lut",
    "zhang_suen_step",
    "guo_hall_thin",
]

# (row, col) offsets of P2..P9 (bit 0..7 of the code).
_OFFSETS = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1))


def _bits(code: int) -> list[int]:
    """P2..P9 of a neighbourhood code."""
    return [(code >> k) & 1 for k in range(8)]


def zhang_suen_tables() -> np.ndarray:
    """(2, 256) bool: deletion of a foreground pixel with neighbour code ``n`` in
    Zhang-Suen sub-iteration 1 (row 0) and 2 (row 1), from the paper's conditions."""
    out = np.zeros((2, 256), bool)
    for n in range(256):
        p = _bits(n)
        p2, _, p4, _, p6, _, p8, _ = p
        b = sum(p)
        a = sum(1 for k in range(8) if p[k] == 0 and p[(k + 1) % 8] == 1)
        base = 2 <= b <= 6 and a == 1
        out[0, n] = base and p2 * p4 * p6 == 0 and p4 * p6 * p8 == 0
        out[1, n] = base and p2 * p4 * p8 == 0 and p2 * p6 * p8 == 0
    return out


def guo_hall_tables() -> np.ndarray:
    """(2, 256) bool deletion tables of Guo & Hall (1989) algorithm A1.

    In Guo-Hall's notation the neighbours x1..x8 run counter-clockwise from east
    (x1 = P4, x2 = P3, x3 = P2, x4 = P9, x5 = P8, x6 = P7, x7 = P6, x8 = P5). A pixel is
    deleted when G1: the crossing number ``X_H = sum_{i=1..4} b_i == 1`` with
    ``b_i = (not x_{2i-1}) and (x_{2i} or x_{2i+1})``; G2: ``2 <= min(N1, N2) <= 3`` with
    ``N1 = sum_k x_{2k-1} or x_{2k}``, ``N2 = sum_k x_{2k} or x_{2k+1}``; and G3 (first
    sub-iteration) ``(x2 or x3 or not x8) and x1 == 0``, or G3' (second)
    ``(x6 or x7 or not x4) and x5 == 0`` (indices mod 8)."""
    out = np.zeros((2, 256), bool)
    for n in range(256):
        p = _bits(n)  # P2..P9
        P = dict(zip(range(2, 10), p, strict=True))
        x = [P[4], P[3], P[2], P[9], P[8], P[7], P[6], P[5]]  # x1..x8 as x[0..7]

        def xi(i: int, x: list[int] = x) -> int:
            return x[(i - 1) % 8]

        xh = sum(1 for i in range(1, 5) if not xi(2 * i - 1) and (xi(2 * i) or xi(2 * i + 1)))
        n1 = sum(1 for k in range(1, 5) if xi(2 * k - 1) or xi(2 * k))
        n2 = sum(1 for k in range(1, 5) if xi(2 * k) or xi(2 * k + 1))
        g12 = xh == 1 and 2 <= min(n1, n2) <= 3
        g3 = not ((xi(2) or xi(3) or not xi(8)) and xi(1))
        g3p = not ((xi(6) or xi(7) or not xi(4)) and xi(5))
        out[0, n] = g12 and g3
        out[1, n] = g12 and g3p
    return out


_ZS = zhang_suen_tables()
_GH = guo_hall_tables()


def neighbour_codes(img: UInt8[Array, "h w"]) -> UInt8[Array, "h w"]:
    """8-bit neighbourhood code of every pixel of a 0/1 ``uint8`` image: bit ``k - 2`` is
    ``P_k`` (zero padding outside the image)."""
    h, w = img.shape
    pad = jnp.pad(img, 1)
    code = jnp.zeros_like(img)
    for k, (dr, dc) in enumerate(_OFFSETS):
        code = code | (pad[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w] << k)
    return code


def _sub_iteration(x: UInt8[Array, "h w"], table: Bool[Array, "256"]) -> UInt8[Array, "h w"]:
    """Delete (in parallel) the foreground pixels whose neighbour code ``table`` marks."""
    dele = jnp.take(table, neighbour_codes(x).astype(jnp.int32), mode="clip")
    return jnp.where(dele, jnp.uint8(0), x)


def _step(x: UInt8[Array, "h w"], tables: Bool[Array, "2 256"]) -> UInt8[Array, "h w"]:
    return _sub_iteration(_sub_iteration(x, tables[0]), tables[1])


def lut_thin(mask: Bool[Array, "h w"], tables: Bool[Array, "2 256"]) -> Bool[Array, "h w"]:
    """Thin ``mask`` (H, W) with a two-sub-iteration deletion table pair (2, 256), until an
    iteration deletes nothing (at most about half the widest stroke's width iterations).
    Single image, traceable (jit/vmap; under vmap the loop runs until every image has
    converged, the converged ones unchanged)."""
    tables = jnp.asarray(tables, bool)

    def cond(state):
        return state[1]

    def body(state):
        x, _ = state
        y = _step(x, tables)
        return y, jnp.any(y != x)

    out, _ = jax.lax.while_loop(cond, body, (mask.astype(jnp.uint8), jnp.array(True)))
    return out.astype(bool)


@jax.jit
def zhang_suen_thin_lut(mask: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """Zhang-Suen thinning by table lookup (:func:`lut_thin`); same result as
    :func:`zhang_suen_thin`, which is faster."""
    return lut_thin(mask, _ZS)


def _pack(mask: Bool[Array, "h w"]) -> UInt32[Array, "h k"]:
    """(H, W) bool, W a multiple of 32 -> (H, W / 32) words, bit j of word i = column 32 i + j."""
    h, w = mask.shape
    b = mask.reshape(h, w // 32, 32).astype(jnp.uint32)
    return jnp.sum(b << jnp.arange(32, dtype=jnp.uint32), axis=2, dtype=jnp.uint32)


def _unpack(words: UInt32[Array, "h k"], w: int) -> Bool[Array, "h w"]:
    h = words.shape[0]
    bits = (words[:, :, None] >> jnp.arange(32, dtype=jnp.uint32)) & jnp.uint32(1)
    return (bits == 1).reshape(h, -1)[:, :w]


def _east(x):  # column c + 1 seen at column c (zero beyond the last word)
    return (x >> 1) | (jnp.pad(x[:, 1:], ((0, 0), (0, 1))) << 31)


def _west(x):  # column c - 1 seen at column c
    return (x << 1) | (jnp.pad(x[:, :-1], ((0, 0), (1, 0))) >> 31)


def _counts(bits) -> tuple:
    """Bitwise "at least one" and "at least two" of a list of words."""
    one = jnp.zeros_like(bits[0])
    two = one
    for b in bits:
        two = two | (one & b)
        one = one | b
    return one, two


def _packed_sub_iteration(x: UInt32[Array, "h k"], first: bool) -> UInt32[Array, "h k"]:
    north = jnp.pad(x[:-1], ((1, 0), (0, 0)))
    south = jnp.pad(x[1:], ((0, 1), (0, 0)))
    p = [north, _east(north), _east(x), _east(south), south, _west(south), _west(x), _west(north)]
    p2, _, p4, _, p6, _, p8, _ = p
    b_ok = _counts(p)[1] & _counts([~q for q in p])[1]  # 2 <= B <= 6
    one, two = _counts([~p[k] & p[(k + 1) % 8] for k in range(8)])  # A == 1
    if first:
        c = ~(p2 & p4 & p6) & ~(p4 & p6 & p8)
    else:
        c = ~(p2 & p4 & p8) & ~(p2 & p6 & p8)
    return x & ~(b_ok & one & ~two & c)


@jax.jit
def zhang_suen_thin(mask: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """Thin a binary mask (H, W) to a one-pixel-wide 8-connected skeleton (Zhang-Suen, the
    paper's rule; bit-parallel, see module docstring). Iterates until an iteration deletes
    nothing. Single image; ``jax.vmap`` for a batch (the loop then runs until every image
    has converged)."""
    h, w = mask.shape
    x = _pack(jnp.pad(mask.astype(bool), ((0, 0), (0, -(-w // 32) * 32 - w))))

    def body(state):
        x, _ = state
        y = _packed_sub_iteration(_packed_sub_iteration(x, True), False)
        return y, jnp.any(y != x)

    out, _ = jax.lax.while_loop(lambda state: state[1], body, (x, jnp.array(True)))
    return _unpack(out, w)


@jax.jit
def guo_hall_thin(mask: Bool[Array, "h w"]) -> Bool[Array, "h w"]:
    """Guo-Hall A1 thinning of a binary mask (H, W); equals ``skimage.morphology.thin``."""
    return lut_thin(mask, _GH)


@functools.partial(jax.jit, static_argnames="variant")
def zhang_suen_step(mask: Bool[Array, "h w"], variant: str = "zhang-suen") -> Bool[Array, "h w"]:
    """One full iteration (sub-iteration 1 then 2) of a binary image (``variant``
    ``"zhang-suen"`` or ``"guo-hall"``)."""
    tables = {"zhang-suen": _ZS, "guo-hall": _GH}[variant]
    return _step(mask.astype(jnp.uint8), jnp.asarray(tables)).astype(bool)
