"""A tube end that curls, fitted to one view's cue map (issue 16 item 2, docs/decisions.md S46).

Where a tube curls at its end (the tip bends sideways or back within a few tube widths), its
silhouette's end is the curl's apex and the tip lies beyond it, sideways or back; the
tracer's path and :mod:`jaxcr.segmentation.capsule_end` (a straight end with a slight
bend behind) stop at the apex. The model here: from an anchor on the traced path
``back_widths`` tube widths behind its end, the axis runs straight for ``L0`` then on an arc
of curvature ``k`` for ``L1`` (px); behind the anchor it is the traced path itself. The
silhouette is the band of half width ``r`` round the axis and a half-ellipse end face of
length ``a`` beyond the axis' end, drawn nearly sharp, blurred by a Gaussian, scaled
between a background and an inside level; robust least squares from three starts
(straight, and curving ``0.8 / r`` either way; scipy's ``trf`` with the ``lsmr`` trust-region
solver: 3.3 times faster than the exact SVD one over eight real_like views, the tips within
0.2 px but on one failed fit). The tip is the axis' end.

The same model with the bend bounded is fitted too (:attr:`CurlEnd.gentle_cost`): one view's
residuals choose between them only weakly (stop 37's prototype,
experiments/results/segmentation/real_like_tip_curl_prototype.md), so the fit is a
*candidate* that the two-view step chooses with the other view
(:func:`jaxcr.stereo.pipeline.traced_stereo_tips`: ``refit_ends``, the gentle fit's end
where the tracer stopped early, on by default; ``curl_ends``, the curled fit's, off:
docs/decisions.md S46-S48).

Pure numpy / scipy, host side, one view at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.special import ndtr

__all__ = ["CurlEnd", "curl_axis", "fit_curl_end"]

_EDGE_PX = 0.25  # the drawn edge's own softness (px), under the blur that is fitted
_STRAIGHT_K = 1e-6  # |k| (1/px) below which the arc is drawn as a straight segment
_GENTLE_KR = 0.25  # the gentle fit's bound on |k| r (the capsule end's bend bound)


@dataclass(frozen=True)
class CurlEnd:
    """A fitted curled tube end (pixels (u, v); :func:`fit_curl_end`).

    Attributes:
        tip: (2,) the axis' end (the end face's centre).
        direction: (2,) unit, the axis direction at the tip, pointing out of the tube.
        curvature: the arc's curvature ``k`` (1/px, positive turning from +u towards +v).
        arc_px: the arc's length ``L1`` (px); ``turn_deg = degrees(k L1)``.
        half_width: the band's half width ``r`` (px).
        cost: the robust least-squares cost of the curled fit; ``gentle_cost``: of the
            same model with the bend bounded, ``|k| r <= 0.25`` (the capsule end's bound;
            the same window and loss), a tube that does not curl.
        gentle_tip: (2,) the gentle fit's tip.
        backbone, gentle_backbone: (m, 2) the path behind the anchor and the fitted axis
            to the tip, of the curled and the gentle fit.
    """

    tip: np.ndarray
    direction: np.ndarray
    curvature: float
    arc_px: float
    half_width: float
    cost: float
    gentle_cost: float
    gentle_tip: np.ndarray
    backbone: np.ndarray
    gentle_backbone: np.ndarray

    @property
    def turn_deg(self) -> float:
        return float(np.degrees(self.curvature * self.arc_px))


def curl_axis(anchor, theta: float, L0: float, k: float, L1: float, step: float = 0.5):
    """The model's axis sampled every ``step`` px: ``L0`` straight from ``anchor`` (u, v)
    at angle ``theta`` (rad), then ``L1`` on an arc of curvature ``k``; ((n, 2) points
    ending at the axis' end, the end's angle)."""
    P = np.asarray(anchor, np.float64)
    d0 = np.array([np.cos(theta), np.sin(theta)])
    s0 = np.arange(0.0, L0 + 1e-9, step)
    E = P + L0 * d0
    s1 = np.arange(step, L1 + 1e-9, step)
    if len(s1) == 0 or s1[-1] < L1 - 1e-9:  # the end itself is the last point
        s1 = np.r_[s1, L1]
    if abs(k) < _STRAIGHT_K:
        q = E + s1[:, None] * d0
    else:
        th = theta + k * s1
        q = E + np.stack([np.sin(th) - np.sin(theta), np.cos(theta) - np.cos(th)], 1) / k
    return np.vstack([P + s0[:, None] * d0, q]), theta + k * L1


def _segment_distance(X, A, B):
    """Distance of points X (n, 2) to the segment A-B."""
    ab = B - A
    ll = float(ab @ ab)
    t = np.zeros(len(X)) if ll == 0 else np.clip((X - A) @ ab / ll, 0.0, 1.0)
    q = X - (A + t[:, None] * ab)
    return np.hypot(q[:, 0], q[:, 1])


def _axis_distance(X, P, theta, L0, k, L1):
    """Distance of points X (n, 2) to the model's axis (without its end point's
    neighbourhood: the arc's interior and the straight part), the end point and the end's
    direction: (distance to the axis, distance to the end, end (2,), end angle)."""
    d0 = np.array([np.cos(theta), np.sin(theta)])
    E = P + L0 * d0
    d_seg = _segment_distance(X, P, E)
    if abs(k) < _STRAIGHT_K:
        end = E + L1 * d0
        d_arc = _segment_distance(X, E, end)
        th_end = theta
    else:
        th_end = theta + k * L1
        end = E + np.array([np.sin(th_end) - np.sin(theta), np.cos(theta) - np.cos(th_end)]) / k
        C = E + np.array([-np.sin(theta), np.cos(theta)]) / k
        R = 1.0 / abs(k)
        rel = X - C
        rad = np.hypot(rel[:, 0], rel[:, 1])
        phi0 = theta - np.sign(k) * np.pi / 2
        phi = np.arctan2(rel[:, 1], rel[:, 0])
        s = np.mod((phi - phi0) * np.sign(k), 2 * np.pi) * R
        inside = (s <= L1) | (abs(k) * L1 >= 2 * np.pi)
        d_arc = np.where(inside, np.abs(rad - R), np.hypot(X[:, 0] - E[0], X[:, 1] - E[1]))
    d_end = np.hypot(X[:, 0] - end[0], X[:, 1] - end[1])
    return np.minimum(d_seg, d_arc), d_end, end, th_end


def _signed_distance(p, X, P, theta, d_tail):
    """Signed distance (px, negative inside) of points X to the silhouette of the model
    ``p`` (L0, k, L1, r, a, sigma, dtheta, offset, ...): the band of half width ``r`` round
    the traced path behind the anchor (``d_tail``, its distances) and the axis, and where the
    end point is the nearest point of the axis the half-ellipse end face (as
    :mod:`jaxcr.segmentation.capsule_end`)."""
    L0, k, L1, r, a, _, dth, off = p[:8]
    th = theta + dth
    P2 = P + off * np.array([-np.sin(theta), np.cos(theta)])
    d_ax, d_end, end, th_end = _axis_distance(X, P2, th, L0, k, L1)
    de = np.array([np.cos(th_end), np.sin(th_end)])
    x = (X - end) @ de
    y = (X - end) @ np.array([-de[1], de[0]])
    a = max(a, 1e-3)
    xp = np.maximum(x, 0.0)
    rho = np.sqrt((xp / a) ** 2 + (y / r) ** 2)
    grad = np.sqrt((xp / a**2) ** 2 + (y / r**2) ** 2) / np.maximum(rho, 1e-9)
    cap = np.where(x > 0, (rho - 1.0) / np.maximum(grad, 1e-9), np.abs(y) - r)
    band = np.minimum(d_ax, d_tail) - r
    return np.where(d_end < np.minimum(d_ax, d_tail), cap, band), end, th_end


def _window(backbone: np.ndarray, width: float, back_widths: float, step: float):
    """The anchor (the path's point ``back_widths`` widths behind its end), its direction's
    angle, the window's grid (U, V) round the path's last stretch and the distances of its
    points to the path behind the anchor (the fixed tail); None for a path too short."""
    bb = np.asarray(backbone, np.float64)
    if len(bb) < 2:
        return None
    seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    back = back_widths * width
    if seg[-1] < 0.5 * back:
        return None
    s0 = max(seg[-1] - back, 0.0)
    P = np.array([np.interp(s0, seg, bb[:, 0]), np.interp(s0, seg, bb[:, 1])])
    # The direction at the anchor: the chord over half a width either side.
    sa, sb = max(s0 - 0.5 * width, 0.0), min(s0 + 0.5 * width, seg[-1])
    A = np.array([np.interp(sa, seg, bb[:, 0]), np.interp(sa, seg, bb[:, 1])])
    B = np.array([np.interp(sb, seg, bb[:, 0]), np.interp(sb, seg, bb[:, 1])])
    if np.linalg.norm(B - A) == 0:
        return None
    theta = float(np.arctan2(B[1] - A[1], B[0] - A[0]))
    c = 0.5 * (P + bb[-1])
    half = 0.5 * back + 2.0 * width
    xs = np.arange(-half, half + 1e-9, step)
    U, V = np.meshgrid(c[0] + xs, c[1] + xs)
    X = np.stack([U.ravel(), V.ravel()], 1)
    ss = np.arange(0.0, s0 + 1e-9, 0.5)
    tail = np.stack([np.interp(ss, seg, bb[:, 0]), np.interp(ss, seg, bb[:, 1])], 1)
    d_tail = cKDTree(tail).query(X)[0] if len(tail) > 1 else np.full(len(X), np.inf)
    return P, theta, U, V, X, d_tail, float(seg[-1] - s0), tail


def _fitted_axis(p, P, theta):
    """The axis of the fitted parameters ``p`` from the anchor ``P`` at angle ``theta``."""
    P2 = P + p[7] * np.array([-np.sin(theta), np.cos(theta)])
    return curl_axis(P2, theta + p[6], p[0], p[1], p[2])[0]


def fit_curl_end(
    score: np.ndarray,
    backbone,
    width: float,
    *,
    back_widths: float = 2.0,
    step: float = 1.0,
    max_nfev: int = 40,
    curled: bool = True,
) -> CurlEnd | None:
    """The end of the tube traced along ``backbone`` ((n, 2) (u, v) from the entry to the
    traced tip; ``width`` its width, px) fitted to the cue ``score`` (H, W) with the model
    of the module docstring, and the gentle model beside it. Window: a square of
    ``back_widths / 2 + 2`` widths half side round the path's last ``back_widths`` widths,
    sampled every ``step`` px (bilinear). Levels start at the window's 95th percentile
    (inside) and median (background); the soft-L1 loss's scale is a tenth of their
    difference. None for a path shorter than half the anchor's distance, a window without
    contrast, or a failed solve. ``curled`` False: the gentle model alone (the curled
    fields are then the gentle fit's, cost ratio 1; a quarter of the work)."""
    score = np.asarray(score, np.float64)
    w = float(width)
    if not (w > 0 and np.isfinite(w)):
        return None
    win = _window(backbone, w, back_widths, step)
    if win is None:
        return None
    P, theta, U, V, X, d_tail, L, tail = win
    g = ndi.map_coordinates(score, [V, U], order=1, mode="nearest").ravel()
    s_in, s_bg = float(np.percentile(g, 95)), float(np.median(g))
    if not s_in > s_bg:
        return None

    def model(p):
        sd, end, th_end = _signed_distance(p, X, P, theta, d_tail)
        cover = ndtr(-sd / _EDGE_PX).reshape(U.shape)
        cover = ndi.gaussian_filter(cover, max(p[5], 0.3) / step, mode="nearest")
        return p[9] + (p[8] - p[9]) * cover.ravel(), end, th_end

    def solve(k0: float, kmax: float):
        p0 = np.array([0.6 * L, k0, 0.4 * L + 0.5 * w, w / 2, w / 4, 1.2, 0.0, 0.0, s_in, s_bg])
        lo = np.array([0.0, -kmax, 0.5, 0.3 * w, 0.05, 0.3, -0.5, -w / 2, -np.inf, -np.inf])
        hi = np.array([2 * L + w, kmax, 3 * w, 0.8 * w, w / 2, 3.0, 0.5, w / 2, np.inf, np.inf])
        try:
            return least_squares(lambda p: model(p)[0] - g, np.clip(p0, lo, hi),
                                 bounds=(lo, hi), loss="soft_l1", f_scale=0.1 * (s_in - s_bg),
                                 max_nfev=max_nfev, tr_solver="lsmr")  # fmt: skip
        except (ValueError, np.linalg.LinAlgError):
            return None

    r = w / 2
    gentle = solve(0.0, _GENTLE_KR / r)
    if gentle is None:
        return None
    if curled:
        sols = [solve(k0, 2.0 / r) for k0 in (0.0, 0.8 / r, -0.8 / r)]
        sols = [s for s in sols if s is not None]
        if not sols:
            return None
        best = min(sols, key=lambda s: s.cost)
    else:
        best = gentle

    def ending(p):  # the fit's end, its angle and its backbone
        _, end, th_end = model(p)
        return end, th_end, np.vstack([tail[:-1], _fitted_axis(p, P, theta)])

    end0, th0, bb0 = ending(gentle.x)
    end, th_end, bb = (end0, th0, bb0) if best is gentle else ending(best.x)
    return CurlEnd(tip=end, direction=np.array([np.cos(th_end), np.sin(th_end)]),
                   curvature=float(best.x[1]), arc_px=float(best.x[2]),
                   half_width=float(best.x[3]), cost=float(best.cost),
                   gentle_cost=float(gentle.cost), gentle_tip=end0, gentle_backbone=bb0,
                   backbone=bb)  # fmt: skip
