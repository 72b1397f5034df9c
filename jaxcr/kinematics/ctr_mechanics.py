"""Concentric-tube mechanics without external load (Rucker, Webster et al. 2010; Dupont et al.
2010): the arclength grid aligned to every discontinuity, the torsion ODE and its fixed-step RK4
integration. The model class, the shooting and the robot description live in
:mod:`jaxcr.kinematics.ctr`.

Notation (tubes ``i = 1..n`` innermost first, arclength ``s`` from the point where the tubes
leave the actuation unit; everything in SI units):

* tube ``i`` occupies ``s in [beta_i, l_i]`` with ``l_i = beta_i + L_i``; it is straight up to
  ``c_i = l_i - Lc_i`` and has precurvature ``u_i* = (kappa_i, 0, 0)`` (its own frame) on
  ``[c_i, l_i]``. Only ``s >= 0`` is free to bend.
* ``psi_i(s)`` is tube ``i``'s rotation about the backbone tangent, ``theta_i = psi_i - psi_1``
  its rotation relative to the innermost tube, ``u_iz = psi_i'`` its torsional twist rate.
* The backbone frame ``R(s)`` is the innermost tube's material frame, ``R' = R hat(u_1)``.

With no external force or moment the total internal moment vanishes, which gives the bending
curvature of tube 1 in its own frame as the stiffness-weighted mean of the rotated
precurvatures (Rucker et al. 2010, eq. 11 without load):

    u_1^{xy} = (sum_i EI_i Rz(theta_i) u_i*^{xy}) / sum_i EI_i        (tubes present at s)

and the torsion ODEs (Rucker et al. 2010, eq. 13 without load; ``u_i* ' = 0`` piecewise):

    u_iz' = (EI_i / GJ_i) (u_ix u_iy* - u_iy u_ix*),   theta_i' = u_iz - u_1z,
    u_i^{xy} = Rz(theta_i)^T u_1^{xy}.

Consequence used as a test: ``sum_i GJ_i u_iz`` is constant along ``s`` and, with the free-end
conditions ``u_iz(l_i) = 0``, equal to zero.

The bending curvature jumps where a tube's curved part starts and where a tube ends, so the
integration is piecewise on a grid whose breakpoints are exactly those points (clipped to
``[0, max_i l_i]``): ``2 n`` pieces sharing a static total of ``N - 1`` RK4 steps in proportion
to their lengths (:func:`allocate_steps`; empty pieces get none).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.kinematics.base import steps_per_piece


class TubeMechanics(NamedTuple):
    """Per-tube constants (all shape (n,), SI units)."""

    EI: Float[Array, " n"]  # bending stiffness (N m^2)
    GJ: Float[Array, " n"]  # torsional stiffness (N m^2)
    kappa: Float[Array, " n"]  # precurvature of the curved part (1/m)
    length: Float[Array, " n"]  # total tube length L_i (m)
    curved_length: Float[Array, " n"]  # length of the distal curved part Lc_i (m)
    radius: Float[Array, " n"]  # outer radius od_i / 2 (m)


def second_moments(od: Array, id_: Array) -> tuple[Array, Array]:
    """Area moment ``I = pi (od^4 - id^4) / 64`` and polar moment ``J = 2 I`` (m^4)."""
    I = jnp.pi * (od**4 - id_**4) / 64.0
    return I, 2.0 * I


class Grid(NamedTuple):
    """Integration grid for one joint vector (N = n_points samples, N - 1 steps)."""

    s: Float[Array, " N"]  # sample arclengths, s[0] = 0 (m)
    h: Float[Array, " N-1"]  # step lengths (m)
    present: Bool[Array, "N-1 n"]  # tube i exists on the step (s < l_i)
    curved: Bool[Array, "N-1 n"]  # tube i is on its precurved part on the step
    rho: Float[Array, " N"]  # outer radius present (m); rho[0] repeats rho[1]


def allocate_steps(lengths: Float[Array, " k"], n_steps: int) -> Int[Array, " k"]:
    """Share ``n_steps`` (static) integration steps among pieces in proportion to ``lengths``.

    Every piece of positive length gets at least one step, a zero-length piece none; the other
    ``n_steps - (number of non-empty pieces)`` steps are shared by rounding the cumulative
    proportions (``round(R C_k / C)`` differences, so the counts always sum to ``n_steps``).
    If every piece is empty (joint limits violated) the first piece gets all steps. Requires
    ``n_steps >= k``. The counts are integers, so no derivative flows through them: the
    discretised model is piecewise smooth in ``beta``, with jumps of the order of the
    discretisation error where a count changes.
    """
    lengths = jnp.maximum(lengths, 0.0)
    nonempty = lengths > 0.0
    m = jnp.sum(nonempty, dtype=jnp.int32)  # int32 under x64 too (counts are int32)
    spare = (n_steps - m).astype(lengths.dtype)
    total = jnp.sum(lengths)
    cum = jnp.cumsum(lengths) / jnp.where(total > 0.0, total, 1.0)
    marks = jnp.round(spare * cum).astype(jnp.int32)
    marks = marks.at[-1].set(n_steps - m)  # exact total despite rounding of cum[-1]
    extra = jnp.diff(jnp.concatenate([jnp.zeros(1, jnp.int32), marks]))
    counts = nonempty.astype(jnp.int32) + extra
    first_only = jnp.zeros_like(counts).at[0].set(n_steps)
    return jnp.where(m > 0, counts, first_only)


def make_grid(tubes: TubeMechanics, beta: Float[Array, " n"], n_points: int) -> Grid:
    """Grid whose breakpoints are every tube's curved-part start and end (clipped to s >= 0).

    The ``N - 1`` RK4 steps (N = ``n_points``, static) are shared among the ``2 n`` pieces at
    run time in proportion to their lengths (:func:`allocate_steps`): a piece that is empty
    (a curved part starting behind s = 0, coinciding breakpoints) gets no step, every other
    piece at least one, and each breakpoint is a sample (``start_k + (j / c_k) L_k`` with
    ``j = c_k`` at the piece end). N does not depend on ``beta``. Masks are evaluated at piece
    midpoints, which is exact because nothing changes inside a piece.
    """
    n = beta.shape[0]
    n_steps = n_points - 1
    ends = beta + tubes.length
    total = jnp.max(ends)
    starts_curved = ends - tubes.curved_length
    pts = jnp.clip(jnp.concatenate([starts_curved, ends]), 0.0, jnp.maximum(total, 0.0))
    bps = jnp.concatenate([jnp.zeros(1, beta.dtype), jnp.sort(pts)])  # 2n + 1 breakpoints
    lengths = jnp.diff(bps)
    counts = allocate_steps(lengths, n_steps)
    first = jnp.cumsum(counts) - counts  # index of each piece's first step
    j = jnp.arange(n_steps)
    idx = jnp.clip(jnp.searchsorted(jnp.cumsum(counts), j, side="right"), 0, 2 * n - 1)
    c = jnp.maximum(counts[idx], 1)
    frac = (j - first[idx] + 1).astype(beta.dtype) / c.astype(beta.dtype)
    s = jnp.concatenate([jnp.zeros(1, beta.dtype), bps[idx] + frac * lengths[idx]])
    mid = 0.5 * (bps[:-1] + bps[1:])  # (2n,) piece midpoints
    present_piece = mid[:, None] < ends[None, :]
    curved_piece = present_piece & (mid[:, None] > starts_curved[None, :])
    present = present_piece[idx]
    curved = curved_piece[idx]
    rho_steps = jnp.max(jnp.where(present, tubes.radius[None, :], 0.0), axis=1)
    rho = jnp.concatenate([rho_steps[:1], rho_steps])
    return Grid(s=s, h=jnp.diff(s), present=present, curved=curved, rho=rho)


def _safe_inverse(x: Array) -> Array:
    """1/x with 0 where x == 0 (double where: finite gradients everywhere)."""
    nz = x > 0
    return jnp.where(nz, 1.0 / jnp.where(nz, x, 1.0), 0.0)


def bending_curvature(
    tubes: TubeMechanics, theta: Array, present: Array, curved: Array
) -> tuple[Array, Array]:
    """``u_1^{xy}`` (tube-1 frame, 1/m) for relative angles ``theta`` (Rucker eq. 11, no load).

    Returns ``(u1x, u1y)`` scalars.
    """
    k = jnp.where(curved, tubes.kappa, 0.0)
    EIp = jnp.where(present, tubes.EI, 0.0)
    inv_K = _safe_inverse(jnp.sum(EIp))
    ux = jnp.sum(EIp * k * jnp.cos(theta)) * inv_K
    uy = jnp.sum(EIp * k * jnp.sin(theta)) * inv_K
    return ux, uy


def torsion_rhs(
    tubes: TubeMechanics, y: tuple[Array, Array, Array], present: Array, curved: Array
) -> tuple[Array, Array, Array]:
    """Derivative of the state ``(u_z (n,), theta (n,), energy)`` with respect to s.

    ``energy' = sum_i [EI_i |u_i^{xy} - u_i*|^2 + GJ_i u_iz^2] / 2`` over the tubes present.
    Tubes that have ended are frozen (their ``u_iz`` stays at its end value).
    """
    uz, theta, _ = y
    k = jnp.where(curved, tubes.kappa, 0.0)
    ux1, uy1 = bending_curvature(tubes, theta, present, curved)
    c, s = jnp.cos(theta), jnp.sin(theta)
    uix = c * ux1 + s * uy1  # u_i^{xy} = Rz(theta_i)^T u_1^{xy}
    uiy = -s * ux1 + c * uy1
    duz = jnp.where(present, -(tubes.EI / tubes.GJ) * k * uiy, 0.0)
    dtheta = jnp.where(present, uz - uz[0], 0.0)
    bend = (ux1**2 + uy1**2) - 2.0 * k * uix + k**2
    dE = 0.5 * jnp.sum(jnp.where(present, tubes.EI * bend + tubes.GJ * uz**2, 0.0))
    return duz, dtheta, dE


class Trajectory(NamedTuple):
    uz0: Float[Array, " n"]  # twist rates u_iz(0) at the base (1/m)
    theta0: Float[Array, " n"]  # relative angles theta_i(0) at the base (rad)
    energy: Float[Array, ""]  # elastic energy of s in [0, max l_i] (J)
    u_steps: Float[Array, "N-1 3"] | None  # tube-1 curvature at each step midpoint (1/m)
    uz_samples: Float[Array, "N n"] | None  # u_iz at every sample (for checks)


def integrate_torsion(
    tubes: TubeMechanics,
    grid: Grid,
    theta_tip: Float[Array, " n"],
    with_centreline: bool = True,
) -> Trajectory:
    """Classical RK4 over the grid from the distal end ``s = max l_i`` back to ``s = 0``.

    The distal state is ``u_z = 0`` for every tube (free ends; a tube that has ended keeps its
    end value, so this is also right for the shorter tubes) and ``theta = theta_tip``, the
    relative angle each tube has at its own distal end (``theta_tip[0] = 0``). Integrating
    towards the base turns the two-point boundary-value problem into a map from tip angles to
    base angles, which is well conditioned and periodic in each angle; the shooting in
    :mod:`jaxcr.kinematics.ctr` matches the base angles to the joint values.

    With ``with_centreline`` also returns the tube-1 curvature ``(u1x, u1y, u1z)`` at each
    step's midpoint, where ``theta`` and ``u_z`` come from cubic Hermite interpolation of the
    step's end states (fourth-order accurate), for
    :func:`jaxcr.kinematics.cosserat.integrate_centreline`.
    """
    coef = step_coefficients(tubes, grid)
    uz0, theta0, energy, out = shoot_torsion(
        coef, grid.h, theta_tip[1:], with_energy=True, with_centreline=with_centreline
    )
    if not with_centreline:
        return Trajectory(uz0=uz0, theta0=theta0, energy=energy, u_steps=None, uz_samples=None)
    u_steps, uz_after = out  # uz_after[k] = u_z at s[k + 1]
    return Trajectory(
        uz0=uz0,
        theta0=theta0,
        energy=energy,
        u_steps=u_steps,
        uz_samples=jnp.concatenate([uz0[None], uz_after]),
    )


class StepCoefficients(NamedTuple):
    """Per-step constants of the torsion ODE (all (N - 1, n), SI units), so that one step of
    the shooting integration is elementwise arithmetic on the state (see
    :func:`shoot_torsion`)."""

    w: Float[Array, "N-1 n"]  # EI_i kappa_i / sum_j EI_j over the tubes present, 0 if straight
    b: Float[Array, "N-1 n"]  # (EI_i / GJ_i) kappa_i on the curved part, else 0
    p: Float[Array, "N-1 n"]  # 1 where tube i is present, else 0
    ei: Float[Array, "N-1 n"]  # EI_i where present, else 0 (energy only)
    gj: Float[Array, "N-1 n"]  # GJ_i where present, else 0 (energy only)
    kappa: Float[Array, "N-1 n"]  # kappa_i on the curved part, else 0 (energy only)


def step_coefficients(tubes: TubeMechanics, grid: Grid) -> StepCoefficients:
    """The masks and stiffness ratios of :func:`torsion_rhs` folded into per-step constants."""
    present, curved = grid.present, grid.curved
    ei = jnp.where(present, tubes.EI, 0.0)
    kappa = jnp.where(curved, tubes.kappa, 0.0)
    inv_k = _safe_inverse(jnp.sum(ei, axis=-1, keepdims=True))
    return StepCoefficients(
        w=ei * kappa * inv_k,
        b=jnp.where(present, tubes.EI / tubes.GJ, 0.0) * kappa,
        p=present.astype(ei.dtype),
        ei=ei,
        gj=jnp.where(present, tubes.GJ, 0.0),
        kappa=kappa,
    )


def _fast_rhs(c: tuple, y: tuple, with_energy: bool):
    """:func:`torsion_rhs` in the variables ``(u_z, cos theta, sin theta)`` with the tube axis
    unrolled (``n`` static): polynomial arithmetic, no trigonometric function, elementwise
    under ``vmap``. ``y = (uz (n), cos (n-1), sin (n-1), energy)`` for tubes 2..n (tube 1's
    relative angle is 0 by definition); ``(cos, sin)' = (-sin, cos) theta'``."""
    w, b, p = c[0], c[1], c[2]
    uz, cs, sn = y[0], y[1], y[2]
    n = len(uz)
    cos = (1.0, *cs)
    sin = (0.0, *sn)
    ux = w[0]
    uy = 0.0
    for i in range(1, n):
        ux = ux + w[i] * cos[i]
        uy = uy + w[i] * sin[i]
    duz = tuple(b[i] * (sin[i] * ux - cos[i] * uy) for i in range(n))  # -b u_iy
    om = tuple(p[i] * (uz[i] - uz[0]) for i in range(1, n))  # theta_i'
    dcs = tuple(-sn[i] * om[i] for i in range(n - 1))
    dsn = tuple(cs[i] * om[i] for i in range(n - 1))
    if not with_energy:
        return duz, dcs, dsn, 0.0
    ei, gj, kappa = c[3], c[4], c[5]
    u2 = ux * ux + uy * uy
    de = 0.0
    for i in range(n):
        uix = cos[i] * ux + sin[i] * uy
        de = de + ei[i] * (u2 - 2.0 * kappa[i] * uix + kappa[i] * kappa[i]) + gj[i] * uz[i] ** 2
    return duz, dcs, dsn, 0.5 * de


def shoot_torsion(
    coef: StepCoefficients,
    h: Float[Array, " N-1"],
    theta_tip: Float[Array, " n-1"],
    with_energy: bool = True,
    with_centreline: bool = False,
):
    """The shooting map: classical RK4 from the distal end (``u_z = 0``, relative tip angles
    ``theta_tip`` of tubes 2..n) to ``s = 0`` over the steps ``h`` (towards the base), with
    the per-step constants ``coef`` (:func:`step_coefficients`).

    The relative angles are carried as ``(cos theta, sin theta)``, which makes every RK4 stage
    polynomial: no sine or cosine inside the loop. With the angles themselves as the state
    (the form of :func:`torsion_rhs`) the trigonometric functions dominated the cost, as XLA's
    CPU fusion recomputes them once per state component they feed (8x more CPU time per
    residual, experiments/results/kinematics/ctr_speed_r3.md). Same equations and step sizes,
    a different fourth-order discretisation of the angles.

    Returns ``(u_z(0) (n,), theta(0) (n,) with theta_1 = 0, energy, extras)``; the energy is 0
    unless ``with_energy``; ``extras`` is None, or with ``with_centreline`` the tube-1
    curvature ``(u1x, u1y, u1z)`` at each step's midpoint ((N-1, 3), cubic Hermite
    interpolation of the step's end states, fourth-order accurate) and ``u_z`` at the samples
    1..N-1 ((N-1, n)).
    """
    dtype = theta_tip.dtype
    n = theta_tip.shape[0] + 1
    cols = coef if (with_energy or with_centreline) else coef[:3]
    xs = (h,) + tuple(tuple(a[:, i] for i in range(n)) for a in cols)
    zero = jnp.zeros((), dtype)
    y_tip = (
        tuple(zero for _ in range(n)),
        tuple(jnp.cos(theta_tip[i]) for i in range(n - 1)),
        tuple(jnp.sin(theta_tip[i]) for i in range(n - 1)),
        zero,
    )

    def step(y, inp):
        hk, c = -inp[0], inp[1:]  # towards the base

        def f(yy):
            return _fast_rhs(c, yy, with_energy)

        def axpy(a, d, yy):
            return jax.tree.map(lambda v, dv: v + a * dv, yy, d)

        k1 = f(y)
        k2 = f(axpy(0.5 * hk, k1, y))
        k3 = f(axpy(0.5 * hk, k2, y))
        k4 = f(axpy(hk, k3, y))
        y_next = jax.tree.map(
            lambda v, a, b, c_, d: v + (hk / 6.0) * (a + 2.0 * b + 2.0 * c_ + d),
            y, k1, k2, k3, k4,
        )  # fmt: skip
        if not with_centreline:
            return y_next, None
        k_end = f(y_next)
        uz_m, cs_m, sn_m, _ = jax.tree.map(
            lambda a, b_, da, db: 0.5 * (a + b_) + (hk / 8.0) * (da - db), y, y_next, k1, k_end
        )
        w = c[0]
        ux = w[0]
        uy = zero
        for i in range(1, n):
            ux = ux + w[i] * cs_m[i - 1]
            uy = uy + w[i] * sn_m[i - 1]
        return y_next, (jnp.stack([ux, uy, uz_m[0]]), jnp.stack(list(y[0])))

    (uz0, cs0, sn0, e_neg), out = jax.lax.scan(step, y_tip, xs, reverse=True)
    th0 = [jnp.arctan2(sn0[i], cs0[i]) for i in range(n - 1)]
    theta0 = jnp.stack([zero, *th0]).astype(dtype)
    energy = (-e_neg) * jnp.ones((), dtype)  # integrated towards decreasing s
    return jnp.stack(list(uz0)).astype(dtype), theta0, energy, out


def telescoping_ok(
    tubes: TubeMechanics, beta: Float[Array, " n"], atol: float = 1e-9
) -> Bool[Array, ""]:
    """Joint limits: ``beta_1 <= ... <= beta_n <= 0``, ``beta_i > -L_i`` (every tube exits the
    actuation unit) and ``l_1 >= l_2 >= ... >= l_n`` (inner tubes extend beyond outer ones)."""
    ends = beta + tubes.length
    ok = jnp.all(beta <= atol) & jnp.all(ends > 0.0)
    if beta.shape[0] > 1:
        ok = ok & jnp.all(jnp.diff(beta) >= -atol) & jnp.all(jnp.diff(ends) <= atol)
    return ok & jnp.all(jnp.isfinite(beta))


def static_counts(n_tubes: int, n_points: int) -> tuple[int, ...]:
    """Equal static split of the steps over ``2 n`` pieces (used only to validate ``n_points``;
    the grid itself uses :func:`allocate_steps`)."""
    return steps_per_piece(2 * n_tubes, n_points)


__all__ = [
    "Grid",
    "StepCoefficients",
    "shoot_torsion",
    "step_coefficients",
    "allocate_steps",
    "TubeMechanics",
    "Trajectory",
    "bending_curvature",
    "integrate_torsion",
    "make_grid",
    "second_moments",
    "static_counts",
    "telescoping_ok",
    "torsion_rhs",
]
