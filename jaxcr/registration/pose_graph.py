"""Weighted pose-graph optimisation on SE(3): the global optimisation of the ring solved to
its fixed point with every registered pair as a constraint (an alternative to, and the
fixed point that, Algorithm 2's deque of local Kabsch fits approaches only slowly).

Nodes are the camera poses ``T_O,i`` (frame O <- camera i, metres). An edge ``(i, j, Z,
Omega)`` is a pairwise registration ``Z = T_{j <- i}`` (target j <- source i, the
convention of :func:`jaxcr.registration.pairwise.register_pair`) with a 6x6 information
matrix ``Omega`` on its left perturbation in frame j, ordered (translation v (m), rotation
w (rad)) like the ICP increment ``T <- [exp(hat(w)), v] T``
(:func:`jaxcr.registration.icp.gauss_newton_update`). Its residual is

    E = (T_O,j^-1 T_O,i) Z^-1,     r = (t_E, log R_E) in R^6,

zero when the poses agree with the registration. The cost is ``sum_e r_e^T Omega_e r_e``;
the anchor pose (frame O, paper eq. 1: the last ring view) is held fixed (the gauge).
Gauss-Newton with pose updates ``T_O,i <- T_O,i [exp(hat(w_i)), v_i]`` (camera frame i)
and Jacobians from ``jax.jacfwd``; the normal equations are Jacobi-scaled before the
solve (translation and rotation information differ by orders of magnitude), which keeps
float32 adequate for a ring of a few tens of views.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float, Int, Mat4
from jaxcr.geometry import invert_transform, make_transform, so3_exp, so3_log


class GraphEdge(NamedTuple):
    """One constraint: ``Z = T_{j <- i}`` with information ``info`` (6, 6) on the left
    perturbation in frame j, order (v, w), units 1/m^2 and 1/rad^2."""

    i: int
    j: int
    Z: np.ndarray
    info: np.ndarray


class PoseGraphResult(NamedTuple):
    poses: list[np.ndarray]  # T_O,i, anchor = identity when the initial anchor was
    initial: list[np.ndarray]
    cost_initial: float
    cost_final: float
    iterations: int
    step_norm: float  # size of the last Gauss-Newton step (m and rad, max abs component)


def edge_residual(T_i: Mat4, T_j: Mat4, Z: Mat4) -> Float[Array, "6"]:
    """``r = (t_E, log R_E)`` of ``E = (T_j^-1 T_i) Z^-1`` (module docstring): the
    registration's error as a left perturbation in frame j (m, rad)."""
    E = invert_transform(T_j) @ T_i @ invert_transform(Z)
    return jnp.concatenate([E[:3, 3], so3_log(E[:3, :3])])


def _perturb(T: Mat4, d: Float[Array, "6"]) -> Mat4:
    return T @ make_transform(so3_exp(d[3:]), d[:3])


def _whitened(poses, src, tgt, Z, L, delta):
    """Whitened residuals ``L_e^T r_e`` (e, 6) of all edges after the pose updates
    ``delta`` (m, 6); ``L_e L_e^T = Omega_e``."""
    P = jax.vmap(_perturb)(poses, delta)
    r = jax.vmap(edge_residual)(P[src], P[tgt], Z)
    return jnp.einsum("eab,ea->eb", L, r)


def graph_cost(
    poses: Float[Array, "m 4 4"],
    src: Int[Array, " e"],
    tgt: Int[Array, " e"],
    Z: Float[Array, "e 4 4"],
    info: Float[Array, "e 6 6"],
) -> Float[Array, ""]:
    """``sum_e r_e^T Omega_e r_e`` (dimensionless when Omega is an inverse covariance)."""
    r = jax.vmap(edge_residual)(poses[src], poses[tgt], Z)
    return jnp.einsum("ea,eab,eb->", r, info, r)


def _factor(info):
    """``L`` with ``L L^T = info`` for positive semi-definite ``info`` (eigen-decomposition,
    zero information allowed: padding edges, unobserved directions)."""
    lam, V = jnp.linalg.eigh(0.5 * (info + jnp.swapaxes(info, -1, -2)))
    return V * jnp.sqrt(jnp.maximum(lam, 0.0))[..., None, :]


def solve_pose_graph(
    poses: Float[Array, "m 4 4"],
    src: Int[Array, " e"],
    tgt: Int[Array, " e"],
    Z: Float[Array, "e 4 4"],
    info: Float[Array, "e 6 6"],
    anchor: Int[Array, ""],
    iterations: int = 10,
):
    """Gauss-Newton on the pose graph (module docstring), ``iterations`` steps (static; a
    ``fori_loop``). Returns (poses (m, 4, 4), cost before, cost after, last step size).
    Edges with zero information are inert (padding). Pure, jit-able."""
    m = poses.shape[0]
    L = _factor(info)
    free = (jnp.arange(m) != anchor).astype(poses.dtype)
    mask = jnp.repeat(free, 6)

    def step(_, carry):
        P, _ = carry
        zero = jnp.zeros((m, 6), P.dtype)

        def res(d):
            return _whitened(P, src, tgt, Z, L, d.reshape(m, 6)).reshape(-1)

        r = res(zero.reshape(-1))
        J = jax.jacfwd(res)(zero.reshape(-1)) * mask[None, :]
        H = J.T @ J
        g = J.T @ r
        # Jacobi scaling (the anchor's rows/columns become the identity: its step is 0).
        s = jnp.where(mask > 0, 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(H), 1e-30)), 0.0)
        Hs = s[:, None] * H * s[None, :] + jnp.diag(1.0 - mask) + 1e-9 * jnp.eye(6 * m)
        d = -s * jnp.linalg.solve(Hs, s * g)
        d = jnp.where(jnp.all(jnp.isfinite(d)), d, 0.0)
        return jax.vmap(_perturb)(P, d.reshape(m, 6)), jnp.max(jnp.abs(d))

    c0 = graph_cost(poses, src, tgt, Z, info)
    P, last = jax.lax.fori_loop(0, iterations, step, (poses, jnp.asarray(0.0, poses.dtype)))
    return P, c0, graph_cost(P, src, tgt, Z, info), last


solve_pose_graph_jit = jax.jit(solve_pose_graph, static_argnames=("iterations",))


def _bucket(n: int) -> int:
    """Edge count padded to a multiple of 16 (one compilation per bucket, not per graph)."""
    return max(16, -(-n // 16) * 16)


edge_residuals_jit = jax.jit(jax.vmap(edge_residual))

# Cauchy kernel width in units of the robust residual scale (95 % efficiency at Gaussian
# residuals, Holland & Welsch 1977), and the median of chi^2 with 6 degrees of freedom.
CAUCHY_C = 2.3849
_CHI2_6_MEDIAN = 5.348


def robust_weights(chi2: np.ndarray) -> np.ndarray:
    """Cauchy IRLS weights of edges with squared whitened residuals ``chi2`` (e,):
    ``1 / (1 + chi2 / (c^2 s^2))`` with the scale ``s^2 = median(chi2) / median(chi^2_6)``
    estimated from the residuals themselves (the registrations' information is right in
    its relative weights but optimistic in absolute terms, so a fixed chi^2 threshold would
    reject everything)."""
    chi2 = np.asarray(chi2, np.float64)
    s2 = max(float(np.median(chi2)) / _CHI2_6_MEDIAN, 1e-30)
    return 1.0 / (1.0 + chi2 / (CAUCHY_C**2 * s2))


def optimize_pose_graph(
    initial: list[np.ndarray],
    edges: list[GraphEdge],
    anchor: int = -1,
    iterations: int = 10,
    robust_rounds: int = 0,
) -> PoseGraphResult:
    """Solve the pose graph (module docstring) from the ``initial`` poses ``T_O,i`` with
    the ``anchor`` pose fixed. ``robust_rounds`` > 0: that many further solves, each with
    every edge's information scaled by its Cauchy weight (:func:`robust_weights`) from the
    previous solution's residuals (iteratively reweighted least squares: a registration
    that disagrees with the rest of the graph counts less). Raises ``ValueError`` for a
    graph that does not constrain every pose (fewer than 2 poses, an edge to a missing
    node, a node without edges, non-finite or non positive semi-definite information)."""
    m = len(initial)
    if m < 2:
        raise ValueError(f"a pose graph needs >= 2 poses, got {m}")
    if not edges:
        raise ValueError("a pose graph needs at least one edge")
    anchor = anchor % m
    seen = set()
    for k, e in enumerate(edges):
        if not (0 <= e.i < m and 0 <= e.j < m) or e.i == e.j:
            raise ValueError(f"edge {k} joins poses {e.i} and {e.j} of a graph of {m}")
        Z, info = np.asarray(e.Z, np.float64), np.asarray(e.info, np.float64)
        if Z.shape != (4, 4) or info.shape != (6, 6):
            raise ValueError(f"edge {k}: Z must be (4, 4) and info (6, 6)")
        if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(info))):
            raise ValueError(f"edge {k} ({e.i} -> {e.j}) has a non-finite transform or info")
        lam = np.linalg.eigvalsh(0.5 * (info + info.T))
        if lam.min() < -1e-6 * max(lam.max(), 1e-30) or lam.max() <= 0:
            raise ValueError(f"edge {k} ({e.i} -> {e.j}): information is not PSD and non-zero")
        seen.update((e.i, e.j))
    if len(seen) < m:
        raise ValueError(f"poses {sorted(set(range(m)) - seen)} have no edge (unconstrained)")
    n = _bucket(len(edges))
    src = np.zeros(n, np.int32)
    tgt = np.zeros(n, np.int32)
    Z = np.tile(np.eye(4, dtype=np.float32), (n, 1, 1))
    info = np.zeros((n, 6, 6), np.float32)
    # Scale the information to order one (only the relative weights matter to the solution).
    scale = max(float(np.median([np.trace(e.info) for e in edges])), 1e-30)
    for k, e in enumerate(edges):
        src[k], tgt[k] = e.i, e.j
        Z[k] = e.Z
        info[k] = np.asarray(e.info, np.float64) / scale
    P, c0, c1, last = solve_pose_graph_jit(
        jnp.asarray(np.stack(initial), jnp.float32),
        jnp.asarray(src),
        jnp.asarray(tgt),
        jnp.asarray(Z),
        jnp.asarray(info),
        jnp.int32(anchor),
        iterations=int(iterations),
    )
    ne = len(edges)
    for _ in range(int(robust_rounds)):
        r = np.asarray(edge_residuals_jit(P[src[:ne]], P[tgt[:ne]], jnp.asarray(Z[:ne])))
        r = r.astype(np.float64)
        chi2 = np.einsum("ea,eab,eb->e", r, info[:ne].astype(np.float64), r)
        w = np.zeros(n, np.float32)
        w[:ne] = robust_weights(chi2)
        P, _, c1, last = solve_pose_graph_jit(
            P,
            jnp.asarray(src),
            jnp.asarray(tgt),
            jnp.asarray(Z),
            jnp.asarray(info * w[:, None, None]),
            jnp.int32(anchor),
            iterations=int(iterations),
        )
    poses = [np.asarray(p, np.float64) for p in np.asarray(P)]
    return PoseGraphResult(
        poses,
        [np.asarray(p, np.float64).copy() for p in initial],
        float(c0) * scale,
        float(c1) * scale,
        int(iterations),
        float(last),
    )


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint (6, 6) of a rigid transform for twists ordered (v, w):
    ``T [exp(xi)] T^-1 = [exp(Ad_T xi)]``, ``Ad_T = [[R, hat(t) R], [0, R]]``."""
    R, t = T[:3, :3], T[:3, 3]
    th = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    A = np.zeros((6, 6))
    A[:3, :3], A[:3, 3:], A[3:, 3:] = R, th @ R, R
    return A


def inverted_edge(Z: np.ndarray, info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same registration read the other way, ``Z^-1 = T_{i <- j}``, with its
    information on the left perturbation in frame i: ``(E Z)^-1 = (Z^-1 E^-1 Z) Z^-1``,
    so the error twist maps by ``-Ad_{Z^-1}`` and ``info -> Ad^-T info Ad^-1``."""
    Zi = np.linalg.inv(Z)
    Ai = np.linalg.inv(adjoint(Zi))
    return Zi, Ai.T @ info @ Ai


def point_information(points: np.ndarray) -> np.ndarray:
    """Information (6, 6) of a rigid alignment of ``points`` (n, 3, frame of the
    perturbation) to mates with unit isotropic noise, per point:
    ``mean_p [I, -hat(p)]^T [I, -hat(p)]``. Summed over the mates of both neighbours this
    is the objective Algorithm 2's Align minimises, so a pose graph weighted this way has
    Algorithm 2's fixed point (every edge counts the same)."""
    p = np.asarray(points, np.float64)
    if len(p) == 0:
        raise ValueError("point_information needs at least one point")
    c = p.mean(0)
    S = (p - c).T @ (p - c) / len(p)
    hc = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
    info = np.zeros((6, 6))
    info[:3, :3] = np.eye(3)
    info[:3, 3:] = -hc
    info[3:, :3] = hc
    # sum hat(p)^T hat(p) / n = (|p|^2 I - p p^T) averaged = hc^T hc + (tr S I - S)
    info[3:, 3:] = hc.T @ hc + np.trace(S) * np.eye(3) - S
    return info
