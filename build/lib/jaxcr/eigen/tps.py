"""Thin-plate smoothing spline (Reiter et al. Sec. III-D.2): psi -> eigen-feature.

For centres x_i (n, d) and values y_i (n, k) (k outputs fitted at once, one spline per
output dimension sharing one factorisation), the spline is

    f(x) = sum_i w_i phi(|x - x_i|) + c_0 + c^T x,      phi(r) = r^2 log r,

with (K + lambda I) w + P c = y and P^T w = 0, where K_ij = phi(|x_i - x_j|) and
P = [1, x]. ``lambda`` (``smoothing``) = 0 interpolates; larger values smooth. This is the
system ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline", smoothing=lambda)``
solves (same function; scipy also rescales its polynomial basis, which leaves the span and
therefore f unchanged). Inputs are shifted by their mean for the polynomial's
conditioning (phi depends on differences only).

The solve is one LU in the working dtype followed by two steps of iterative refinement,
which recovers most of the accuracy float32 loses on this ill-conditioned system.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float
from jaxcr.errors import InputError


def tps_kernel(r2: Float[Array, "..."]) -> Float[Array, "..."]:
    """phi = r^2 log r = 0.5 r^2 log r^2, 0 at r = 0 with a finite gradient (double where)."""
    pos = r2 > 0
    safe = jnp.where(pos, r2, 1.0)
    return jnp.where(pos, 0.5 * safe * jnp.log(safe), 0.0)


class ThinPlateSpline(eqx.Module):
    """A fitted spline: ``centres`` (n, d) (shifted by ``shift``), kernel weights
    ``weights`` (n, k), polynomial coefficients ``poly`` (d + 1, k) for [1, x - shift]."""

    centres: Float[Array, "n d"]
    shift: Float[Array, " d"]
    weights: Float[Array, "n k"]
    poly: Float[Array, "d1 k"]
    smoothing: Float[Array, ""]

    def __call__(self, x: Float[Array, " d"]) -> Float[Array, " k"]:
        """Spline value at one point x (d,)."""
        xs = jnp.asarray(x, self.centres.dtype) - self.shift
        r2 = jnp.sum((self.centres - xs) ** 2, axis=1)
        return tps_kernel(r2) @ self.weights + self.poly[0] + xs @ self.poly[1:]


def _system(centres, smoothing):
    n, d = centres.shape
    r2 = jnp.sum((centres[:, None, :] - centres[None, :, :]) ** 2, axis=-1)
    K = tps_kernel(r2) + smoothing * jnp.eye(n, dtype=centres.dtype)
    P = jnp.concatenate([jnp.ones((n, 1), centres.dtype), centres], axis=1)
    top = jnp.concatenate([K, P], axis=1)
    bottom = jnp.concatenate([P.T, jnp.zeros((d + 1, d + 1), centres.dtype)], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


@jax.jit
def _solve(centres, values, smoothing):
    n, d = centres.shape
    A = _system(centres, smoothing)
    rhs = jnp.concatenate([values, jnp.zeros((d + 1, values.shape[1]), values.dtype)], axis=0)
    lu = jax.scipy.linalg.lu_factor(A)
    sol = jax.scipy.linalg.lu_solve(lu, rhs)
    for _ in range(2):  # iterative refinement
        sol = sol + jax.scipy.linalg.lu_solve(lu, rhs - A @ sol)
    return sol[:n], sol[n:]


def fit_tps(
    x: Float[Array, "n d"], y: Float[Array, "n k"], smoothing: float = 0.0
) -> ThinPlateSpline:
    """Fit the thin-plate smoothing spline through (x_i, y_i) (see module docstring).

    Needs at least d + 2 points not all on one hyperplane (otherwise the polynomial part
    is not determined). ``smoothing`` >= 0 in units of y per unit weight (as scipy).
    """
    x = jnp.asarray(x)
    y = jnp.asarray(y, x.dtype)
    if x.ndim != 2 or y.ndim != 2 or x.shape[0] != y.shape[0]:
        raise InputError(f"spline needs x (n, d) and y (n, k); got {x.shape} and {y.shape}")
    if x.shape[0] < x.shape[1] + 2:
        raise InputError(f"spline needs at least {x.shape[1] + 2} samples, got {x.shape[0]}")
    if smoothing < 0:
        raise InputError(f"smoothing must be >= 0, got {smoothing}", field="smoothing")
    shift = x.mean(axis=0)
    c = x - shift
    w, p = _solve(c, y, jnp.asarray(smoothing, x.dtype))
    return ThinPlateSpline(c, shift, w, p, jnp.asarray(smoothing, x.dtype))


@eqx.filter_jit
def evaluate_tps(spline: ThinPlateSpline, x: Float[Array, "m d"], chunk: int = 4096):
    """Spline values (m, k) at many points, vmapped in chunks of ``chunk`` (bounded memory)."""
    m = x.shape[0]
    pad = (-m) % chunk
    xp = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, x.shape[1]))], axis=0) if pad else x
    out = jax.lax.map(jax.vmap(spline), xp.reshape(-1, chunk, x.shape[1]))
    return out.reshape(-1, out.shape[-1])[:m]
