"""One smooth 3-D curve fitted to two views' traced backbones (issue 16 item 2, round 13:
the whole-backbone test of a branch choice with a shape prior).

:mod:`jaxcr.stereo.backbone_consistency` matches two traced backbones monotonically along
the epipolar geometry and triangulates each matched pair on its own. Where a backbone runs
near the epipolar lines any pairing is consistent, so a wrong branch that spans the same
epipolar range as the right one costs nothing there: each pair's 3-D point may zig-zag in
depth. Here the two backbones must instead be the images of **one smooth curve** that
starts at both entries and ends at both tips: a clamped cubic B-spline ``C(t)``, ``t`` in
[0, 1], with ``n_ctrl`` control points (the shared frame of the cameras, metres when the
poses are), and for every resampled backbone point of each view a foot-point parameter
``t_i`` (the first point of each view at ``t = 0``, the last at ``t = 1``). It minimises

    sum_views sum_i rho(|pi_k(C(t_i)) - y_ki|) + (bend * s)^2 sum_j |c_(j-1) - 2 c_j + c_(j+1)|^2

(``pi_k`` the pinhole projection on undistorted pixels ``y``, ``rho`` the soft-L1 loss with
scale ``loss_px``, ``s`` the pixels per metre at the curve's depth, so the bending term is
in pixels) by :func:`scipy.optimize.least_squares` with the analytic Jacobian, from the
monotone matching's triangulated points. After the fit each point's reprojection residual
tells whether the smooth curve explains it; ``unexplained_px`` is the length of the points
whose residual exceeds ``tol_px``, both views summed, plus the projected length of the
curve's stretches that a view's backbone does not follow (the same measure as
:class:`~jaxcr.stereo.backbone_consistency.BackboneConsistency`'s ``inconsistent_px``, with
the shape prior).

Pixels are distorted (as the camera records them) at the interface and undistorted inside
(:func:`jaxcr.stereo.tip_consistency.undistort_pixels`). Numpy float64, scipy and cv2
(undistortion), per frame, at the edge of the stereo pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from jaxcr.stereo.backbone_consistency import (
    _project_h,
    _symmetric_epipolar,
    _triangulate_h,
    resample_polyline,
)
from jaxcr.stereo.correspondence import dtw_path
from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses

__all__ = ["SplineFit", "fit_spline_pair", "spline_basis"]


@dataclass
class SplineFit:
    """Result of :func:`fit_spline_pair`.

    ``ctrl`` (n_ctrl, 3) control points of the clamped cubic B-spline (the cameras' shared
    frame); ``knots`` its knot vector; ``t`` [(n1,), (n2,)] each resampled point's foot
    parameter; ``residual_px`` [(n1,), (n2,)] each point's reprojection distance to the
    curve (undistorted px); ``unexplained_px`` the length (px, both views) of the points
    over ``tol_px`` plus the projected length of the curve's stretches over ``tol_px`` from
    a view's backbone; ``rms_px`` the root mean square residual of all points; ``samples``
    [(n1, 2), (n2, 2)] the resampled backbones (distorted px) and ``steps_px`` (2,) their
    steps; ``success`` the solver's flag; ``nfev`` its function evaluations."""

    ctrl: np.ndarray
    knots: np.ndarray
    t: list
    residual_px: list
    unexplained_px: float
    rms_px: float
    samples: list
    steps_px: np.ndarray
    success: bool
    nfev: int

    def points(self, t) -> np.ndarray:
        """(n, 3) curve points at parameters ``t`` (n,)."""
        return BSpline(self.knots, self.ctrl, 3)(np.asarray(t, np.float64))


def spline_basis(n_ctrl: int, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The clamped cubic B-spline on [0, 1] with ``n_ctrl`` (>= 4) control points and
    uniform interior knots: (knots, B (n, n_ctrl) basis values at ``t`` (n,), dB (n,
    n_ctrl) their derivatives in ``t``). ``C(t) = B @ ctrl``."""
    inner = np.linspace(0.0, 1.0, n_ctrl - 2)
    knots = np.r_[[0.0] * 3, inner, [1.0] * 3]
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    eye = np.eye(n_ctrl)
    spl = BSpline(knots, eye, 3, extrapolate=False)
    B = np.nan_to_num(spl(t))
    dB = np.nan_to_num(spl.derivative()(t))
    return knots, B, dB


def _project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (n, 2) of points X (n, 3) through P (3, 4), and the projection's Jacobian
    (n, 2, 3) in X."""
    x = X @ P[:, :3].T + P[:, 3]
    z = x[:, 2:3]
    uv = x[:, :2] / z
    # d(x0/x2)/dX = (P0 - u P2) / x2
    J = (P[None, :2, :3] - uv[:, :, None] * P[None, 2:3, :3]) / z[:, :, None]
    return uv, J


def fit_spline_pair(
    cams, backbone1, backbone2, *, n_ctrl: int | None = None, step_px: float = 4.0,
    max_samples: int = 150, bend: float = 0.01, loss_px: float = 2.0, tol_px: float = 3.0,
    max_nfev: int = 40, ordered: bool = True,
) -> SplineFit | None:  # fmt: skip
    """The smooth 3-D curve whose projections best explain both traced backbones (module
    docstring).

    ``cams``: two calibrated cameras (``K``, ``dist``, ``T_cam_robot``, one shared frame).
    ``backbone1``, ``backbone2``: (n, 2) distorted (u, v), each from the robot's entry to
    its tip. Each is resampled every ``step_px`` (coarser if that gives more than
    ``max_samples`` points). ``n_ctrl``: control points (default: one per 30 px of the
    longer backbone, 8 to 24: a hook of two tube widths' radius needs about four).
    ``bend``: weight of the control polygon's second differences (in pixels, per pixel of
    residual); ``loss_px``: the soft-L1 scale; ``tol_px``: the residual over which a point
    is unexplained (3 px, as ``backbone_consistency``). ``ordered``: each view's points keep
    their order along the curve (their feet found by a monotone matching to the curve's
    projection; both backbones run from the entry to the tip), else each point's foot is
    its nearest point on the projected curve (a wrong end may then borrow the curve's
    other parts). None when a backbone has fewer
    than two points or no finite matched point to start from."""
    bbs = [np.asarray(b, np.float64).reshape(-1, 2) for b in (backbone1, backbone2)]
    if any(len(b) < 2 for b in bbs):
        return None
    lengths = [float(np.sum(np.linalg.norm(np.diff(b, axis=0), axis=1))) for b in bbs]
    steps = np.array([max(step_px, L / max(max_samples - 1, 1)) for L in lengths])
    samples = [resample_polyline(b, s) for b, s in zip(bbs, steps, strict=True)]
    ys = [undistort_pixels(c, s) for c, s in zip(cams, samples, strict=True)]
    if n_ctrl is None:
        n_ctrl = int(np.clip(round(max(lengths) / 30.0), 8, 24))
    Ps = [np.asarray(c.K, np.float64) @ np.asarray(c.T_cam_robot, np.float64)[:3] for c in cams]

    # Start: the monotone matching's triangulated pairs, parameterised by their order.
    K1, K2 = (np.asarray(c.K, np.float64) for c in cams)
    T1, T2 = (np.asarray(c.T_cam_robot, np.float64) for c in cams)
    F = fundamental_from_poses(K1, T1, K2, T2)
    pairs = dtw_path(np.minimum(_symmetric_epipolar(F, ys[0], ys[1]), 50.0))
    Xh = _triangulate_h(Ps[0], Ps[1], ys[0][pairs[:, 0]], ys[1][pairs[:, 1]])
    err = np.maximum(
        np.linalg.norm(_project_h(Ps[0], Xh) - ys[0][pairs[:, 0]], axis=1),
        np.linalg.norm(_project_h(Ps[1], Xh) - ys[1][pairs[:, 1]], axis=1),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        X0 = Xh[:, :3] / Xh[:, 3:]
    tp = np.linspace(0.0, 1.0, len(pairs))
    good = np.all(np.isfinite(X0), axis=1) & (err < 10.0)
    if good.sum() < n_ctrl:
        good = np.all(np.isfinite(X0), axis=1)
    if good.sum() < 2:
        return None
    depth = np.median(np.concatenate([(X0[good] @ np.asarray(c.T_cam_robot)[:3, :3].T
                                       + np.asarray(c.T_cam_robot)[:3, 3])[:, 2]
                                      for c in cams]))  # fmt: skip
    fpx = float(np.mean([np.asarray(c.K)[0, 0] for c in cams]))
    s_px = fpx / max(abs(depth), 1e-6)  # pixels per metre at the curve
    knots, B0, _ = spline_basis(n_ctrl, tp[good])
    D2 = np.diff(np.eye(n_ctrl), 2, axis=0)
    A = np.vstack([B0, 0.1 * D2])
    rhs = np.vstack([X0[good], np.zeros((n_ctrl - 2, 3))])
    ctrl0 = np.linalg.lstsq(A, rhs, rcond=None)[0]
    n_c = 3 * n_ctrl
    wb = bend * s_px
    # The curve on a dense grid (the basis is constant there); each point's foot is its
    # nearest point on the projected grid polyline (variable projection: the feet are
    # solved for exactly at every step, the solver sees the control points only). Each
    # view's first and last points are tied to the curve's ends.
    n_grid = max(160, 10 * n_ctrl)
    tg = np.linspace(0.0, 1.0, n_grid)
    _, Bg, _ = spline_basis(n_ctrl, tg)

    memo = {}
    # Curve points that also must lie on each view's backbone (the reverse term: without
    # it the curve may wander where no backbone point is nearest to it).
    gsub = np.unique(np.linspace(0, n_grid - 1, max(len(y) for y in ys)).round().astype(int))

    def _nearest_on(poly, pts, in_order=False):
        """Index and fraction of the nearest point of polyline ``poly`` to each of ``pts``;
        ``in_order``: the points' feet keep their order along ``poly`` (the cheapest
        monotone path through the distances, first point to first segment, last to last)."""
        a_, d_ = poly[:-1], np.diff(poly, axis=0)
        rel = pts[:, None, :] - a_[None]
        lam = np.clip(np.sum(rel * d_[None], -1) / np.maximum(np.sum(d_ * d_, -1), 1e-12),
                      0.0, 1.0)  # fmt: skip
        dist = np.linalg.norm(rel - lam[..., None] * d_[None], axis=-1)
        if in_order:
            path = dtw_path(np.minimum(dist, 50.0))
            g = np.zeros(len(pts), int)
            best = np.full(len(pts), np.inf)
            for i, j in path:
                if dist[i, j] < best[i]:
                    best[i], g[i] = dist[i, j], j
        else:
            g = np.argmin(dist, axis=1)
        return g, lam[np.arange(len(g)), g]

    def feet(ctrl):
        key = ctrl.tobytes()
        if key in memo:
            return memo[key]
        memo.clear()
        out = []
        for k in range(2):
            uv, Jp = _project(Ps[k], Bg @ ctrl)
            g, lg = _nearest_on(uv, ys[k], in_order=ordered)
            g[0], lg[0] = 0, 0.0
            g[-1], lg[-1] = n_grid - 2, 1.0
            h, lh = _nearest_on(ys[k], uv[gsub])
            target = (1 - lh)[:, None] * ys[k][h] + lh[:, None] * ys[k][h + 1]
            out.append((g, lg, uv, Jp, target))
        memo[key] = out
        return out

    def fun(z):
        ctrl = z.reshape(n_ctrl, 3)
        res = []
        for k, (g, lg, uv, _, target) in enumerate(feet(ctrl)):
            p = (1 - lg)[:, None] * uv[g] + lg[:, None] * uv[g + 1]
            res.append((p - ys[k]).ravel())
            res.append((uv[gsub] - target).ravel())
        res.append((wb * (D2 @ ctrl)).ravel())
        return np.concatenate(res)

    def jac(z):
        ctrl = z.reshape(n_ctrl, 3)
        rows = []
        for g, lg, _, Jp, _ in feet(ctrl):
            J0 = np.einsum("nij,nm->nimj", Jp[g], Bg[g])
            J1 = np.einsum("nij,nm->nimj", Jp[g + 1], Bg[g + 1])
            J = (1 - lg)[:, None, None, None] * J0 + lg[:, None, None, None] * J1
            rows.append(J.reshape(2 * len(g), n_c))
            rows.append(np.einsum("nij,nm->nimj", Jp[gsub], Bg[gsub]).reshape(2 * len(gsub), n_c))
        rows.append(wb * np.kron(D2, np.eye(3)))
        return np.vstack(rows)

    # One BLAS thread: OpenBLAS's threads make the solver's small SVDs (a few hundred rows)
    # 100x slower on a loaded machine (as registration.pose_graph does).
    with threadpool_limits(1, user_api="blas"):
        sol = least_squares(fun, ctrl0.ravel(), jac=jac, loss="soft_l1", f_scale=loss_px,
                            max_nfev=max_nfev, x_scale="jac")  # fmt: skip
    ctrl = sol.x.reshape(n_ctrl, 3)
    ts, resid = [], []
    for k, (g, lg, uv, _, _) in enumerate(feet(ctrl)):
        ts.append(tg[g] + lg * (tg[g + 1] - tg[g]))
        p = (1 - lg)[:, None] * uv[g] + lg[:, None] * uv[g + 1]
        resid.append(np.linalg.norm(p - ys[k], axis=1))
    bad = float(sum(np.sum(r > tol_px) * s for r, s in zip(resid, steps, strict=True)))
    # The curve's own stretches that a view's backbone does not follow (the curve bent to
    # explain one view's wrong end runs off the other view's backbone): their projected
    # length in that view.
    for k, (_, _, uv, _, _) in enumerate(feet(ctrl)):
        h, lh = _nearest_on(ys[k], uv)
        near = (1 - lh)[:, None] * ys[k][h] + lh[:, None] * ys[k][h + 1]
        off = np.linalg.norm(uv - near, axis=1) > tol_px
        seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
        # At most the other view's length: near an epipolar plane the curve may run far
        # along a ray of one camera, a long line in the other view, to explain a few points.
        bad += min(float(np.sum(seg[off[:-1] & off[1:]])), lengths[1 - k])
    rms = float(np.sqrt(np.mean(np.concatenate(resid) ** 2)))
    return SplineFit(ctrl, knots, ts, resid, bad, rms, samples, steps, bool(sol.success),
                     int(sol.nfev))  # fmt: skip
