"""Weighted ICP with projective data association (paper Sec. IV.A match weights; association
as in KinectFusion, Newcombe et al. 2011): the target is an organised RGB-D view, so the
candidate correspondence of a source point is found by projecting it into the target image
with the target camera's intrinsics instead of by a nearest-neighbour search. One step costs
O(n_src (2 r + 1)^2), independent of the target size, with fixed shapes (jit once per size).

Association of a transformed source point p (target camera frame, metres) with colour c:
pixel (u, v) = round(fx x / z + cx, fy y / z + cy); among the valid target pixels in the
(2 ``window`` + 1)^2 neighbourhood of (u, v), the one nearest in the joint space
(position, ``colour_scale`` x RGB) of :func:`jaxcr.registration.icp.correspondences`
(``window = 0``: the projected pixel itself). Rejected: points behind the camera or
projecting outside the image, target pixels without a valid depth/normal (which includes
every pixel whose normal window straddles a depth jump > 2 cm, see
:func:`jaxcr.registration.clouds.organised_cloud`), pairs farther apart than the current
radius, normals differing by more than 60 degrees. Accepted pairs get the paper's combined
weight (distance, colour similarity, normal difference, point-to-plane distance;
:func:`jaxcr.registration.icp.pair_weights`) and the same damped Gauss-Newton update with the
keypoint term as the nearest-neighbour ICP (:func:`jaxcr.registration.icp.gauss_newton_update`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Mat4
from jaxcr.registration.icp import (
    DEFAULT_ICP,
    CloudArrays,
    IcpConfig,
    IcpResult,
    Keypoints,
    gauss_newton_update,
    no_keypoints,
    pair_weights,
)


class DepthImage(NamedTuple):
    """An organised target view: camera-frame points / colours / unit normals (h, w, 3)
    (float32, zeros where invalid), the validity mask (h, w) and the intrinsics K (3, 3)."""

    points: Float[Array, "h w 3"]
    colours: Float[Array, "h w 3"]
    normals: Float[Array, "h w 3"]
    mask: Bool[Array, "h w"]
    K: Float[Array, "3 3"]


def depth_image(P, C, N, ok, K) -> DepthImage:
    """:class:`DepthImage` from the numpy output of
    :func:`jaxcr.registration.clouds.organised_cloud` and ``K``."""
    f = np.float32
    return DepthImage(
        jnp.asarray(np.where(ok[..., None], P, 0.0), f),
        jnp.asarray(C, f),
        jnp.asarray(np.where(ok[..., None], N, 0.0), f),
        jnp.asarray(ok, bool),
        jnp.asarray(K, f),
    )


def project(ps: Float[Array, "n 3"], K: Float[Array, "3 3"]):
    """Pixel coordinates (u, v) (n,) of camera-frame points and a mask of points in front of
    the camera (z > 1 mm); (u, v) of the others are finite but meaningless."""
    z = ps[:, 2]
    front = z > 1e-3
    zs = jnp.where(front, z, 1.0)
    u = K[0, 0] * ps[:, 0] / zs + K[0, 2]
    v = K[1, 1] * ps[:, 1] / zs + K[1, 2]
    return u, v, front


def projective_correspondences(
    ps: Float[Array, "n 3"],
    cs: Float[Array, "n 3"],
    tgt: DepthImage,
    window: int,
    colour_scale: float,
) -> tuple[Array, Bool[Array, " n"]]:
    """Flat target pixel index (n,) (row-major, ``v * w + u``) associated with each source
    point (module docstring) and whether there is one."""
    h, w = tgt.mask.shape
    u, v, front = project(ps, tgt.K)
    iu = jnp.round(jnp.clip(u, -1.0, w)).astype(jnp.int32)
    iv = jnp.round(jnp.clip(v, -1.0, h)).astype(jnp.int32)
    flat_p = tgt.points.reshape(-1, 3)
    flat_c = tgt.colours.reshape(-1, 3)
    flat_m = tgt.mask.reshape(-1)
    r = int(window)
    offs = [(du, dv) for dv in range(-r, r + 1) for du in range(-r, r + 1)]
    du = jnp.asarray([o[0] for o in offs], jnp.int32)
    dv = jnp.asarray([o[1] for o in offs], jnp.int32)
    cu = iu[:, None] + du[None, :]  # (n, k)
    cv = iv[:, None] + dv[None, :]
    inside = (cu >= 0) & (cu < w) & (cv >= 0) & (cv < h)
    idx = jnp.clip(cv, 0, h - 1) * w + jnp.clip(cu, 0, w - 1)
    ok = inside & flat_m[idx] & front[:, None]
    if len(offs) == 1:
        return idx[:, 0], ok[:, 0]
    d2 = jnp.sum((flat_p[idx] - ps[:, None, :]) ** 2, -1) + colour_scale**2 * jnp.sum(
        (flat_c[idx] - cs[:, None, :]) ** 2, -1
    )
    d2 = jnp.where(ok, d2, jnp.inf)
    best = jnp.argmin(d2, axis=1)
    take = jnp.take_along_axis
    return take(idx, best[:, None], 1)[:, 0], take(ok, best[:, None], 1)[:, 0]


def _matches(T, src: CloudArrays, tgt: DepthImage, radius, cfg: IcpConfig, window: int):
    R, t = T[:3, :3], T[:3, 3]
    ps, ns = src.points @ R.T + t, src.normals @ R.T
    j, found = projective_correspondences(ps, src.colours, tgt, window, cfg.colour_scale)
    q = tgt.points.reshape(-1, 3)[j]
    nq = tgt.normals.reshape(-1, 3)[j]
    cq = tgt.colours.reshape(-1, 3)[j]
    w, pl, keep = pair_weights(ps, ns, src.colours, q, nq, cq, src.mask & found, radius, cfg)
    return ps, q, nq, w, pl, keep


def projective_icp_step(
    T: Mat4, radius, src: CloudArrays, tgt: DepthImage, cfg: IcpConfig, kp: Keypoints, window: int
) -> Mat4:
    """One weighted Gauss-Newton step with projective association; returns the new ``T``."""
    ps, q, nq, w, pl, _ = _matches(T, src, tgt, radius, cfg, window)
    return gauss_newton_update(T, ps, q, nq, w, pl, cfg, kp)


def projective_evaluate(
    T: Mat4, src: CloudArrays, tgt: DepthImage, cfg: IcpConfig = DEFAULT_ICP, window: int = 1
) -> IcpResult:
    """Fitness (fraction of valid source points with an accepted match within
    ``cfg.min_dist``) and point-to-plane RMSE (m) of ``T`` under projective association."""
    _, _, _, _, pl, keep = _matches(T, src, tgt, cfg.min_dist, cfg, window)
    k = jnp.sum(keep)
    rmse = jnp.sqrt(jnp.sum(jnp.where(keep, pl**2, 0.0)) / jnp.maximum(k, 1))
    return IcpResult(T, k / jnp.maximum(jnp.sum(src.mask), 1), rmse, k)


def projective_icp(
    src: CloudArrays,
    tgt: DepthImage,
    T0: Mat4,
    cfg: IcpConfig = DEFAULT_ICP,
    kp: Keypoints | None = None,
    window: int = 1,
) -> IcpResult:
    """Register the source cloud ``src`` (any padded sample of a view, camera frame) to the
    organised target view ``tgt`` from ``T0`` (target <- source), optionally with matched
    keypoints: ``cfg.iterations`` steps with the correspondence radius shrinking
    geometrically from ``cfg.max_dist`` to ``cfg.min_dist``, as :func:`icp`. Pure,
    jit-able (``window`` static)."""
    kp = no_keypoints() if kp is None else kp
    n = cfg.iterations
    ratio = (cfg.min_dist / cfg.max_dist) ** (1.0 / max(n - 1, 1))

    def body(k, T):
        radius = cfg.max_dist * ratio ** jnp.minimum(k, n - 1)
        return projective_icp_step(T, radius, src, tgt, cfg, kp, window)

    T = jax.lax.fori_loop(0, n, body, T0.astype(src.points.dtype))
    return projective_evaluate(T, src, tgt, cfg, window)


projective_icp_jit = jax.jit(projective_icp, static_argnames=("window",))
