"""Loop closure refinement: Algorithm 2 of the paper with virtual mates (ref. [34]).

Clouds C_0..C_{m-1} form a ring (C_m = C_0). ``rel[i]`` is the pairwise registration
``T_{i+1 <- i}`` (the last one, ``T_{0 <- m-1}``, is the loop-closure registration).
Initial poses follow eqs. (1)-(2): ``T_O,m-1 = I``, ``T_O,i = T_O,i+1 T_{i+1 <- i}``.

For cloud i, points p are sampled in its overlaps with both neighbours; each gets a virtual
mate q = T_{j <- i} p in the neighbour's frame, carried into O by the neighbour's current
pose. Align(i) is the Kabsch fit of p (frame i) to all mates (frame O). A double-ended queue
holds the poses to refine: start with the last cloud; whenever a pose changes by more than
``tol`` (sum of absolute matrix element differences) its two neighbours are queued.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Mat4
from jaxcr.geometry import kabsch, transform_points


def overlap_mask(
    src: Float[Array, "n 3"],
    src_mask: Bool[Array, " n"],
    tgt: Float[Array, "m 3"],
    tgt_mask: Bool[Array, " m"],
    T: Mat4,
    radius: float,
) -> Bool[Array, " n"]:
    """Source points whose transform ``T src`` has a target point within ``radius`` (m)."""
    ps = transform_points(T, src)
    d2 = jnp.sum((ps[:, None, :] - tgt[None, :, :]) ** 2, -1)
    d2 = jnp.where(tgt_mask[None, :], d2, jnp.inf)
    return src_mask & (jnp.min(d2, axis=1) < radius**2)


overlap_mask_jit = jax.jit(overlap_mask)


@jax.jit
def align(
    p_prev: Float[Array, "k 3"],
    w_prev: Float[Array, " k"],
    p_next: Float[Array, "k 3"],
    w_next: Float[Array, " k"],
    T_O_prev: Mat4,
    T_prev_i: Mat4,
    T_O_next: Mat4,
    T_next_i: Mat4,
) -> Mat4:
    """Align(C_i, C_i-1, C_i+1): the pose T_O,i best mapping the sampled points to their
    virtual mates in O (weighted Kabsch)."""
    q_prev = transform_points(T_O_prev @ T_prev_i, p_prev)
    q_next = transform_points(T_O_next @ T_next_i, p_next)
    p = jnp.concatenate([p_prev, p_next])
    q = jnp.concatenate([q_prev, q_next])
    w = jnp.concatenate([w_prev, w_next])
    return kabsch(p, q, w + 1e-12)


class GlobalResult(NamedTuple):
    poses: list[np.ndarray]  # T_O,i
    initial: list[np.ndarray]
    n_refinements: int
    converged: bool


def _sample(
    points: np.ndarray, mask: np.ndarray, k: int, rng, fallback: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    idx = np.flatnonzero(mask)
    if len(idx) < 20 and fallback is not None:
        # Too little measured overlap: the mates are virtual anyway (pure functions of the
        # pairwise transform), so take them from the whole cloud rather than dropping the
        # constraint, which would turn the ring into a chain and let the loop error circulate.
        idx = np.flatnonzero(fallback)
    out = np.zeros((k, 3), np.float32)
    w = np.zeros(k, np.float32)
    if len(idx):
        pick = rng.choice(idx, min(k, len(idx)), replace=False)
        out[: len(pick)] = points[pick]
        w[: len(pick)] = 1.0
    return out, w


def chain_poses(rel: list[np.ndarray]) -> list[np.ndarray]:
    """Eqs. (1)-(2): T_O,m-1 = I and T_O,i = T_O,i+1 T_{i+1 <- i} (the closure is unused)."""
    m = len(rel)
    poses = [None] * m
    poses[m - 1] = np.eye(4)
    for i in range(m - 2, -1, -1):
        poses[i] = poses[i + 1] @ rel[i]
    return poses


def global_optimize(
    clouds: list[tuple[np.ndarray, np.ndarray]],
    rel: list[np.ndarray],
    overlap_radius: float = 0.004,
    n_samples: int = 256,
    tol: float = 1e-4,
    max_refinements: int = 5000,
    seed: int = 0,
    engine: str = "jax",
) -> GlobalResult:
    """Algorithm 2 over the ring of ``clouds`` (padded points (n, 3), mask (n,)) with
    pairwise transforms ``rel`` (see module docstring). ``engine="jax"``: the whole
    deque loop is one jitted ``lax.while_loop`` (:func:`algorithm2_loop`); ``"python"``:
    the same loop in Python calling the jitted :func:`align` (the reference)."""
    m = len(clouds)
    if m < 3 or len(rel) != m:
        raise ValueError(f"a loop needs >= 3 clouds and one transform per edge, got {m}/{len(rel)}")
    rng = np.random.default_rng(seed)
    inv = [np.linalg.inv(np.asarray(T, np.float64)) for T in rel]
    # Samples of C_i overlapping C_{i+1} (mates via rel[i]) and C_{i-1} (via inv[i-1]).
    samples = []
    for i in range(m):
        pts, msk = clouds[i]
        nxt, prv = (i + 1) % m, (i - 1) % m
        o_next = np.asarray(
            overlap_mask_jit(
                pts, msk, clouds[nxt][0], clouds[nxt][1], rel[i].astype(np.float32), overlap_radius
            )
        )
        o_prev = np.asarray(
            overlap_mask_jit(
                pts,
                msk,
                clouds[prv][0],
                clouds[prv][1],
                inv[prv].astype(np.float32),
                overlap_radius,
            )
        )
        samples.append(
            (_sample(pts, o_prev, n_samples, rng, msk), _sample(pts, o_next, n_samples, rng, msk))
        )
    poses = chain_poses(rel)
    initial = [P.copy() for P in poses]
    if engine == "jax":
        pp = np.stack([smp[0][0] for smp in samples])
        wp = np.stack([smp[0][1] for smp in samples])
        pn = np.stack([smp[1][0] for smp in samples])
        wn = np.stack([smp[1][1] for smp in samples])
        out, count, left = algorithm2_loop(
            jnp.asarray(np.stack(poses), jnp.float32),
            jnp.asarray(np.stack(rel), jnp.float32),
            jnp.asarray(np.stack(inv), jnp.float32),
            jnp.asarray(pp),
            jnp.asarray(wp),
            jnp.asarray(pn),
            jnp.asarray(wn),
            float(tol),
            int(max_refinements),
        )
        poses = list(np.asarray(out, np.float64))
        count, converged = int(count), int(left) == 0
    elif engine == "python":
        poses, count, converged = _algorithm2_python(poses, rel, inv, samples, tol, max_refinements)
    else:
        raise ValueError(f"engine must be 'jax' or 'python', got {engine!r}")
    # Re-anchor so that O is again the frame of the last cloud (eq. 1): Align also moves it.
    anchor = np.linalg.inv(poses[m - 1])
    poses = [anchor @ P for P in poses]
    return GlobalResult(poses, initial, count, converged)


def _algorithm2_python(poses, rel, inv, samples, tol, max_refinements):
    """The deque loop of Algorithm 2 in Python (reference for :func:`algorithm2_loop`)."""
    m = len(poses)
    poses = [P.copy() for P in poses]
    # The paper starts by refining T_O,m; we keep O = C_m fixed instead (it removes the
    # global-motion gauge, along which the Gauss-Seidel updates otherwise drift without
    # converging) and start from its two neighbours.
    queue = deque([0, m - 2])
    queued = {0, m - 2}
    count = 0
    while queue and count < max_refinements:
        i = queue.popleft()
        queued.discard(i)
        if i == m - 1:
            continue
        prv, nxt = (i - 1) % m, (i + 1) % m
        (pp, wp), (pn, wn) = samples[i]
        new = np.asarray(
            align(
                pp,
                wp,
                pn,
                wn,
                poses[prv].astype(np.float32),
                inv[prv].astype(np.float32),
                poses[nxt].astype(np.float32),
                rel[i].astype(np.float32),
            ),
            np.float64,
        )
        count += 1
        change = float(np.abs(new - poses[i]).sum())
        poses[i] = new
        if change > tol:
            for j in (prv, nxt):
                if j not in queued:
                    queue.append(j)
                    queued.add(j)
    return poses, count, not queue


@jax.jit
def algorithm2_loop(
    poses: Float[Array, "m 4 4"],
    rel: Float[Array, "m 4 4"],
    inv: Float[Array, "m 4 4"],
    p_prev: Float[Array, "m k 3"],
    w_prev: Float[Array, "m k"],
    p_next: Float[Array, "m k 3"],
    w_next: Float[Array, "m k"],
    tol: Float[Array, ""],
    max_refinements: Array,
):
    """The deque loop of Algorithm 2 as one ``lax.while_loop`` (same order of refinements
    as :func:`_algorithm2_python`). The deque is a ring buffer of size m: an index is
    queued at most once (the ``queued`` flags), so it never holds more than m entries.
    Returns (poses (m, 4, 4), number of Align calls, entries left in the queue)."""
    m = poses.shape[0]
    queue = jnp.zeros(m, jnp.int32).at[0].set(0).at[1].set(m - 2)
    queued = jnp.zeros(m, bool).at[0].set(True).at[m - 2].set(True)
    init = (poses, queue, jnp.int32(0), jnp.int32(2), queued, jnp.int32(0))

    def cond(state):
        _, _, _, size, _, count = state
        return (size > 0) & (count < max_refinements)

    def push(queue, head, size, queued, j, do):
        do = do & ~queued[j]
        queue = jnp.where(do, queue.at[(head + size) % m].set(j), queue)
        return queue, size + do.astype(jnp.int32), queued.at[j].set(queued[j] | do)

    def body(state):
        poses, queue, head, size, queued, count = state
        i = queue[head]
        head, size = (head + 1) % m, size - 1
        queued = queued.at[i].set(False)
        prv, nxt = (i - 1) % m, (i + 1) % m
        new = align(
            p_prev[i], w_prev[i], p_next[i], w_next[i], poses[prv], inv[prv], poses[nxt], rel[i]
        )
        active = i != m - 1
        change = jnp.sum(jnp.abs(new - poses[i]))
        poses = jnp.where(active, poses.at[i].set(new), poses)
        moved = active & (change > tol)
        queue, size, queued = push(queue, head, size, queued, prv, moved)
        queue, size, queued = push(queue, head, size, queued, nxt, moved)
        return poses, queue, head, size, queued, count + active.astype(jnp.int32)

    poses, _, _, size, _, count = jax.lax.while_loop(cond, body, init)
    return poses, count, size
