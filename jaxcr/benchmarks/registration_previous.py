"""The projective ICP before issue 18 (commit 31765ad), for same-run ratios in
:mod:`jaxcr.benchmarks.registration`: the fixed ``IcpConfig.iterations`` schedule (no
convergence stop) and the photometric term's robust scales by ``jnp.nanmedian`` (an XLA
sort). Everything else (association, weights, Gauss-Newton update) is the current code,
unchanged by issue 18."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr.registration.icp import gauss_newton_update, no_keypoints, normal_equations
from jaxcr.registration.projective import (
    _matches,
    bilinear,
    photometric_channels,
    project,
    projective_evaluate,
)


def photometric_terms(ps, i_src, tgt, w, pl, keep, channels="intensity"):
    """:func:`jaxcr.registration.projective.photometric_terms` as of 31765ad (nanmedian)."""
    img, grad = photometric_channels(tgt, channels)
    u, v, front = project(ps, tgt.K)
    it, inside = bilinear(img, u, v)
    gr, _ = bilinear(grad, u, v)
    mk, _ = bilinear(tgt.mask.astype(ps.dtype), u, v)
    ok = keep & front & inside & (mk > 0.999)
    r = it - i_src
    nan = jnp.nan
    s_i = 1.4826 * jnp.nanmedian(jnp.where(ok[:, None], jnp.abs(r), nan)) + 1e-4
    s_g = 1.4826 * jnp.nanmedian(jnp.where(ok, jnp.abs(pl), nan)) + 1e-6
    s_i = jnp.where(jnp.isfinite(s_i), s_i, 1.0)
    s_g = jnp.where(jnp.isfinite(s_g), s_g, 1e-3)
    z = jnp.where(front, ps[:, 2], 1.0)[:, None]
    x, y = ps[:, 0:1], ps[:, 1:2]
    fx, fy = tgt.K[0, 0], tgt.K[1, 1]
    gp = jnp.stack(
        [
            gr[..., 0] * fx / z,
            gr[..., 1] * fy / z,
            -(gr[..., 0] * fx * x + gr[..., 1] * fy * y) / z**2,
        ],
        -1,
    )
    J = jnp.concatenate([gp, jnp.cross(ps[:, None, :], gp)], axis=-1)
    wc = w[:, None] * jnp.exp(-(r**2) / (2 * (3 * s_i) ** 2)) * (s_g / s_i) ** 2
    wc = jnp.where(ok[:, None], wc, 0.0)
    r = jnp.where(ok[:, None], r, 0.0)
    return jnp.einsum("nc,nca,ncb->ab", wc, J, J), jnp.einsum("nc,nca,nc->a", wc, J, r)


def _i_src(src, src_image, photometric):
    u, v, _ = project(src.points, src_image.K)
    return bilinear(photometric_channels(src_image, photometric)[0], u, v)[0]


def projective_icp(
    src, tgt, T0, cfg, kp=None, window=1, src_image=None, photometric="intensity",
    photo_points=None,
):  # fmt: skip
    """:func:`jaxcr.registration.projective.projective_icp` as of 31765ad."""
    kp = no_keypoints() if kp is None else kp
    i_src = None if src_image is None else _i_src(src, src_image, photometric)
    n = cfg.iterations
    ratio = (cfg.min_dist / cfg.max_dist) ** (1.0 / max(n - 1, 1))

    def body(k, T):
        radius = cfg.max_dist * ratio ** jnp.minimum(k, n - 1)
        ps, q, nq, w, pl, keep = _matches(T, src, tgt, radius, cfg, window)
        extra = None
        if i_src is not None:
            pp = ps if photo_points is None else photo_points @ T[:3, :3].T + T[:3, 3]
            extra = photometric_terms(pp, i_src, tgt, w, pl, keep, photometric)
        return gauss_newton_update(T, ps, q, nq, w, pl, cfg, kp, extra)

    T = jax.lax.fori_loop(0, n, body, T0.astype(src.points.dtype))
    return projective_evaluate(T, src, tgt, cfg, window)


def projective_information(
    T, src, tgt, cfg, kp=None, window=0, src_image=None, photometric="intensity",
    photo_points=None,
):  # fmt: skip
    """:func:`jaxcr.registration.projective.projective_information` as of 31765ad."""
    kp = no_keypoints() if kp is None else kp
    ps, q, nq, w, pl, keep = _matches(T, src, tgt, cfg.min_dist, cfg, window)
    extra = None
    if src_image is not None:
        i_src = _i_src(src, src_image, photometric)
        pp = ps if photo_points is None else photo_points @ T[:3, :3].T + T[:3, 3]
        extra = photometric_terms(pp, i_src, tgt, w, pl, keep, photometric)
    H, _ = normal_equations(T, ps, q, nq, w, pl, cfg, kp, extra)
    s2 = jnp.sum(w * pl**2) / jnp.maximum(jnp.sum(w), 1e-30)
    s2 = jnp.maximum(s2, 1e-12)
    return 0.5 * (H + H.T) / s2, jnp.sqrt(s2)


projective_icp_jit = jax.jit(projective_icp, static_argnames=("window", "photometric"))
projective_information_jit = jax.jit(
    projective_information, static_argnames=("window", "photometric")
)
