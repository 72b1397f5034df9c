"""Per-segment motion models Q_j^i and the end-effector prediction error (M-L eqs. 4-9).

Each segment's model is fitted to the flow vectors of the grid points lying in it:

* translation (eq. 4): Q(a) = a + b_j, with b_j the mean flow of the segment, optionally as
  a Cauchy M-estimate (:func:`robust_translation`);
* homography (eqs. 7-8): Q(a) = pi(H_j [a; 1]), H_j fitted to the segment's point
  correspondences (p, p + f) by the normalised DLT (Hartley normalisation per segment), made
  robust by iteratively reweighted least squares with Cauchy weights on the transfer error.
  Segments with fewer than ``min_points`` valid points fall back to their translation.

Camera motion: eqs. 4-9 compare the segments' image motion with the end-effector motion
predicted by a *fixed* projection P (eq. 3), i.e. they assume a static camera. When the camera
shakes (a small rotation R between two frames) every static point moves by the infinite
homography K R K^-1 and no segment's flow matches the prediction any more.
:func:`stabilise_flow` fits that global homography robustly (RANSAC) to all the flow (the static
background is the dominant motion) and maps each point's end position back through its
inverse, so that the flow is expressed in the camera of the first frame of the pair, which is
what the fixed P describes. With a static camera the fitted homography is the identity up to
the flow noise and the flow is unchanged.

The error (eqs. 5 and 9) is rho = |Q_j(x_i) - x_{i+1}|^2 in px^2, x_i the end-effector image
position h(x) at frame i. All segments are handled at once with ``jax.ops.segment_sum`` over
a static number of segments.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


def _take(col: Float[Array, " k"], idx: Int[Array, " n"]) -> Float[Array, " n"]:
    """col[idx] as a flat 1-D gather (XLA's CPU gather of rows of a (k, d) table, b[seg] or
    H[seg], is several times slower than d separate 1-D gathers)."""
    return jnp.take(col, idx, mode="clip")


def _segsum(
    x: Float[Array, "n ..."], seg: Int[Array, " n"], n_segments: int
) -> Float[Array, "k ..."]:
    """Per-segment sums; a plain reduction when there is one segment (a scatter-add into a
    single row is a serial loop on CPU)."""
    if n_segments == 1:
        return jnp.sum(x, axis=0, keepdims=True)
    return jax.ops.segment_sum(x, seg, n_segments)


def _transfer(
    h: tuple[Float[Array, "..."], ...], x: Float[Array, "..."], y: Float[Array, "..."]
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """pi(H [x; y; 1]) on separate x and y arrays, H given by its nine entries (row-major,
    each broadcastable against x); as :func:`apply_homography`, w ~ 0 gives the far point
    (1e6, 1e6)."""
    qx = h[0] * x + h[1] * y + h[2]
    qy = h[3] * x + h[4] * y + h[5]
    qw = h[6] * x + h[7] * y + h[8]
    ok = jnp.abs(qw) > 1e-9
    w = jnp.where(ok, qw, 1.0)
    return jnp.where(ok, qx / w, 1e6), jnp.where(ok, qy / w, 1e6)


def _entries(H: Float[Array, "k 3 3"]) -> tuple[Float[Array, " k"], ...]:
    return tuple(H[:, i, j] for i in range(3) for j in range(3))


def _transfer_error2(
    H: Float[Array, "k 3 3"],
    seg: Int[Array, " n"],
    x: Float[Array, " n"],
    y: Float[Array, " n"],
    u: Float[Array, " n"],
    v: Float[Array, " n"],
) -> Float[Array, " n"]:
    """|pi(H_seg(i) [x_i; y_i; 1]) - (u_i, v_i)|^2 for every point, px^2."""
    px, py = _transfer(tuple(_take(e, seg) for e in _entries(H)), x, y)
    return (px - u) ** 2 + (py - v) ** 2


def segment_translation(
    flow: Float[Array, "n 2"], seg: Int[Array, " n"], weight: Float[Array, " n"], n_segments: int
) -> tuple[Float[Array, "k 2"], Float[Array, " k"]]:
    """Mean flow b_j of every segment (eq. 4) and its total weight (number of valid points)."""
    wsum = _segsum(weight, seg, n_segments)
    fsum = _segsum(flow * weight[:, None], seg, n_segments)
    return fsum / jnp.maximum(wsum, 1e-12)[:, None], wsum


def robust_translation(
    flow: Float[Array, "n 2"],
    seg: Int[Array, " n"],
    weight: Float[Array, " n"],
    n_segments: int,
    n_iter: int = 5,
    scale: float = 1.0,
) -> tuple[Float[Array, "k 2"], Float[Array, " k"]]:
    """Robust b_j (eq. 4): the mean flow reweighted ``n_iter`` times with Cauchy weights
    1 / (1 + (|f - b_j| / scale)^2), ``scale`` in px (an M-estimator of location started at
    the mean). A segment's flow is bimodal where the LK window straddles its boundary with a
    moving neighbour or where tracked labels leak onto it; the plain mean then lands between
    the two motions, the M-estimate on the dominant one. Returns (b, number of valid points);
    ``n_iter`` = 0 is :func:`segment_translation`."""
    b, count = segment_translation(flow, seg, weight, n_segments)
    fx, fy = flow[:, 0], flow[:, 1]

    def body(_, b):
        e2 = (fx - _take(b[:, 0], seg)) ** 2 + (fy - _take(b[:, 1], seg)) ** 2
        return segment_translation(flow, seg, weight / (1.0 + e2 / scale**2), n_segments)[0]

    return jax.lax.fori_loop(0, n_iter, body, b), count


def apply_homography(H: Float[Array, "3 3"], a: Float[Array, "2"]) -> Float[Array, "2"]:
    """pi(H [a; 1]) with a double where so that w ~ 0 gives a finite (far) point."""
    q = H @ jnp.array([a[0], a[1], 1.0], dtype=H.dtype)
    ok = jnp.abs(q[2]) > 1e-9
    w = jnp.where(ok, q[2], 1.0)
    return jnp.where(ok, q[:2] / w, jnp.full(2, 1e6, H.dtype))


def _normalise(
    x: Float[Array, " n"], y: Float[Array, " n"], seg, weight, wsum, n_segments: int
) -> tuple[
    Float[Array, " k"],
    Float[Array, " k"],
    Float[Array, " k"],
    Float[Array, " n"],
    Float[Array, " n"],
]:
    """Hartley normalisation per segment: weighted centroid c and scale s = sqrt(2) / (mean
    distance to c). Returns (cx, cy, s) per segment and the normalised point coordinates
    s (p - c)."""
    cx = _segsum(x * weight, seg, n_segments) / wsum
    cy = _segsum(y * weight, seg, n_segments) / wsum
    dx, dy = x - _take(cx, seg), y - _take(cy, seg)
    d = _segsum(jnp.sqrt(dx**2 + dy**2) * weight, seg, n_segments) / wsum
    s = jnp.sqrt(2.0) / jnp.maximum(d, 1e-6)
    sp = _take(s, seg)
    return cx, cy, s, sp * dx, sp * dy


def weighted_homographies(
    src: Float[Array, "n 2"],
    dst: Float[Array, "n 2"],
    seg: Int[Array, " n"],
    weight: Float[Array, " n"],
    n_segments: int,
    perspective_penalty: float = 0.0,
) -> Float[Array, "k 3 3"]:
    """Weighted normalised DLT homography of every segment (dst ~ H src), ||H||_F = 1.

    The algebraic error sum_i w_i (|r1_i . h|^2 + |r2_i . h|^2), with the two DLT rows
    r1 = (0, -a, v a), r2 = (a, 0, -u a) of a correspondence a = (x, y, 1) -> (u, v) in
    normalised coordinates, is h^T M h with the 9 x 9 block matrix
    M = [[A, 0, -A_u], [0, A, -A_v], [-A_u, -A_v, A_uv]], where A = sum w a a^T,
    A_u = sum w u a a^T, A_v = sum w v a a^T and A_uv = sum w (u^2 + v^2) a a^T: each segment's
    M is assembled from 24 weighted moments per point instead of summing 81-entry outer
    products. h is M's eigenvector of the smallest eigenvalue.

    ``perspective_penalty`` (>= 0) adds penalty x (sum of weights) x (h31^2 + h32^2) in the
    normalised coordinates to the algebraic error: a ridge prior towards an affine map that
    keeps the homographies of small segments (a few px across, whose perspective terms the
    flow barely constrains) from extrapolating wildly to a distant end-effector. 0 gives the
    plain DLT."""
    wsum = jnp.maximum(_segsum(weight, seg, n_segments), 1e-12)
    csx, csy, ss, x, y = _normalise(src[:, 0], src[:, 1], seg, weight, wsum, n_segments)
    cdx, cdy, sd, u, v = _normalise(dst[:, 0], dst[:, 1], seg, weight, wsum, n_segments)
    mono = jnp.stack([x * x, x * y, x, y * y, y, jnp.ones_like(x)], axis=1) * weight[:, None]
    mom = _segsum(
        jnp.concatenate(
            [mono, mono * u[:, None], mono * v[:, None], mono * (u * u + v * v)[:, None]], axis=1
        ),
        seg,
        n_segments,
    )

    def sym(m):  # (k, 6) moments (xx, xy, x, yy, y, 1) -> (k, 3, 3)
        r0 = jnp.stack([m[:, 0], m[:, 1], m[:, 2]], -1)
        r1 = jnp.stack([m[:, 1], m[:, 3], m[:, 4]], -1)
        r2 = jnp.stack([m[:, 2], m[:, 4], m[:, 5]], -1)
        return jnp.stack([r0, r1, r2], axis=1)

    A, Au, Av, Auv = (sym(mom[:, 6 * i : 6 * i + 6]) for i in range(4))
    Z = jnp.zeros_like(A)
    M = jnp.concatenate(
        [
            jnp.concatenate([A, Z, -Au], axis=2),
            jnp.concatenate([Z, A, -Av], axis=2),
            jnp.concatenate([-Au, -Av, Auv], axis=2),
        ],
        axis=1,
    )
    ridge = jnp.zeros(9, src.dtype).at[6].set(1.0).at[7].set(1.0)
    M = M + perspective_penalty * wsum[:, None, None] * jnp.diag(ridge)[None]
    _, vecs = jnp.linalg.eigh(M)
    Hn = vecs[:, :, 0].reshape(-1, 3, 3)
    # denormalise: H = Td^-1 Hn Ts with the similarities T = [[s, 0, -s cx], [0, s, -s cy],
    # [0, 0, 1]], Td^-1 = [[1/s, 0, cx], [0, 1/s, cy], [0, 0, 1]] in closed form
    z, o = jnp.zeros_like(ss), jnp.ones_like(ss)
    Ts = jnp.stack(
        [
            jnp.stack([ss, z, -ss * csx], -1),
            jnp.stack([z, ss, -ss * csy], -1),
            jnp.stack([z, z, o], -1),
        ],
        axis=1,
    )
    Tdi = jnp.stack(
        [
            jnp.stack([1.0 / sd, z, cdx], -1),
            jnp.stack([z, 1.0 / sd, cdy], -1),
            jnp.stack([z, z, o], -1),
        ],
        axis=1,
    )
    H = Tdi @ Hn @ Ts
    H = H / jnp.linalg.norm(H, axis=(1, 2), keepdims=True)
    return H * jnp.sign(H[:, 2, 2])[:, None, None]


def segment_homography(
    pts: Float[Array, "n 2"],
    flow: Float[Array, "n 2"],
    seg: Int[Array, " n"],
    valid: Bool[Array, " n"],
    n_segments: int,
    n_irls: int = 3,
    scale: float = 1.0,
    min_points: int = 6,
    perspective_penalty: float = 0.0,
    select_sigma: float = 0.0,
    translation_irls: int = 0,
    translation: tuple[Float[Array, "k 2"], Float[Array, " k"]] | None = None,
) -> Float[Array, "k 3 3"]:
    """Robust homography per segment (eqs. 7-8): weighted normalised DLT, then ``n_irls``
    reweightings with Cauchy weights 1 / (1 + (e / scale)^2), e the transfer error in px.
    Segments with fewer than ``min_points`` valid points get their mean-flow translation;
    ``perspective_penalty`` see :func:`weighted_homographies`.

    With ``translation_irls`` > 0 the fit is started from the segment's robust translation
    (:func:`robust_translation`) instead of from all its points, and every refinement uses
    hard inlier weights (transfer error < 2 ``scale``) instead of Cauchy weights: the
    algebraic DLT is not robust, a bimodal segment (a moving boundary straddled by the LK
    window, leaked labels) bends a fit that gives its minority even a few per cent of weight.
    The inliers of the last refinement must then number ``min_points``; the fallback is the
    robust translation.

    With ``select_sigma`` > 0 (the flow noise, px) each segment keeps the homography only if it
    explains its flow better than the translation by more than the AIC penalty for the six
    extra parameters, sum w (e_t^2 - e_h^2) > 2 * 6 * sigma^2 (model selection in the spirit of
    Torr 1998, which M-L cites); otherwise the segment's model is its translation.

    ``translation`` is ``robust_translation(flow, seg, valid, n_segments, translation_irls)``
    when the caller has it already (the pipeline's translation model): it is then not computed
    again."""
    w0 = valid.astype(pts.dtype)
    dst = pts + flow
    x, y, u, v = pts[:, 0], pts[:, 1], dst[:, 0], dst[:, 1]
    if translation is None:
        translation = robust_translation(flow, seg, w0, n_segments, translation_irls)
    b, count = translation
    robust = translation_irls > 0
    inlier2 = (2.0 * scale) ** 2
    et2 = (flow[:, 0] - _take(b[:, 0], seg)) ** 2 + (flow[:, 1] - _take(b[:, 1], seg)) ** 2
    w_start = w0 * (et2 < (3.0 * scale) ** 2) if robust else w0
    H = weighted_homographies(pts, dst, seg, w_start, n_segments, perspective_penalty)

    def weights(e2):
        return w0 * (e2 < inlier2) if robust else w0 / (1.0 + e2 / scale**2)

    def body(_, H):
        w = weights(_transfer_error2(H, seg, x, y, u, v))
        return weighted_homographies(pts, dst, seg, w, n_segments, perspective_penalty)

    H = jax.lax.fori_loop(0, n_irls, body, H)
    Ht = jnp.tile(jnp.eye(3, dtype=pts.dtype), (n_segments, 1, 1)).at[:, :2, 2].set(b)
    good = (count >= min_points) & jnp.all(jnp.isfinite(H), axis=(1, 2))
    if robust or select_sigma > 0:
        eh2 = _transfer_error2(H, seg, x, y, u, v)
    w_sel = w0
    if robust:
        w_sel = weights(eh2)
        good = good & (_segsum(w_sel, seg, n_segments) >= min_points)
    if select_sigma > 0:
        rss_h = _segsum(w_sel * eh2, seg, n_segments)
        rss_t = _segsum(w_sel * et2, seg, n_segments)
        good = good & (rss_t - rss_h > 12.0 * select_sigma**2)
    return jnp.where(good[:, None, None], H, Ht)


def translation_error(
    b: Float[Array, "k 2"], x_now: Float[Array, "2"], x_next: Float[Array, "2"]
) -> Float[Array, " k"]:
    """rho_j = |x_i + b_j - x_{i+1}|^2 (eq. 5), px^2."""
    return jnp.sum((x_now + b - x_next) ** 2, axis=-1)


def homography_error(
    H: Float[Array, "k 3 3"], x_now: Float[Array, "2"], x_next: Float[Array, "2"]
) -> Float[Array, " k"]:
    """rho_j = |pi(H_j x_i) - x_{i+1}|^2 (eq. 9), px^2."""
    pred = jax.vmap(apply_homography, in_axes=(0, None))(H, x_now)
    return jnp.sum((pred - x_next) ** 2, axis=-1)


def background_homography(
    pts: Float[Array, "n 2"],
    flow: Float[Array, "n 2"],
    valid: Bool[Array, " n"],
    n_hypotheses: int = 64,
    inlier_px: float = 1.0,
    n_refine: int = 3,
    seed: int = 0,
) -> Float[Array, "3 3"]:
    """The dominant (background) image motion between two frames as one homography,
    ``pts + flow ~ H pts``, by RANSAC in JAX: ``n_hypotheses`` normalised DLTs on random
    4-point samples of the valid points (a fixed ``seed``: deterministic) plus the median
    translation, scored by their number of inliers (transfer error < ``inlier_px``); the best
    is refined ``n_refine`` times by the weighted DLT on its inliers (error < 2 x inlier_px).
    Algebraic DLT is not robust: even a 10 % weight on a block of points moving 6 px
    differently bends the fit by pixels, so the outliers (the arm, a pushed object) must get
    zero weight, not a small one. Camera rotation and zoom give exactly a homography
    (H = K R K^-1); camera translation is approximated for a distant, near-planar scene.
    Fewer than 8 valid points, or no finite fit, give the identity."""
    w0 = valid.astype(pts.dtype)
    n = pts.shape[0]
    dst = pts + flow
    nvalid = jnp.sum(w0)
    prob = jnp.where(nvalid > 0, w0 / jnp.maximum(nvalid, 1.0), jnp.full(n, 1.0 / n, pts.dtype))
    idx = jax.random.choice(jax.random.PRNGKey(seed), n, (n_hypotheses, 4), p=prob)
    seg = jnp.repeat(jnp.arange(n_hypotheses), 4)
    hyp = weighted_homographies(
        pts[idx].reshape(-1, 2),
        dst[idx].reshape(-1, 2),
        seg,
        jnp.ones(4 * n_hypotheses, pts.dtype),
        n_hypotheses,
    )
    med = jnp.nanmedian(jnp.where(valid[:, None], flow, jnp.nan), axis=0)
    med = jnp.where(jnp.isfinite(med), med, 0.0)
    Ht = jnp.eye(3, dtype=pts.dtype).at[:2, 2].set(med)
    hyp = jnp.concatenate([Ht[None], hyp], axis=0)

    x, y, u, v = pts[:, 0], pts[:, 1], dst[:, 0], dst[:, 1]

    def sq_err(H):  # (..., 3, 3) -> (..., n) squared transfer errors, px^2
        h = tuple(H[..., i, j, None] for i in range(3) for j in range(3))
        px, py = _transfer(h, x, y)
        return (px - u) ** 2 + (py - v) ** 2

    e2 = sq_err(hyp)
    score = jnp.sum(w0[None] * (e2 < inlier_px**2), axis=1)
    score = jnp.where(jnp.all(jnp.isfinite(hyp), axis=(1, 2)), score, -1.0)
    H = hyp[jnp.argmax(score)]
    zero = jnp.zeros(n, jnp.int32)

    def body(_, H):
        w = w0 * (sq_err(H) < (2.0 * inlier_px) ** 2)
        Hn = weighted_homographies(pts, dst, zero, w, 1)[0]
        keep = (jnp.sum(w) >= 8) & jnp.all(jnp.isfinite(Hn))
        return jnp.where(keep, Hn, H)

    H = jax.lax.fori_loop(0, n_refine, body, H)
    ok = jnp.all(jnp.isfinite(H)) & (jnp.abs(H[2, 2]) > 1e-9) & (nvalid >= 8)
    h22 = jnp.where(ok, H[2, 2], 1.0)
    return jnp.where(ok, H / h22, jnp.eye(3, dtype=pts.dtype))


def stabilise_flow(
    pts: Float[Array, "n 2"],
    flow: Float[Array, "n 2"],
    valid: Bool[Array, " n"],
    n_hypotheses: int = 64,
    inlier_px: float = 1.0,
) -> tuple[Float[Array, "n 2"], Float[Array, "3 3"]]:
    """Flow relative to the background: f' = pi(H^-1 [p + f; 1]) - p with H
    :func:`background_homography` (px). Invalid points keep flow 0. Returns (f', H)."""
    H = background_homography(pts, flow, valid, n_hypotheses, inlier_px)
    Hi = jnp.linalg.inv(H)
    dst = pts + flow
    bx, by = _transfer(tuple(Hi[i, j] for i in range(3) for j in range(3)), dst[:, 0], dst[:, 1])
    back = jnp.stack([bx - pts[:, 0], by - pts[:, 1]], axis=1)
    return jnp.where(valid[:, None], back, 0.0), H
