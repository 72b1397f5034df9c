"""One end for both views of a tube (issue 16 item 2, docs/decisions.md S27).

Not called by the pipeline: on real_like development it lost (163 -> 144 of 189 frames, S27),
because the other view's end carried along the 3-D axis inherits the calibration's epipolar
error divided by the sine of the end line's angle to the epipolar lines. It is kept, tested,
for rigs whose calibration is sub-pixel.

The tube's tip is one 3-D point, yet each view places its tip on its own silhouette's end
(:func:`jaxcr.segmentation.foreground.refine_tip_details`, then the end face's length from
both views, :func:`jaxcr.stereo.tip_geometry.end_face_lengths`). Where one view's silhouette
goes on past the end (a shadow or other foreground touching it) or stops short, its tip is
off along the tube while the other view's is right. Here the end is fitted once, to both
views' evidence together:

- The tube's last stretch is a 3-D line ``L``: the plane through camera ``k``'s centre and
  the image line ``x_k + t d_k`` (the view's tip and end direction) holds the axis; ``L`` is
  the two planes' intersection (:func:`axis_line`). ``L`` projects onto each view's own end
  line, so only the position *along* the tube is decided here.
- Each view's score is sampled along its end line, averaged across the central half of
  the tube's projected width (:func:`end_profile`), from 3 widths behind the tip to 2.5
  widths past it.
- A 3-D end ``X(s) = X0 + s u`` predicts in view ``k`` a blurred step (the inside level
  1-2.5 widths behind the tip, the background level beside the tube) whose edge is the
  projection of ``X(s)`` plus the end face's foreshortened length ``a_k = 0.957 R_k |u . v_k|``
  (the disc seen along the ray ``v_k``; 0.957 the half-ellipse's mean length over the central
  half width). ``s*`` minimises the sum over both views of the absolute residuals (a joint
  L1 fit on a 1-D grid of ``s``, 0.25 px steps in the faster view, two widths either side).
  A view's residual scales with its step's contrast, so a view without a step says little;
  and with an L1 cost the view whose edge costs more per unit of ``s`` (higher contrast,
  more pixels per metre along ``L``) decides, not a compromise between the two.
- Degenerate, None returned (the caller keeps the per-view tips): the two planes within
  ``asin(min_sin)`` of each other (the axis near an epipolar plane, its image near the
  epipolar lines in both views: the planes nearly coincide, so their intersection, and with
  it which point of one view's end line matches which of the other's, is ill-determined),
  one view seeing ``L`` over
  ``max_ratio`` times shorter than the other (the axis nearly along its viewing ray), no step
  in either view, or the minimum at the end of the searched stretch.

Measured (docs/decisions.md S27; experiments/results/segmentation/
real_like_tip_r12_rig31b_dev.md): on the real_like preset the other view's end, carried along ``L``, is 3.2 px (median) from
the truth where a view's own edge is 0.5 px, through the rig's calibration error (true tips
1.5 px median from each other's epipolar lines) and the end directions' error; the joint end
lost frames on development at every gate tried and is not used by
:func:`jaxcr.stereo.pipeline.traced_stereo_tips`.

Pure numpy; no cv2 and no file I/O. Pixels are undistorted (the caller samples its
distorted score through ``samplers``). Poses ``T_cam_world`` (4, 4), any world frame shared
by both cameras; ``s`` in that frame's length unit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import erfc

__all__ = ["JointEnd", "axis_line", "end_profile", "joint_end"]

# Mean over |t| <= R/2 of sqrt(1 - (t/R)^2): the half-ellipse's length in the central band.
_CENTRAL_CAP = 0.957


@dataclass
class JointEnd:
    """Result of :func:`joint_end`: ``tips`` [(2,), (2,)] undistorted pixels (the 3-D end's
    projections), ``point`` (3,) the end (world frame), ``direction`` (3,) unit axis (out of
    the tip), ``s`` the end's offset along ``L`` from the two tips' triangulation,
    ``moved_px`` (2,) how far each view's tip moved, ``contrast`` (2,) each view's step
    (inside minus background level), ``cost`` (2,) each view's L1 residual at ``s``."""

    tips: list
    point: np.ndarray
    direction: np.ndarray
    s: float
    moved_px: np.ndarray
    contrast: np.ndarray
    cost: np.ndarray


def _centre(T: np.ndarray) -> np.ndarray:
    return -T[:3, :3].T @ T[:3, 3]


def _project(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Undistorted pixels (n, 2) of world points ``X`` (n, 3)."""
    x = (T[:3, :3] @ X.T + T[:3, 3:4]).T @ K.T
    return x[:, :2] / x[:, 2:3]


def axis_line(Ks, Ts, tips, dirs) -> tuple[np.ndarray, np.ndarray, float]:
    """The 3-D line through both views' end lines: ``(X0, u, sin)`` with ``X0`` the point
    of the line nearest the two tips' rays (midpoint triangulation), ``u`` its unit
    direction pointing out of the tip (its projection in view 1 along ``dirs[0]``), and
    ``sin`` the sine of the angle between the two planes (0: the axis lies in an epipolar
    plane and is not fixed). ``tips``/``dirs``: per view (u, v) undistorted pixel and unit
    image direction."""
    normals, centres, rays = [], [], []
    for K, T, x, d in zip(Ks, Ts, tips, dirs, strict=True):
        K, T = np.asarray(K, np.float64), np.asarray(T, np.float64)
        Ki = np.linalg.inv(K)
        R = T[:3, :3]
        r0 = Ki @ np.r_[np.asarray(x, np.float64), 1.0]
        r1 = Ki @ np.r_[np.asarray(x, np.float64) + 10.0 * np.asarray(d, np.float64), 1.0]
        nrm = np.cross(r0, r1)
        normals.append(R.T @ (nrm / np.linalg.norm(nrm)))
        centres.append(_centre(T))
        rays.append(R.T @ (r0 / np.linalg.norm(r0)))
    u = np.cross(normals[0], normals[1])
    sin = float(np.linalg.norm(u))
    u = u / max(sin, 1e-300)
    # Midpoint of the shortest segment between the two tips' rays.
    c0, c1, r0, r1 = centres[0], centres[1], rays[0], rays[1]
    A = np.array([[r0 @ r0, -r0 @ r1], [r0 @ r1, -r1 @ r1]])
    lam = np.linalg.lstsq(A, np.array([(c1 - c0) @ r0, (c1 - c0) @ r1]), rcond=None)[0]
    Xm = 0.5 * (c0 + lam[0] * r0 + c1 + lam[1] * r1)
    # The point of L (on both planes) nearest Xm along u.
    M = np.stack([normals[0], normals[1], u])
    X0 = np.linalg.solve(M, np.array([normals[0] @ c0, normals[1] @ c1, u @ Xm]))
    K0, T0 = np.asarray(Ks[0], np.float64), np.asarray(Ts[0], np.float64)
    p = _project(K0, T0, np.stack([X0, X0 + 1e-3 * u]))
    if (p[1] - p[0]) @ np.asarray(dirs[0], np.float64) < 0:
        u = -u
    return X0, u, sin


def end_profile(
    sampler: Callable[[np.ndarray], np.ndarray], tip, d, half_width: float, *, step: float = 0.25
) -> tuple[np.ndarray, np.ndarray, float]:
    """The score along a view's end line: ``(tau, profile, background)``, ``tau`` (m,) px
    from ``tip`` along the unit direction ``d`` (3 widths back to 2.5 past, ``step`` px),
    ``profile`` the score averaged over the central half width (5 samples across
    ``|t| <= half_width / 2``), ``background`` the median score beside the tube
    (``1-1.5`` widths either side, 1-3 widths behind the tip). ``sampler`` maps
    undistorted pixels (n, 2) to score values (n,)."""
    tip, d = np.asarray(tip, np.float64), np.asarray(d, np.float64)
    n = np.array([-d[1], d[0]])
    w = 2.0 * half_width
    tau = np.arange(-3.0 * w, 2.5 * w + 1e-9, step)
    tt = np.linspace(-0.5, 0.5, 5) * half_width
    pts = tip[None, None] + tau[:, None, None] * d + tt[None, :, None] * n
    prof = sampler(pts.reshape(-1, 2)).reshape(len(tau), len(tt)).mean(1)
    behind = tau[(tau >= -3.0 * w) & (tau <= -w)]
    side = np.r_[np.linspace(-1.5, -1.0, 3), np.linspace(1.0, 1.5, 3)] * w
    spts = tip[None, None] + behind[:, None, None] * d + side[None, :, None] * n
    bg = float(np.median(sampler(spts.reshape(-1, 2))))
    return tau, prof, bg


def joint_end(
    Ks, Ts, tips, dirs, half_widths, samplers, *, min_sin: float = 0.25, max_ratio: float = 4.0,
    blur_px: float = 1.0, search_widths: float = 2.0, step: float = 0.25,
) -> JointEnd | None:  # fmt: skip
    """The tube's one 3-D end from both views' score profiles (module docstring).

    ``Ks``, ``Ts``: the two cameras' intrinsics (3, 3) and ``T_cam_world`` (4, 4); ``tips``,
    ``dirs``: per view the current tip and the unit end direction (undistorted pixels);
    ``half_widths``: the tube's projected half width at the tip per view (px);
    ``samplers``: per view a function from undistorted pixels (n, 2) to the score (n,).
    ``blur_px``: the step's Gaussian blur (the image's and the score's); ``s`` is searched
    over ``search_widths`` tube widths either side of the tips' triangulation (in pixels of
    the view where ``L`` is longest). Returns :class:`JointEnd`, or None where degenerate
    (module docstring)."""
    Ks = [np.asarray(K, np.float64) for K in Ks]
    Ts = [np.asarray(T, np.float64) for T in Ts]
    tips = [np.asarray(t, np.float64) for t in tips]
    dirs = [np.asarray(d, np.float64) / np.linalg.norm(d) for d in dirs]
    X0, u, sin = axis_line(Ks, Ts, tips, dirs)
    if sin < min_sin:
        return None
    # Pixels per unit of s along each view's end line, at X0.
    eps = 1e-4 * max(np.linalg.norm(X0 - _centre(T)) for T in Ts)
    J = []
    for K, T, d in zip(Ks, Ts, dirs, strict=True):
        p = _project(K, T, np.stack([X0 - eps * u, X0 + eps * u]))
        J.append(float((p[1] - p[0]) @ d / (2 * eps)))
    J = np.array(J)
    if np.any(J <= 0) or max(J) / min(J) > max_ratio:
        return None
    a = []
    for K, T, x, R in zip(Ks, Ts, tips, half_widths, strict=True):
        ray = T[:3, :3].T @ (np.linalg.inv(K) @ np.r_[x, 1.0])
        a.append(_CENTRAL_CAP * R * abs(u @ ray) / np.linalg.norm(ray))
    profs = [
        end_profile(f, x, d, R)
        for f, x, d, R in zip(samplers, tips, dirs, half_widths, strict=True)
    ]
    contrast = []
    for (tau, prof, bg), R_k in zip(profs, half_widths, strict=True):
        w = 2.0 * R_k
        inside = float(np.median(prof[(tau >= -2.5 * w) & (tau <= -w)]))
        contrast.append(inside - bg)
    contrast = np.array(contrast)
    if not np.any(contrast > 0):
        return None
    s_range = search_widths * 2.0 * max(half_widths) / max(J)
    ds = step / max(J)
    ss = np.arange(-s_range, s_range + 1e-15, ds)
    pts = X0[None] + ss[:, None] * u[None]
    cost = np.zeros((2, len(ss)))
    for k in range(2):
        tau, prof, bg = profs[k]
        c = max(contrast[k], 0.0)
        # Edge of view k's silhouette for each s: the projection of X(s) along its end line
        # (measured from its tip) plus the end face's foreshortened length.
        edge = (_project(Ks[k], Ts[k], pts) - tips[k]) @ dirs[k] + a[k]
        z = (tau[None, :] - edge[:, None]) / (np.sqrt(2.0) * blur_px)
        model = bg + c * 0.5 * erfc(z)
        cost[k] = np.abs(prof[None, :] - model).sum(1) * step
    total = cost.sum(0)
    i = int(np.argmin(total))
    if i in (0, len(ss) - 1):  # no end within the searched stretch
        return None
    X = pts[i]
    new = [_project(K, T, X[None])[0] for K, T in zip(Ks, Ts, strict=True)]
    moved = np.array([np.linalg.norm(p - x) for p, x in zip(new, tips, strict=True)])
    return JointEnd(new, X, u, float(ss[i]), moved, contrast, cost[:, i])
