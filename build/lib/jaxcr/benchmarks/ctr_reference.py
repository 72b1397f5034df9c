"""Slow independent reference for the concentric-tube model (numpy + scipy only).

Written separately from ``jaxcr.kinematics.ctr``: adaptive ``scipy.integrate.solve_ivp`` (DOP853)
on each interval between discontinuities, state = position, rotation matrix (9 entries), absolute
tube angles psi_i, torsional moments m_i = GJ_i u_iz and the elastic energy; shooting on the
initial moments with ``scipy.optimize.root`` (hybrid Powell) from several starts; the
equilibrium with least elastic energy among the converged starts is returned by
:func:`solve_equilibrium`.

Model (Rucker, Jones & Webster 2010 without external load): the total internal moment is zero,
so in the innermost tube's frame the bending curvature is the stiffness-weighted mean of the
tubes' precurvatures rotated into that frame, and each tube's torsional moment changes as
``m_i' = e3 . (EI_i u_i x u_i*)`` with ``u_i`` the bending curvature in tube i's frame.
Free distal ends: ``m_i(l_i) = 0``. Transmission torsion: ``psi_i(0) = alpha_i - beta_i m_i/GJ_i``.

It is the reference of ``jaxcr bench fk`` (:mod:`jaxcr.benchmarks.fk`) and of
tests/kinematics/test_ctr.py, whose stored tips ``python tests/helpers/ctr_reference.py``
regenerates.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import root

TEST_ROBOT = [  # innermost first: length, curved length (m), id, od (m), E, G (Pa), kappa (1/m)
    (0.431, 0.103, 0.70e-3, 1.10e-3, 64.3e9, 25.0e9, 21.3),
    (0.332, 0.113, 1.40e-3, 1.80e-3, 52.5e9, 21.4e9, 13.108),
    (0.174, 0.134, 2.0e-3, 2.2e-3, 47.1e9, 29.7e9, 3.5),
]


class Tubes:
    def __init__(self, rows, transmission_torsion=False):
        a = np.asarray(rows, float)
        self.L, self.Lc, self.id, self.od, self.E, self.G, self.kappa = a.T
        area_moment = np.pi / 64.0 * (self.od**4 - self.id**4)
        self.EI = self.E * area_moment
        self.GJ = self.G * 2.0 * area_moment
        self.n = len(rows)
        self.transmission_torsion = transmission_torsion


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _rhs_factory(t: Tubes, here, curved):
    """ODE right-hand side on one interval; ``here``/``curved`` are boolean (n,) masks."""
    ustar = [np.array([t.kappa[i] if curved[i] else 0.0, 0.0, 0.0]) for i in range(t.n)]
    K = sum(t.EI[i] for i in range(t.n) if here[i])

    def rhs(s, y):
        R = y[3:12].reshape(3, 3)
        psi = y[12 : 12 + t.n]
        m = y[12 + t.n : 12 + 2 * t.n]
        # bending of tube 1 in its own frame (Rucker eq. 11, no load)
        acc = np.zeros(3)
        for i in range(t.n):
            if here[i]:
                acc += t.EI[i] * (_rz(psi[i] - psi[0]) @ ustar[i])
        u1 = acc / K
        u1[2] = 0.0
        dm = np.zeros(t.n)
        dpsi = np.zeros(t.n)
        energy_rate = 0.0
        for i in range(t.n):
            if not here[i]:
                continue
            ui = _rz(psi[i] - psi[0]).T @ u1  # xy bending in tube i's frame
            ui[2] = 0.0
            dm[i] = np.cross(t.EI[i] * ui, ustar[i])[2]
            uz = m[i] / t.GJ[i]
            dpsi[i] = uz
            energy_rate += 0.5 * t.EI[i] * np.sum((ui - ustar[i]) ** 2) + 0.5 * t.GJ[i] * uz**2
        u_full = u1.copy()
        u_full[2] = m[0] / t.GJ[0]
        dp = R[:, 2]
        dR = R @ _skew(u_full)
        return np.concatenate([dp, dR.ravel(), dpsi, dm, [energy_rate]])

    return rhs


def _intervals(t: Tubes, beta):
    ends = beta + t.L
    total = ends.max()
    pts = np.clip(np.concatenate([ends - t.Lc, ends]), 0.0, total)
    knots = np.unique(np.concatenate([[0.0], pts]))
    return knots, ends


def integrate(t: Tubes, q, m0, rtol=1e-10, atol=1e-12, dense=False):
    """Integrate from s = 0 with initial torsional moments ``m0`` (N m).

    Returns dict with tip position, end moments (each tube's moment at its own end), energy,
    and optionally the samples (s, p) at interval ends.
    """
    q = np.asarray(q, float)
    beta, alpha = q[: t.n], q[t.n :]
    m0 = np.asarray(m0, float)
    psi0 = alpha - beta * m0 / t.GJ if t.transmission_torsion else alpha.copy()
    knots, ends = _intervals(t, beta)
    y = np.concatenate([np.zeros(3), _rz(psi0[0]).ravel(), psi0, m0, [0.0]])
    samples_s, samples_p = [0.0], [y[:3].copy()]
    for a, b in zip(knots[:-1], knots[1:], strict=True):
        if b - a <= 0.0:
            continue
        mid = 0.5 * (a + b)
        here = mid < ends
        curved = here & (mid > ends - t.Lc)
        sol = solve_ivp(
            _rhs_factory(t, here, curved), (a, b), y, method="DOP853", rtol=rtol, atol=atol
        )
        y = sol.y[:, -1]
        samples_s.append(b)
        samples_p.append(y[:3].copy())
    energy = y[-1]
    if t.transmission_torsion:
        energy += float(np.sum(0.5 * m0**2 / t.GJ * (-beta)))
    out = {
        "tip": y[:3].copy(),
        "R_tip": y[3:12].reshape(3, 3).copy(),
        "m_end": y[12 + t.n : 12 + 2 * t.n].copy(),  # frozen after each tube's end
        "energy": float(energy),
    }
    if dense:
        out["s"] = np.array(samples_s)
        out["p"] = np.array(samples_p)
    return out


def default_starts(t: Tubes, q, n_random=6, seed=0):
    """Initial torsional moments to start the shooting from: zero, and twisted states."""
    rng = np.random.default_rng(seed)
    starts = [np.zeros(t.n)]
    for _ in range(n_random):
        uz = rng.uniform(-40.0, 40.0, size=t.n)
        m = uz * t.GJ
        m -= t.GJ * np.sum(m) / np.sum(t.GJ)  # zero total moment
        starts.append(m)
    return starts


def solve_all(t: Tubes, q, starts=None, rtol=1e-10, atol=1e-12, tol=1e-9):
    """Solve from every start; return the list of distinct converged equilibria."""
    starts = default_starts(t, q) if starts is None else starts
    scale = t.GJ  # residual in twist rate units (1/m)
    found = []
    for m0 in starts:

        def fun(x):
            return integrate(t, q, x * scale, rtol, atol)["m_end"] / scale

        sol = root(fun, np.asarray(m0) / scale, method="hybr", tol=1e-12)
        x = sol.x
        res = np.linalg.norm(fun(x))
        if not np.isfinite(res) or res > tol:
            continue
        info = integrate(t, q, x * scale, rtol, atol)
        uz0 = x
        if any(np.allclose(uz0, f["uz0"], atol=1e-5) for f in found):
            continue
        found.append(
            {
                "uz0": uz0,
                "tip": info["tip"],
                "R_tip": info["R_tip"],
                "energy": info["energy"],
                "residual": res,
            }
        )
    return found


def solve_equilibrium(t: Tubes, q, starts=None, **kw):
    """The converged equilibrium of least elastic energy (dict as in :func:`solve_all`)."""
    found = solve_all(t, q, starts, **kw)
    if not found:
        raise RuntimeError(f"no equilibrium found for q={q}")
    return min(found, key=lambda f: f["energy"])


def random_q(rng, t: Tubes):
    """Joint values inside the limits: telescoping betas, alphas in [-pi, pi)."""
    n = t.n
    beta = np.zeros(n)
    # outermost first: exposed length of tube n, then each inner tube within its limits
    ell_n = rng.uniform(0.3, 1.0) * t.L[-1]
    beta[-1] = ell_n - t.L[-1]
    for i in range(n - 2, -1, -1):
        lo = max(beta[i + 1] + t.L[i + 1] - t.L[i], -t.L[i] + 1e-3)
        hi = beta[i + 1]
        beta[i] = rng.uniform(lo, hi)
    alpha = rng.uniform(-np.pi, np.pi, size=n)
    return np.concatenate([beta, alpha])
