"""Fit joint values q, and optionally a base-pose correction, to measurements of a real robot.

Two kinds of measurement (both pure JAX, no file I/O; the CLI is ``jaxcr fit``):

* a **measured 3-D backbone**: M points (metres) in a reference frame (e.g. a tracker's), not
  at known arclengths. Each point contributes the vector from it to its closest point on the
  model's sampled centreline (point-to-polyline, arclength-free), and the last point (the
  measured tip) also contributes ``tip_weight`` times the vector from it to the model tip,
  since a point-to-polyline distance alone does not see a model that is too long;
* **tip pixels** in calibrated views: the reprojection error (pixels) of the model tip through
  :func:`jaxcr.camera.project_points`, one 2-vector per camera.

The unknowns are q and, with ``fit_pose=True``, a twist ``xi`` (6,) with
``T_ref_robot = T0 @ se3_exp(xi)``: the robot base in the reference frame (backbone) or the
correction of the dataset's robot frame that the cameras see (``T_cam_robot @ T_ref_robot``).
A rotation about the robot's z axis is then equivalent to the bending-plane joints (phi,
delta, alpha) when they are fitted too; Levenberg-Marquardt's damping picks one of the
equivalent solutions, and the residuals do not depend on which.

Solver: ``optx.least_squares`` with ``optx.LevenbergMarquardt`` (``throw=False``; ``result``
and ``num_steps`` are returned). Joint limits are enforced by a reparametrisation (the solver
works on unconstrained ``z``, see :func:`joints_from_free`):

* ``constant_curvature``: a section ``length`` joint is ``softplus(z)`` (> 0); kappa, phi free.
* ``single_segment``: no limits (theta_L outside [-pi/2, pi/2] is the same arc bent the other
  way); the result is mapped back to the workspace by :func:`canonical_joints`.
* ``ctr``: sequential sigmoids for the translations: ``beta_1`` in ``(-L_1, 0)``, then
  ``beta_{i+1}`` in ``(max(beta_i, -L_{i+1}), min(0, beta_i + L_i - L_{i+1}))``, which is exactly
  the set :func:`jaxcr.kinematics.ctr_mechanics.telescoping_ok` accepts (each interval shrunk
  by 1 micrometre at both ends, so that float32 rounding stays inside); alphas free. A start
  on a limit is moved 1 % of its interval inside (a sigmoid's derivative vanishes at the
  bound). The CTR is solved cold at every evaluation (its least-energy branch, as ``forward``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcr._types import Array, Bool, Float, Int
from jaxcr.camera import Camera, project_points
from jaxcr.geometry import se3_exp

#: A start on a joint limit is moved this fraction of its interval inside.
_INSIDE = 0.01
#: CTR translation intervals are shrunk by this (m) at both ends: float32 rounding of
#: ``beta + L`` (~3e-8 m for 0.4 m tubes) would otherwise cross the limit test's 1e-9 m.
_CTR_MARGIN = 1e-6


class FitResult(eqx.Module):
    """Result of :func:`fit_backbone` / :func:`fit_tip_pixels`.

    Attributes:
        q: (m,) fitted joint values (the model's units: m, rad, 1/m).
        T_ref_robot: (4, 4) fitted base pose (``T0`` when the pose is not fitted).
        errors: (k,) per-measurement error: distance (m) of each backbone point to the model
            centreline, or pixel distance of each view's tip.
        tip_error: distance (m) of the measured tip to the model tip (backbone fits), or the
            largest view's tip error (px).
        rms, max: root mean square and maximum of ``errors``.
        cost: the minimised ``0.5 * |r|^2`` (r the full weighted residual vector).
        result: ``optx.RESULTS`` of the solve (``successful`` or why it stopped).
        num_steps: Levenberg-Marquardt iterations.
        ok: solver successful, every output finite and the forward kinematics ok at q.
    """

    q: Float[Array, " m"]
    T_ref_robot: Float[Array, "4 4"]
    errors: Float[Array, " k"]
    tip_error: Float[Array, ""]
    rms: Float[Array, ""]
    max: Float[Array, ""]
    cost: Float[Array, ""]
    result: optx.RESULTS
    num_steps: Int[Array, ""]
    ok: Bool[Array, ""]


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def closest_points_on_polyline(
    points: Float[Array, "m 3"], polyline: Float[Array, "n 3"]
) -> Float[Array, "m 3"]:
    """Closest point on the polyline (n >= 2 vertices) to each of ``points``.

    Each segment's parameter is clamped to [0, 1]; the segment of least squared distance wins.
    Differentiable (piecewise): the returned point moves with the polyline and the points, and
    no square root is taken, so the derivative is finite where a point lies on the polyline.
    """
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    len2 = jnp.sum(ab * ab, axis=-1)
    safe_len2 = jnp.where(len2 > 0, len2, 1.0)  # a zero-length segment: its first vertex
    ap = points[:, None, :] - a[None]
    t = jnp.where(len2 > 0, jnp.sum(ap * ab[None], axis=-1) / safe_len2, 0.0)
    t = jnp.clip(t, 0.0, 1.0)
    c = a[None] + t[..., None] * ab[None]
    d2 = jnp.sum((points[:, None, :] - c) ** 2, axis=-1)
    best = jnp.argmin(d2, axis=1)
    return jnp.take_along_axis(c, best[:, None, None], axis=1)[:, 0]


def _norm(v: Array) -> Array:
    """Euclidean norm over the last axis with a finite derivative at 0 ("double where")."""
    n2 = jnp.sum(v * v, axis=-1)
    pos = n2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, n2, 1.0)), 0.0)


# --------------------------------------------------------------------------------------------
# Joint limits by reparametrisation
# --------------------------------------------------------------------------------------------


def _softplus_inv(y: Array) -> Array:
    return jnp.where(y > 20.0, y, jnp.log(jnp.expm1(jnp.minimum(y, 20.0))))


def _shrink(lo: Array, hi: Array) -> tuple[Array, Array]:
    m = jnp.minimum(_CTR_MARGIN, 0.25 * (hi - lo))
    return lo + m, hi - m


def _ctr_betas(model, z: Array) -> Array:
    L = model.length.astype(z.dtype)
    beta = []
    lo, hi = -L[0], jnp.zeros((), z.dtype)
    for i in range(model.n_tubes):
        if i > 0:
            prev = beta[-1]
            lo = jnp.maximum(prev, -L[i])
            hi = jnp.maximum(jnp.minimum(0.0, prev + L[i - 1] - L[i]), lo)
        lo_in, hi_in = _shrink(lo, hi)
        beta.append(lo_in + (hi_in - lo_in) * jax.nn.sigmoid(z[i]))
    return jnp.stack(beta)


def _ctr_free(model, beta: Array) -> Array:
    L = model.length.astype(beta.dtype)
    z, prev = [], None
    lo, hi = -L[0], jnp.zeros((), beta.dtype)
    for i in range(model.n_tubes):
        if i > 0:
            lo = jnp.maximum(prev, -L[i])
            hi = jnp.maximum(jnp.minimum(0.0, prev + L[i - 1] - L[i]), lo)
        lo, hi = _shrink(lo, hi)
        width = hi - lo
        frac = jnp.where(width > 0, (beta[i] - lo) / jnp.where(width > 0, width, 1.0), 0.5)
        frac = jnp.clip(frac, _INSIDE, 1.0 - _INSIDE)
        z.append(jnp.log(frac / (1.0 - frac)))
        prev = lo + width * frac
    return jnp.stack(z)


def joints_from_free(model, z: Float[Array, " m"]) -> Float[Array, " m"]:
    """Joint values q from the unconstrained solver variables ``z`` (module docstring)."""
    kind = model.kind
    if kind == "constant_curvature" and "length" in model.joints:
        zs = z.reshape(model.n_sections, len(model.joints))
        j = model.joints.index("length")
        return zs.at[:, j].set(jax.nn.softplus(zs[:, j])).reshape(-1)
    if kind == "ctr":
        n = model.n_tubes
        return jnp.concatenate([_ctr_betas(model, z[:n]), z[n:]])
    return z


def free_from_joints(model, q: Float[Array, " m"]) -> Float[Array, " m"]:
    """Inverse of :func:`joints_from_free` (a start on a limit moves inside, see the module)."""
    q = jnp.asarray(q)
    kind = model.kind
    if kind == "constant_curvature" and "length" in model.joints:
        qs = q.reshape(model.n_sections, len(model.joints))
        j = model.joints.index("length")
        length = jnp.maximum(qs[:, j], 1e-6)
        return qs.at[:, j].set(_softplus_inv(length)).reshape(-1)
    if kind == "ctr":
        n = model.n_tubes
        return jnp.concatenate([_ctr_free(model, q[:n]), q[n:]])
    return q


def pose_start(points, *, length: float = 0.015) -> np.ndarray:
    """A start ``T0`` (4, 4) for a backbone fit with ``fit_pose``: the robot frame at the
    measured base ``points[0]`` with z along the measured initial direction (the slope at the
    base of a least-squares quadratic through ``points[0]`` over the first ``length`` metres of
    chord length, at least the first three further points), and x the reference frame's x
    axis made perpendicular to z (its y axis when z is within 18 deg of x), so that a backbone
    already in the robot frame starts at (nearly) the identity. Host-side numpy.

    From the identity a Levenberg-Marquardt pose fit to a backbone a quarter metre away (a
    camera's or tracker's frame) stalls in a local minimum; from here it starts within the
    measurement's tilt of the truth."""
    P = np.asarray(points, np.float64)
    if P.shape[0] < 2:
        return np.eye(4)
    c = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    n = max(int(np.searchsorted(c, length, side="right")), min(4, len(P)))
    s, D = c[1:n], P[1:n] - P[0]
    A = np.stack([s, s**2], axis=1) if len(s) >= 3 else s[:, None]
    z = np.linalg.lstsq(A, D, rcond=None)[0][0]
    if not np.all(np.isfinite(z)) or np.linalg.norm(z) < 1e-12:
        return np.eye(4)
    z = z / np.linalg.norm(z)
    ref = np.array([1.0, 0, 0]) if abs(z[0]) < np.cos(np.radians(18)) else np.array([0, 1.0, 0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = P[0]
    return T


def default_start(model) -> np.ndarray:
    """A start inside the joint limits: slightly bent so that the bending plane has a gradient
    (kappa = 1/m, theta_L = pi/2 - 0.1 rad), phi = delta = 0, nominal section lengths; CTR
    translations mid-interval (each sigmoid at 1/2), alphas 0."""
    kind = model.kind
    if kind == "constant_curvature":
        vals = {
            "kappa": np.full(model.n_sections, 1.0),
            "phi": np.zeros(model.n_sections),
            "length": np.asarray(model.length, np.float64),
        }
        return np.stack([vals[j] for j in model.joints], axis=1).reshape(-1)
    if kind == "single_segment":
        return np.array([np.pi / 2 - 0.1, 0.0])
    if kind == "ctr":
        n = model.n_tubes
        beta = np.asarray(_ctr_betas(model, jnp.zeros(n)), np.float64)
        return np.concatenate([beta, np.zeros(n)])
    raise ValueError(f"unknown robot kind {kind!r}")


def start_set(model, n: int, *, q0=None) -> np.ndarray:
    """(k, m) start joint vectors for a multi-start fit, k = min(n, available): ``q0`` (default
    :func:`default_start`) first, then the same start with other bending planes, since a
    least-squares fit of several sections' planes has local minima (a plane off by ~pi/2
    can stall). ``constant_curvature`` with a ``phi`` joint: kappa a bend of 1 rad per section
    (``1 / length``) and every combination of phi in (0, 2 pi/3, -2 pi/3) over the sections,
    the last section varying fastest; ``single_segment``: delta spread over the circle;
    ``ctr``: every combination of the alphas of tubes 2.. in (0, 2 pi/3, -2 pi/3)."""
    import itertools

    base = default_start(model) if q0 is None else np.asarray(q0, np.float64)
    rows = [base]
    angles = (0.0, 2 * np.pi / 3, -2 * np.pi / 3)
    kind = model.kind
    if kind == "constant_curvature" and "phi" in model.joints:
        nj = len(model.joints)
        for combo in itertools.product(angles, repeat=model.n_sections):
            q = base.reshape(model.n_sections, nj).copy()
            q[:, model.joints.index("phi")] = combo
            if "kappa" in model.joints:
                q[:, model.joints.index("kappa")] = 1.0 / np.asarray(model.length, np.float64)
            rows.append(q.reshape(-1))
    elif kind == "single_segment":
        for k in range(1, max(n, 1)):
            q = base.copy()
            q[1] = base[1] + 2 * np.pi * k / max(n, 1)
            rows.append(q)
    elif kind == "ctr" and model.n_tubes > 1:
        nt = model.n_tubes
        for combo in itertools.product(angles, repeat=nt - 1):
            q = base.copy()
            q[nt + 1 :] = np.asarray(combo)
            rows.append(q)
    return np.stack(rows[: max(n, 1)])


def _wrap(a):
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def canonical_joints(model, q: Float[Array, " m"]) -> Float[Array, " m"]:
    """The same shape with angles wrapped to (-pi, pi] and, for ``single_segment``, the
    bending angle in the workspace [0, pi] (theta_L > pi/2 is theta_L' = pi - theta_L bent
    towards delta + pi). ``constant_curvature`` keeps its signed kappa."""
    q = jnp.asarray(q)
    kind = model.kind
    if kind == "single_segment":
        theta, delta = q[0], q[1]
        flip = theta > jnp.pi / 2
        theta = jnp.where(flip, jnp.pi - theta, theta)
        delta = jnp.where(flip, delta + jnp.pi, delta)
        return jnp.stack([theta, _wrap(delta)])
    if kind == "constant_curvature" and "phi" in model.joints:
        qs = q.reshape(model.n_sections, len(model.joints))
        j = model.joints.index("phi")
        return qs.at[:, j].set(_wrap(qs[:, j])).reshape(-1)
    if kind == "ctr":
        n = model.n_tubes
        return jnp.concatenate([q[:n], _wrap(q[n:])])
    return q


# --------------------------------------------------------------------------------------------
# Residuals
# --------------------------------------------------------------------------------------------


def _centreline(model, q: Array, guess: Array | None = None) -> tuple[Array, Array]:
    fk = model.forward(q) if guess is None else model.forward(q, guess)
    return fk.centreline.p, fk.ok


def backbone_residual(
    model,
    q: Float[Array, " m"],
    T_ref_robot: Float[Array, "4 4"],
    points: Float[Array, "k 3"],
    tip_weight: float = 1.0,
    guess: Array | None = None,
    base_weight: float = 0.0,
) -> Float[Array, " r"]:
    """Residual vector (3k + 3,) in metres: each measured point minus its closest point on the
    model centreline (mapped into the reference frame by ``T_ref_robot``), then
    ``tip_weight * (points[-1] - model tip)``, and with ``base_weight > 0`` also
    ``base_weight * (points[0] - model base)`` (3k + 6,): with a free base pose, a
    point-to-curve distance alone lets the model start before the measured base (a longer
    first section with its base below the real one). ``guess``: the CTR's warm start
    (``state``)."""
    p, _ = _centreline(model, q, guess)
    return _backbone_residual_of(p, T_ref_robot, points, tip_weight, base_weight)


def _backbone_residual_of(p, T_ref_robot, points, tip_weight, base_weight):
    """:func:`backbone_residual` given the model centreline ``p`` (robot frame)."""
    p = p @ T_ref_robot[:3, :3].T + T_ref_robot[:3, 3]
    c = closest_points_on_polyline(points, p)
    parts = [(points - c).reshape(-1), tip_weight * (points[-1] - p[-1])]
    if base_weight:
        parts.append(base_weight * (points[0] - p[0]))
    return jnp.concatenate(parts)


def tip_pixel_residual(
    model,
    q: Float[Array, " m"],
    T_ref_robot: Float[Array, "4 4"],
    cameras: tuple[Camera, ...],
    tips_px: Float[Array, "v 2"],
    guess: Array | None = None,
) -> Float[Array, " r"]:
    """Residual (2v,) in pixels: each view's projected model tip minus the measured tip pixel
    (OpenCV pixel convention); the cameras see ``T_cam_robot @ T_ref_robot``. ``guess``: the
    CTR's warm start."""
    p, _ = _centreline(model, q, guess)
    return _tip_pixel_residual_of(p, T_ref_robot, cameras, tips_px)


def _tip_pixel_residual_of(p, T_ref_robot, cameras, tips_px):
    """:func:`tip_pixel_residual` given the model centreline ``p`` (robot frame)."""
    tip = p[-1:] @ T_ref_robot[:3, :3].T + T_ref_robot[:3, 3]
    uv = jnp.stack([project_points(cam, tip)[0][0] for cam in cameras])
    return (uv - tips_px).reshape(-1)


# --------------------------------------------------------------------------------------------
# Solver
# --------------------------------------------------------------------------------------------


@eqx.filter_jit
def _solve(
    model,
    data,
    q0,
    T0,
    guess,
    *,
    mode,
    fit_pose,
    tip_weight,
    prior_weight,
    max_steps,
    rtol,
    atol,
    base_weight=0.0,
):
    """One Levenberg-Marquardt solve (compiled once per model structure and data shape)."""
    dtype = T0.dtype
    z0 = free_from_joints(model, q0).astype(dtype)
    y0 = (z0, jnp.zeros(6, dtype))

    def unpack(y):
        z, xi = y
        q = joints_from_free(model, z)
        T = T0 @ se3_exp(xi) if fit_pose else T0
        return q, T

    def residual(y, p):
        q, T = unpack(y)
        if mode == "backbone":
            r = _backbone_residual_of(p, T, data, tip_weight, base_weight)
        else:
            cameras, tips_px = data
            r = _tip_pixel_residual_of(p, T, cameras, tips_px)
        if prior_weight:
            r = jnp.concatenate([r, prior_weight * (q - q0)])
            if fit_pose:
                r = jnp.concatenate([r, prior_weight * y[1]])
        return r

    def fn(y, args):
        q, _ = unpack(y)
        return residual(y, _centreline(model, q, guess)[0])

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(fn, solver, y0, max_steps=max_steps, throw=False)
    q, T = unpack(sol.value)
    # the residual and the tip at the solution from one forward solve (this program held
    # two, one each: ~12 % of the CTR fit's program, compiled for nothing)
    p, fk_ok = _centreline(model, q, guess)
    r = residual(sol.value, p)
    tip = p[-1] @ T[:3, :3].T + T[:3, 3]
    return q, T, r, tip, fk_ok, sol.result, jnp.asarray(sol.stats["num_steps"], jnp.int32)


@eqx.filter_jit
def _cold_forward(model, q: Float[Array, " m"]):
    """``model.forward(q)`` (cold start: a CTR's least-energy branch), compiled once per model
    structure and dtype: the CTR fit's warm starts, and anyone who needs the same compiled
    forward kinematics (the tests' synthetic backbones) without compiling it again."""
    return model.forward(q)


def _solve_stored(model, data, q0, T0, guess, options: tuple):
    """:func:`_solve` with its keyword options as one static tuple of (name, value) pairs: the
    positional form :func:`jaxcr.io.exported.cached_call` takes."""
    return _solve(model, data, q0, T0, guess, **dict(options))


def _caller(jit_call):
    """How the fit's programs are called: ``jit_call(fn, *args)``, e.g.
    :func:`jaxcr.io.exported.cached_call` (what ``jaxcr fit`` passes: a second process loads
    the LM solve, the cold forward kinematics and the summary instead of tracing them through
    the CTR solver again, docs/decisions.md K4); None: ``fn(*args)``."""
    return jit_call if jit_call is not None else (lambda fn, *args: fn(*args))


def _tolerances(dtype, rtol, atol, model=None):
    # float32: the cost's relative resolution is ~eps32 = 1.2e-7, so a step test much below
    # ~1e-6 never triggers; float64 can go to 1e-10. A CTR's equilibrium is itself solved
    # only to ~1e-5 rad in float32 (ConcentricTubeRobot._solver_tol), which limits q to ~1e-4.
    f32 = jnp.dtype(dtype) == jnp.float32
    if model is not None and model.kind == "ctr" and f32:
        default = 1e-4
    else:
        default = 1e-6 if f32 else 1e-10
    return (default if rtol is None else rtol), (default if atol is None else atol)


def _fit(
    model,
    data,
    q0,
    T0,
    *,
    mode,
    fit_pose,
    tip_weight,
    prior_weight,
    max_steps,
    rtol,
    atol,
    rounds,
    base_weight=0.0,
    jit_call=None,
):
    """Solve; for a CTR, ``rounds`` LM solves each warm-started from the equilibrium (least
    energy branch, cold-solved outside the LM) at the previous round's q: a cold solve at
    every LM evaluation would be ~50x dearer, and its branch search makes the residual noisy
    at the solver tolerance."""
    dtype = T0.dtype
    q0 = jnp.asarray(q0, dtype)
    rtol, atol = _tolerances(dtype, rtol, atol, model)
    kw = dict(
        mode=mode,
        fit_pose=fit_pose,
        tip_weight=tip_weight,
        base_weight=float(base_weight),
        prior_weight=float(prior_weight),
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
    )
    options = tuple(sorted(kw.items()))
    _stored = _caller(jit_call)
    if model.kind != "ctr" or model.n_tubes == 1:
        return _stored(_solve_stored, model, data, q0, T0, None, options)
    q, steps, out = q0, 0, None
    for _ in range(max(1, rounds)):
        guess = _stored(_cold_forward, model, q).state
        out = _stored(_solve_stored, model, data, q0, T0, guess, options)
        steps += int(out[-1])
        q = out[0]
    return (*out[:-1], jnp.asarray(steps, jnp.int32))


def fit_backbone(
    model,
    points: Float[Array, "k 3"],
    *,
    q0: Float[Array, " m"] | None = None,
    T0: Float[Array, "4 4"] | None = None,
    fit_pose: bool = False,
    tip_weight: float = 1.0,
    base_weight: float = 0.0,
    prior_weight: float = 0.0,
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float | None = None,
    rounds: int = 3,
    jit_call=None,
) -> FitResult:
    """Fit q (and the base pose with ``fit_pose``) to a measured backbone.

    Args:
        model: any :class:`jaxcr.kinematics.RobotModel`.
        points: (k, 3) measured backbone points (metres, reference frame), k >= 1, the last
            one the tip; any spacing, no arclengths needed.
        q0: start (default :func:`default_start`). T0: base pose start (default identity:
            the points are in the robot frame).
        tip_weight: weight of the tip-to-tip term (0 disables it).
        base_weight: weight of the measured-base-to-model-base term (default 0: off; the
            points' first one is then free to lie anywhere along the model).
        prior_weight: adds ``prior_weight * (q - q0)`` (metres of residual per unit of q),
            and with ``fit_pose`` ``prior_weight * xi`` (the pose twist, m and rad), to keep an
            under-determined fit near its start; 0 by default.
        max_steps, rtol, atol: Levenberg-Marquardt limits per solve (tolerances default 1e-6
            in float32 (1e-4 for a CTR, whose equilibrium is solved to ~1e-5 rad), 1e-10 in
            float64).
        rounds: CTR only: warm-started solves, each from the equilibrium at the last q.
        jit_call: how the compiled programs are called, ``jit_call(fn, *args)``; None calls
            them directly; ``jaxcr.io.exported.cached_call`` stores their traced programs
            for a later process (what ``jaxcr fit`` passes, docs/decisions.md K4).

    Returns:
        :class:`FitResult` with ``errors`` the (k,) point-to-centreline distances (m).
    """
    points = jnp.asarray(points)
    dtype = points.dtype
    T0 = jnp.eye(4, dtype=dtype) if T0 is None else jnp.asarray(T0, dtype)
    q0 = default_start(model) if q0 is None else q0
    q, T, r, tip, fk_ok, result, steps = _fit(
        model,
        points,
        q0,
        T0,
        mode="backbone",
        fit_pose=fit_pose,
        tip_weight=float(tip_weight),
        base_weight=float(base_weight),
        prior_weight=prior_weight,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        rounds=rounds,
        jit_call=jit_call,
    )
    return _caller(jit_call)(_backbone_result, model, points, q, T, r, tip, fk_ok, result, steps)


def fit_tip_pixels(
    model,
    cameras: tuple[Camera, ...],
    tips_px: Float[Array, "v 2"],
    *,
    q0: Float[Array, " m"] | None = None,
    T0: Float[Array, "4 4"] | None = None,
    fit_pose: bool = False,
    prior_weight: float = 0.0,
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float | None = None,
    rounds: int = 3,
    jit_call=None,
) -> FitResult:
    """Fit q (and the base-pose correction with ``fit_pose``) to tip pixels in calibrated
    views (one (u, v) per camera, OpenCV pixel convention).

    Two views give 4 equations: a model with more free parameters is under-determined, and
    ``prior_weight`` (pixels per unit of q) keeps it near ``q0``. ``errors`` are the (v,)
    per-view tip errors in pixels; other arguments as :func:`fit_backbone`.
    """
    cameras = tuple(cameras)
    dtype = cameras[0].K.dtype
    tips_px = jnp.asarray(tips_px, dtype)
    T0 = jnp.eye(4, dtype=dtype) if T0 is None else jnp.asarray(T0, dtype)
    q0 = default_start(model) if q0 is None else q0
    q, T, r, tip, fk_ok, result, steps = _fit(
        model,
        (cameras, tips_px),
        q0,
        T0,
        mode="tips",
        fit_pose=fit_pose,
        tip_weight=0.0,
        prior_weight=prior_weight,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        rounds=rounds,
        jit_call=jit_call,
    )
    return _caller(jit_call)(_tips_result, model, len(cameras), q, T, r, fk_ok, result, steps)


# The summaries below are compiled (one small program per model structure and data shape):
# run eagerly, their ~30 operations were each compiled on their own at every new shape.


@eqx.filter_jit
def _backbone_result(model, points, q, T, r, tip, fk_ok, result, steps) -> FitResult:
    k = points.shape[0]
    errors = _norm(r[: 3 * k].reshape(k, 3))
    return _result(model, q, T, errors, _norm(points[-1] - tip), r, result, steps, fk_ok)


@eqx.filter_jit
def _tips_result(model, v: int, q, T, r, fk_ok, result, steps) -> FitResult:
    errors = _norm(r[: 2 * v].reshape(v, 2))
    return _result(model, q, T, errors, jnp.max(errors), r, result, steps, fk_ok)


def _result(model, q, T, errors, tip_error, r, result, steps, fk_ok) -> FitResult:
    finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(T)) & jnp.all(jnp.isfinite(r))
    return FitResult(
        q=canonical_joints(model, q),
        T_ref_robot=T,
        errors=errors,
        tip_error=tip_error,
        rms=jnp.sqrt(jnp.mean(errors**2)),
        max=jnp.max(errors),
        cost=0.5 * jnp.sum(r**2),
        result=result,
        num_steps=steps,
        ok=finite & fk_ok & (result == optx.RESULTS.successful),
    )


__all__ = [
    "FitResult",
    "backbone_residual",
    "canonical_joints",
    "closest_points_on_polyline",
    "default_start",
    "fit_backbone",
    "fit_tip_pixels",
    "free_from_joints",
    "joints_from_free",
    "pose_start",
    "start_set",
    "tip_pixel_residual",
]
