"""Concentric-tube robot (CTR): Rucker/Webster Cosserat model without external load, solved by
shooting on the initial twist rates.

Joint vector ``q = (beta_1..beta_n, alpha_1..alpha_n)`` (tubes innermost first): ``beta_i <= 0``
is the arclength of tube ``i``'s proximal end (s = 0 where the tubes leave the actuation unit),
``alpha_i`` its rotation about the insertion axis z. Robot frame: ``p(0) = 0``, the backbone
leaves s = 0 along +z, ``R(s)`` is the innermost tube's material frame and
``R(0) = Rz(psi_1(0))``.

* Default (``transmission_torsion=False``): tubes are torsionally rigid behind s = 0, so
  ``psi_i(0) = alpha_i`` and ``R(0) = Rz(alpha_1)``.
* ``transmission_torsion=True`` (Rucker et al. 2010): the straight part ``[beta_i, 0]`` twists
  uniformly, ``alpha_i`` is applied at ``s = beta_i``, so ``psi_i(0) = alpha_i - beta_i u_iz(0)``
  and ``R(0) = Rz(psi_1(0))`` (the innermost tube's material frame where it leaves the unit).

Mechanics and the integration grid: :mod:`jaxcr.kinematics.ctr_mechanics` (the ``N - 1`` RK4
steps are shared among the pieces between discontinuities in proportion to their lengths; the
relative angles are integrated as ``(cos, sin)`` pairs, so the loop has no trigonometric
function: :func:`jaxcr.kinematics.ctr_mechanics.shoot_torsion`).
Shooting unknowns: ``x`` = the ``n - 1`` tip angles of tubes 2..n relative to tube 1; the torsion
ODE is integrated from the free distal ends (``u_iz = 0``) to the base, and the residual is the
mismatch of the base angles with the joint values (:meth:`ConcentricTubeRobot.shooting_residual`).

Solvers (issue 18: the cold path compiles once per robot shape class and costs a fixed amount
per q; the warm path stops at convergence).

* Cold start (``guess=None``), a fixed-size branch search on a *coarse* copy of the grid
  (``scan_n_points`` samples, default 25: the RK4 error there is ~1e-5 of the residual's
  scale, far below the spacing of distinct equilibria): the residual scan of
  :meth:`ConcentricTubeRobot.initial_guesses`, then ``cold_steps`` Newton iterations with a
  forward-difference Jacobian (:func:`jaxcr.kinematics.newton.fd_newton`, a ``fori_loop``)
  from each of the ``n_starts`` starts, vmapped over the starts; the least-energy start whose
  residual is within ``tol`` is then polished on the full grid by the warm path. No while loop
  over the starts, no Jacobian by automatic differentiation: the compiled function is small.
* Warm start (``guess``) and that polish: quasi-Newton iterations on the coarse grid
  (:func:`jaxcr.kinematics.newton.chord_newton`: one difference Jacobian at the guess, then
  one residual per iteration with Broyden updates, a ``while_loop`` that stops once the
  residual is within the solver tolerance, at most ``warm_steps`` iterations), then one
  chord step on the full grid (it removes the coarse grid's RK4 error, ~1e-5 rad, to
  rounding), with the implicit-function derivative
  (:func:`jaxcr.kinematics.newton.implicit_root`, exact Jacobian formed only when
  differentiated, tested against finite differences), so ``forward`` is differentiable in q.

The previous solvers (LM cold, fixed Newton warm) and the measurements behind the change:
docs/decisions.md K1 and K2.
``FkResult.num_steps`` = coarse Newton iterations (summed over the starts) plus the chord
iterations of the polish. ``ok`` = finite outputs, residual within ``tol`` on the full grid and
joint limits.

Several equilibria. For some ``q`` the rod has several (two stable, one unstable) solutions.
``forward(q)`` without ``guess`` solves from a fixed set of initial twist guesses
(:meth:`ConcentricTubeRobot.initial_guesses`) and returns, among the converged ones, the one with
the least elastic energy (the global minimum found); ``forward(q, guess)`` runs warm-started
Newton from ``guess`` only (continuation: follows the branch the guess lies on, e.g. the
previous frame's ``state``). :meth:`ConcentricTubeRobot.forward_branches` returns all of them.
``FkResult.energy`` and ``FkResult.residual`` say which solution was found.

Joint limits (``beta_1 <= ... <= beta_n <= 0``, ``l_1 >= ... >= l_n``, every ``l_i > 0``): when
violated, ``forward`` still returns finite numbers (the same mechanics with whichever tubes are
present) but ``ok = False``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float
from jaxcr.errors import InputError
from jaxcr.geometry import rot_z
from jaxcr.kinematics.base import (
    MAX_POINTS,
    FkResult,
    check_keys,
    get_int,
    get_number,
    require_mapping,
    steps_per_piece,
)
from jaxcr.kinematics.cosserat import integrate_centreline
from jaxcr.kinematics.ctr_mechanics import (
    TubeMechanics,
    integrate_torsion,
    make_grid,
    second_moments,
    shoot_torsion,
    step_coefficients,
    telescoping_ok,
)
from jaxcr.kinematics.newton import chord_newton, clipped_newton_step, fd_newton, implicit_root

#: Public 3-tube test robot (innermost first), SI units, in the dataset robot schema.
TEST_CTR: dict[str, Any] = {
    "kind": "ctr",
    "tubes": [
        {
            "length": 0.431,
            "curved_length": 0.103,
            "id": 0.70e-3,
            "od": 1.10e-3,
            "E": 64.3e9,
            "G": 25.0e9,
            "kappa": 21.3,
        },
        {
            "length": 0.332,
            "curved_length": 0.113,
            "id": 1.40e-3,
            "od": 1.80e-3,
            "E": 52.5e9,
            "G": 21.4e9,
            "kappa": 13.108,
        },
        {
            "length": 0.174,
            "curved_length": 0.134,
            "id": 2.0e-3,
            "od": 2.2e-3,
            "E": 47.1e9,
            "G": 29.7e9,
            "kappa": 3.5,
        },
    ],
    "transmission_torsion": False,
}

_TUBE_KEYS = ("length", "curved_length", "od", "id", "E", "G", "kappa")
_TOP_KEYS = {"kind", "tubes", "transmission_torsion", "n_points", "name"}


class ConcentricTubeRobot(eqx.Module):
    """n concentric precurved tubes (see module docstring for q, frames and conventions).

    Attributes (all (n,) arrays, innermost tube first, SI units):
        length: total tube lengths L_i (m).
        curved_length: lengths of the distal precurved parts Lc_i (m), ``<= length``.
        od, id: outer and inner diameters (m).
        E, G: Young's and shear moduli (Pa).
        kappa: precurvatures (1/m) of the curved parts, about the tube's own x axis.
        n_points: centreline samples N (static). The 2n pieces between breakpoints get
            ``(N - 1) / 2n`` RK4 steps each (the remainder to the first pieces).
        transmission_torsion: let the transmission behind s = 0 twist (static).
        tol: converged when the base-angle mismatch is at most ``tol`` (rad) (static).
        warm_steps: iteration bound of the warm-start chord iterations, which stop at
            convergence (static).
        cold_steps: fixed number of Newton iterations of each cold start (static).
        scan_points: tip angles per tube in the cold-start residual scan (static).
        n_starts: cold starts refined by Newton (static); see :meth:`initial_guesses`.
        scan_n_points: samples of the coarse grid the cold branch search runs on (static;
            at most ``n_points``).
    """

    kind: ClassVar[str] = "ctr"

    length: Float[Array, " n"]
    curved_length: Float[Array, " n"]
    od: Float[Array, " n"]
    id: Float[Array, " n"]
    E: Float[Array, " n"]
    G: Float[Array, " n"]
    kappa: Float[Array, " n"]
    n_points: int = eqx.field(static=True, default=97)
    transmission_torsion: bool = eqx.field(static=True, default=False)
    tol: float = eqx.field(static=True, default=1e-4)
    warm_steps: int = eqx.field(static=True, default=8)
    cold_steps: int = eqx.field(static=True, default=8)
    scan_points: int = eqx.field(static=True, default=24)
    n_starts: int = eqx.field(static=True, default=6)
    scan_n_points: int = eqx.field(static=True, default=25)

    def __check_init__(self):
        steps_per_piece(2 * self.n_tubes, self.n_points)  # raises if n_points is too small
        steps_per_piece(2 * self.n_tubes, self._coarse_points)

    @property
    def _coarse_points(self) -> int:
        return min(self.scan_n_points, self.n_points)

    # ------------------------------------------------------------------ construction

    @classmethod
    def make(
        cls,
        tubes: list[Mapping[str, float]],
        *,
        transmission_torsion: bool = False,
        n_points: int = 97,
        dtype=None,
        **kwargs,
    ) -> ConcentricTubeRobot:
        """Build from a list of tube dicts (keys as in the robot schema), innermost first."""
        dtype = jnp.zeros(0).dtype if dtype is None else dtype
        cols = {k: jnp.asarray([float(t[k]) for t in tubes], dtype) for k in _TUBE_KEYS}
        return cls(
            **cols,
            n_points=int(n_points),
            transmission_torsion=bool(transmission_torsion),
            **kwargs,
        )

    @classmethod
    def from_dict(
        cls, d: Mapping[str, Any], file: str | None = None, **kwargs
    ) -> ConcentricTubeRobot:
        """Parse ``{"kind": "ctr", "tubes": [...], "transmission_torsion": false}``.

        Validates every field (finite, positive lengths/moduli, ``id < od``,
        ``curved_length <= length``, tubes nested: each tube's ``od`` at most the next outer
        tube's ``id``) and raises :class:`InputError` naming the offending field.
        """
        d = require_mapping(d, file=file, field=None)
        check_keys(d, _TOP_KEYS, file=file)
        if d.get("kind", "ctr") != "ctr":
            raise InputError(f"expected kind 'ctr', got {d.get('kind')!r}", file=file, field="kind")
        if "tubes" not in d:
            raise InputError("missing required key", file=file, field="tubes")
        tubes = d["tubes"]
        if not isinstance(tubes, list) or not tubes:
            raise InputError("expected a non-empty list of tubes", file=file, field="tubes")
        rows = []
        for i, t in enumerate(tubes):
            prefix = f"tubes[{i}]."
            t = require_mapping(t, file=file, field=f"tubes[{i}]")
            check_keys(t, set(_TUBE_KEYS), file=file, prefix=prefix)
            row = {}
            for k in ("length", "od", "id", "E", "G"):
                row[k] = get_number(t, k, file=file, prefix=prefix, positive=True)
            row["curved_length"] = get_number(
                t, "curved_length", file=file, prefix=prefix, nonnegative=True
            )
            row["kappa"] = get_number(t, "kappa", file=file, prefix=prefix)
            if row["id"] >= row["od"]:
                raise InputError(
                    f"inner diameter {row['id']} must be < outer diameter {row['od']}",
                    file=file,
                    field=prefix + "id",
                )
            if row["curved_length"] > row["length"]:
                raise InputError(
                    f"curved_length {row['curved_length']} exceeds length {row['length']}",
                    file=file,
                    field=prefix + "curved_length",
                )
            if rows and row["id"] < rows[-1]["od"]:
                raise InputError(
                    f"inner diameter {row['id']} is smaller than the outer diameter "
                    f"{rows[-1]['od']} of tube {i - 1} inside it (tubes are innermost first)",
                    file=file,
                    field=prefix + "id",
                )
            rows.append(row)
        tt = d.get("transmission_torsion", False)
        if not isinstance(tt, bool):
            raise InputError(
                f"expected true or false, got {tt!r}", file=file, field="transmission_torsion"
            )
        n_points = get_int(
            d, "n_points", file=file, default=97, minimum=2 * len(rows) + 1, maximum=MAX_POINTS
        )
        options = {"transmission_torsion": tt, "n_points": n_points} | kwargs
        return cls.make(rows, **options)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (``from_dict(to_dict())`` rebuilds the same model)."""
        cols = {k: np.asarray(getattr(self, k), np.float64) for k in _TUBE_KEYS}
        tubes = [{k: float(cols[k][i]) for k in _TUBE_KEYS} for i in range(self.n_tubes)]
        return {
            "kind": "ctr",
            "tubes": tubes,
            "transmission_torsion": bool(self.transmission_torsion),
            "n_points": int(self.n_points),
        }

    # ------------------------------------------------------------------ properties

    @property
    def n_tubes(self) -> int:
        return int(self.length.shape[0])

    @property
    def n_joints(self) -> int:
        return 2 * self.n_tubes

    def mechanics(self, dtype=None) -> TubeMechanics:
        """Per-tube stiffnesses and geometry in ``dtype``."""
        dtype = self.length.dtype if dtype is None else dtype
        od, id_ = self.od.astype(dtype), self.id.astype(dtype)
        I, J = second_moments(od, id_)
        return TubeMechanics(
            EI=self.E.astype(dtype) * I,
            GJ=self.G.astype(dtype) * J,
            kappa=self.kappa.astype(dtype),
            length=self.length.astype(dtype),
            curved_length=self.curved_length.astype(dtype),
            radius=0.5 * od,
        )

    def _split(self, q: Array) -> tuple[Array, Array]:
        q = jnp.asarray(q)
        if q.shape != (self.n_joints,):
            raise ValueError(f"q must have shape ({self.n_joints},), got {q.shape}")
        dtype = jnp.result_type(q.dtype, self.length.dtype)
        q = q.astype(dtype)
        return q[: self.n_tubes], q[self.n_tubes :]

    def _base_angles(self, beta: Array, alpha: Array, uz0: Array) -> Array:
        """``psi_i(0)``: alpha_i, or alpha_i - beta_i u_iz(0) with transmission torsion."""
        if self.transmission_torsion:
            return alpha - beta * uz0
        return alpha

    # ------------------------------------------------------------------ shooting

    def _trajectory(self, q: Array, x: Array, with_centreline: bool):
        """Integrate from the tip angles ``x`` (n - 1,) to the base; also the grid and psi(0)."""
        beta, alpha = self._split(q)
        tubes = self.mechanics(beta.dtype)
        grid = make_grid(tubes, beta, self.n_points)
        theta_tip = jnp.concatenate([jnp.zeros(1, beta.dtype), x.astype(beta.dtype)])
        traj = integrate_torsion(tubes, grid, theta_tip, with_centreline=with_centreline)
        psi0 = self._base_angles(beta, alpha, traj.uz0)
        return tubes, grid, traj, psi0

    def _shooting(self, q: Array, n_points: int | None = None, with_energy: bool = True):
        """``x -> (residual, energy)`` for fixed q, its grid (``n_points`` samples, default
        the model's) and per-step constants built once, so the solver loops do not rebuild
        them at every residual (:func:`shoot_torsion`). Without ``with_energy`` the energy
        is 0 and not integrated (the warm iterations do not need it)."""
        beta, alpha = self._split(jax.lax.stop_gradient(q))
        tubes = self.mechanics(beta.dtype)
        grid = make_grid(tubes, beta, self.n_points if n_points is None else n_points)
        coef = step_coefficients(tubes, grid)

        def fun(x):
            uz0, theta0, energy, _ = shoot_torsion(
                coef, grid.h, x.astype(beta.dtype), with_energy=with_energy
            )
            psi0 = self._base_angles(beta, alpha, uz0)
            d = theta0[1:] - (psi0[1:] - psi0[0])
            if with_energy:
                energy = energy + self._transmission_energy(tubes, beta, uz0)
            return jnp.arctan2(jnp.sin(d), jnp.cos(d)), energy

        return fun

    def shooting_residual(self, q: Float[Array, " m"], x: Float[Array, " n-1"]) -> Array:
        """Base-angle mismatch (rad, wrapped to (-pi, pi]) for tip angles ``x``.

        ``x_j = theta_{j+1}(l_{j+1})`` is the angle of tube ``j + 1`` relative to the innermost
        tube at its own distal end. Integrating the torsion ODE from the tips (where all
        ``u_z = 0``) to ``s = 0`` gives ``theta(0)``; at an equilibrium it equals
        ``psi(0) - psi_1(0)`` prescribed by the joint values. Zero at an equilibrium.
        """
        return self._residual_and_energy(q, x)[0]

    def _residual_and_energy(self, q: Array, x: Array) -> tuple[Array, Array]:
        beta, _ = self._split(q)
        tubes, _, traj, psi0 = self._trajectory(q, x, with_centreline=False)
        d = traj.theta0[1:] - (psi0[1:] - psi0[0])
        energy = traj.energy + self._transmission_energy(tubes, beta, traj.uz0)
        return jnp.arctan2(jnp.sin(d), jnp.cos(d)), energy

    def initial_guesses(self, q: Float[Array, " m"]) -> Float[Array, "k n-1"]:
        """Cold-start tip angles: the most promising local minima of a residual scan.

        The base-angle residual and the elastic energy are evaluated (no Jacobian, on the
        coarse grid of ``scan_n_points`` samples) on a regular grid of ``scan_points`` angles
        per tube on the torus of relative tip angles
        (``scan_points ** (n - 1)`` points, offset by the untwisted state
        ``alpha_i - alpha_1``). Grid points whose residual norm is no larger than that of every
        (periodic) neighbour are candidates; the ``n_starts - n_starts // 2`` candidates of
        least energy and the ``n_starts // 2`` of least residual are returned (repeating the
        first one if there are fewer). Distinct equilibria lie in distinct basins of this
        periodic map, which a scan resolves where Newton from a few fixed starts does not;
        ranking by energy favours the basin of the least-energy equilibrium (the one
        :meth:`forward` returns), ranking by residual guards against local minima of the
        residual that are not equilibria.
        """
        beta, alpha = self._split(q)
        n, g = self.n_tubes, self.scan_points
        base = alpha[1:] - alpha[0]
        offsets = 2.0 * np.pi * (np.arange(g) / g) - np.pi
        mesh = np.stack(np.meshgrid(*([offsets] * (n - 1)), indexing="ij"), -1)
        pts = base + jnp.asarray(mesh.reshape(-1, n - 1), beta.dtype)
        r, energy = jax.vmap(self._shooting(q, self._coarse_points))(pts)
        r = jnp.sum(r**2, axis=-1)
        r = jnp.where(jnp.isfinite(r), r, jnp.inf).reshape((g,) * (n - 1))
        is_min = jnp.isfinite(r)
        for ax in range(n - 1):
            for shift in (1, -1):
                is_min = is_min & (r <= jnp.roll(r, shift, axis=ax))
        cand = is_min.reshape(-1) & jnp.isfinite(energy)
        by_energy = jnp.where(cand, energy, jnp.inf)
        by_residual = jnp.where(cand, r.reshape(-1), jnp.inf)
        k_res = self.n_starts // 2
        k_en = min(self.n_starts - k_res, by_energy.shape[0])
        _, idx_r = jax.lax.top_k(-by_residual, min(k_res, by_residual.shape[0]))
        _, idx_e = jax.lax.top_k(-by_energy, k_en)
        idx = jnp.concatenate([idx_e, idx_r])
        idx = jnp.where(jnp.isfinite(by_energy[idx]), idx, idx_e[0])
        return pts[idx]

    def _solver_tol(self, dtype) -> float:
        # Iterate well below the `ok` tolerance (a converged solve lands near rounding).
        return self.tol * (1e-8 if dtype == jnp.float64 else 0.1)

    @staticmethod
    def _fd_step(dtype) -> float:
        # forward-difference step (rad): ~sqrt(eps) balances truncation and rounding
        return 1e-6 if dtype == jnp.float64 else 1e-3

    def _cold_solve(self, q: Array, guesses: Array) -> tuple[Array, Array, Array, Array]:
        """``cold_steps`` difference-Jacobian Newton iterations from every guess on the coarse
        grid (fixed count, vmapped over the guesses), no derivative.

        Returns the solved tip angles (k, n - 1), their max-abs residuals and energies (k,)
        on the coarse grid, and the iteration counts (k,).
        """
        fun = self._shooting(q, self._coarse_points)
        tol = self._solver_tol(guesses.dtype)

        def one(g):
            res = fd_newton(
                fun,
                g,
                steps=self.cold_steps,
                tol=tol,
                fd_step=self._fd_step(g.dtype),
                max_step=0.5,  # rad: a fraction of the branch spacing on the tip-angle torus
            )
            r, energy = fun(res.x)
            return res.x, jnp.max(jnp.abs(r), initial=0.0), energy, res.num_steps

        return jax.vmap(one)(guesses)

    def _warm_solve(self, q: Array, guess: Array) -> tuple[Array, Array, Array]:
        """Quasi-Newton iterations from ``guess`` that stop at convergence, on the coarse grid
        (``scan_n_points`` samples), then one chord step on the full grid; differentiable in q.

        The coarse and full-grid roots differ by the RK4 error of the coarse grid (~1e-5 rad
        for TEST_CTR at 25 samples); one chord step with the coarse iterations' Jacobian (whose
        relative error is ~1e-3, the difference step's) reduces that difference ~1000-fold, to
        the float32 rounding of the residual (in float64 the full-grid steps are iterated to
        the float64 tolerance). Each coarse iteration costs a quarter of a
        full-grid one. The derivative is the implicit-function one (:func:`implicit_root`: the
        exact Jacobian at the solution, formed only when differentiated, no derivative through
        the iterations). Returns ``(x, num_steps, True)`` (``num_steps`` counts the coarse
        iterations and the final step); convergence is judged by the residual in
        :meth:`_result`.
        """
        guess = jax.lax.stop_gradient(guess)
        res = chord_newton(
            self._shooting(q, self._coarse_points, with_energy=False),
            guess,
            max_steps=self.warm_steps,
            tol=self._solver_tol(guess.dtype),
            fd_step=self._fd_step(guess.dtype),
            max_step=0.5,  # rad: a fraction of the branch spacing on the tip-angle torus
        )
        x, steps = res.x, res.num_steps
        if self._coarse_points < self.n_points:
            fine = self._shooting(q, with_energy=False)
            if guess.dtype == jnp.float64:
                # x64 asks for a residual near 1e-12: iterate the full-grid chord steps
                # (linear rate ~1e-5, the coarse Jacobian's error) until it is reached
                res = chord_newton(
                    fine, x, max_steps=self.warm_steps, tol=self._solver_tol(guess.dtype),
                    fd_step=self._fd_step(guess.dtype), max_step=0.5, jac0=res.jac,
                )  # fmt: skip
                x, steps = res.x, steps + res.num_steps
            else:
                r, _ = fine(x)
                x = x - clipped_newton_step(res.jac, r, 0.5)
                steps = steps + 1
        x = implicit_root(lambda p, z: p[0].shooting_residual(p[1], z), (self, q), x)
        return x, steps, jnp.asarray(True)

    def _result(self, q: Array, x: Array, num_steps: Array, solved: Array) -> FkResult:
        """Centreline, energy and flags at the solved tip angles ``x`` (differentiable in q)."""
        beta, _ = self._split(q)
        tubes, grid, traj, psi0 = self._trajectory(q, x, with_centreline=True)
        R0 = rot_z(psi0[0])
        centreline = integrate_centreline(grid.s, traj.u_steps, grid.rho, None, R0)
        energy = traj.energy + self._transmission_energy(tubes, beta, traj.uz0)
        d = traj.theta0[1:] - (psi0[1:] - psi0[0])
        residual = jnp.max(jnp.abs(jnp.arctan2(jnp.sin(d), jnp.cos(d))), initial=0.0)
        finite = (
            jnp.all(jnp.isfinite(centreline.p))
            & jnp.all(jnp.isfinite(centreline.R))
            & jnp.isfinite(energy)
        )
        ok = finite & solved & (residual <= self.tol) & telescoping_ok(tubes, beta)
        return FkResult(
            centreline=centreline,
            ok=ok,
            residual=jax.lax.stop_gradient(residual),
            energy=energy,
            num_steps=jnp.asarray(num_steps, jnp.int32),
            state=jax.lax.stop_gradient(x),
        )

    def twist_profile(
        self, q: Float[Array, " m"], state: Float[Array, " n-1"]
    ) -> tuple[Float[Array, " N"], Float[Array, "N n"]]:
        """Arclengths (m) and every tube's twist rate ``u_iz`` (1/m) at the samples, for the
        solution with tip angles ``state`` (e.g. ``forward(q).state``). A tube that has ended
        keeps its end value (0). Useful to check ``sum_i GJ_i u_iz = 0`` along s."""
        _, grid, traj, _ = self._trajectory(q, jnp.asarray(state), with_centreline=True)
        return grid.s, traj.uz_samples

    def _transmission_energy(self, tubes: TubeMechanics, beta: Array, uz0: Array) -> Array:
        """Torsion energy of the straight transmissions ``[beta_i, 0]`` (J); 0 if rigid."""
        if not self.transmission_torsion:
            return jnp.zeros((), beta.dtype)
        return 0.5 * jnp.sum(tubes.GJ * uz0**2 * (-beta))

    def forward(self, q: Float[Array, " m"], guess: Array | None = None) -> FkResult:
        """Equilibrium centreline for joint vector ``q`` (see the module docstring).

        Args:
            q: (2n,) ``(beta, alpha)`` in metres and radians.
            guess: (n - 1,) tip angles (rad) to start Newton from, e.g. a previous ``state``.
                ``None``: cold start from every :meth:`initial_guesses` entry, keep the
                converged solution of least elastic energy.

        Returns:
            :class:`FkResult` with N = ``n_points`` samples; ``residual`` = max base-angle
            mismatch (rad); ``state`` = the tip angles (warm start for a nearby q).
        """
        beta, _ = self._split(q)
        if self.n_tubes == 1:  # a single tube has no twist: nothing to solve
            empty = jnp.zeros((0,), beta.dtype)
            return self._result(q, empty, jnp.int32(0), jnp.asarray(True))
        if guess is not None:
            guess = jnp.asarray(guess, beta.dtype)
            if guess.shape != (self.n_tubes - 1,):
                raise ValueError(f"guess must have shape ({self.n_tubes - 1},), got {guess.shape}")
            x, steps, solved = self._warm_solve(q, guess)
            return self._result(q, x, steps, solved)
        x, res, energy, steps = self._cold_solve(q, self.initial_guesses(q))
        best = self._pick_branch(res, energy)
        # Newton polish from the chosen branch: also attaches the implicit derivative.
        x, polish, solved = self._warm_solve(q, x[best])
        return self._result(q, x, jnp.sum(steps) + polish, solved)

    def _pick_branch(self, residual: Array, energies: Array) -> Array:
        """Index of the converged solution with least energy (least residual if none)."""
        converged = (residual <= self.tol) & jnp.isfinite(energies)
        key = jnp.where(converged, energies, jnp.inf)
        residual = jnp.where(jnp.isfinite(residual), residual, jnp.inf)
        return jnp.where(jnp.any(converged), jnp.argmin(key), jnp.argmin(residual))

    def forward_branches(
        self, q: Float[Array, " m"], guesses: Float[Array, "k n-1"] | None = None
    ) -> FkResult:
        """Solve from each of ``guesses`` (default :meth:`initial_guesses`) independently.

        Returns an :class:`FkResult` with a leading axis k (one per guess; several may land on
        the same equilibrium). Compare ``residual`` and ``energy`` to tell the branches apart.
        """
        guesses = self.initial_guesses(q) if guesses is None else jnp.asarray(guesses)

        x, _, _, steps = self._cold_solve(q, guesses)

        def one(xk, nk):
            xk, polish, solved = self._warm_solve(q, xk)
            return self._result(q, xk, nk + polish, solved)

        return jax.vmap(one)(x, steps)


def make_test_ctr(**kwargs) -> ConcentricTubeRobot:
    """:data:`TEST_CTR` as a model (keyword arguments override e.g. ``n_points``)."""
    return ConcentricTubeRobot.from_dict(TEST_CTR, **kwargs)


__all__ = ["TEST_CTR", "ConcentricTubeRobot", "make_test_ctr"]
