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

The registrations' information (:func:`jaxcr.registration.projective.projective_information`)
assumes independent residuals: against the truth of the synthetic tasks e^T Omega e has
medians ~100 instead of ~5.3 (chi^2_6), mostly because it is far too anisotropic (directions
it claims to know to a few micrometres err by tenths of a millimetre). ``calibrate=True``
(the pipeline's default) re-estimates the edge covariances as ``a Omega^-1 + isotropic
floor`` from the graph's own cycles (variance components, whose fixed point is the REML
estimate: :func:`variance_components`) and solves again. Errors shared by every edge of a
view (a biased cloud) move that view's pose consistently in all its edges, so no cycle
sees them and no weighting can remove them (experiments/results/registration/model_object_calibration.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import threadpool_limits

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
    # calibrate=True: the covariance model estimated from the graph (EdgeCalibration) and the
    # poses of the first solve with the information as stated.
    calibration: object = None
    stated_poses: list | None = None


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
    n_poses: Int[Array, ""] | None = None,
):
    """Gauss-Newton on the pose graph (module docstring), ``iterations`` steps (static; a
    ``fori_loop``). Returns (poses (m, 4, 4), cost before, cost after, last step size).
    Edges with zero information are inert (padding). ``n_poses``: poses from this index on
    are padding (no edge, held fixed like the anchor); default none. Pure, jit-able."""
    m = poses.shape[0]
    L = _factor(info)
    free = jnp.arange(m) != anchor
    if n_poses is not None:
        free = free & (jnp.arange(m) < n_poses)
    free = free.astype(poses.dtype)
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


def _bucket(n: int, least: int = 16) -> int:
    """Edge or pose count padded to a multiple of 16, at least ``least`` (one compilation
    per bucket, not per graph: rings of 2-16 views with up to 32 edges, e.g. a ring of 13
    and its edges two views apart, all use one program)."""
    return max(least, -(-n // 16) * 16)


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
    calibrate: bool = False,
) -> PoseGraphResult:
    """Solve the pose graph (module docstring) from the ``initial`` poses ``T_O,i`` with
    the ``anchor`` pose fixed. ``calibrate``: solve with the information as stated, estimate
    the covariance model ``scale * Omega^-1 + floor`` from that solution's residuals
    (:func:`calibrate_edges`: variance components / REML on the graph's cycles), then
    solve again from there with the calibrated information (a graph without a cycle keeps
    the stated information). ``robust_rounds`` > 0: that many further solves, each with
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
    if calibrate:
        first = optimize_pose_graph(initial, edges, anchor, iterations)
        try:
            cal_edges, cal = calibrate_edges(first.poses, edges, anchor)
        except ValueError:  # no cycle: nothing to calibrate from
            return first._replace(stated_poses=first.poses)
        out = optimize_pose_graph(first.poses, cal_edges, anchor, iterations, robust_rounds)
        return out._replace(
            initial=[np.asarray(p, np.float64).copy() for p in initial],
            cost_initial=first.cost_initial,
            calibration=cal,
            stated_poses=first.poses,
        )
    n = _bucket(len(edges), least=32)
    # Padding poses (identity, no edge) are held fixed: their rows of the normal equations
    # are the identity and their step is 0, so they change neither the cost nor the others.
    P0 = np.tile(np.eye(4, dtype=np.float32), (_bucket(m), 1, 1))
    P0[:m] = np.stack(initial)
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
        jnp.asarray(P0),
        jnp.asarray(src),
        jnp.asarray(tgt),
        jnp.asarray(Z),
        jnp.asarray(info),
        jnp.int32(anchor),
        iterations=int(iterations),
        n_poses=jnp.int32(m),
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
            n_poses=jnp.int32(m),
        )
    poses = [np.asarray(p, np.float64) for p in np.asarray(P)[:m]]
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


# --- covariance calibration from the graph's own redundancy ---------------------------------


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (float64; angles below pi). The angle is
    atan2(|v| / 2, (tr R - 1) / 2) with v = vee(R - R^T) = 2 sin(th) axis: arccos of the
    trace would lose angles below sqrt(2 eps)."""
    R = np.asarray(R, np.float64)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s2 = np.linalg.norm(v)  # 2 sin(th)
    th = np.arctan2(0.5 * s2, 0.5 * (np.trace(R) - 1.0))
    # th / (2 sin th) -> 1/2 (+ th^2 / 12) at the identity
    return v * (0.5 + th * th / 12.0 if th < 1e-4 else th / s2)


def _so3_jac_inv(phi: np.ndarray, left: bool) -> np.ndarray:
    """Inverse left (right) Jacobian of SO(3): ``d log(exp(d) R) / dd`` at ``log R = phi``
    (``d log(R exp(d)) / dd`` for the right one)."""
    th = float(np.linalg.norm(phi))
    P = _hat(phi)
    if th < 1e-6:
        c = 1.0 / 12.0
    else:
        c = (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / th**2
    return np.eye(3) + (-0.5 if left else 0.5) * P + c * P @ P


def graph_linearisation(
    poses: list[np.ndarray], edges: list[GraphEdge], anchor: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``r`` (6e,) of the edges at ``poses`` (:func:`edge_residual`, float64) and
    their exact Jacobian ``J`` (6e, 6(m-1)) with respect to the pose updates of
    :func:`solve_pose_graph` (``T_i <- T_i [exp(hat(w_i)), v_i]``, order (v, w)), the
    anchor's columns removed. With ``E = T_j^-1 T_i Z^-1`` and ``P(d) = [exp(hat(w)), v]``:
    ``T_i P(d) -> E Z P(d) Z^-1`` (a right perturbation ``Ad_Z d`` of E), ``T_j P(d) ->
    P(d)^-1 E`` (a left perturbation ``-d``); the residual ``(t_E, log R_E)`` maps these by
    ``[[R_E, 0], [0, Jr^-1]]`` and ``[[I, -hat(t_E)], [0, Jl^-1]]``."""
    m = len(poses)
    a = anchor % m
    cols = [k for k in range(m) if k != a]
    col = {k: n for n, k in enumerate(cols)}
    r = np.zeros(6 * len(edges))
    J = np.zeros((6 * len(edges), 6 * len(cols)))
    for n, e in enumerate(edges):
        Ti, Tj, Z = (np.asarray(x, np.float64) for x in (poses[e.i], poses[e.j], e.Z))
        E = np.linalg.inv(Tj) @ Ti @ np.linalg.inv(Z)
        t, phi = E[:3, 3], _rotvec(E[:3, :3])
        r[6 * n : 6 * n + 3], r[6 * n + 3 : 6 * n + 6] = t, phi
        if e.i in col:
            A = np.zeros((6, 6))
            A[:3, :3], A[3:, 3:] = E[:3, :3], _so3_jac_inv(phi, left=False)
            J[6 * n : 6 * n + 6, 6 * col[e.i] : 6 * col[e.i] + 6] += A @ adjoint(Z)
        if e.j in col:
            B = np.zeros((6, 6))
            B[:3, :3], B[:3, 3:], B[3:, 3:] = np.eye(3), -_hat(t), _so3_jac_inv(phi, left=True)
            J[6 * n : 6 * n + 6, 6 * col[e.j] : 6 * col[e.j] + 6] -= B
    return r, J


class EdgeCalibration(NamedTuple):
    """Covariance model of the registrations, ``Sigma_e = scale * Omega_e^-1 + diag(floor_t
    I3, floor_r I3)``: a common variance factor of the registrations' own information and an
    additive isotropic floor (errors that do not average out over a registration's matches:
    depth bias, correlated residuals), estimated from the graph's redundancy."""

    scale: float  # dimensionless
    floor_t: float  # m^2
    floor_r: float  # rad^2
    redundancy: float  # 6e - 6(m-1): the degrees of freedom the estimate rests on
    iterations: int
    converged: bool

    def covariance(self, info: np.ndarray) -> np.ndarray:
        """Calibrated covariance (6, 6) of an edge with information ``info``."""
        floor = np.diag([self.floor_t] * 3 + [self.floor_r] * 3)
        return self.scale * _covariance(info) + floor


def _sym(x: np.ndarray) -> np.ndarray:
    return 0.5 * (x + x.T)


def _covariance(info: np.ndarray) -> np.ndarray:
    """Inverse of a positive semi-definite information matrix, directions without
    information (eigenvalue below 1e-10 of the largest) given a variance 1e10 times the
    largest observed one (they stay unconstrained after calibration)."""
    lam, V = np.linalg.eigh(_sym(np.asarray(info, np.float64)))
    lam = np.maximum(lam, 1e-10 * max(float(lam.max()), 1e-300))
    return (V / lam) @ V.T


def variance_components(
    r: np.ndarray,
    J: np.ndarray,
    infos: list[np.ndarray],
    iterations: int = 200,
    tol: float = 1e-4,
) -> EdgeCalibration:
    """Variance-component estimate (Foerstner 1979; its fixed point is the restricted
    maximum likelihood, REML) of ``Sigma_e = a Q_e + f_t [I 0; 0 0] + f_r [0 0; 0 I]``
    with ``Q_e = Omega_e^-1``, from the residuals ``r`` (6e,) of a linearised pose graph
    with Jacobian ``J`` (:func:`graph_linearisation`). Each step solves the weighted least
    squares with the current ``Sigma``, then updates every component ``theta_k <- theta_k
    (v^T W S_k W v) / tr(W S_k W Q_vv)`` (``S_k`` its current share of Sigma, ``v`` the
    residuals, ``Q_vv = Sigma - J N^-1 J^T`` their covariance: the denominator is the
    component's share of the redundancy). float64, positive components stay positive.
    Raises ``ValueError`` without redundancy (a tree: no cycle to calibrate from)."""
    e = len(infos)
    if r.shape != (6 * e,) or J.shape[0] != 6 * e:
        raise ValueError(f"r must be (6e,) and J (6e, n) for e = {e} edges")
    red = 6 * e - J.shape[1]
    if red <= 0:
        raise ValueError("the graph has no redundancy (no cycle): nothing to calibrate from")
    Q = np.stack([_covariance(w) for w in infos])
    It = np.diag([1.0, 1, 1, 0, 0, 0])
    Ir = np.diag([0.0, 0, 0, 1, 1, 1])
    # start: the information as stated, floors at the median stated variance
    th = np.array(
        [
            1.0,
            float(np.median(np.trace(Q[:, :3, :3], axis1=1, axis2=2))) / 3,
            float(np.median(np.trace(Q[:, 3:, 3:], axis1=1, axis2=2))) / 3,
        ]
    )
    Jb = J.reshape(e, 6, -1)
    rb = r.reshape(e, 6)
    qd = np.diagonal(Q, axis1=1, axis2=2)  # (e, 6)
    converged, n_it = False, 0
    for _ in range(iterations):
        n_it += 1
        S = [th[0] * Q, th[1] * It[None], th[2] * Ir[None]]
        W = np.linalg.inv(S[0] + S[1] + S[2])
        WJ = W @ Jb  # (e, 6, n)
        N = np.einsum("eai,eaj->ij", Jb, WJ)
        # N^-1 J^T by Cholesky (one factorisation; no explicit inverse of N)
        X = cho_solve(cho_factor(N), J.T).reshape(-1, e, 6)  # (n, e, 6)
        x = -np.einsum("nea,ea->n", X, np.einsum("eab,eb->ea", W, rb))
        v = rb + Jb @ x
        Wv = np.einsum("eab,eb->ea", W, v)
        Qvv = S[0] + S[1] + S[2] - np.einsum("ean,neb->eab", Jb, X)
        WQW = W @ Qvv @ W
        new = th.copy()
        for k in range(3):
            num = float(np.einsum("ea,eab,eb->", Wv, S[k], Wv))
            den = float(np.einsum("eab,eba->", S[k], WQW))
            if den > 1e-12 * red:
                new[k] = th[k] * num / den
        new = np.maximum(new, 1e-12 * np.maximum(th, 1e-300))
        # converged when no edge's covariance changes by more than tol (relative, on its
        # diagonal): a component shrinking towards 0 need not converge in relative terms
        d_old = th[0] * qd + th[1] * It.diagonal() + th[2] * Ir.diagonal()
        d_new = new[0] * qd + new[1] * It.diagonal() + new[2] * Ir.diagonal()
        done = np.all(np.abs(d_new - d_old) <= tol * d_old)
        th = new
        if done:
            converged = True
            break
    return EdgeCalibration(float(th[0]), float(th[1]), float(th[2]), float(red), n_it, converged)


def calibrate_edges(
    poses: list[np.ndarray], edges: list[GraphEdge], anchor: int = -1, **kw
) -> tuple[list[GraphEdge], EdgeCalibration]:
    """The edges with their information replaced by the inverse of the calibrated
    covariance (:class:`EdgeCalibration`, :func:`variance_components`) estimated at
    ``poses`` (a pose-graph solution with the stated information)."""
    r, J = graph_linearisation(poses, edges, anchor)
    # The matrices are small (~100-300 rows): multi-threaded BLAS only adds contention
    # (T2 seed 3 on the loaded 2-core machine: 0.43 s with 2 threads, 0.08 s with 1).
    with threadpool_limits(1, user_api="blas"):
        cal = variance_components(r, J, [e.info for e in edges], **kw)
    out = [e._replace(info=_sym(np.linalg.inv(cal.covariance(e.info)))) for e in edges]
    return out, cal


def consistency_chi2(
    poses: list[np.ndarray], edges: list[GraphEdge], anchor: int = -1
) -> tuple[float, int]:
    """Consistency test of a set of edges (e.g. the ring alone: the loop closure against
    the chain): the minimum of ``sum_e r_e^T Omega_e r_e`` over the poses, linearised at
    ``poses`` (one Gauss-Newton step from there, float64), and its degrees of freedom
    ``6e - 6(m'-1)`` (m' the poses the edges touch). chi^2 with those degrees of freedom
    when ``Omega_e`` are calibrated inverse covariances (:func:`calibrate_edges`)."""
    used = sorted({k for e in edges for k in (e.i, e.j)})
    a = anchor % len(poses)
    if a not in used:
        raise ValueError(f"the anchor {a} is not on any of the edges")
    idx = {k: n for n, k in enumerate(used)}
    sub = [e._replace(i=idx[e.i], j=idx[e.j]) for e in edges]
    r, J = graph_linearisation([poses[k] for k in used], sub, idx[a])
    W = [np.asarray(e.info, np.float64) for e in sub]
    Jb, rb = J.reshape(len(sub), 6, -1), r.reshape(len(sub), 6)
    WJ = np.stack(W) @ Jb
    N = np.einsum("eai,eaj->ij", Jb, WJ)
    x = -np.linalg.lstsq(N, np.einsum("eai,ea->i", WJ, rb), rcond=None)[0]
    v = rb + Jb @ x
    return float(np.einsum("ea,eab,eb->", v, np.stack(W), v)), 6 * len(sub) - J.shape[1]
