"""Covariance of a projective registration from its own residuals (a cluster-robust sandwich).

The pose graph weights each registration by an information matrix. The usual one,
:func:`jaxcr.registration.projective.projective_information`, is ``H / s^2``: the
Gauss-Newton normal matrix over the mean squared point-to-plane residual. It assumes
independent residuals of one variance, so it cannot see that

- the residuals of neighbouring pixels are correlated (denoised source positions share a
  7-pixel plane fit, target normals come from smoothed depth), and
- the residuals that pin the geometry's weak direction (creases and silhouettes of a box
  seen from afar) are the noisiest ones.

Both make the registration's real scatter larger, and differently shaped, than ``H / s^2``
says (experiments/results/registration/model_object_far_view_noise_diagnosis.md: the ICP
information did not predict which of a far view's links erred most).

The sandwich estimate (Huber 1967; White 1980; the cluster form of Liang & Zeger 1986)
takes the scatter from the residuals themselves. The estimate ``delta`` solves
``g(delta) = sum_k s_k = 0`` (``s_k`` the score of residual k: ``w_k r_k J_k`` after the
degeneracy split), so to first order ``Cov(delta) = H^-1 Cov(g) H^-1``, with
``Cov(g) ~ sum_c S_c S_c^T`` and ``S_c`` the summed scores of cluster c. The clusters are
square tiles of ``tile`` source pixels (residuals within a tile may be correlated,
residuals of different tiles are taken as independent); each keypoint is its own cluster.
The information is its inverse, ``H (sum_c S_c S_c^T)^-1 H``. With one pixel per tile,
unit weights and residuals of one variance it reduces to ``H / s^2``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float, Mat4
from jaxcr.registration.icp import (
    DEFAULT_ICP,
    CloudArrays,
    IcpConfig,
    Keypoints,
    degenerate_split,
    no_keypoints,
    normal_equations,
)
from jaxcr.registration.projective import (
    DepthImage,
    _matches_indexed,
    bilinear,
    noise_weights,
    photometric_channels,
    photometric_rows,
    project,
)


def _hat(p: Float[Array, "3"]) -> Float[Array, "3 3"]:
    z = jnp.zeros((), p.dtype)
    return jnp.array([[z, -p[2], p[1]], [p[2], z, -p[0]], [-p[1], p[0], z]])


def _point_jacobians(ps: Float[Array, "n 3"]) -> Float[Array, "n 3 6"]:
    """d(p + w x p + v)/d(v, w) = [I, -hat(p)] per point."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=ps.dtype), (ps.shape[0], 3, 3))
    return jnp.concatenate([eye, -jax.vmap(_hat)(ps)], axis=2)


def keypoint_rows(
    T: Mat4, kp: Keypoints, balance, cfg: IcpConfig
) -> tuple[Float[Array, "k 6"], Float[Array, "k 6 6"]]:
    """Score ``w_k J_k^T r_k`` (k, 6) and normal-matrix share ``w_k J_k^T J_k`` (k, 6, 6) of
    each keypoint residual of :func:`jaxcr.registration.icp.normal_equations` (the residual
    across the target ray), zero for padding. ``balance``: the dense term's quantity that
    sets the keypoint weights there (``cfg.keypoint_balance`` "noise": the dense residual
    variance; "fraction": the dense weight sum)."""
    ks = kp.src @ T[:3, :3].T + T[:3, 3]
    rk = ks - kp.tgt
    sk = cfg.sigma_keypoint if kp.scale is None else kp.scale
    wk = jnp.where(kp.mask, jnp.exp(-jnp.sum(rk**2, -1) / (2 * sk**2)), 0.0)
    if cfg.keypoint_balance == "noise":
        wk = wk * cfg.keypoint_weight * balance / jnp.maximum((sk / 3.0) ** 2, 1e-12)
    else:
        wk = wk * cfg.keypoint_weight * balance / jnp.maximum(jnp.sum(kp.mask), 1)
    ray = kp.tgt / jnp.maximum(jnp.linalg.norm(kp.tgt, axis=-1, keepdims=True), 1e-9)
    P = jnp.eye(3) - ray[:, :, None] * ray[:, None, :]
    J = jnp.einsum("kij,kja->kia", P, _point_jacobians(ks))
    r = jnp.einsum("kij,kj->ki", P, rk)
    return (
        wk[:, None] * jnp.einsum("kia,ki->ka", J, r),
        jnp.einsum("k,kia,kib->kab", wk, J, J),
    )


def sandwich(
    H: Float[Array, "6 6"],
    scores: Float[Array, "c 6"],
    hessians: Float[Array, "c 6 6"],
    *,
    leave_out: bool = True,
) -> tuple[Float[Array, "6 6"], Float[Array, "6 6"]]:
    """Sandwich information and covariance of an M-estimate with normal matrix ``H`` from
    its clusters' summed scores ``S_c`` (c, 6) at the estimate and their shares ``H_c`` of
    ``H`` (c, 6, 6). ``leave_out``: each score is first taken to the estimate without its
    cluster, ``S_c <- H (H - H_c)^-1 S_c`` (the approximate jackknife, "CR3" of Bell &
    McCaffrey 2002: a score at the estimate is shrunk by the cluster's own pull on it,
    most for few clusters of high leverage, e.g. a far view's few tiles). Then
    ``B = sum_c S_c S_c^T``, covariance ``H^-1 B H^-1``, information ``H B^-1 H``
    (pseudo-inverses: directions without data stay without information)."""
    H = 0.5 * (H + H.T)
    if leave_out:
        eye = jnp.eye(6, dtype=H.dtype)
        M = H[None] - hessians + 1e-9 * jnp.trace(H) * eye[None]
        x = jnp.linalg.solve(M, scores[:, :, None])[:, :, 0]
        scores = x @ H.T
    B = scores.T @ scores
    B = 0.5 * (B + B.T)
    lh, Vh = jnp.linalg.eigh(H)
    lh_inv = jnp.where(lh > 1e-9 * jnp.maximum(lh[-1], 1e-30), 1.0 / lh, 0.0)
    Hinv = (Vh * lh_inv) @ Vh.T
    cov = Hinv @ B @ Hinv
    lb, Vb = jnp.linalg.eigh(B)
    lb_inv = jnp.where(lb > 1e-9 * jnp.maximum(lb[-1], 1e-30), 1.0 / lb, 0.0)
    info = H @ ((Vb * lb_inv) @ Vb.T) @ H
    return 0.5 * (info + info.T), 0.5 * (cov + cov.T)


def projective_sandwich_information(
    T: Mat4,
    src: CloudArrays,
    tgt: DepthImage,
    cfg: IcpConfig = DEFAULT_ICP,
    kp: Keypoints | None = None,
    window: int = 0,
    src_image: DepthImage | None = None,
    photometric: str = "intensity",
    photo_points: Float[Array, "n 3"] | None = None,
    tile: int = 8,
    leave_out: bool = True,
) -> tuple[Float[Array, "6 6"], Float[Array, "6 6"]]:
    """Cluster-robust sandwich information (6, 6) of a registration ``T`` (target <- source)
    found by :func:`jaxcr.registration.projective.projective_icp` with the same arguments
    (module docstring, :func:`sandwich`): ``H B^-1 H`` with ``H`` the normal matrix of the
    ICP's objective at ``T`` (point-to-plane, keypoint and colour terms, degeneracy split;
    as :func:`jaxcr.registration.projective.projective_information`) and ``B`` the scatter
    of its scores summed over ``tile`` x ``tile`` source-pixel tiles (keypoints one cluster
    each; ``leave_out``: jackknife-corrected). Same frame and order as
    ``projective_information``: left perturbation in the target frame, (v, w), 1/m^2 and
    1/rad^2. A source sample's tile is that of its position ``src.points`` projected by
    ``tgt.K`` (the two views share the camera). Returns (information, covariance
    ``H^-1 B H^-1``). Pure, jit-able (``window``, ``photometric``, ``tile``, ``leave_out``
    static)."""
    kp = no_keypoints() if kp is None else kp
    ps, q, nq, w, pl, keep, j = _matches_indexed(T, src, tgt, cfg.min_dist, cfg, window)
    extra, rows = None, None
    if src_image is not None:
        u, v, _ = project(src.points, src_image.K)
        i_src, _ = bilinear(photometric_channels(src_image, photometric)[0], u, v)
        pp = ps if photo_points is None else photo_points @ T[:3, :3].T + T[:3, 3]
        rows = photometric_rows(pp, i_src, tgt, w, pl, keep, photometric)
        Jc, wc, rc = rows
        extra = (
            jnp.einsum("nc,nca,ncb->ab", wc, Jc, Jc),
            jnp.einsum("nc,nca,nc->a", wc, Jc, rc),
        )
    w = noise_weights(T, src.points, ps, q, nq, w, j, tgt, cfg)
    H, _ = normal_equations(T, ps, q, nq, w, pl, cfg, kp, extra)
    # per source point: score and normal-matrix share of the dense terms
    J_pl = jnp.concatenate([nq, jnp.cross(ps, nq)], axis=1)
    s_geo = J_pl * (w * pl)[:, None]
    h_geo = jnp.einsum("n,na,nb->nab", w, J_pl, J_pl)
    if cfg.point_weight:
        Jp = _point_jacobians(ps)
        s_geo = s_geo + jnp.einsum("n,nia,ni->na", cfg.point_weight * w, Jp, ps - q)
        h_geo = h_geo + jnp.einsum("n,nia,nib->nab", cfg.point_weight * w, Jp, Jp)
    if rows is None:
        s_col, h_col = jnp.zeros_like(s_geo), jnp.zeros_like(h_geo)
    else:
        Jc, wc, rc = rows
        s_col = jnp.einsum("nc,nca,nc->na", wc, Jc, rc)
        h_col = jnp.einsum("nc,nca,ncb->nab", wc, Jc, Jc)
    if cfg.degeneracy_ratio > 0:
        # geometry in its observed directions, colour in the others (normal_equations)
        A, Pg, _ = degenerate_split(jnp.sum(h_geo, 0), ps, w, cfg.degeneracy_ratio)
        Ai = jnp.linalg.inv(A)
        Lg = A.T @ Pg @ Ai.T
        Lc = A.T @ (jnp.eye(6) - Pg) @ Ai.T
        s_geo, h_geo = s_geo @ Lg.T, Lg[None] @ h_geo @ Lg.T[None]
        s_col, h_col = s_col @ Lc.T, Lc[None] @ h_col @ Lc.T[None]
    # keypoint rows, with normal_equations' balance of the keypoint term
    s_g2 = jnp.sum(w * pl**2) / jnp.maximum(jnp.sum(w), 1e-30)
    bal = s_g2 if cfg.keypoint_balance == "noise" else jnp.sum(w)
    s_kp, h_kp = keypoint_rows(T, kp, bal, cfg)
    # tiles of the source image (one more cluster for points behind the camera: no data)
    h, wd = tgt.mask.shape
    nx, ny = -(-wd // tile), -(-h // tile)
    u, v, front = project(src.points, tgt.K)
    iu = jnp.clip(jnp.floor(u / tile), 0, nx - 1).astype(jnp.int32)
    iv = jnp.clip(jnp.floor(v / tile), 0, ny - 1).astype(jnp.int32)
    cluster = jnp.where(front, iv * nx + iu, nx * ny)
    S = jax.ops.segment_sum(s_geo + s_col, cluster, num_segments=nx * ny + 1)
    Hc = jax.ops.segment_sum(h_geo + h_col, cluster, num_segments=nx * ny + 1)
    return sandwich(
        H,
        jnp.concatenate([S, s_kp], 0),
        jnp.concatenate([Hc, h_kp], 0),
        leave_out=leave_out,
    )


projective_sandwich_information_jit = jax.jit(
    projective_sandwich_information, static_argnames=("window", "photometric", "tile", "leave_out")
)
