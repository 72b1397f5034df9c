"""What the images cannot see: a Laplace covariance of the refined shape and the tip.

After :func:`jaxcr.segmentation.refine.refine_frame` has converged, the curvature of the
region energy at its optimum says how well the images pin down each combination of the
delta-u coefficients (:mod:`jaxcr.segmentation.shape`). This module turns that curvature into
a covariance (a Laplace approximation) and propagates it through the forward kinematics to
the tip, then splits the tip's 1-sigma uncertainty, for every camera, into the part along the
optical axis (depth, which a single view barely sees) and the part in the image plane
(metres and pixels). The derivation, the assumptions under which the Chan-Vese energy
is read as a likelihood, and the measured calibration are in ``docs/uncertainty.md``.

Summary of the model (``docs/uncertainty.md`` eq. U1-U5):

* negative log-likelihood of the images, per camera c, with per-channel noise variance
  ``sigma_c^2`` estimated from the residual energy at the optimum
  (:func:`jaxcr.segmentation.energy.residual_variance` / 3)::

      NLL(theta) = sum_c [g_in e_in + g_out e_out + g_pen v_c e_pen](theta) / (2 sigma_c^2)

  with ``v_c`` the colour variance that the solver's objective uses to weigh the
  background-overlap penalty against the data terms;
* ``H = d^2 NLL / d theta^2`` over the flattened delta-u coefficients theta, at the refined
  theta, on the energy of the solver's last solve (its finest pyramid level, soft silhouette
  temperature and band) with the camera-pose corrections held at their estimates;
* the shape prior (``g_reg``) is *not* in ``H``: it is a tuning weight, not a calibrated prior,
  and scaled as a likelihood it would claim a certainty the images do not give;
* ``Cov(theta) = H^+`` (pseudo-inverse over eigenvalues above ``rcond`` times the largest);
  directions below that (or of negative curvature) are unobservable, and any tip quantity
  they move gets an infinite sigma;
* ``Cov(tip) = J Cov(theta) J^T`` with ``J = d tip / d theta`` through the forward kinematics
  (:func:`jaxcr.segmentation.shape.perturbed_centreline`).

Everything here is pure and jit-compatible; :func:`shape_uncertainty` handles one frame,
:func:`shape_uncertainty_batch` a batch (one compiled call, ``lax.map``), computed once per
frame after convergence, outside the solver loop.

Usage::

    res = refine_frame(base, cams, imgs, bgs, cfg)
    unc = shape_uncertainty(base, cams, imgs, bgs, cfg, res.coeffs, res.camera_correction)
    unc.sigma_depth      # (n_cameras,) 1-sigma tip uncertainty along each optical axis, m
    unc.sigma_px         # (n_cameras,) worst 1-sigma uncertainty of the projected tip, px
    unc.sigma_lateral    # (n_cameras,) the same in metres at the tip's depth
    depth_ambiguous(unc, DEPTH_FACTOR)   # the frame's warning flag
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.camera import Camera, project_points
from jaxcr.geometry import so3_exp
from jaxcr.kinematics.cosserat import Centreline
from jaxcr.segmentation.energy import (
    pyramid,
    region_data_from_level,
    region_terms,
    residual_variance,
    soft_band,
)
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.silhouette import level_tube, project_tube, select_band

#: default warning factor: a frame is flagged when, for some camera, the 1-sigma tip
#: uncertainty along the optical axis exceeds this many times the worst one in the image
#: plane (``docs/uncertainty.md``, "The warning factor": a stereo pair of vergence angle
#: ``a`` gives about ``1 / sin(a)`` by triangulation, so 3 flags rigs under ~20 degrees and
#: every single view of a tube bending across it).
DEPTH_FACTOR = 3.0

#: relative eigenvalue threshold of the pseudo-inverse (see :func:`laplace_covariance`)
RCOND = 1e-5

#: a null direction "moves" a tip quantity when it moves it by more than this fraction of
#: the tip's largest motion per unit coefficient (float32 eigenvector noise is far below)
LEAK_TOL = 1e-3


class ShapeUncertainty(eqx.Module):
    """Laplace covariance of one refined frame (arrays gain a leading axis in batches).

    Attributes:
        hessian: (n, n) Gauss-Newton Hessian (information matrix) of the image negative
            log-likelihood w.r.t. the flattened delta-u coefficients (row-major (a, k)), at
            the refined coefficients (:func:`fisher_matrix`).
        eigvals: (n,) eigenvalues, ascending, of the information matrix scaled to unit
            diagonal (:func:`laplace_covariance`).
        cov_coeffs: (n, n) pseudo-inverse covariance of the coefficients (the finite part;
            unobservable directions contribute zero here and infinity to the sigmas).
        null_dims: number of unobservable directions (eigenvalue <= ``rcond`` x largest).
        noise_std: (n_cameras,) per-channel colour noise std (RGB in [0, 1]) estimated from
            the residual energy.
        tip: (3,) refined tip position, robot frame, m.
        tip_jacobian: (3, n) d tip / d coefficients, m per unit coefficient.
        tip_cov: (3, 3) finite part of the tip covariance, robot frame, m^2.
        tip_null: (3, n) tip motion (m) per unit step along each unobservable direction of
            the coefficients (zero columns for the observable ones): a tip direction d has an
            infinite sigma when ``|d^T tip_null|`` exceeds :data:`LEAK_TOL` times
            ``|tip_jacobian|``.
        sigma_depth: (n_cameras,) 1-sigma tip uncertainty along each camera's optical axis
            (m; inf when unobservable).
        sigma_px: (n_cameras,) largest 1-sigma uncertainty of the projected tip in each
            image (square root of the larger eigenvalue of its 2x2 pixel covariance), px; inf
            when unobservable.
        sigma_lateral: (n_cameras,) the same in metres at the tip's depth Z:
            ``sigma_px * Z / sqrt(fx fy)`` (a motion along the viewing ray counts as depth,
            not as image-plane motion).
        depth_ratio: (n_cameras,) ``sigma_depth / sigma_lateral`` (inf when only the depth is
            unbounded, nan when both are).
    """

    hessian: Float[Array, "n n"]
    eigvals: Float[Array, " n"]
    cov_coeffs: Float[Array, "n n"]
    null_dims: Int[Array, ""]
    noise_std: Float[Array, " c"]
    tip: Float[Array, " 3"]
    tip_jacobian: Float[Array, "3 n"]
    tip_cov: Float[Array, "3 3"]
    tip_null: Float[Array, "3 n"]
    sigma_depth: Float[Array, " c"]
    sigma_lateral: Float[Array, " c"]
    sigma_px: Float[Array, " c"]
    depth_ratio: Float[Array, " c"]


def corrected_cameras(
    cameras: tuple[Camera, ...], correction: Float[Array, "c 6"]
) -> tuple[Camera, ...]:
    """Cameras moved by :attr:`RefineResult.camera_correction` (per camera: rotation vector w
    (rad) about the optical centre, translation d (m); ``X_cam' = exp(w) X_cam + d``), which
    is what the refinement's masks were drawn with (both correction modes)."""
    out = []
    for i, cam in enumerate(cameras):
        E = so3_exp(correction[i, :3])
        T = cam.T_cam_robot
        top = jnp.concatenate([E @ T[:3, :3], (E @ T[:3, 3] + correction[i, 3:])[:, None]], 1)
        T2 = jnp.concatenate([top, T[3:]], axis=0)
        out.append(eqx.tree_at(lambda c: c.T_cam_robot, cam, T2))
    return tuple(out)


def fisher_matrix(
    base, cameras, images, backgrounds, config, coeffs, camera_correction, sizes=None, nums=None
) -> tuple[Float[Array, "n n"], Float[Array, " c"], Float[Array, " 3"], Float[Array, "3 n"]]:
    """Gauss-Newton information matrix of the flat delta-u coefficients
    (``docs/uncertainty.md`` eq. U2), the per-camera per-channel noise variances, and the
    tip (robot frame, m) with its Jacobian (m per unit coefficient), which share the one
    forward-mode pass through the kinematics.

    The image model behind it: every full-resolution pixel p of camera c is the soft
    silhouette ``s_p(theta)`` (the solver's sigmoid of the capsule margin, temperature
    ``config.tau[-1]``) blended between the region colours, ``I_p = mu_out + s_p (mu_in -
    mu_out) + n_p`` with white Gaussian noise of per-channel variance ``sigma_c^2``, whose
    Gauss-Newton (Fisher) matrix is ``sum_p |mu_in - mu_out|^2 grad s_p grad s_p^T /
    sigma_c^2``. Pixels of the background mask B carry no colour; the solver charges
    ``g_pen v_c`` per unit of silhouette on them (``v_c`` the colour variance normalising
    its data terms), and they enter with that squared contrast in place of ``|mu_in -
    mu_out|^2``. ``mu_in``, ``mu_out`` (band-local if ``config.local``) and ``sigma_c^2``
    (:func:`jaxcr.segmentation.energy.residual_variance` / 3) are taken at ``coeffs``, the
    camera corrections are held fixed, the band is selected at ``coeffs``. Only band pixels
    have a non-zero ``grad s_p``.

    ``sizes`` (n_cameras, 2) int: the real (height, width) of images padded to the cameras'
    larger size (shape buckets, :func:`jaxcr.segmentation.refine.refine_frame`'s ``sizes``):
    the padded pixels weigh nothing and never enter the band.

    ``nums``: ``config``'s numeric settings as arrays when ``config`` holds placeholders
    (:func:`jaxcr.segmentation.refine._traced_apart`, traced by :func:`shape_uncertainty_batch`).
    """
    if nums is None:
        tau, robust, g_pen = config.tau[-1], config.robust, config.g_pen
    else:  # Welsch (robust > 0) or quadratic: structural, kept in the placeholders
        tau, g_pen = nums.tau[-1], nums.g_pen
        robust = nums.robust if config.robust > 0 else 0.0
    shape = config.coeff_shape
    cams = corrected_cameras(cameras, camera_correction)
    real = _real_sizes(sizes, len(cameras))
    datas = tuple(
        region_data_from_level(*pyramid(im, bg, 1, _valid(im.shape[:2], sz))[0], 0, config.tile)
        for im, bg, sz in zip(images, backgrounds, real, strict=True)
    )
    flat0 = jax.lax.stop_gradient(coeffs.reshape(-1))

    def tubes_of(cl):
        return tuple(
            level_tube(project_tube(c, cl, size=sz), 0, config.seg_merge)
            for c, sz in zip(cams, real, strict=True)
        )

    def tubes(flat):
        return tubes_of(perturbed_centreline(base, flat.reshape(shape), config.torsion))

    def band_of(t, d, sz):
        k = config.tiles_at(0)
        if sz is None:
            return select_band(t, d.grid, k, config.k_seg)
        rr, cr = ((x + config.tile - 1) // config.tile for x in sz)
        row = jnp.arange(d.grid.n_tiles) // d.grid.cols
        col = jnp.arange(d.grid.n_tiles) % d.grid.cols
        return select_band(
            t, d.grid, k, config.k_seg, (row < rr) & (col < cr), jnp.minimum(k, rr * cr)
        )

    bands = tuple(band_of(t, d, sz) for t, d, sz in zip(tubes(flat0), datas, real, strict=True))

    def forward(flat):
        cl = perturbed_centreline(base, flat.reshape(shape), config.torsion)
        ts = tubes_of(cl)
        softs = tuple(
            soft_band(t, band, d.grid, tau) for t, band, d in zip(ts, bands, datas, strict=True)
        )
        return cl.p[-1], softs

    tip, s0s = forward(flat0)
    tip_jac, jacs = jax.jacfwd(forward)(flat0)  # (3, n); per camera (k, p, n)
    eps = 1e-6
    info = jnp.zeros((flat0.size, flat0.size), flat0.dtype)
    sig2 = []
    for soft, js, band, d in zip(s0s, jacs, bands, datas, strict=True):
        bw, bb, img = d.gather(band.tiles)
        if band.active is not None:  # slots past the real image's band weigh nothing
            act = band.active.astype(bw.dtype)[:, None]
            bw, bb = bw * act, bb * act
        ins = band.inside.astype(soft.dtype)
        w_in = bw * soft
        s0 = jnp.sum(w_in) + jnp.dot(ins, d.tile_w)
        s1 = jnp.einsum("kp,kpc->c", w_in, img) + ins @ d.tile_s1
        mu_in = s1 / jnp.maximum(s0, eps)
        if config.local:
            w_out = bw * (1.0 - soft)
            mu_out = jnp.einsum("kp,kpc->c", w_out, img) / jnp.maximum(jnp.sum(w_out), eps)
        else:
            mu_out = (d.total_s1 - s1) / jnp.maximum(d.total_w - s0, eps)
        t = region_terms(soft, band, d, config.local, robust)
        s2 = residual_variance(
            {"e_in": t.e_in, "e_out": t.e_out, "area_in": t.area_in, "area_out": t.area_out}
        )
        s2 = jnp.maximum(s2 / 3.0, 1e-10)
        v = d.total_s2 / jnp.maximum(d.total_w, eps)
        contrast = bw * jnp.sum((mu_in - mu_out) ** 2) + bb * g_pen * v  # (k, p)
        info = info + jnp.einsum("kp,kpi,kpj->ij", contrast, js, js) / s2
        sig2.append(s2)
    return jax.lax.stop_gradient((info, jnp.stack(sig2), tip, tip_jac))


def _real_sizes(sizes, n_cam: int) -> tuple:
    if sizes is None:
        return (None,) * n_cam
    sizes = jnp.asarray(sizes, jnp.int32).reshape(n_cam, 2)
    return tuple((sizes[k, 0], sizes[k, 1]) for k in range(n_cam))


def _valid(shape, sz):
    if sz is None:
        return None
    return (jnp.arange(shape[0])[:, None] < sz[0]) & (jnp.arange(shape[1])[None, :] < sz[1])


def laplace_covariance(
    info: Float[Array, "n n"], rcond: float = RCOND
) -> tuple[Float[Array, " n"], Float[Array, "n n"], Float[Array, "n n"], Bool[Array, " n"]]:
    """Pseudo-inverse of a symmetric positive semi-definite information matrix.

    The matrix is first scaled to unit diagonal (``D = diag(info)^-1/2``, Jacobi scaling):
    coefficients that move the silhouette a lot and ones that barely move it differ in
    curvature by 1e6 or more, and float32 ``eigh`` resolves eigenvalues only to about
    ``eps * max eigenvalue``; after scaling each coefficient's own curvature is 1.
    Eigenvalues of the scaled matrix ``<= rcond`` times its largest (flat or, from rounding,
    negative curvature, a coefficient that does not move the silhouette at all, or a
    non-finite matrix) are unobservable. ``rcond = 1e-5`` is about 100 float32 epsilons.

    Returns:
        ``(eigvals, null_dirs, cov, null)``: the scaled matrix's ascending eigenvalues, the
        (n, n) directions in coefficient space of its eigenvectors (columns ``D v``, unit
        norm), the finite covariance ``D V diag(1/lambda on the observable set) V^T D`` and
        the (n,) bool mask of unobservable directions.
    """
    h = 0.5 * (info + info.T)
    finite = jnp.all(jnp.isfinite(h))
    h = jnp.where(finite, h, jnp.eye(h.shape[0], dtype=h.dtype))
    diag = jnp.diagonal(h)
    top_diag = jnp.max(diag)
    used = diag > 1e-12 * jnp.maximum(top_diag, 1e-30)  # coefficients that move anything
    dinv = jnp.where(used, 1.0 / jnp.sqrt(jnp.where(used, diag, 1.0)), 0.0)
    hs = h * dinv[:, None] * dinv[None, :]
    hs = jnp.where(used[:, None] & used[None, :], hs, jnp.eye(h.shape[0], dtype=h.dtype))
    lam, vec = jnp.linalg.eigh(hs)
    # a coefficient that moves nothing is a unit eigenvector with eigenvalue 1 above: unused
    unused_vec = jnp.abs(vec.T) @ (~used).astype(h.dtype) > 0.5
    top = lam[-1]
    keep = finite & (top > 0) & (lam > rcond * top) & ~unused_vec
    inv = jnp.where(keep, 1.0 / jnp.where(keep, lam, 1.0), 0.0)
    cov_s = (vec * inv) @ vec.T
    cov = cov_s * dinv[:, None] * dinv[None, :]
    dirs = jnp.where(used[:, None], dinv[:, None] * vec, vec)
    dirs = dirs / jnp.maximum(jnp.linalg.norm(dirs, axis=0, keepdims=True), 1e-30)
    lam = jnp.where(finite, lam, jnp.nan)
    return lam, dirs, cov, ~keep


def _sigma_of(A, tip_jac, cov, vec, null):
    """Largest 1-sigma of the linear tip map ``A`` (k x 3, k = 1 or 2) and whether an
    unobservable direction moves it (then inf)."""
    M = A @ tip_jac  # (k, n)
    C = M @ cov @ M.T
    if C.shape[0] == 1:
        var = C[0, 0]
    else:
        a, b, c = C[0, 0], C[0, 1], C[1, 1]
        var = 0.5 * (a + c) + jnp.sqrt(0.25 * (a - c) ** 2 + b * b)
    leak = jnp.sqrt(jnp.sum(jnp.where(null[None, :], M @ vec, 0.0) ** 2))
    scale = jnp.sqrt(jnp.sum(tip_jac * tip_jac)) * jnp.sqrt(jnp.sum(A * A))
    unbounded = leak > LEAK_TOL * scale
    return jnp.where(unbounded, jnp.inf, jnp.sqrt(jnp.maximum(var, 0.0)))


def shape_uncertainty(
    base: Centreline,
    cameras: Camera | tuple[Camera, ...],
    images,
    backgrounds,
    config,
    coeffs: Float[Array, "a k"],
    camera_correction: Float[Array, "c 6"] | None = None,
    *,
    rcond: float = RCOND,
    sizes=None,
    nums=None,
) -> ShapeUncertainty:
    """Laplace covariance of a refined frame and its tip (module docstring).

    Args:
        base: the nominal centreline the frame was refined from (robot frame, m).
        cameras, images, backgrounds: as given to
            :func:`jaxcr.segmentation.refine.refine_frame` (one or a tuple per camera).
        config: the :class:`jaxcr.segmentation.refine.RefineConfig` of the refinement.
        coeffs: (a, k) refined delta-u coefficients (:attr:`RefineResult.coeffs`).
        camera_correction: (n_cameras, 6) :attr:`RefineResult.camera_correction` (held
            fixed); None = zeros.
        rcond: relative eigenvalue threshold of the pseudo-inverse
            (:func:`laplace_covariance`).
        sizes: (n_cameras, 2) real (height, width) of images padded to the cameras' larger
            size (shape buckets; :func:`fisher_matrix`); None = unpadded.
        nums: (private) the config's numeric settings as arrays (:func:`fisher_matrix`).

    Returns:
        :class:`ShapeUncertainty`.
    """
    as_t = lambda x: tuple(x) if isinstance(x, (tuple, list)) else (x,)  # noqa: E731
    cameras, images, backgrounds = as_t(cameras), as_t(images), as_t(backgrounds)
    dtype = base.p.dtype
    n_cam = len(cameras)
    corr = (
        jnp.zeros((n_cam, 6), dtype)
        if camera_correction is None
        else jnp.asarray(camera_correction, dtype).reshape(n_cam, 6)
    )
    coeffs = jnp.asarray(coeffs, dtype).reshape(config.coeff_shape)
    H, sigma2, tip, Jt = fisher_matrix(
        base, cameras, images, backgrounds, config, coeffs, corr, sizes, nums
    )
    real = _real_sizes(sizes, n_cam)
    lam, vec, cov, null = laplace_covariance(H, rcond)

    tip_cov = Jt @ cov @ Jt.T
    tip_cov = 0.5 * (tip_cov + tip_cov.T)  # exact symmetry (rounding of V diag V^T)
    tip_null = jnp.where(null[None, :], Jt @ vec, 0.0)

    cams = corrected_cameras(cameras, corr)
    depth, lat, px = [], [], []

    def tip_px(p, cam, sz):
        uv = project_points(cam, p[None])[0][0]
        if sz is None:
            return uv
        # clamped to the real image's box, as a camera of that size clamps (project_xy)
        lim = jnp.stack([sz[1], sz[0]]).astype(uv.dtype)
        return jnp.clip(uv, -lim, 2.0 * lim)

    for cam, sz in zip(cams, real, strict=True):
        depth.append(_sigma_of(cam.R[2:3], Jt, cov, vec, null))
        Juv = jax.jacfwd(lambda p, cam=cam, sz=sz: tip_px(p, cam, sz))(tip)
        spx = _sigma_of(Juv, Jt, cov, vec, null)
        px.append(spx)
        # image plane in metres: the pixel sigma at the tip's depth (a motion along the
        # viewing ray is depth, not image-plane motion, even off the optical axis)
        z = jnp.maximum(tip @ cam.R[2] + cam.t[2], 1e-6)
        lat.append(spx * z / jnp.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    depth, lat, px = jnp.stack(depth), jnp.stack(lat), jnp.stack(px)
    ratio = depth / jnp.where(jnp.isinf(lat) | (lat <= 0), 1.0, lat)
    ratio = jnp.where(lat <= 0, jnp.where(depth > 0, jnp.inf, 1.0), ratio)
    ratio = jnp.where(jnp.isinf(lat), jnp.where(jnp.isinf(depth), jnp.nan, 0.0), ratio)
    return ShapeUncertainty(
        hessian=H,
        eigvals=lam,
        cov_coeffs=cov,
        null_dims=jnp.sum(null).astype(jnp.int32),
        noise_std=jnp.sqrt(sigma2),
        tip=tip,
        tip_jacobian=Jt,
        tip_cov=tip_cov,
        tip_null=tip_null,
        sigma_depth=depth,
        sigma_lateral=lat,
        sigma_px=px,
        depth_ratio=ratio,
    )


def depth_ambiguous(unc: ShapeUncertainty, factor: float = DEPTH_FACTOR) -> Bool[Array, "..."]:
    """The frame's warning flag: for some camera the depth sigma exceeds ``factor`` times the
    image-plane sigma, or the depth is unbounded (works on a batch: leading axes kept)."""
    flag = (unc.sigma_depth > factor * unc.sigma_lateral) | jnp.isinf(unc.sigma_depth)
    return jnp.any(flag, axis=-1)


@eqx.filter_jit
def _batch_jit(bases, cameras, images, backgrounds, config, coeffs, corrections, rcond, sizes=None):
    config, nums = config  # placeholders and traced numeric settings (_traced_apart)

    def one(args):
        base, ims, bgs, c, corr = args
        return shape_uncertainty(
            base, cameras, ims, bgs, config, c, corr, rcond=rcond, sizes=sizes, nums=nums
        )

    return jax.lax.map(one, (bases, images, backgrounds, coeffs, corrections))


def shape_uncertainty_batch(
    bases: Centreline,
    cameras,
    images,
    backgrounds,
    config,
    coeffs: Float[Array, "f a k"],
    camera_corrections: Float[Array, "f c 6"] | None = None,
    *,
    rcond: float = RCOND,
    jit_call=None,
    shape_buckets: bool = False,
) -> ShapeUncertainty:
    """:func:`shape_uncertainty` of F frames in one compiled call (arguments as
    :func:`jaxcr.segmentation.refine.refine_batch`, plus the results' ``coeffs`` and
    ``camera_correction`` with a leading frame axis). ``jit_call``: how the compiled function
    is called, ``jit_call(fn, *args)``; None calls ``fn(*args)``
    (``jaxcr.io.exported.cached_call``: as ``refine_batch``'s). ``shape_buckets``: images
    padded to a larger shape than the cameras', as ``refine_batch``'s."""
    from jaxcr.segmentation.refine import _traced_apart, bucket_cameras

    as_t = lambda x: tuple(x) if isinstance(x, (tuple, list)) else (x,)  # noqa: E731
    cameras, images, backgrounds = as_t(cameras), as_t(images), as_t(backgrounds)
    f = bases.p.shape[0]
    if camera_corrections is None:
        camera_corrections = jnp.zeros((f, len(cameras), 6), bases.p.dtype)
    cameras, sizes = bucket_cameras(cameras, images, shape_buckets)
    # the config's numeric settings traced: one program for configs differing only in them
    # (e.g. `jaxcr segment --prior-weight`, which this covariance does not even read)
    config = _traced_apart(config, bases.p.dtype)
    args = (bases, cameras, images, backgrounds, config, coeffs, camera_corrections, float(rcond))
    args = args + (() if sizes is None else (sizes,))
    return _batch_jit(*args) if jit_call is None else jit_call(_batch_jit, *args)
