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

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Mat4
from jaxcr.registration.clouds import plane_residual_variance
from jaxcr.registration.icp import (
    DEFAULT_ICP,
    CloudArrays,
    IcpConfig,
    IcpResult,
    Keypoints,
    gauss_newton_update,
    no_keypoints,
    normal_equations,
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
    intensity: Float[Array, "h w"]  # grey level (mean of RGB), Gaussian-smoothed (1 px)
    gradient: Float[Array, "h w 2"]  # its d/du, d/dv (central differences, per pixel)
    chroma: Float[Array, "h w 2"]  # chromaticity r, g = (R, G) / (R + G + B), smoothed (1 px)
    chroma_gradient: Float[Array, "h w 2 2"]  # d/du, d/dv of each chromaticity channel
    # Variance of each pixel's 7 x 7 window about its tangent plane (m^2,
    # :func:`jaxcr.registration.clouds.plane_residual_variance`; the "sensor+fit" noise
    # weight); None: not computed.
    plane_var: Float[Array, "h w"] | None = None


def _smooth_and_gradient(img: np.ndarray, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian smoothing (std ``blur`` px; none if 0) of a (h, w) image and its central
    differences d/du, d/dv (h, w, 2) (zero on the border columns / rows)."""
    import cv2

    img = np.ascontiguousarray(img, np.float32)
    ism = cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img
    grad = np.zeros(ism.shape + (2,), np.float32)
    grad[:, 1:-1, 0] = 0.5 * (ism[:, 2:] - ism[:, :-2])
    grad[1:-1, :, 1] = 0.5 * (ism[2:, :] - ism[:-2, :])
    return ism, grad


def chromaticity(rgb: np.ndarray, min_sum: float = 0.05) -> np.ndarray:
    """Normalised chromaticity (r, g) = (R, G) / (R + G + B) (h, w, 2) of an RGB image;
    0 where R + G + B < ``min_sum`` (black: no hue). Invariant to a per-pixel scaling of
    the RGB values, i.e. to the shading of a surface under white light, which changes with
    the surface normal and, for a light that moves with the camera, with the viewpoint."""
    C = np.asarray(rgb, np.float64)
    s = C.sum(-1, keepdims=True)
    return np.where(s > min_sum, C[..., :2] / np.maximum(s, 1e-12), 0.0).astype(np.float32)


def depth_image(P, C, N, ok, K, blur: float = 1.0, plane_var: bool = False) -> DepthImage:
    """:class:`DepthImage` from the numpy output of
    :func:`jaxcr.registration.clouds.organised_cloud` and ``K``; ``blur``: standard
    deviation (px) of the Gaussian smoothing of the intensity and chromaticity images;
    ``plane_var``: also the plane-fit residual variance (``IcpConfig.noise_weight``
    "sensor+fit"; ~8 ms per 320 x 240 frame)."""
    f = np.float32
    ism, grad = _smooth_and_gradient(np.asarray(C, f).mean(-1), blur)
    ch = chromaticity(C)
    cs, cg = zip(*(_smooth_and_gradient(ch[..., k], blur) for k in range(2)), strict=True)
    pv = jnp.asarray(plane_residual_variance(P, N, ok), f) if plane_var else None
    return DepthImage(
        jnp.asarray(np.where(ok[..., None], P, 0.0), f),
        jnp.asarray(C, f),
        jnp.asarray(np.where(ok[..., None], N, 0.0), f),
        jnp.asarray(ok, bool),
        jnp.asarray(K, f),
        jnp.asarray(ism, f),
        jnp.asarray(grad, f),
        jnp.asarray(np.stack(cs, -1), f),
        jnp.asarray(np.stack(cg, -2), f),
        pv,
    )


def scale_matching_blur(z_src: float, z_tgt: float, base_blur: float = 1.0) -> tuple[float, float]:
    """Extra Gaussian blur (std, pixels) of the (source, target) colour images that gives
    both the same blur *on the surface* before the photometric term compares them.

    A pixel of a view at distance z covers z / f of the surface: a camera integrating over
    its pixel (box, variance 1/12 px^2) and :func:`depth_image`'s smoothing (std
    ``base_blur`` px) blur the texture by b z / f metres, b = sqrt(base_blur^2 + 1/12).
    Registering a view at z_s against one at z_t < z_s compares the texture blurred by
    b z_s / f with the same texture blurred by b z_t / f: a different signal, whose
    difference the colour term reads as motion wherever the texture is not symmetric
    about the pixel (a systematic pull, growing with z_s / z_t). Gaussian blurs compose
    by adding variances, so the nearer view gets the extra std b sqrt(r^2 - 1) pixels
    (its own pixels; r = z_far / z_near) and the farther none. Depths in metres (e.g. the
    median depth of each view); returns (0, 0) for equal or invalid depths."""
    if not (np.isfinite(z_src) and np.isfinite(z_tgt) and z_src > 0 and z_tgt > 0):
        return 0.0, 0.0
    b = float(np.sqrt(base_blur**2 + 1.0 / 12.0))
    r = z_src / z_tgt
    if r >= 1.0:
        return 0.0, b * float(np.sqrt(r * r - 1.0))
    return b * float(np.sqrt(1.0 / (r * r) - 1.0)), 0.0


def blurred_image(img: DepthImage, extra_blur: float, base_blur: float = 1.0) -> DepthImage:
    """``img`` (made by :func:`depth_image` with smoothing ``base_blur`` px) with its
    intensity and chromaticity images blurred further by a Gaussian of std ``extra_blur``
    pixels (:func:`scale_matching_blur`) and their gradients recomputed (central
    differences, as :func:`depth_image`). Both are recomputed from the raw colours with the
    total std sqrt(base_blur^2 + extra_blur^2) as a normalised convolution over the valid
    pixels, ``G * (m I) / G * m``, so the background (no depth, black) does not bleed into
    the object's border pixels; invalid pixels keep their values. Geometry (points,
    normals, mask) is unchanged. Host side; ``extra_blur <= 0`` returns ``img``."""
    if extra_blur <= 0:
        return img
    import cv2

    sigma = float(np.hypot(base_blur, extra_blur))
    m = np.asarray(img.mask, np.float32)
    wm = cv2.GaussianBlur(m, (0, 0), sigma)
    valid = (m > 0) & (wm > 1e-6)

    def blur(x: np.ndarray, old: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(x, np.float32)
        bx = cv2.GaussianBlur(x * m, (0, 0), sigma) / np.maximum(wm, 1e-6)
        return _smooth_and_gradient(np.where(valid, bx, old), 0.0)

    C = np.asarray(img.colours, np.float32)
    ism, grad = blur(C.mean(-1), np.asarray(img.intensity))
    ch, old = chromaticity(C), np.asarray(img.chroma)
    cs, cg = zip(*(blur(ch[..., k], old[..., k]) for k in range(2)), strict=True)
    f = np.float32
    return img._replace(
        intensity=jnp.asarray(ism, f),
        gradient=jnp.asarray(grad, f),
        chroma=jnp.asarray(np.stack(cs, -1), f),
        chroma_gradient=jnp.asarray(np.stack(cg, -2), f),
    )


def bilinear(img: Float[Array, "h w ..."], u, v):
    """Bilinear interpolation of ``img`` at pixel coordinates (u, v) (n,) and a mask of the
    points whose four neighbours lie inside the image."""
    h, w = img.shape[:2]
    u0, v0 = jnp.floor(u), jnp.floor(v)
    a, b = u - u0, v - v0
    inside = (u0 >= 0) & (u0 <= w - 2) & (v0 >= 0) & (v0 <= h - 2)
    i0 = jnp.clip(u0, 0, w - 2).astype(jnp.int32)
    j0 = jnp.clip(v0, 0, h - 2).astype(jnp.int32)
    ex = (slice(None),) + (None,) * (img.ndim - 2)
    a, b = a[ex], b[ex]
    val = (
        (1 - a) * (1 - b) * img[j0, i0]
        + a * (1 - b) * img[j0, i0 + 1]
        + (1 - a) * b * img[j0 + 1, i0]
        + a * b * img[j0 + 1, i0 + 1]
    )
    return val, inside


def photometric_channels(img: DepthImage, channels: str):
    """The (h, w, c) image and (h, w, c, 2) gradient used by the photometric term:
    ``"intensity"`` (grey level, c = 1) or ``"chromaticity"`` (r, g; c = 2)."""
    if channels == "intensity":
        return img.intensity[..., None], img.gradient[..., None, :]
    if channels == "chromaticity":
        return img.chroma, img.chroma_gradient
    raise ValueError(
        f"photometric channels must be 'intensity' or 'chromaticity', got {channels!r}"
    )


def masked_median(x: Float[Array, " n"], ok: Bool[Array, " n"], *, iters: int = 40):
    """Median of the non-negative values ``x[ok]`` (the mean of the two middle ones for an
    even count, as ``numpy.median``); NaN when nothing is selected. Found by bisection on
    the value (``iters`` passes counting ``x <= t``, O(n iters)): on a CPU, XLA's sort of
    8-16k values (``jnp.nanmedian``) cost ~15 ms, half of an ICP step; the bisection
    ~0.4 ms. After ``iters`` = 40 halvings of [0, max] the bracket is below float32
    resolution at the median for any median > max 2^-16, so the result is the order
    statistic itself."""
    x = jnp.where(ok, x, 0.0)
    n = jnp.sum(ok)
    k = jnp.stack([(n + 1) // 2, n // 2 + 1])  # equal for odd n
    lo = jnp.full(2, -1e-30, x.dtype)  # count(x <= lo) = 0 < k
    hi = jnp.full(2, jnp.max(x), x.dtype)  # count(x <= hi) = n >= k

    def body(_, c):
        lo, hi = c
        mid = 0.5 * (lo + hi)
        cnt = jnp.sum(ok[None, :] & (x[None, :] <= mid[:, None]), axis=1)
        up = cnt >= k
        return jnp.where(up, lo, mid), jnp.where(up, mid, hi)

    _, hi = jax.lax.fori_loop(0, iters, body, (lo, hi))
    return jnp.where(n > 0, 0.5 * (hi[0] + hi[1]), jnp.nan)


def photometric_terms(ps, i_src, tgt: DepthImage, w, pl, keep, channels: str = "intensity"):
    """Normal equations (H (6, 6), g (6,)) of the dense photometric residuals of
    :func:`photometric_rows`: ``sum wc J^T J`` and ``sum wc J^T r`` over points and channels."""
    J, wc, r = photometric_rows(ps, i_src, tgt, w, pl, keep, channels)
    return jnp.einsum("nc,nca,ncb->ab", wc, J, J), jnp.einsum("nc,nca,nc->a", wc, J, r)


def photometric_rows(ps, i_src, tgt: DepthImage, w, pl, keep, channels: str = "intensity"):
    """Jacobians J (n, c, 6), weights wc (n, c) and residuals r (n, c) of the dense
    photometric residuals
    ``r = I_t(pi(p)) - I_s`` (one per channel of :func:`photometric_channels`; ``i_src``
    (n, c)) of the transformed source points ``ps`` (Jacobian
    ``grad I_t . d pi / dp . [I, -hat(p)]``), each weighted by its pair weight ``w`` times
    ``(s_g / s_I)^2`` where s_g, s_I are robust scales (1.4826 x median absolute residual
    over the accepted pairs, all channels) of the point-to-plane and the photometric
    residuals: the two terms count in units of their own noise, no hand-set balance.
    Residuals beyond 3 s_I get a Gaussian down-weight (occlusions, specularities). Pairs
    need all four target pixels around pi(p) valid."""
    img, grad = photometric_channels(tgt, channels)
    u, v, front = project(ps, tgt.K)
    it, inside = bilinear(img, u, v)  # (n, c)
    gr, _ = bilinear(grad, u, v)  # (n, c, 2)
    mk, _ = bilinear(tgt.mask.astype(ps.dtype), u, v)
    ok = keep & front & inside & (mk > 0.999)
    r = it - i_src
    okc = jnp.broadcast_to(ok[:, None], r.shape).reshape(-1)
    s_i = 1.4826 * masked_median(jnp.abs(r).reshape(-1), okc) + 1e-4
    s_g = 1.4826 * masked_median(jnp.abs(pl), ok) + 1e-6
    s_i = jnp.where(jnp.isfinite(s_i), s_i, 1.0)
    s_g = jnp.where(jnp.isfinite(s_g), s_g, 1e-3)
    z = jnp.where(front, ps[:, 2], 1.0)[:, None]
    x, y = ps[:, 0:1], ps[:, 1:2]
    fx, fy = tgt.K[0, 0], tgt.K[1, 1]
    # d pi / dp: [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]
    gp = jnp.stack(
        [
            gr[..., 0] * fx / z,
            gr[..., 1] * fy / z,
            -(gr[..., 0] * fx * x + gr[..., 1] * fy * y) / z**2,
        ],
        -1,
    )  # (n, c, 3) = grad I . d pi / dp
    J = jnp.concatenate([gp, jnp.cross(ps[:, None, :], gp)], axis=-1)  # gp . [I, -hat(p)]
    wc = w[:, None] * jnp.exp(-(r**2) / (2 * (3 * s_i) ** 2)) * (s_g / s_i) ** 2
    wc = jnp.where(ok[:, None], wc, 0.0)
    r = jnp.where(ok[:, None], r, 0.0)
    return J, wc, r


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
    return _matches_indexed(T, src, tgt, radius, cfg, window)[:6]


def _matches_indexed(T, src: CloudArrays, tgt: DepthImage, radius, cfg: IcpConfig, window: int):
    """:func:`_matches` plus the flat target pixel index of each pair."""
    R, t = T[:3, :3], T[:3, 3]
    ps, ns = src.points @ R.T + t, src.normals @ R.T
    j, found = projective_correspondences(ps, src.colours, tgt, window, cfg.colour_scale)
    q = tgt.points.reshape(-1, 3)[j]
    nq = tgt.normals.reshape(-1, 3)[j]
    cq = tgt.colours.reshape(-1, 3)[j]
    w, pl, keep = pair_weights(ps, ns, src.colours, q, nq, cq, src.mask & found, radius, cfg)
    return ps, q, nq, w, pl, keep, j


def depth_sigma(z, cfg: IcpConfig):
    """Axial depth noise (m) of the sensor model in ``cfg`` at depth ``z`` (m)."""
    return cfg.depth_sigma0 + cfg.depth_sigma2 * (z - cfg.depth_z0) ** 2


def residual_variance(T, src_points, ps, q, nq, plane_var, f, cfg: IcpConfig):
    """Variance (m^2) of each pair's point-to-plane residual ``n . (p - q)`` (errors in
    variables): the target point's depth noise along its ray, ``sigma_z(z_q) n . q / z_q``,
    the source point's, ``source_noise_factor sigma_z(z_s) n . R p_s / z_s`` (``src_points``
    p_s in the source frame), the target normal's error ``normal_noise_gain sigma_z(z_q)
    f / z_q`` (rad; ``f`` the focal length in pixels) times the pair's offset in the
    tangent plane, and with ``cfg.noise_weight == "sensor+fit"`` the excess of the
    target's plane-fit residual variance ``plane_var`` (per pair) over its noise term."""
    zq = jnp.maximum(q[:, 2], 1e-3)
    zs = jnp.maximum(src_points[:, 2], 1e-3)
    st, ss = depth_sigma(zq, cfg), cfg.source_noise_factor * depth_sigma(zs, cfg)
    ct = jnp.sum(nq * q, -1) / zq
    cs = jnp.sum(nq * ((ps - T[:3, 3]) / zs[:, None]), -1)
    d = ps - q
    tan2 = jnp.sum(d**2, -1) - jnp.sum(d * nq, -1) ** 2
    sn = cfg.normal_noise_gain * st * f / zq
    var = (st * ct) ** 2 + (ss * cs) ** 2 + sn**2 * jnp.maximum(tan2, 0.0)
    if cfg.noise_weight == "sensor+fit":
        var = var + jnp.maximum(plane_var - (st * ct) ** 2, 0.0)
    return var


def noise_weights(T, src_points, ps, q, nq, w, j, tgt: DepthImage, cfg: IcpConfig):
    """The pair weights ``w`` of the geometric term with ``cfg.noise_weight`` applied: each
    times 1 / (its :func:`residual_variance`), rescaled so that ``sum(w)`` is unchanged
    (the balance against the colour term and a "fraction" keypoint balance stays; the
    "noise" keypoint balance follows the reweighted residual scale; equal variances give
    ``w``).
    ``"none"``: ``w``. ``j``: the flat target pixel of each pair."""
    if cfg.noise_weight == "none":
        return w
    if cfg.noise_weight not in ("sensor", "sensor+fit"):
        raise ValueError(
            f"noise_weight must be 'none', 'sensor' or 'sensor+fit', got {cfg.noise_weight!r}"
        )
    if tgt.plane_var is None and cfg.noise_weight == "sensor+fit":
        raise ValueError(
            "noise_weight 'sensor+fit' needs the target's plane_var "
            "(depth_image(..., plane_var=True), make_frame(..., plane_var=True))"
        )
    pv = 0.0 if tgt.plane_var is None else tgt.plane_var.reshape(-1)[j]
    f = jnp.sqrt(jnp.abs(tgt.K[0, 0] * tgt.K[1, 1]))
    var = residual_variance(T, src_points, ps, q, nq, pv, f, cfg)
    wn = w / jnp.maximum(var, 1e-14)
    return wn * (jnp.sum(w) / jnp.maximum(jnp.sum(wn), 1e-30))


def projective_icp_step(
    T: Mat4,
    radius,
    src: CloudArrays,
    tgt: DepthImage,
    cfg: IcpConfig,
    kp: Keypoints,
    window: int,
    i_src=None,
    channels: str = "intensity",
    photo_points=None,
) -> Mat4:
    """One weighted Gauss-Newton step with projective association (plus the photometric
    term when the source values ``i_src`` (n, c) of the photometric ``channels`` are
    given, evaluated at ``photo_points`` (n, 3) (source frame) if given, else at the source
    points); returns the new ``T``."""
    ps, q, nq, w, pl, keep, j = _matches_indexed(T, src, tgt, radius, cfg, window)
    extra = None
    if i_src is not None:
        pp = ps if photo_points is None else photo_points @ T[:3, :3].T + T[:3, 3]
        extra = photometric_terms(pp, i_src, tgt, w, pl, keep, channels)
    w = noise_weights(T, src.points, ps, q, nq, w, j, tgt, cfg)
    return gauss_newton_update(T, ps, q, nq, w, pl, cfg, kp, extra)


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
    src_image: DepthImage | None = None,
    photometric: str = "intensity",
    photo_points: Float[Array, "n 3"] | None = None,
) -> IcpResult:
    """Register the source cloud ``src`` (any padded sample of a view, camera frame) to the
    organised target view ``tgt`` from ``T0`` (target <- source), optionally with matched
    keypoints: ``cfg.iterations`` steps with the correspondence radius shrinking
    geometrically from ``cfg.max_dist`` to ``cfg.min_dist``, as :func:`icp`; with
    ``cfg.tol_rotation`` / ``cfg.tol_translation`` > 0 (``DEFAULT_ICP``) it stops at
    convergence instead (a step smaller than both jumps to the final radius; one there
    ends the loop; at most ``cfg.iterations`` steps). Pure,
    jit-able (``window`` static). With ``src_image`` (the organised source view the
    points were sampled from) a dense photometric term (:func:`photometric_terms` on the
    ``photometric`` channels, "intensity" or "chromaticity") joins the point-to-plane and
    keypoint terms: it constrains the directions along which the geometry slides (planes,
    cylinders) with every textured pixel. With ``cfg.degeneracy_ratio > 0`` it acts in the
    geometry's degenerate directions only (:func:`jaxcr.registration.icp.gauss_newton_update`).
    ``photo_points`` (n, 3), optional: the source pixels' denoised positions
    (:func:`jaxcr.registration.clouds.plane_points`, same rows as ``src``) at which the
    photometric term predicts where each source pixel lands in the target image. A pixel's
    raw depth noise sigma moves that prediction along the epipolar line by about
    f sigma sin(angle between the rays) / z; near the target's silhouette the shifts that
    leave the valid region are dropped and the others kept, so on a wide baseline the
    surviving samples are shifted one way: a systematic pull along the colour term's own
    direction (a can's axis rotation). The geometric term uses ``src.points`` as given:
    :func:`jaxcr.registration.pairwise.geometric_sample` chooses raw or denoised positions
    (the pipeline uses denoised ones: raw points bias the geometric term too).
    """
    kp = no_keypoints() if kp is None else kp
    i_src = None
    if src_image is not None:
        u, v, _ = project(src.points, src_image.K)
        i_src, _ = bilinear(photometric_channels(src_image, photometric)[0], u, v)
    n = cfg.iterations
    ratio = (cfg.min_dist / cfg.max_dist) ** (1.0 / max(n - 1, 1))
    T0 = T0.astype(src.points.dtype)
    if cfg.tol_rotation <= 0 and cfg.tol_translation <= 0:

        def body(k, T):
            radius = cfg.max_dist * ratio ** jnp.minimum(k, n - 1)
            return projective_icp_step(
                T, radius, src, tgt, cfg, kp, window, i_src, photometric, photo_points
            )

        T = jax.lax.fori_loop(0, n, body, T0)
        return projective_evaluate(T, src, tgt, cfg, window)
    T, _ = coarse_to_fine_icp(T0, src, tgt, cfg, kp, window, i_src, photometric, photo_points)
    return projective_evaluate(T, src, tgt, cfg, window)


def strided_rows(x, stride: int):
    """Every ``stride``-th row of each array in ``x`` (an array, a NamedTuple of arrays or
    None)."""
    if x is None or stride <= 1:
        return x
    return jax.tree_util.tree_map(lambda a: a[::stride], x)


def coarse_to_fine_icp(T0, src, tgt, cfg, kp, window, i_src, photometric, photo_points):
    """:func:`_converging_icp`, with ``cfg.coarse_stride`` > 1 in two stages: the whole
    radius schedule to convergence on every ``coarse_stride``-th source row (its source
    values ``i_src`` and ``photo_points`` alike), then the full sample from that pose at
    the final radius ``min_dist`` until converged; ``cfg.iterations`` steps at most over
    both stages, one full-sample step at least. Returns (T, (coarse steps, fine steps))."""
    s = int(cfg.coarse_stride)
    if s <= 1:
        T, steps = _converging_icp(T0, src, tgt, cfg, kp, window, i_src, photometric, photo_points)
        return T, (jnp.int32(0), steps)
    sub = [strided_rows(a, s) for a in (src, i_src, photo_points)]
    loose = dataclasses.replace(
        cfg,
        tol_rotation=cfg.tol_rotation * cfg.coarse_tol_factor,
        tol_translation=cfg.tol_translation * cfg.coarse_tol_factor,
    )
    T1, n1 = _converging_icp(T0, sub[0], tgt, loose, kp, window, sub[1], photometric, sub[2])
    budget = jnp.maximum(cfg.iterations - n1, 1)
    T, n2 = _converging_icp(
        T1,
        src,
        tgt,
        cfg,
        kp,
        window,
        i_src,
        photometric,
        photo_points,
        k0=cfg.iterations - 1,
        max_steps=budget,
    )
    return T, (n1, n2)


def pose_update(T_old: Mat4, T_new: Mat4) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Size of the left update ``T_new T_old^-1``: (sin of its rotation angle (rad for
    small angles; from the skew part, exact near 0 in float32 unlike arccos of the trace),
    norm of its translation (m))."""
    dR = T_new[:3, :3] @ T_old[:3, :3].T
    w = jnp.stack([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
    dt = T_new[:3, 3] - dR @ T_old[:3, 3]
    return 0.5 * jnp.sqrt(jnp.sum(w**2)), jnp.sqrt(jnp.sum(dt**2))


def _converging_icp(
    T0, src, tgt, cfg, kp, window, i_src, photometric, photo_points, k0=0, max_steps=None
):
    """The ICP of :func:`projective_icp` with ``cfg``'s convergence stop
    (:class:`jaxcr.registration.icp.IcpConfig`): the radius schedule in a ``while_loop``
    from its ``k0``-th radius; a converged step jumps to the final radius ``min_dist``, a
    converged step there ends it, ``max_steps`` (default ``cfg.iterations``) steps at most.
    Returns (T, number of steps)."""
    n = cfg.iterations
    ratio = (cfg.min_dist / cfg.max_dist) ** (1.0 / max(n - 1, 1))
    limit = n if max_steps is None else max_steps

    def cond(c):
        k, it, T, done = c
        return (~done) & (it < limit)

    def body(c):
        k, it, T, _ = c
        radius = cfg.max_dist * ratio**k
        T1 = projective_icp_step(
            T, radius, src, tgt, cfg, kp, window, i_src, photometric, photo_points
        )
        dr, dt = pose_update(T, T1)
        conv = (dr <= cfg.tol_rotation) & (dt <= cfg.tol_translation)
        done = conv & (k >= n - 1)
        k = jnp.where(conv, n - 1, jnp.minimum(k + 1, n - 1))
        return k, it + 1, T1, done

    init = (jnp.int32(k0), jnp.int32(0), T0, jnp.asarray(False))
    _, steps, T, _ = jax.lax.while_loop(cond, body, init)
    return T, steps


projective_icp_jit = jax.jit(projective_icp, static_argnames=("window", "photometric"))


def projective_information(
    T: Mat4,
    src: CloudArrays,
    tgt: DepthImage,
    cfg: IcpConfig = DEFAULT_ICP,
    kp: Keypoints | None = None,
    window: int = 0,
    src_image: DepthImage | None = None,
    photometric: str = "intensity",
    photo_points: Float[Array, "n 3"] | None = None,
) -> tuple[Float[Array, "6 6"], Float[Array, ""]]:
    """Information matrix (6, 6) of a registration ``T`` (target <- source) found by
    :func:`projective_icp` with the same arguments: the Gauss-Newton normal matrix ``H``
    of its weighted objective at ``T`` (matches within ``cfg.min_dist``; point-to-plane,
    keypoint and photometric terms, degeneracy split; :func:`normal_equations`) divided by
    ``s^2``, the weighted mean squared point-to-plane residual (m^2): the usual
    least-squares covariance ``s^2 H^-1`` of the estimate, on the left perturbation
    ``T <- [exp(hat(w)), v] T`` in the target frame, order (v, w), units 1/m^2, 1/rad^2.
    Returns (information, s (m)). It assumes independent residuals, so it is optimistic in
    absolute terms (systematic errors do not average out); its use is the *relative*
    weight of registrations of different overlap and texture in a pose graph. Pure,
    jit-able."""
    kp = no_keypoints() if kp is None else kp
    ps, q, nq, w, pl, keep, j = _matches_indexed(T, src, tgt, cfg.min_dist, cfg, window)
    extra = None
    if src_image is not None:
        u, v, _ = project(src.points, src_image.K)
        i_src, _ = bilinear(photometric_channels(src_image, photometric)[0], u, v)
        pp = ps if photo_points is None else photo_points @ T[:3, :3].T + T[:3, 3]
        extra = photometric_terms(pp, i_src, tgt, w, pl, keep, photometric)
    w = noise_weights(T, src.points, ps, q, nq, w, j, tgt, cfg)
    H, _ = normal_equations(T, ps, q, nq, w, pl, cfg, kp, extra)
    s2 = jnp.sum(w * pl**2) / jnp.maximum(jnp.sum(w), 1e-30)
    s2 = jnp.maximum(s2, 1e-12)
    return 0.5 * (H + H.T) / s2, jnp.sqrt(s2)


projective_information_jit = jax.jit(
    projective_information, static_argnames=("window", "photometric")
)
