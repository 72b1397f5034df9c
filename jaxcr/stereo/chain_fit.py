"""Joint fit of all segments of a concentric-tube backbone to both views' silhouettes.

Model. A CTR's exposed backbone is a chain of constant-curvature, torsion-free arcs with a
continuous tangent (each tube is precurved with constant curvature; where a tube ends the
next one continues along the same tangent). With the rod frame ``R(s) = [d1 d2 t]`` and
``dR/ds = R hat(u)``, segment ``i`` has a constant body curvature ``u_i = (ux, uy, 0)``
(1/m) over ``[S_i, S_{i+1})``; from the base point ``b`` and frame ``R_0``::

    R_{i+1} = R_i exp(L_i hat(u_i)),   p_{i+1} = p_i + R_i J_l(L_i u_i) (L_i e_z),
    X(s) = p_i + R_i J_l((s - S_i) u_i) ((s - S_i) e_z)

(``J_l`` = :func:`jaxcr.geometry.so3_left_jacobian`, exact for piecewise-constant
curvature). Segment ``i``'s curvature is ``|u_i|`` and its bending plane's normal (world) is
``R_i u_i / |u_i|``.

Data. Fitting each segment's plane and arc separately to triangulated points is fragile
where the stereo correspondence is ill-conditioned: where the backbone runs along the
epipolar lines, or is foreshortened in one view, the triangulated points slide in a
direction neither view measures, and a short or nearly straight segment's plane swings.
Here no triangulated point enters the cost. Each observation ``j`` is a backbone sample at
arclength ``s_j``; in view ``k`` its measurement is the centre ``c_jk`` of the tube's
silhouette across the tube (pixels, from :func:`jaxcr.stereo.diameter.profile_widths`)
and the unit image normal ``m_jk`` of the silhouette there. A cylinder's silhouette has
its centreline on the projected axis, and sliding along the silhouette is not measured,
so the residual is the *normal* distance (pixels)::

    r_jk = sqrt(w_jk) * m_jk . (project_k(X(s_j)) - c_jk)

which is the linearised reprojection error of the axis curve, each view weighted only in
the direction it measures (the information a triangulated point actually carries: rank 2
in general, rank 1 where the tangent lies in the epipolar plane). The model's shape
(continuity, constant curvature) fills in what the views do not fix. The weight ``w_jk``
is the sine of the angle between the tube axis and view ``k``'s ray (a tube foreshortened
by ``sin`` in a view yields that fraction of independent samples per unit arclength) times
a validity flag (silhouette width measured, clean cloth beside both edges). Outliers
(skeleton artefacts at crossings, end caps) get Huber weights (1 px) by iterative
reweighting. Solved by Levenberg-Marquardt (early-stopped, at most 20 iterations per pass,
never raises) over
``(b, two tilt angles of R_0, u_1..u_k)``; the roll of ``R_0`` about the tangent is a gauge
freedom (it only relabels ``d1, d2``) and is not a parameter.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float
from jaxcr.camera import Camera, project_points
from jaxcr.geometry import so3_exp, so3_left_jacobian
from jaxcr.stereo.diameter import (
    cylinder_diameters,
    edge_clearance,
    profile_widths,
    view_weights,
)
from jaxcr.stereo.fits import plane_angles

__all__ = [
    "chain_frames",
    "chain_points",
    "chain_segment_parameters",
    "init_chain",
    "fit_chain",
    "silhouette_observations",
    "observations_from_profiles",
    "fit_segments_jointly",
    "drop_inconsistent_widths",
    "pad_chain",
    "tail_observations",
]

# Parameter scaling (metres -> mm, 1/m -> 1/(100 m)): similar magnitudes for LM damping.
_B_SCALE = 1e-3
_U_SCALE = 100.0


def chain_frames(
    base: Float[Array, "3"],
    R0: Float[Array, "3 3"],
    curvatures: Float[Array, "k 2"],
    seg_start: Float[Array, " k"],
) -> tuple[Float[Array, "k 3 3"], Float[Array, "k 3"]]:
    """Frames ``R_i`` (k, 3, 3) and points ``p_i`` (k, 3) at the start of each segment.

    ``seg_start`` (k,) arclengths (m) where the segments start (``seg_start[0]`` is where
    ``base``/``R0`` sit, normally 0); ``curvatures`` (k, 2) body curvatures ``(ux, uy)``
    (1/m). Base frame in, base frame out (metres)."""
    u3 = jnp.concatenate([curvatures, jnp.zeros_like(curvatures[:, :1])], axis=1)
    lengths = jnp.diff(seg_start)
    ez = jnp.array([0.0, 0.0, 1.0], base.dtype)

    def step(carry, x):
        R, p = carry
        u, L = x
        Rn = R @ so3_exp(L * u)
        pn = p + R @ (so3_left_jacobian(L * u) @ (L * ez))
        return (Rn, pn), (Rn, pn)

    _, (Rs, ps) = jax.lax.scan(step, (R0, base), (u3[:-1], lengths))
    return jnp.concatenate([R0[None], Rs]), jnp.concatenate([base[None], ps])


def chain_points(
    base: Float[Array, "3"],
    R0: Float[Array, "3 3"],
    curvatures: Float[Array, "k 2"],
    seg_start: Float[Array, " k"],
    s: Float[Array, " n"],
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"]]:
    """Backbone points (n, 3) and unit tangents (n, 3) at arclengths ``s`` (n,) of the
    piecewise-constant-curvature chain (module docstring). Arclengths before
    ``seg_start[0]`` or past the last start extrapolate the first/last arc."""
    Rs, ps = chain_frames(base, R0, curvatures, seg_start)
    k = seg_start.shape[0]
    idx = jnp.clip(jnp.searchsorted(seg_start, s, side="right") - 1, 0, k - 1)
    h = s - seg_start[idx]
    u3 = jnp.concatenate([curvatures, jnp.zeros_like(curvatures[:, :1])], axis=1)[idx]
    ez = jnp.array([0.0, 0.0, 1.0], base.dtype)

    def one(R, p, u, hh):
        X = p + R @ (so3_left_jacobian(hh * u) @ (hh * ez))
        t = R @ (so3_exp(hh * u) @ ez)
        return X, t

    return jax.vmap(one)(Rs[idx], ps[idx], u3, h)


def chain_segment_parameters(
    base: Float[Array, "3"],
    R0: Float[Array, "3 3"],
    curvatures: Float[Array, "k 2"],
    seg_start: Float[Array, " k"],
) -> tuple[Float[Array, " k"], Float[Array, "k 3"]]:
    """Per segment: curvature ``|u_i|`` (1/m) and the unit normal of the bending plane in
    the base frame, ``R_i u_i / |u_i|`` (sign made deterministic as in
    :func:`jaxcr.stereo.fits.fit_plane`: largest-magnitude component non-negative). A
    straight segment (``u_i = 0``) has no bending plane: its normal is returned as the
    frame's ``d1`` (finite, gradient-safe)."""
    Rs, _ = chain_frames(base, R0, curvatures, seg_start)
    kappa2 = jnp.sum(curvatures**2, axis=1)
    straight = kappa2 < 1e-20
    kappa = jnp.sqrt(jnp.where(straight, 1.0, kappa2))
    dirs = jnp.where(straight[:, None], jnp.array([1.0, 0.0]), curvatures / kappa[:, None])
    d3 = jnp.concatenate([dirs, jnp.zeros_like(dirs[:, :1])], axis=1)
    n = jnp.einsum("kij,kj->ki", Rs, d3)
    big = jnp.argmax(jnp.abs(n), axis=1)
    sign = jnp.sign(jnp.take_along_axis(n, big[:, None], axis=1))
    return jnp.where(straight, 0.0, kappa), n * sign


def _frame_from_tangent(t: np.ndarray) -> np.ndarray:
    t = t / np.linalg.norm(t)
    a = np.array([1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, t)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(t, x), t], axis=1)


def _min_rotations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotations (n, 3, 3) taking unit vectors ``a`` (n, 3) to ``b`` (n, 3)
    (Rodrigues form ``I + V + V^2 / (1 + c)``, ``V = hat(a x b)``, ``c = a . b``); the
    identity where ``c <= -0.999`` (nearly opposite: the axis is undefined)."""
    v = np.cross(a, b)
    c = np.clip(np.sum(a * b, axis=1), -1.0, 1.0)
    z = np.zeros(len(v))
    V = np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], 1),
            np.stack([v[:, 2], z, -v[:, 0]], 1),
            np.stack([-v[:, 1], v[:, 0], z], 1),
        ],
        1,
    )
    flip = c <= -0.999
    Rm = np.eye(3) + V + (V @ V) / np.where(flip, 1.0, 1.0 + c)[:, None, None]
    Rm[flip] = np.eye(3)
    return Rm


def _transport_frames(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation-minimising frames (n, 3, 3) along unit tangents ``t`` (n, 3), starting from
    ``R`` (3, 3) at sample 0: ``F_0 = R``, ``F_i = M_i F_{i-1}`` with ``M_i`` the minimal
    rotation taking ``F_{i-1}``'s third column to ``t_i``. After a step ``F_i e_z = t_i``,
    so every ``M_i`` (``i >= 2``) is known up front and the frames are prefix products,
    computed in ``log2 n`` batched matrix products (Hillis-Steele scan). A step between
    nearly opposite tangents (identity, see :func:`_min_rotations`) breaks that; then the
    sequential loop runs instead (same result)."""
    n = len(t)
    a = np.concatenate([R[None, :, 2], t[1:-1]])[: max(n - 1, 0)]
    Rm = _min_rotations(a, t[1:])
    flipped = np.sum(a * t[1:], axis=1) <= -0.999
    if flipped.any():
        frames = np.empty((n, 3, 3))
        frames[0] = R
        for i in range(1, n):
            frames[i] = _min_rotations(frames[i - 1][None, :, 2], t[i : i + 1])[0] @ frames[i - 1]
        return frames
    Q = np.concatenate([R[None], Rm])
    d = 1
    while d < n:
        Q[d:] = Q[d:] @ Q[:-d]
        d *= 2
    return Q


def init_chain(
    s: np.ndarray, p: np.ndarray, seg_start: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starting values ``(base (3,), R0 (3, 3), curvatures (k, 2))`` from an ordered,
    smoothed 3-D backbone ``p`` (n, 3) at arclengths ``s`` (n,) (m).

    The base is ``p[0]`` moved back along the first tangent to ``seg_start[0]``; the frame
    is transported along the points without twist (rotation-minimising frame); each
    segment's body curvature is the median over its samples of ``R^T (t x dt/ds)``."""
    s = np.asarray(s, np.float64)
    p = np.asarray(p, np.float64)
    t = np.gradient(p, s, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n0 = min(len(s) - 1, max(2, int(np.searchsorted(s, s[0] + 2e-3))))
    t0 = p[n0] - p[0]
    t0 /= np.linalg.norm(t0)
    R = _frame_from_tangent(t0)
    frames = _transport_frames(R, t)
    dt = np.gradient(t, s, axis=0)
    kw = np.cross(t, dt)  # curvature vector (world), |kw| = curvature
    body = np.einsum("nji,nj->ni", frames, kw)[:, :2]
    ends = list(seg_start[1:]) + [np.inf]
    curv = np.zeros((len(seg_start), 2))
    for i, (a, b) in enumerate(zip(seg_start, ends, strict=True)):
        sel = (s >= a) & (s < b)
        if sel.sum() >= 3:
            curv[i] = np.median(body[sel], axis=0)
    base = p[0] - (s[0] - seg_start[0]) * t0
    return base, R, curv


def _dev(x, dt):
    """``x`` as a device array of dtype ``dt``. Host values are converted by numpy and put on
    the device: ``jnp.asarray`` would compile a small staging or conversion program per
    shape, each a compilation in a first process and a cache load in a second (issue 18)."""
    if isinstance(x, jax.Array):
        return x if x.dtype == dt else x.astype(dt)
    return jax.device_put(np.asarray(x, dtype=np.dtype(dt)))


def _direct(fn, *args):
    """``fn(*args)``: the default ``jit_call`` (see :func:`fit_chain`)."""
    return fn(*args)


#: Segments of the chain are padded to a multiple of this many (:func:`pad_chain`).
SEGMENT_PAD = 4
#: Arclength (m) where padding segments start: beyond every backbone (the pipeline refuses
#: backbones over 5 m, ``pipeline.MAX_BACKBONE_M``; tails add at most 5 cm), so no sample,
#: observation or search grid reaches them.
PAD_START = 100.0


def pad_chain(curvatures, seg_start) -> tuple[np.ndarray, np.ndarray]:
    """The chain's ``curvatures`` (k, 2) and ``seg_start`` (k,) padded to ``K`` segments
    (``K`` the multiple of :data:`SEGMENT_PAD` at or above ``k``): zero curvatures starting at
    :data:`PAD_START`. :func:`chain_points` at any arclength below ``PAD_START`` is unchanged
    (each point uses its own segment's frame, and the frames up to the last real segment
    do not depend on later segments), so the jitted chain functions compile once for 1-4
    segments instead of once per segment count (issue 18, docs/decisions.md S23)."""
    curvatures = np.asarray(curvatures, np.float64).reshape(-1, 2)
    seg_start = np.asarray(seg_start, np.float64).reshape(-1)
    k = len(seg_start)
    K = max(SEGMENT_PAD, -(-k // SEGMENT_PAD) * SEGMENT_PAD)
    return (
        np.concatenate([curvatures, np.zeros((K - k, 2))]),
        np.concatenate([seg_start, np.full(K - k, PAD_START)]),
    )


def _pack(base0, R_init, theta, k):
    base = base0 + _B_SCALE * theta[:3]
    R0 = R_init @ so3_exp(jnp.concatenate([theta[3:5], jnp.zeros(1, theta.dtype)]))
    curv = _U_SCALE * theta[5:].reshape(k, 2)
    return base, R0, curv


def _residuals(theta, args):
    base0, R_init, seg_start, s_obs, cam1, cam2, centres, normals, sqrt_w = args
    k = seg_start.shape[0]
    base, R0, curv = _pack(base0, R_init, theta, k)
    X, _ = chain_points(base, R0, curv, seg_start, s_obs)
    out = []
    for v, cam in enumerate((cam1, cam2)):
        uv, _ = project_points(cam, X)
        out.append(sqrt_w[v] * jnp.sum(normals[v] * (uv - centres[v]), axis=1))
    return jnp.concatenate(out)


def _lm(theta0, args, max_iterations: int, ftol: float, xtol: float):
    """Levenberg-Marquardt with Marquardt's diagonal scaling (traceable, not jitted).

    Iterates while not converged, at most ``max_iterations`` times (``lax.while_loop``:
    one compile per shape, no Python loop). Converged when a trial step (accepted or not)
    changed the cost by at most ``ftol`` relative (plus ``(1e-4 px)^2`` per residual, the
    float32 floor: a rejected step that close means the minimum is reached at float32
    precision), or changed no scaled parameter by more than ``xtol`` (see :func:`fit_chain`),
    or the cost vanished. ``ftol = xtol = 0`` never stops
    early (the fixed-iteration reference). Returns ``(theta, residuals at theta,
    converged, iterations)``."""
    n_res = 2 * args[3].shape[0]
    atol = 1e-8 * n_res

    def res_aux(th):
        r = _residuals(th, args)
        return r, r

    def cond(carry):
        i, _, _, _, _, done = carry
        return (i < max_iterations) & ~done

    def body(carry):
        i, th, r, lam, c, _ = carry
        J, r = jax.jacfwd(res_aux, has_aux=True)(th)
        A = J.T @ J
        g = J.T @ r
        D = jnp.diag(jnp.diag(A)) + 1e-12 * jnp.eye(A.shape[0], dtype=A.dtype)
        step = -jnp.linalg.solve(A + lam * D, g)
        th_new = th + step
        r_new = _residuals(th_new, args)
        c_new = jnp.sum(r_new * r_new)
        better = c_new < c
        small = (jnp.abs(c - c_new) <= ftol * c + atol) | (jnp.max(jnp.abs(step)) <= xtol)
        done = small | (jnp.minimum(c, c_new) <= atol)
        # the fixed-iteration reference (ftol and xtol are traced: one program for both)
        done = done & ~((ftol == 0.0) & (xtol == 0.0))
        return (
            i + 1,
            jnp.where(better, th_new, th),
            jnp.where(better, r_new, r),
            jnp.where(better, lam * 0.3, lam * 10.0),
            jnp.where(better, c_new, c),
            done,
        )

    r0 = _residuals(theta0, args)
    one = jnp.asarray(1.0, theta0.dtype)
    carry = (0, theta0, r0, 1e-3 * one, jnp.sum(r0 * r0), jnp.asarray(False))
    i, th, r, _, _, done = jax.lax.while_loop(cond, body, carry)
    return th, r, done, i


@functools.partial(jax.jit, static_argnames=("passes", "max_iterations"))
def _robust_solve(theta0, args0, w, huber_px, passes: int, max_iterations: int,
                  ftol: Array, xtol: Array):  # fmt: skip
    """All Huber reweighting passes of :func:`fit_chain` in one compiled call (``ftol`` and
    ``xtol`` traced, so the fixed-iteration reference shares the program): each pass
    solves with weights ``w * huber`` (:func:`_lm`) and recomputes the Huber factors
    (scale ``huber_px``) from the unweighted normal residuals. Returns ``(theta,
    unweighted residuals (2, n), Huber factors (2, n), converged in every pass, total
    iterations)``."""

    def one_pass(_, carry):
        theta, _, robust, ok, steps = carry
        args = (*args0, jnp.sqrt(w * robust))
        theta, _, conv, n = _lm(theta, args, max_iterations, ftol, xtol)
        r = _residuals(theta, (*args0, jnp.ones_like(w))).reshape(2, -1)
        a = jnp.abs(r)
        robust = jnp.where(a <= huber_px, 1.0, huber_px / jnp.maximum(a, 1e-12))
        return theta, r, robust, ok & conv, steps + n

    # The passes as a loop, not unrolled: one copy of the LM solver in the program (half the
    # compile time of two unrolled passes; docs/decisions.md S23).
    r0 = jnp.zeros((2, w.shape[-1]), theta0.dtype)
    carry = (theta0, r0, jnp.ones_like(w), jnp.asarray(True), jnp.asarray(0))
    return jax.lax.fori_loop(0, passes, one_pass, carry)


@functools.partial(jax.jit, static_argnames=("k",))
def _finish(theta, base0, R_init, seg_start, k):
    base, R0, curv = _pack(base0, R_init, theta, k)
    kappa, normal = chain_segment_parameters(base, R0, curv, seg_start)
    return base, R0, curv, kappa, normal


def fit_chain(
    cam1: Camera,
    cam2: Camera,
    s_obs: Float[Array, " n"],
    centres: Float[Array, "2 n 2"],
    normals: Float[Array, "2 n 2"],
    weights: Float[Array, "2 n"],
    seg_start: Float[Array, " k"],
    base0: Float[Array, "3"],
    R0_init: Float[Array, "3 3"],
    curvatures0: Float[Array, "k 2"],
    huber_px: float = 1.0,
    reweight: int = 3,
    max_iterations: int = 20,
    ftol: float = 1e-6,
    xtol: float = 1e-4,
    jit_call=None,
) -> dict:
    """Fit the chain (module docstring) to silhouette centres in two views.

    ``cam1``/``cam2`` map base-frame points to pixels (distortion included).
    Observations ``j``: arclength ``s_obs[j]`` (m), per view the silhouette centre
    ``centres[v, j]`` (pixels), unit image normal ``normals[v, j]`` and weight
    ``weights[v, j]`` (0 ignores it: padding, unusable views). ``seg_start`` (k,) segment
    start arclengths (m, first = where ``base0`` sits). Starting values from
    :func:`init_chain`. ``reweight``: Huber reweighting passes (scale ``huber_px``), all
    in one compiled call. Each pass is Levenberg-Marquardt stopped early
    (:func:`_lm`) when an accepted step lowers the cost by at most ``ftol`` relative or
    moves no scaled parameter by more than ``xtol`` (scaled units: mm for the base,
    rad for the tilts, 100/m for curvatures: ``xtol = 1e-4`` is 0.1 um, 1e-4 rad, 0.01 /m), at
    most ``max_iterations`` iterations; ``ftol = xtol = 0`` runs all of them.

    Returns (numpy) ``base`` (3,), ``R0`` (3, 3), ``curvatures`` (k, 2) body (1/m),
    ``kappa`` (k,), ``normal`` (k, 3) bending-plane normals, ``rms_px`` (weighted RMS of the
    normal residuals), ``ok`` (solver converged in every pass), ``num_steps``,
    ``residuals_px`` (2, n) unweighted normal residuals and ``weights`` (2, n) final
    weights (including the Huber factors).

    The chain is solved with its segments padded to a multiple of four (:func:`pad_chain`:
    the extra segments start beyond every observation, so no residual depends on them and
    their steps are zero), so that one compiled solver serves 1-4 segments. ``jit_call``:
    how the compiled functions are called, ``jit_call(fn, *args)`` (default ``fn(*args)``;
    the CLI passes :func:`jaxcr.io.exported.cached_call`, so that a second process loads
    the traced solver instead of tracing it again)."""
    call = jit_call or _direct
    k = int(np.shape(seg_start)[0])
    curvatures0, seg_start = pad_chain(curvatures0, seg_start)
    dt = jnp.result_type(float)
    w = _dev(weights, dt)
    args0 = [
        _dev(base0, dt),
        _dev(R0_init, dt),
        _dev(seg_start, dt),
        _dev(s_obs, dt),
        cam1,
        cam2,
        _dev(centres, dt),
        _dev(normals, dt),
    ]
    # on the host in the solver's dtype, times the reciprocal as XLA computes the division by
    # a constant (bit-identical to the former eager jnp expression; no eager programs)
    ft = np.dtype(dt)
    curv_scaled = np.asarray(curvatures0, ft).ravel() * ft.type(1.0 / _U_SCALE)
    theta = _dev(np.concatenate([np.zeros(5, ft), curv_scaled]), dt)
    theta, r, robust, ok, steps = call(
        _robust_solve, theta, tuple(args0), w, _dev(huber_px, dt), max(reweight, 1),
        int(max_iterations), _dev(ftol, dt), _dev(xtol, dt),
    )  # fmt: skip
    r = np.asarray(r)
    base, R0, curv, kappa, normal = call(
        _finish, theta, args0[0], args0[1], args0[2], len(seg_start)
    )
    # the padding segments dropped (on the host: no eager slicing programs)
    curv, kappa, normal = (np.asarray(x)[:k] for x in (curv, kappa, normal))
    wn = np.asarray(w) * np.asarray(robust)
    rms = float(np.sqrt(np.sum(wn * r**2) / max(np.sum(wn), 1e-12)))
    return {
        "base": np.asarray(base, np.float64),
        "R0": np.asarray(R0, np.float64),
        "curvatures": np.asarray(curv, np.float64),
        "kappa": np.asarray(kappa, np.float64),
        "normal": np.asarray(normal, np.float64),
        "rms_px": rms,
        "ok": bool(ok),
        "num_steps": int(steps),
        "residuals_px": r,
        "weights": wn,
    }


@jax.jit
def silhouette_observations(
    cam: Camera,
    alpha: Float[Array, "h w"],
    key_proj: Float[Array, "h w"],
    points: Float[Array, "n 3"],
    tangents: Float[Array, "n 3"],
) -> tuple[Float[Array, "n 2"], Float[Array, "n 2"], Float[Array, " n"]]:
    """One view's measurements for :func:`fit_chain` at backbone samples ``points`` (n, 3)
    (base frame, m) with unit ``tangents``: silhouette centres across the tube (pixels),
    the unit image normals along which they were measured, and the weights (sine of the
    angle between the tube and the viewing ray; 0 where the projection is invalid, no
    width was measured or another part of the robot lies beside an edge, see
    :func:`jaxcr.stereo.diameter.edge_clearance`). ``alpha``: the robot's foreground alpha;
    ``key_proj``: the key-colour projection (:func:`profile_widths`). Also returns the
    diameters (m) those widths give (:func:`jaxcr.stereo.diameter.cylinder_diameters`),
    for a consistency check by the caller."""
    uv0, ok = project_points(cam, points)
    uv1, _ = project_points(cam, points + 1e-4 * tangents)
    du = uv1 - uv0
    nrm = jnp.stack([-du[:, 1], du[:, 0]], axis=1)
    nrm = nrm / jnp.maximum(jnp.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    width, offset = profile_widths(alpha, uv0, nrm, key_proj)
    clean = edge_clearance(alpha, uv0, nrm, width, offset)
    return observations_from_profiles(cam, points, tangents, uv0, ok, nrm, width, offset, clean)


def observations_from_profiles(
    cam: Camera,
    points: Float[Array, "n 3"],
    tangents: Float[Array, "n 3"],
    uv0: Float[Array, "n 2"],
    ok: Float[Array, " n"],
    nrm: Float[Array, "n 2"],
    width: Float[Array, " n"],
    offset: Float[Array, " n"],
    clean: Float[Array, " n"],
) -> tuple[Float[Array, "n 2"], Float[Array, "n 2"], Float[Array, " n"], Float[Array, " n"]]:
    """:func:`silhouette_observations` from width profiles already measured (traceable):
    projections ``uv0`` (pixels) of ``points`` and their validity ``ok``, unit image
    normals ``nrm``, silhouette ``width``/centre ``offset`` along them (pixels,
    :func:`jaxcr.stereo.diameter.profile_widths`) and the edge-clearance flag ``clean``
    (:func:`jaxcr.stereo.diameter.edge_clearance`). Lets the pipeline reuse its diameter
    stage's profiles instead of measuring them again."""
    sin_view = view_weights(cam, points, tangents)
    w = jnp.where(ok & (width > 0.5) & (clean > 0), sin_view, 0.0)
    d = cylinder_diameters(cam, points, tangents, uv0, nrm, width, offset)
    return uv0 + offset[:, None] * nrm, nrm, w, jnp.where(jnp.isfinite(d), d, 0.0)


@functools.partial(jax.jit, static_argnames=("n_grid",))
def _reparametrise(base, R0, curv, seg_start, s_obs, cam1, cam2, centres, weights,
                   half_window, n_grid: int = 81):  # fmt: skip
    """Arclength of each observation on the current chain: the ``s`` within
    ``half_window`` of ``s_obs`` whose projections are nearest (weighted squared pixel
    distance over both views) to the observation's silhouette centres."""
    offs = jnp.linspace(-half_window, half_window, n_grid)
    cand = jnp.maximum(s_obs[:, None] + offs[None], 0.0)
    X, _ = chain_points(base, R0, curv, seg_start, cand.ravel())
    cost = 0.0
    for v, cam in enumerate((cam1, cam2)):
        uv, _ = project_points(cam, X)
        d2 = jnp.sum((uv.reshape(*cand.shape, 2) - centres[v][:, None]) ** 2, axis=-1)
        cost = cost + weights[v][:, None] * d2
    return jnp.take_along_axis(cand, jnp.argmin(cost, axis=1)[:, None], axis=1)[:, 0]


def drop_inconsistent_widths(
    weights: np.ndarray,
    diameters: np.ndarray,
    s: np.ndarray,
    seg_start: np.ndarray,
    max_dev: float = 0.15,
    min_weight: float = 0.25,
) -> np.ndarray:
    """Weights (2, n) with observations zeroed whose silhouette diameter (2, n) deviates
    from their segment's median by more than ``max_dev`` (relative).

    A silhouette wider or narrower than the segment's tube is another part of the robot
    overlapping it in that view (a curled tip lying on the shaft) or a partial occlusion:
    its centre is biased. The width is only a diameter where the view is not nearly
    end-on (weight = sin >= ``min_weight``, the pipeline's usable-view limit for the
    refinement): more foreshortened views of a curved tube have wider silhouettes without
    being contaminated, and keep their centres. The median is taken over those views'
    observations of the segment (``s`` (n,) arclengths, ``seg_start`` (k,) starts)."""
    ws = np.asarray(weights, np.float64).copy()
    ds = np.asarray(diameters, np.float64)
    seg_of = np.clip(np.searchsorted(seg_start, s, side="right") - 1, 0, None)
    usable = ws >= min_weight
    for i in range(len(seg_start)):
        sel = (seg_of[None] == i) & usable
        if sel.any():
            d_ref = np.nanmedian(ds[sel])
            dev = np.abs(ds / max(d_ref, 1e-12) - 1.0) > max_dev
            ws[sel & dev] = 0.0
    return ws


@functools.partial(jax.jit, static_argnames=("n_grid",))
def _tail_measure(base, R0, curv, seg_start, cam, uv, nrm, s_lo, s_hi, alpha, key_proj,
                  n_grid: int = 257):  # fmt: skip
    """:func:`tail_observations` after the pixel sampling, in one compiled call (``uv``,
    ``nrm`` padded to a bucket by repeating the last row): per pixel the arclength in
    ``[s_lo, s_hi]`` whose projection in ``cam`` is nearest, made non-decreasing; the
    chain's points and tangents there; the measured observations (or, with ``alpha``
    None, the pixels themselves, the sine weights and NaN diameters)."""
    cand = jnp.linspace(s_lo, s_hi, n_grid)
    Xc, _ = chain_points(base, R0, curv, seg_start, cand)
    proj, _ = project_points(cam, Xc)
    d2 = jnp.sum((proj[None] - uv[:, None]) ** 2, axis=-1)
    s_t = jax.lax.cummax(cand[jnp.argmin(d2, axis=1)])
    X, t3 = chain_points(base, R0, curv, seg_start, s_t)
    if alpha is None:
        return s_t, uv, nrm, view_weights(cam, X, t3), jnp.full(s_t.shape, jnp.nan)
    width, offset = profile_widths(alpha, uv, nrm, key_proj)
    clean = edge_clearance(alpha, uv, nrm, width, offset)
    ok = jnp.ones(uv.shape[0], bool)
    return s_t, *observations_from_profiles(cam, X, t3, uv, ok, nrm, width, offset, clean)


def tail_observations(
    cam: Camera,
    tail_uv: np.ndarray,
    fit: dict,
    seg_start: np.ndarray,
    s_end: float,
    max_extension: float,
    spacing_px: float = 2.0,
    alpha: np.ndarray | None = None,
    key_proj: np.ndarray | None = None,
    jit_call=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Single-view observations of the backbone beyond the last stereo-matched sample.

    Where a tip is foreshortened or folded in one view the stereo matching stops early,
    but the other view still sees the tube: its ordered skeleton continues beyond the
    projection of the last reconstructed point. Each skeleton pixel there is a centre of
    the tube's silhouette (a thinned cylinder's silhouette lies on its projected axis), and
    only the direction across the skeleton is measured, exactly the residual of
    :func:`fit_chain` with the other view's weight 0. ``tail_uv`` (t, 2): those ordered
    pixels (u, v; distorted image), taken every ``spacing_px`` of image arclength. Each
    gets the arclength in ``[s_end, s_end + max_extension]`` (m) of the current chain
    ``fit`` (extrapolated along its last arc) whose projection is nearest, made
    non-decreasing along the tail; the refit and the arclength re-reading
    (:func:`_reparametrise`) then move both. With the view's robot ``alpha`` and
    ``key_proj`` the centres are measured across the skeleton like the stereo
    observations' (:func:`observations_from_profiles`: sub-pixel silhouette centre, weight
    0 where no width was measured or another part of the robot lies beside an edge, and the
    diameter for :func:`drop_inconsistent_widths`); without, the skeleton pixels are the
    centres and the diameters NaN. Returns ``(s (t,), centres (t, 2), unit image normals
    (t, 2), weights (t,), diameters (t,) m)``; the weight is the sine of the angle between
    the chain's tangent and the viewing ray (as for the stereo observations). ``jit_call``:
    as :func:`fit_chain`'s."""
    uv = np.asarray(tail_uv, np.float64)
    if len(uv) < 3:
        z = np.zeros((0, 2))
        return np.zeros(0), z, z, np.zeros(0), np.zeros(0)
    seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    idx = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1] + 1e-9, spacing_px)))
    idx = idx[idx < len(uv)]
    tang = np.gradient(uv, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    nrm = np.stack([-tang[:, 1], tang[:, 0]], axis=1)[idx]
    uv = uv[idx]
    dt = jnp.result_type(float)
    n_t = len(uv)
    m = _bucket(n_t, 32)  # shape bucket: powers of two from 32 samples

    def pad(x):
        return _dev(np.concatenate([x, np.repeat(x[-1:], m - n_t, axis=0)]), dt)

    curv, seg_start = pad_chain(fit["curvatures"], seg_start)
    out = (jit_call or _direct)(
        _tail_measure,
        *(_dev(x, dt) for x in (fit["base"], fit["R0"], curv)),
        _dev(seg_start, dt), cam, pad(uv), pad(nrm), _dev(s_end, dt),
        _dev(s_end + max_extension, dt),
        None if alpha is None else _dev(alpha, dt),
        None if key_proj is None else _dev(key_proj, dt),
    )  # fmt: skip
    return tuple(np.asarray(x, np.float64)[:n_t] for x in out)


_plane_angles_jit = jax.jit(jax.vmap(plane_angles))


def _plane_angles(normals: np.ndarray) -> np.ndarray:
    """:func:`plane_angles` of each row of ``normals`` (k, 3), as float64 numpy; the rows
    padded to :data:`SEGMENT_PAD` (one compile for 1-4 segments)."""
    n = np.asarray(normals, np.float32).reshape(-1, 3)
    k = len(n)
    K = max(SEGMENT_PAD, -(-k // SEGMENT_PAD) * SEGMENT_PAD)
    pad = np.concatenate([n, np.tile(np.float32([0.0, 0.0, 1.0]), (K - k, 1))])
    return np.asarray(_plane_angles_jit(jax.device_put(pad)), np.float64)[:k]


def _bucket(n: int, size: int = 256) -> int:
    """``n`` rounded up to ``size`` times a power of two (few shapes to compile: 256, 512,
    1024 observations)."""
    m = size
    while m < n:
        m *= 2
    return m


def fit_segments_jointly(
    cams: tuple[Camera, Camera],
    alphas: tuple[np.ndarray, np.ndarray],
    key_projs: tuple,
    s: np.ndarray,
    p: np.ndarray,
    boundaries_s: np.ndarray,
    huber_px: float = 1.0,
    reparametrise: int = 1,
    reparam_window: float = 5e-3,
    max_width_dev: float = 0.15,
    reweight: int = 2,
    obs_spacing: float = 5e-4,
    observations: tuple | None = None,
    tails: tuple | None = None,
    max_extension: float = 0.05,
    jit_call=None,
) -> dict:
    """Per-segment curvature, bending plane and arc length of a reconstructed backbone by
    the joint chain fit (module docstring), for the stereo pipeline.

    ``cams``: both views with the base pose; ``alphas``: each view's robot alpha (H, W);
    ``key_projs``: key-colour projections; ``s`` (n,), ``p`` (n, 3): the triangulated,
    resampled backbone (arclength from the base, m); ``boundaries_s`` (k-1,): segment
    boundaries (m). ``reparametrise``: passes of re-reading each observation's arclength
    on the fitted chain (within ``reparam_window`` m) and refitting. ``max_width_dev``:
    see :func:`drop_inconsistent_widths` (the pipeline's diameter fusion uses the same
    15 % disagreement rule). ``reweight``: Huber passes per fit (:func:`fit_chain`).
    ``obs_spacing``: arclength between observations (m; 1 mm is ~3.5 px at 0.29 mm/px).
    Returns numpy arrays ``kappa`` (k,) 1/m, ``normal`` (k, 3),
    ``angles_deg`` (k, 3) (X-Y, Z-X, Y-Z planes), ``arc_length`` (k,) m (the last segment
    up to the last observed sample), ``rms_px``, ``ok``, ``weights`` (2, n) used.
    ``observations``: optionally, both views' :func:`silhouette_observations` outputs
    ``(centres (2, n, 2), normals (2, n, 2), weights (2, n), diameters (2, n))`` already
    measured at every sample of ``p`` with unit tangents ``np.gradient(p, axis=0)``
    (e.g. from :func:`observations_from_profiles` in the pipeline's diameter stage; the
    same as measured here when ``s`` is uniformly spaced); else they are measured.
    ``tails``: optionally, per view ``None`` or the ordered skeleton pixels (t, 2) (u, v)
    continuing beyond the projection of the last sample of ``p`` (the part of the tube
    the stereo matching lost, e.g. a tip foreshortened in the other view). After the
    first fit they enter as single-view observations (:func:`tail_observations`, at most
    ``max_extension`` m past the last sample), the chain's last arc extends over them and
    the last segment's ``arc_length`` reaches their last arclength; ``n_tail`` (2,) says
    how many each view contributed. ``jit_call``: as :func:`fit_chain`'s."""
    call = jit_call or _direct
    s = np.asarray(s, np.float64)
    p = np.asarray(p, np.float64)
    seg_start = np.concatenate([[0.0], np.asarray(boundaries_s, np.float64)])
    base0, R_init, curv0 = init_chain(s, p, seg_start)
    tang = np.gradient(p, s, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    # Observations every obs_spacing of arclength (silhouette centres closer than a few
    # pixels are not independent measurements); the last sample is always kept.
    stride = max(1, int(round(obs_spacing / max(np.median(np.diff(s)), 1e-12))))
    keep = np.unique(np.r_[np.arange(0, len(s), stride), len(s) - 1])
    s, p, tang = s[keep], p[keep], tang[keep]
    n = len(s)
    m = _bucket(n)

    def pad(x):
        return np.concatenate([x, np.repeat(x[-1:], m - n, axis=0)]) if m > n else x

    dt = jnp.result_type(float)
    if observations is not None:
        obs = [np.asarray(x)[:, keep] for x in observations]
        cs, ns = (np.stack([pad(x[v]) for v in range(2)]) for x in obs[:2])
        ws, ds = (np.stack([pad(np.asarray(x[v], np.float64)) for v in range(2)]) for x in obs[2:])
        ws[:, n:] = 0.0
    else:
        cs, ns, ws, ds = [], [], [], []
        for cam, a, kp in zip(cams, alphas, key_projs, strict=True):
            c, nr, w, d = silhouette_observations(
                cam, _dev(a, dt), _dev(kp, dt), _dev(pad(p), dt),
                _dev(pad(tang), dt),
            )  # fmt: skip
            w = np.asarray(w, np.float64)
            w[n:] = 0.0
            cs.append(np.asarray(c))
            ns.append(np.asarray(nr))
            ws.append(w)
            ds.append(np.asarray(d, np.float64))
    cs, ns, ws, ds = (np.stack(x) for x in (cs, ns, ws, ds))
    ws = drop_inconsistent_widths(ws, ds, pad(s), seg_start, max_width_dev)
    s_obs = pad(s)
    fit = fit_chain(
        cams[0], cams[1], s_obs, cs, ns, ws, seg_start, base0, R_init, curv0,
        huber_px=huber_px, reweight=reweight, jit_call=call,
    )  # fmt: skip
    n_real, n_tail = n, np.zeros(2, int)
    if tails is not None and any(x is not None and len(x) >= 3 for x in tails):
        # The tube beyond the last stereo match, seen by one view only (tail_observations).
        s_end = float(s[-1])
        s_all, c_all, n_all, w_all = [s], [cs[:, :n]], [ns[:, :n]], [ws[:, :n]]
        d_all = [ds[:, :n]]
        for v in range(2):
            if tails[v] is None:
                continue
            st, c, nr, w, d = tail_observations(
                cams[v], tails[v], fit, seg_start, s_end, max_extension,
                alpha=alphas[v], key_proj=key_projs[v], jit_call=call,
            )  # fmt: skip
            n_tail[v] = len(st)
            if len(st) == 0:
                continue
            c2, n2, w2 = (
                np.zeros((2, len(st), 2)),
                np.zeros((2, len(st), 2)),
                np.zeros((2, len(st))),
            )
            c2[v], n2[v], w2[v] = c, nr, w
            n2[1 - v, :, 0] = 1.0
            d2 = np.full((2, len(st)), np.nan)
            d2[v] = d
            s_all.append(st), c_all.append(c2), n_all.append(n2), w_all.append(w2)
            d_all.append(d2)
        n_real = n + int(n_tail.sum())
        m = _bucket(n_real)

        def padv(x):  # (2, n_real, ...) -> (2, m, ...), zero weight on padding
            x = np.concatenate(x, axis=1)
            return np.concatenate([x, np.repeat(x[:, -1:], m - n_real, axis=1)], axis=1)

        cs, ns, ws = padv(c_all), padv(n_all), padv(w_all)
        ws[:, n_real:] = 0.0
        s_cat = np.concatenate(s_all)
        s_obs = np.concatenate([s_cat, np.repeat(s_cat[-1:], m - n_real)])
        # The same width-consistency rule for the tail (a tip lying on the shaft in this
        # view); the stereo observations' weights stay as they were.
        w_rule = drop_inconsistent_widths(ws, padv(d_all), s_obs, seg_start, max_width_dev)
        ws[:, n:n_real] = w_rule[:, n:n_real]
        fit = fit_chain(
            cams[0], cams[1], s_obs, cs, ns, ws, seg_start, fit["base"], fit["R0"],
            fit["curvatures"], huber_px=huber_px, reweight=reweight, jit_call=call,
        )  # fmt: skip
    for _ in range(reparametrise):
        # Where the correspondence was ill-conditioned the triangulated points, hence
        # their arclengths, slid along the ambiguous direction; each observation's
        # arclength is re-read on the fitted chain (nearest in both images), and the
        # boundaries (found at observations) move with their observations.
        curv_pad, start_pad = pad_chain(fit["curvatures"], seg_start)
        s_new = np.asarray(
            call(
                _reparametrise,
                _dev(fit["base"], dt), _dev(fit["R0"], dt),
                _dev(curv_pad, dt), _dev(start_pad, dt),
                _dev(s_obs, dt), cams[0], cams[1], _dev(cs, dt),
                _dev(ws * fit["weights"] / np.maximum(ws, 1e-12), dt),
                _dev(reparam_window, dt),
            ),
            np.float64,
        )  # fmt: skip
        s_new[n_real:] = s_new[n_real - 1]
        lo = n
        for v in range(2):  # each view's tail stays ordered and beyond the stereo part
            hi = lo + n_tail[v]
            s_new[lo:hi] = np.maximum.accumulate(np.maximum(s_new[lo:hi], s[n - 1]))
            lo = hi
        mono = np.maximum.accumulate(s_new[:n])
        seg_start = np.concatenate([[0.0], np.interp(seg_start[1:], s[:n], mono)])
        s_obs = s_new
        fit = fit_chain(
            cams[0], cams[1], s_obs, cs, ns, ws, seg_start, fit["base"], fit["R0"],
            fit["curvatures"], huber_px=huber_px, reweight=reweight, jit_call=call,
        )  # fmt: skip
    ends = np.concatenate([seg_start[1:], [max(s_obs[:n_real].max(), seg_start[-1])]])
    return {
        "kappa": fit["kappa"],
        "normal": fit["normal"],
        "angles_deg": _plane_angles(fit["normal"]),
        "arc_length": ends - seg_start,
        "rms_px": fit["rms_px"],
        "ok": fit["ok"],
        "weights": ws[:, :n],
        "seg_start": seg_start,
        "n_tail": n_tail,
        "fit": fit,
    }
