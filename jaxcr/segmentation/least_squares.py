"""A least-squares form of the band region energy, and a damped Gauss-Newton solver for it.

The refinement's objective (:mod:`jaxcr.segmentation.energy`) is, on the band pixels p with
soft silhouette ``H_p = sigmoid(m_p / tau)`` (``m_p`` the pixel's signed margin, pixels),

    J(theta) = J_img(H(theta)) + R(theta),

with ``R`` the regulariser (quadratic in theta: ``g_reg L int |delta-u|^2 ds`` and the camera
terms) and ``J_img`` the Chan-Vese data and penalty terms (eq. 5 with eq. 6). For *fixed*
region means mu, ``J_img`` is linear in H:

    J_img^mu(H) = C(mu) + sum_p e_p H_p,
    e_p = a_p [w_p (g1 |I_p - mu_in|^2 - g2 |I_p - mu_out|^2) / (A var) + g4 b_p / A],

and with mu the regions' exact means (the minimisers of eq. 6), ``dJ_img / dH_p = e_p``
(envelope theorem: the derivative through mu vanishes), so ``e = grad_H J_img`` is what
:func:`jaxcr.segmentation.energy.chan_vese_soft` differentiates to. Since H lies in (0, 1),
``e_p H_p = |e_p| |H_p - t_p| - |e_p| t_p`` with the label ``t_p = 1`` where ``e_p < 0``
(the pixel prefers the inside) and ``t_p = 0`` otherwise, so

    J^mu(theta) = const + 1/2 |r(theta)|^2,
    r_p = sqrt(2 |e_p| g_p),   g_p = |H_p - t_p| = sigmoid(s_p m_p / tau),   s_p = sign(e_p),
    r_reg = sqrt(2) L_reg theta    (R = |L_reg theta|^2).

This is an *exact* least-squares form of the energy at fixed means (not the squared-label
surrogate ``|e_p|^(1/2) (H_p - t_p)``, whose gradient ``|e_p| (H_p - t_p) H'_p`` weighs each
pixel by its disagreement ``|H_p - t_p|`` and so moves the minimum). Because J_img is concave
in H (a minimum over mu of linear functions), ``J^mu`` touches J at the current means and
lies above it elsewhere: a step that lowers ``J^mu`` lowers J (majorise-minimise, as the
Chan-Vese alternation). Consequences used here:

* the gradient of 1/2 |r|^2 is J's gradient: ``r_p dr_p/dm_p = |e_p| s_p sigma(1 - sigma) / tau
  = e_p H_p (1 - H_p) / tau = dJ/dm_p`` (``sigma = sigmoid(s_p m_p / tau)``);
* the Gauss-Newton matrix is ``G = sum_p c_p grad m_p grad m_p^T + hess R`` with
  ``c_p = (dr_p/dm_p)^2 = |e_p| sigma (1 - sigma)^2 / (2 tau^2)``: positive semidefinite, and
  no square root is ever taken (no NaN where ``e_p = 0`` or ``g_p -> 0``).

:func:`damped_gauss_newton` minimises J with Levenberg-Marquardt steps ``(G + lam diag(G)) d =
-g``, accepting a step when J itself (with re-estimated means) decreases, and stops by the
image-space test of :class:`jaxcr.segmentation.refine.ImageSpaceBFGS` (a step moving every
projected centreline point by less than ``xtol`` px and changing J by less than ``ftol``).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.segmentation.silhouette import Band, TileGrid, TubeImage, capsule_margin


def region_residuals(
    margin: Float[Array, "k p"], e: Float[Array, "k p"], tau: float | Float[Array, ""]
) -> Float[Array, "k p"]:
    """Residuals ``r_p = sqrt(2 |e_p| sigmoid(sign(e_p) m_p / tau))`` of the band pixels (module
    docstring): ``1/2 sum r_p^2`` equals the image energy at fixed region means up to a
    constant. ``e`` = d J_img / d H (held fixed). The square root is guarded (double where)
    so that its derivative is 0, not NaN, where ``e_p = 0``."""
    g = jax.nn.sigmoid(jnp.sign(e) * margin / tau)
    x = 2.0 * jnp.abs(e) * g
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def normal_terms(
    margin: Float[Array, "k p"],
    dmargin: Float[Array, "k p n"],
    e: Float[Array, "k p"],
    tau: float | Float[Array, ""],
) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Gradient ``sum_p e_p H_p (1 - H_p) / tau grad m_p`` and Gauss-Newton matrix
    ``sum_p c_p grad m_p grad m_p^T`` of the band pixels' residuals (module docstring), from
    the margins (k, p), their Jacobian (k, p, n) with respect to the n parameters and the
    pixel weights ``e = dJ_img / dH``."""
    h = jax.nn.sigmoid(margin / tau)
    grad = jnp.einsum("kp,kpn->n", e * h * (1.0 - h) / tau, dmargin)
    sig = jax.nn.sigmoid(jnp.sign(e) * margin / tau)
    c = jnp.abs(e) * sig * (1.0 - sig) ** 2 / (2.0 * tau * tau)
    gn = jnp.einsum("kpi,kpj->ij", dmargin * c[..., None], dmargin)
    return grad, gn


def winner_margins(
    tube: TubeImage, grid: TileGrid, band: Band
) -> tuple[Float[Array, "k p"], Float[Array, "k p 6"], Int[Array, "k p"]]:
    """The band margins of :func:`jaxcr.segmentation.silhouette.band_margin` (same value),
    their derivatives with respect to the six fields ``(ax, ay, bx, by, ra, rb)`` of each
    pixel's winning capsule, and the winner's slot among its tile's candidates
    (``band.segs``). Forward mode over six local tangents: no gather of parameter tangents
    per pixel (what makes ``jacfwd`` of ``band_margin`` ~10x a reverse pass on CPU)."""
    dtype = tube.ax.dtype
    t = grid.tile
    ox, oy = grid.pixel_offsets(dtype)
    row, col = grid.row_col(band.tiles)
    px = col.astype(dtype)[:, None] * t + ox[None]
    py = row.astype(dtype)[:, None] * t + oy[None]
    fields = (tube.ax, tube.ay, tube.bx, tube.by, tube.ra, tube.rb)
    valid = tube.valid[band.segs][:, None, :]
    cand = [a[band.segs][:, None, :] for a in fields]
    slot = jnp.argmax(capsule_margin(px[..., None], py[..., None], *cand, valid), axis=-1)
    seg = jnp.take_along_axis(band.segs, slot, axis=1)
    win = [a[seg] for a in fields]

    def margin(x):
        return capsule_margin(px, py, *(w + x[i] for i, w in enumerate(win)), tube.valid[seg])

    x0 = jnp.zeros(6, dtype)
    return margin(x0), jax.jacfwd(margin)(x0), slot


def band_normal_terms(
    margin: Float[Array, "k p"],
    dfield: Float[Array, "k p 6"],
    slot: Int[Array, "k p"],
    field_jac: Float[Array, "6 m n"],
    band: Band,
    e: Float[Array, "k p"],
    tau: float | Float[Array, ""],
) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """:func:`normal_terms` from the outputs of :func:`winner_margins`: ``grad m_p = dfield_p .
    F_s`` with F_s the (6, n) Jacobian of the winning capsule s's fields (``field_jac[:, s]``,
    gathered per band tile and candidate slot, then per pixel), then the two contractions of
    :func:`normal_terms` as matrix products over the band pixels. (Summing 6x6 blocks per tile
    slot or per capsule first does fewer flops but measured 1.6-3.7x slower on CPU.)"""
    h = jax.nn.sigmoid(margin / tau)
    ge = e * h * (1.0 - h) / tau
    sig = jax.nn.sigmoid(jnp.sign(e) * margin / tau)
    c = jnp.abs(e) * sig * (1.0 - sig) ** 2 / (2.0 * tau * tau)
    n = field_jac.shape[-1]
    # a product with the identity (which XLA cannot fold: it depends on the data) keeps
    # field_jac a materialised array: otherwise XLA CPU fuses the tube Jacobian's
    # computation into the per-pixel gather below and redoes it for each of the k p 6 n
    # gathered elements (measured 15 ms instead of 3.5 per linearisation at 640x480)
    eye = jnp.eye(n, dtype=field_jac.dtype) * (1.0 + 0.0 * field_jac[0, 0, 0])
    field_jac = jnp.einsum("fmn,nj->fmj", field_jac, eye)
    fs = jnp.moveaxis(field_jac[:, band.segs], 0, 2)  # (k, C, 6, n)
    per_pixel = jnp.take_along_axis(fs, slot[:, :, None, None], axis=1)  # (k, p, 6, n)
    dm = jnp.einsum("kpf,kpfn->kpn", dfield, per_pixel).reshape(-1, n)
    return dm.T @ ge.reshape(-1), (dm * c.reshape(-1, 1)).T @ dm


LAM_MIN = 1e-4  # floor of the Marquardt damping (relative to diag G)
MU_MIN = 1.0 / 64.0  # the longest step: 64 times the Gauss-Newton one (then capped by max_px)


class GaussNewtonResult(eqx.Module):
    """Output of :func:`damped_gauss_newton`: the parameters, J there, whether the image-space
    test stopped the solve (else the step budget did), and the steps taken (one linearisation
    of J each)."""

    y: Float[Array, " n"]
    value: Float[Array, ""]
    converged: Bool[Array, ""]
    num_steps: Int[Array, ""]


def damped_gauss_newton(
    linearise: Callable[[Array], tuple[Array, Array, Array]],
    y0: Float[Array, " n"],
    motion_jac: Float[Array, "P 2 n"],
    *,
    xtol: float,
    ftol: float,
    budget: Int[Array, ""] | int,
    lam0: float = 1e-2,
    max_px: float | Float[Array, ""] = 4.0,
) -> GaussNewtonResult:
    """Levenberg-Marquardt minimisation of J from ``y0`` (a ``lax.while_loop``; never raises).

    Args:
        linearise: ``y -> (J, grad J, G)`` with G a positive semidefinite Gauss-Newton matrix
            (n, n) of J at y (:func:`normal_terms` plus the regulariser's Hessian).
        y0: (n,) start.
        motion_jac: (P, 2, n) motion of the projected centreline points (pixels of the level)
            per unit of y, for the image-space stop and the step cap.
        xtol, ftol: the image-space stop (:class:`jaxcr.segmentation.refine.ImageSpaceBFGS`):
            an accepted step moving every point by less than ``xtol`` px and changing J by
            less than ``ftol``, or a rejected one that small whose model decrease is below
            ``ftol``.
        budget: most linearisations (steps); a traced count is fine.
        lam0: initial Marquardt damping (relative to diag(G)); divided by 3 after a step
            whose decrease exceeds 3/4 of the model's (down to ``LAM_MIN``; below that the
            step is lengthened instead: ``G`` is scaled by ``mu``, halved each time, down to
            ``MU_MIN``), multiplied by 2 after one below 1/4 of it and by 4 after a rejected
            one (once ``mu`` is back to 1).
        max_px: cap on a step's image motion (px of the level): a longer step is shortened
            to it (the band, fixed during a solve, reaches a few tiles from the silhouette).
    """
    dtype = y0.dtype
    J0, g0, G0 = linearise(y0)

    def motion(d):
        uv = motion_jac @ d
        return jnp.max(jnp.hypot(uv[:, 0], uv[:, 1]))

    def cond(state):
        *_, k, done = state
        return ~done & (k < budget)

    def body(state):
        y, J, g, G, (lam, mu), _, k, _ = state
        diag = jnp.diagonal(G)
        damp = lam * (diag + 1e-9 * jnp.max(diag) + 1e-12)
        d = jnp.linalg.solve(mu * (G + jnp.diag(damp)), -g)
        d = jnp.where(jnp.all(jnp.isfinite(d)), d, -g * 1e-3)
        px = motion(d)
        d = d * jnp.minimum(1.0, max_px / jnp.maximum(px, 1e-12))
        px = jnp.minimum(px, max_px)
        # the decrease predicted by the model the step minimises (curvature mu G)
        pred = -(jnp.dot(g, d) + 0.5 * mu * jnp.dot(d, G @ d))
        J1, g1, G1 = linearise(y + d)
        ok = jnp.isfinite(J1) & (J1 < J) & jnp.all(jnp.isfinite(g1)) & jnp.all(jnp.isfinite(G1))
        rho = (J - J1) / jnp.maximum(pred, 1e-30)
        # lam steers the direction (Marquardt); once it is at its floor, a step that did
        # better than the model (rho > 3/4) lengthens the next one (mu < 1: the
        # Gauss-Newton matrix of this energy over-estimates its curvature far from the
        # minimum, measured rho 1.3-2.5 with steps of 0.05-0.15 px); a poor or rejected
        # step first brings mu back to 1, then raises lam
        good, poor = ok & (rho > 0.75), ~ok | (rho < 0.25)
        up = jnp.where(ok, 2.0, 4.0)
        lam_floor = lam <= LAM_MIN
        lam = jnp.where(good & ~lam_floor, lam / 3.0, jnp.where(poor & (mu >= 1.0), lam * up, lam))
        mu = jnp.where(good & lam_floor, mu / 2.0, jnp.where(poor, mu * up, mu))
        lam, mu = jnp.clip(lam, LAM_MIN, 1e7), jnp.clip(mu, MU_MIN, 1.0)
        small = px < xtol
        conv = jnp.where(ok, small & (jnp.abs(J - J1) < ftol), small & (pred < ftol))
        pick = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
        new = (pick(y + d, y), pick(J1, J), pick(g1, g), pick(G1, G), (lam, mu))
        return new + (conv, k + 1, conv)

    one = jnp.asarray(1.0, dtype)
    init = (y0, J0, g0, G0, (jnp.asarray(lam0, dtype), one), jnp.asarray(False), jnp.asarray(0),
            jnp.asarray(False))  # fmt: skip
    y, J, *_, conv, k, _ = jax.lax.while_loop(cond, body, init)
    return GaussNewtonResult(y=y, value=J, converged=conv, num_steps=k.astype(jnp.int32))
