"""Weighted ICP (paper Sec. IV.A, ref. [33]) for coloured point clouds with normals.

Correspondences: nearest neighbour of each transformed source point in the joint space
(position, ``colour_scale`` x RGB), so that colour keeps textured surfaces from sliding along
their flat or cylindrical directions. Each pair gets the weight the paper describes, a
product of four factors:

    w = exp(-d^2 / 2 sd^2) * exp(-|c_s - c_t|^2 / 2 sc^2) * max(n_s . n_t, 0)
        * exp(-((p_s - p_t) . n_t)^2 / 2 sp^2),

and zero beyond ``max_dist`` or when the normals differ by more than 60 degrees. One step
is a damped Gauss-Newton step of the weighted point-to-plane objective plus
``point_weight`` x point-to-point (which fixes directions the planes leave free), applied as
``T <- [exp(w^), v] T``. A fixed number of iterations (``lax.fori_loop``) with a
correspondence radius shrinking geometrically from ``max_dist`` to ``min_dist``.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from jaxcr._types import Array, Bool, Float, Mat4
from jaxcr.geometry import hat, make_transform, so3_exp


class IcpConfig(eqx.Module):
    iterations: int = eqx.field(static=True, default=30)
    max_dist: float = eqx.field(static=True, default=0.02)
    min_dist: float = eqx.field(static=True, default=0.004)
    sigma_dist: float = eqx.field(static=True, default=0.005)
    sigma_colour: float = eqx.field(static=True, default=0.2)
    sigma_plane: float = eqx.field(static=True, default=0.003)
    colour_scale: float = eqx.field(static=True, default=0.01)
    point_weight: float = eqx.field(static=True, default=0.0)
    damping: float = eqx.field(static=True, default=1e-6)
    keypoint_weight: float = eqx.field(static=True, default=0.3)
    sigma_keypoint: float = eqx.field(static=True, default=0.005)
    # Degeneracy-aware geometric term (:func:`degeneracy_filter`; 0 = off, the paper's plain
    # weighted ICP): directions whose eigenvalue is below this fraction of the largest, i.e.
    # observed 10x worse (in standard deviation) than the best one at 0.01, are taken from
    # the keypoint / photometric terms only. On in DEFAULT_ICP (pairwise registration).
    degeneracy_ratio: float = eqx.field(static=True, default=0.0)
    # Balance of the keypoint term against the dense term (:func:`normal_equations`):
    # "fraction" (the keypoints' total weight is ``keypoint_weight`` x the dense total
    # weight, a hand-set share) or "noise" (each keypoint residual weighted by its inverse
    # variance in the units of the dense residuals, ``keypoint_weight`` x s_g^2 / s_k^2:
    # s_g^2 the weighted mean squared point-to-plane residual, s_k the keypoints' robust
    # scale; no hand-set share, like the photometric term's balance).
    keypoint_balance: str = eqx.field(static=True, default="fraction")
    # Convergence stop of the projective ICP (:func:`jaxcr.registration.projective.
    # projective_icp`; 0 = off: the fixed ``iterations`` schedule). A step whose pose update
    # is below both tolerances (rotation rad, translation m) counts as converged: at a wide
    # radius the schedule jumps to ``min_dist``; at ``min_dist`` the stage ends. The
    # per-iteration updates of the dev pairs plateau at ~2e-5 rad / 5e-6 m (association
    # jitter), so the tolerances sit above that floor and ~10x below the pose errors.
    tol_rotation: float = eqx.field(static=True, default=0.0)
    tol_translation: float = eqx.field(static=True, default=0.0)
    # Coarse-to-fine source sampling of the convergence-stopped projective ICP
    # (:func:`jaxcr.registration.projective.projective_icp`; 1 = off): the radius schedule
    # runs to convergence on every ``coarse_stride``-th source row only (the rows are a
    # random pixel sample in raster order, so the subset is spread over the view), then the
    # full sample refines from there at ``min_dist`` until converged. The final pose comes
    # from full-sample steps; the early, wide-radius steps cost 1 / ``coarse_stride``.
    coarse_stride: int = eqx.field(static=True, default=1)
    # The coarse stage's convergence tolerances are ``tol_*`` times this: its pose is only
    # the fine stage's start, and a sparser sample's step-to-step jitter is larger.
    coarse_tol_factor: float = eqx.field(static=True, default=1.0)
    # Errors-in-variables weight of the point-to-plane pairs (projective association only,
    # :func:`jaxcr.registration.projective.noise_weights`): "none" (the paper's weights), or
    # each pair's paper weight times 1 / sigma_n^2, sigma_n^2 the variance of its
    # point-to-plane residual from both points' depth noise along the target normal and the
    # target normal's own error ("sensor"), plus the excess of the target's local plane
    # fit residual over the sensor noise, i.e. the fit's model error at creases and on
    # curved patches ("sensor+fit"); normalised so the total weight is unchanged (equal
    # variances give the paper's weights exactly).
    noise_weight: str = eqx.field(static=True, default="none")
    # The depth sensor's axial noise sigma_z(z) = depth_sigma0 + depth_sigma2 (z - depth_z0)^2
    # (m; z in m). Default: the Kinect structured-light model of Nguyen, Izadi & Lovell
    # (3DIMPVT 2012; measured at 10-60 deg incidence); a scene that declares its sensor
    # (``depth_noise`` of a jaxcr.rgbd_scene/1 file) replaces it
    # (:func:`jaxcr.registration.pipeline.PipelineConfig.with_sensor`).
    depth_sigma0: float = eqx.field(static=True, default=0.0012)
    depth_sigma2: float = eqx.field(static=True, default=0.0019)
    depth_z0: float = eqx.field(static=True, default=0.4)
    # Standard deviation of the source positions' depth error as a fraction of sigma_z: 1 for
    # raw back-projections, 0.2 for the denoised positions of a 7-pixel plane fit
    # (:func:`jaxcr.registration.clouds.plane_points`: about sigma / window x 1.4).
    source_noise_factor: float = eqx.field(static=True, default=1.0)
    # Target normal error (rad) per unit of sigma_z f / z (pixel pitch z / f): the normals of
    # :func:`jaxcr.registration.clouds.organised_cloud` (7 x 7 box mean differenced over
    # +-2 px) tilt by sqrt(2 x 28) / 49 sigma_z over 4 pixel pitches, 0.153 / 4 = 0.038.
    normal_noise_gain: float = eqx.field(static=True, default=0.038)


DEFAULT_ICP = IcpConfig(
    degeneracy_ratio=0.01,
    keypoint_weight=1.0,
    keypoint_balance="noise",
    tol_rotation=1e-4,
    tol_translation=2e-5,
)


class IcpResult(NamedTuple):
    T: Mat4  # target <- source
    fitness: Array  # fraction of valid source points with a correspondence within min_dist
    rmse: Array  # point-to-plane RMS (m) over those correspondences
    n_matched: Array


class Keypoints(NamedTuple):
    """Matched 3-D keypoints (k, 3) in the source / target frames and a mask (k,).
    ``scale`` (m, scalar) is the robust scale of their residuals (the Gaussian width of the
    keypoint weights); ``None`` uses ``IcpConfig.sigma_keypoint``."""

    src: Float[Array, "k 3"]
    tgt: Float[Array, "k 3"]
    mask: Bool[Array, " k"]
    scale: Float[Array, ""] | None = None


def no_keypoints(k: int = 1) -> Keypoints:
    z = jnp.zeros((k, 3), jnp.float32)
    return Keypoints(z, z, jnp.zeros(k, bool))


class CloudArrays(NamedTuple):
    """Padded cloud: points/colours/normals (n, 3) float32 and a validity mask (n,)."""

    points: Float[Array, "n 3"]
    colours: Float[Array, "n 3"]
    normals: Float[Array, "n 3"]
    mask: Bool[Array, " n"]


def correspondences(ps, cs, tgt: CloudArrays, colour_scale: float):
    """Index of the joint-space nearest target point for each source point (brute force)."""
    d2 = (
        jnp.sum(ps**2, 1)[:, None]
        + jnp.sum(tgt.points**2, 1)[None, :]
        - 2.0 * ps @ tgt.points.T
        + colour_scale**2
        * (
            jnp.sum(cs**2, 1)[:, None]
            + jnp.sum(tgt.colours**2, 1)[None, :]
            - 2.0 * cs @ tgt.colours.T
        )
    )
    d2 = jnp.where(tgt.mask[None, :], d2, jnp.inf)
    return jnp.argmin(d2, axis=1)


def pair_weights(ps, ns, cs, q, nq, cq, valid, radius, cfg: IcpConfig):
    """The paper's combined match weight (module docstring) and the point-to-plane residual."""
    diff = ps - q
    d2 = jnp.sum(diff**2, -1)
    pl = jnp.sum(diff * nq, -1)
    ndot = jnp.sum(ns * nq, -1)
    dc2 = jnp.sum((cs - cq) ** 2, -1)
    keep = valid & (d2 < radius**2) & (ndot > 0.5)
    w = (
        jnp.exp(-d2 / (2 * cfg.sigma_dist**2))
        * jnp.exp(-dc2 / (2 * cfg.sigma_colour**2))
        * jnp.maximum(ndot, 0.0)
        * jnp.exp(-(pl**2) / (2 * cfg.sigma_plane**2))
    )
    return jnp.where(keep, w, 0.0), pl, keep


def _apply(T, src: CloudArrays):
    R, t = T[:3, :3], T[:3, 3]
    return src.points @ R.T + t, src.normals @ R.T


def _point_terms(ps, q, w, P=None):
    """Normal equations of weighted point-to-point residuals p - q, J = [I, -hat(p)];
    with ``P`` (n, 3, 3) projectors the residuals are ``P (p - q)``."""
    J = jnp.concatenate(
        [jnp.broadcast_to(jnp.eye(3), (ps.shape[0], 3, 3)), -jax.vmap(hat)(ps)], axis=2
    )  # (n, 3, 6)
    if P is not None:
        J = jnp.einsum("nij,nja->nia", P, J)
        r = jnp.einsum("nij,nj->ni", P, ps - q)
    else:
        r = ps - q
    return jnp.einsum("n,nia,nib->ab", w, J, J), jnp.einsum("n,nia,ni->a", w, J, r)


def icp_step(T, radius, src: CloudArrays, tgt: CloudArrays, cfg: IcpConfig, kp: Keypoints):
    """One weighted Gauss-Newton ICP step; returns the updated ``T``. The matched keypoints
    ``kp`` (RANSAC inliers) add point-to-point residuals whose total weight is
    ``keypoint_weight`` times the total dense weight (robustified with ``sigma_keypoint``),
    measured across the target camera's viewing ray only (the keypoint's depth is the noisy
    coordinate; its image position is precise): they pin the directions flat or round
    textured surfaces leave free."""
    ps, ns = _apply(T, src)
    j = correspondences(ps, src.colours, tgt, cfg.colour_scale)
    q, nq, cq = tgt.points[j], tgt.normals[j], tgt.colours[j]
    w, pl, _ = pair_weights(ps, ns, src.colours, q, nq, cq, src.mask, radius, cfg)
    return gauss_newton_update(T, ps, q, nq, w, pl, cfg, kp)


def gauss_newton_update(T, ps, q, nq, w, pl, cfg: IcpConfig, kp: Keypoints, extra=None):
    """The damped Gauss-Newton update of ``T`` from weighted matches (transformed source
    points ``ps``, target points ``q`` with normals ``nq``, weights ``w``, point-to-plane
    residuals ``pl``) plus the keypoint term (see :func:`icp_step`); shared by the
    nearest-neighbour and the projective (:mod:`jaxcr.registration.projective`) ICP.
    ``extra``: optional (H (6, 6), g (6,)) normal-equation terms added before the solve
    (the photometric term). With ``cfg.degeneracy_ratio > 0`` the geometric terms are
    removed from the directions they cannot observe (:func:`degeneracy_filter`) and
    ``extra`` is restricted to exactly those directions: geometry where it is informative,
    colour where it is not (there a colour term's own systematic errors, e.g. texture
    blurred differently under different foreshortening, would otherwise compete with
    the geometry)."""
    H, g = normal_equations(T, ps, q, nq, w, pl, cfg, kp, extra)
    scale = jnp.maximum(jnp.trace(H) / 6.0, 1e-12)
    delta = -jnp.linalg.solve(H + cfg.damping * scale * jnp.eye(6), g)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)) & (jnp.sum(w) > 0), delta, 0.0)
    return make_transform(so3_exp(delta[3:]), delta[:3]) @ T


def normal_equations(T, ps, q, nq, w, pl, cfg: IcpConfig, kp: Keypoints, extra=None):
    """The normal equations (H (6, 6), g (6,)) of the combined weighted objective that
    :func:`gauss_newton_update` solves (point-to-plane, optional point-to-point, keypoint
    term, degeneracy split, ``extra``), increment ``delta = (v, w)`` applied as
    ``T <- [exp(hat(w)), v] T`` (target frame, m and rad). ``H`` is also the (unscaled)
    information of the registration: see
    :func:`jaxcr.registration.projective.projective_information`."""
    # point-to-plane: r = n.(p + w x p + v - q)  ->  J = [n, p x n]
    J_pl = jnp.concatenate([nq, jnp.cross(ps, nq)], axis=1)  # (n, 6)
    H = (J_pl * w[:, None]).T @ J_pl
    g = (J_pl * w[:, None]).T @ pl
    # point-to-point: r = p - q + v - hat(p) w  ->  J = [I, -hat(p)]
    if cfg.point_weight:
        Hp, gp = _point_terms(ps, q, cfg.point_weight * w)
        H, g = H + Hp, g + gp
    split = None
    if cfg.degeneracy_ratio > 0:
        split = degenerate_split(H, ps, w, cfg.degeneracy_ratio)
        H, g = project_normal_equations(H, g, split[0], split[1])
    ks = kp.src @ T[:3, :3].T + T[:3, 3]
    rk2 = jnp.sum((ks - kp.tgt) ** 2, -1)
    sk = cfg.sigma_keypoint if kp.scale is None else kp.scale
    wk = jnp.where(kp.mask, jnp.exp(-rk2 / (2 * sk**2)), 0.0)
    if cfg.keypoint_balance == "noise":
        # weight width sk = 3 sigma_k (pairwise.keypoint_scale); dense residual variance s_g^2
        s_g2 = jnp.sum(w * pl**2) / jnp.maximum(jnp.sum(w), 1e-30)
        wk = wk * cfg.keypoint_weight * s_g2 / jnp.maximum((sk / 3.0) ** 2, 1e-12)
    elif cfg.keypoint_balance == "fraction":
        wk = wk * cfg.keypoint_weight * jnp.sum(w) / jnp.maximum(jnp.sum(kp.mask), 1)
    else:
        raise ValueError(
            f"keypoint_balance must be 'fraction' or 'noise', got {cfg.keypoint_balance!r}"
        )
    # Keypoint depth is the noisy coordinate: keep only the residual across the target ray.
    ray = kp.tgt / jnp.maximum(jnp.linalg.norm(kp.tgt, axis=-1, keepdims=True), 1e-9)
    P = jnp.eye(3) - ray[:, :, None] * ray[:, None, :]
    Hk, gk = _point_terms(ks, kp.tgt, wk, P)
    H, g = H + Hk, g + gk
    if extra is not None:
        He, ge = extra
        if split is not None:  # the colour term only where the geometry is blind
            He, ge = project_normal_equations(He, ge, split[0], jnp.eye(6) - split[1])
        H, g = H + He, g + ge
    return H, g


def scaled_coordinates(ps: Float[Array, "n 3"], w: Float[Array, " n"]) -> Float[Array, "6 6"]:
    """The matrix ``A`` (6, 6) taking an increment ``delta = (v, omega)`` (applied as
    ``p -> p + omega x p + v``, target frame) to unit-consistent coordinates
    ``(v + omega x c, L omega)``: translation of the weighted centroid ``c`` of ``ps`` and
    rotation times the weighted RMS radius ``L`` of ``ps`` about ``c`` (both metres). In
    these coordinates the eigen-decomposition of the normal-equation matrix does not depend
    on where the camera origin is or on the choice of length unit."""
    ws = jnp.maximum(jnp.sum(w), 1e-30)
    c = (w @ ps) / ws
    L = jnp.sqrt(jnp.maximum(w @ jnp.sum((ps - c) ** 2, -1) / ws, 1e-12))
    top = jnp.concatenate([jnp.eye(3, dtype=ps.dtype), -hat(c)], axis=1)
    bottom = jnp.concatenate([jnp.zeros((3, 3), ps.dtype), L * jnp.eye(3, dtype=ps.dtype)], 1)
    return jnp.concatenate([top, bottom], axis=0)


def degenerate_split(
    H: Float[Array, "6 6"], ps: Float[Array, "n 3"], w: Float[Array, " n"], ratio: float
):
    """Eigen-decomposition of the geometric normal-equation matrix ``H`` in the
    unit-consistent coordinates of :func:`scaled_coordinates` (``A``). Returns ``A``, the
    projector ``P`` (6, 6, scaled coordinates) on the well-observed eigen-directions
    (eigenvalue >= ``ratio`` x the largest) and their number."""
    A = scaled_coordinates(ps, w)
    Ai = jnp.linalg.inv(A)
    Hs = Ai.T @ H @ Ai
    lam, V = jnp.linalg.eigh(0.5 * (Hs + Hs.T))
    good = lam >= ratio * jnp.maximum(lam[-1], 1e-30)
    return A, (V * good[None, :]) @ V.T, jnp.sum(good)


def project_normal_equations(H, g, A, P):
    """Restrict normal equations (H, g) (coordinates ``delta``) to the subspace of the
    projector ``P`` (scaled coordinates ``A delta``): ``A^T P A^-T H A^-1 P A`` and
    ``A^T P A^-T g``."""
    Ai = jnp.linalg.inv(A)
    return A.T @ P @ (Ai.T @ H @ Ai) @ P @ A, A.T @ P @ (Ai.T @ g)


def degeneracy_filter(
    H: Float[Array, "6 6"],
    g: Float[Array, " 6"],
    ps: Float[Array, "n 3"],
    w: Float[Array, " n"],
    ratio: float,
):
    """Degeneracy-aware geometric term (Zhang, Kaess & Singh 2016, "On degeneracy of
    optimization-based state estimation problems"): eigen-decompose the normal-equation
    matrix ``H`` of the geometric residuals in the unit-consistent coordinates of
    :func:`scaled_coordinates`; directions whose eigenvalue is below ``ratio`` times the
    largest are ones the geometry cannot observe (rotation about a cylinder's axis,
    sliding along a plane or an edge). There the geometric term holds only noise and
    systematic model errors (normals from smoothed depth, pixel rounding), which a weak
    curvature turns into a bias, so the term is removed from them: ``H -> P H P``,
    ``g -> P g`` with ``P`` the projector on the well-observed eigen-directions. The update
    along degenerate directions then comes from the other terms (keypoints, photometric)
    or, without them, stays at the seed (the damping), as in Zhang et al.'s solution
    remapping. Returns the filtered (H, g) in the original coordinates and the number of
    degenerate directions."""
    A, P, n_good = degenerate_split(H, ps, w, ratio)
    Hf, gf = project_normal_equations(H, g, A, P)
    return Hf, gf, 6 - n_good


def icp(
    src: CloudArrays,
    tgt: CloudArrays,
    T0: Mat4,
    cfg: IcpConfig = DEFAULT_ICP,
    kp: Keypoints | None = None,
) -> IcpResult:
    """Register ``src`` to ``tgt`` starting from ``T0`` (target <- source), optionally with
    matched keypoints ``kp``. Pure, jit-able."""
    kp = no_keypoints() if kp is None else kp
    n = cfg.iterations
    ratio = (cfg.min_dist / cfg.max_dist) ** (1.0 / max(n - 1, 1))

    def body(k, T):
        radius = cfg.max_dist * ratio ** jnp.minimum(k, n - 1)
        return icp_step(T, radius, src, tgt, cfg, kp)

    T = jax.lax.fori_loop(0, n, body, T0.astype(src.points.dtype))
    return evaluate(T, src, tgt, cfg)


def evaluate(
    T: Mat4, src: CloudArrays, tgt: CloudArrays, cfg: IcpConfig = DEFAULT_ICP
) -> IcpResult:
    """Fitness/RMSE of ``T`` at the final correspondence radius ``cfg.min_dist``."""
    ps, ns = _apply(T, src)
    j = correspondences(ps, src.colours, tgt, cfg.colour_scale)
    q, nq, cq = tgt.points[j], tgt.normals[j], tgt.colours[j]
    _, pl, keep = pair_weights(ps, ns, src.colours, q, nq, cq, src.mask, cfg.min_dist, cfg)
    k = jnp.sum(keep)
    rmse = jnp.sqrt(jnp.sum(jnp.where(keep, pl**2, 0.0)) / jnp.maximum(k, 1))
    return IcpResult(T, k / jnp.maximum(jnp.sum(src.mask), 1), rmse, k)


icp_jit = jax.jit(icp)
