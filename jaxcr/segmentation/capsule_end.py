"""A tube's end located by fitting a blurred capsule end to the cue map (issue 16 item 2,
docs/decisions.md S42).

A tube of half width ``r`` (px) ends in a flat disc whose normal is the tube's axis; seen at
an angle, the disc is an ellipse of semi-axes ``r`` across the tube and ``a = r |u . v|``
along it (``0 <= a <= r``; a rounded end seen from any side shows ``a = r``). The
silhouette near the end is the union of a band (two parallel edges ``2 r`` apart) and that
half-ellipse beyond the end point ``c`` (the disc's centre, the tip), blurred by the
optics and the cue's smoothing. :func:`fit_capsule_end` fits that picture to the cue score
in a window around a traced end: the end point ``c`` (sub-pixel), the axis direction from
the two edges (not from the traced path's last points, which can run along one edge), the
half width ``r``, the end face's length ``a``, the blur, the levels inside and beside the
tube, and a slight bend of the axis behind the end. It is what
:func:`jaxcr.segmentation.foreground.refine_tip_details` measures step by step (the axis,
the half-level end, the cap from the soft area), in one least-squares fit whose residuals
say whether the window shows one tube end.

Pure numpy / scipy, host side, one view at a time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from scipy.optimize import least_squares
from scipy.special import ndtr

__all__ = ["CapsuleEnd", "capsule_end_image", "fit_capsule_end", "with_capsule_end"]


@dataclass(frozen=True)
class CapsuleEnd:
    """A fitted tube end (pixels (u, v); :func:`fit_capsule_end`).

    Attributes:
        tip: (2,) the end point on the axis (the end face's centre).
        direction: (2,) unit, the axis direction at the end, pointing out of the tube.
        half_width: the tube's half width ``r`` (px).
        cap: the end face's length beyond ``tip`` along ``direction`` (px, ``0..r``): the
            silhouette ends at ``tip + cap * direction``.
        blur: the edge blur (Gaussian sigma, px).
        inside, background: the cue levels on the tube at the end and beside it.
        bend: the axis' curvature behind the end (1/px; the axis is
            ``y = bend x^2 / 2`` for ``x < 0`` in the end's frame).
        rms: the residual's root mean square over the window, as a fraction of the
            contrast ``inside - background``.
    """

    tip: np.ndarray
    direction: np.ndarray
    half_width: float
    cap: float
    blur: float
    inside: float
    background: float
    bend: float
    rms: float


def _silhouette_distance(p, x0, y0):
    """Signed distance (px, negative inside) of points (x0, y0) of the image to the
    silhouette of the capsule end ``p`` (cx, cy, theta, r, a, ...; bend last): behind the
    end the band's edges ``|y| = r`` (the axis bent as ``y = bend x^2 / 2``); beyond it the
    half-ellipse's, to first order ``(rho - 1) / |grad rho|`` with
    ``rho = sqrt((x/a)^2 + (y/r)^2)`` (``x - a`` on the axis, ``|y| - r`` at the end's
    corners, exact on the ellipse, so exact where the sharp edge is drawn)."""
    cx, cy, th, r, a = p[:5]
    k = p[-1]
    c, sn = np.cos(th), np.sin(th)
    dx, dy = x0 - cx, y0 - cy
    x = c * dx + sn * dy
    y = -sn * dx + c * dy
    yc = y - 0.5 * k * np.minimum(x, 0.0) ** 2
    a = max(a, 1e-3)
    xp = np.maximum(x, 0.0)
    rho = np.sqrt((xp / a) ** 2 + (yc / r) ** 2)
    grad = np.sqrt((xp / a**2) ** 2 + (yc / r**2) ** 2) / np.maximum(rho, 1e-9)
    return np.where(x > 0, (rho - 1.0) / np.maximum(grad, 1e-9), np.abs(yc) - r)


_EDGE_PX = 0.25  # the drawn edge's own softness (px), under the blur that is fitted


def _cover(p, U, V, step):
    """The capsule end's coverage (0..1) on the window's grid (U, V) (image points, a
    regular grid of spacing ``step`` px) for the geometry ``p`` (cx, cy, theta, r, a,
    sigma, ..., bend): the silhouette drawn nearly sharp, blurred by a Gaussian of
    ``sigma`` px on the grid (a blurred corner or curved end is not a blurred straight
    edge: drawing then blurring keeps the end's half level where the optics put it)."""
    cover = ndtr(-_silhouette_distance(p, U, V) / _EDGE_PX)
    blur = np.sqrt(max(p[5] ** 2 - _EDGE_PX**2, 1e-6)) / step
    return ndi.gaussian_filter(cover, blur, mode="nearest", truncate=3.0)


def capsule_end_image(
    shape: tuple[int, int],
    tip,
    direction,
    half_width: float,
    cap: float,
    *,
    blur: float = 1.0,
    inside: float = 1.0,
    background: float = 0.0,
    supersample: int = 8,
) -> np.ndarray:
    """A tube end rendered in closed form (the test's reference): an image ``shape``
    (H, W), ``inside`` on the pixels the silhouette covers and ``background`` elsewhere,
    blurred by a Gaussian of ``blur`` px. The silhouette is the straight band of half width
    ``half_width`` behind ``tip`` (u, v) along ``-direction`` to the image's border, and
    the half-ellipse of semi-axes ``cap`` (along) and ``half_width`` (across) beyond it;
    each pixel's coverage is counted on a ``supersample`` x ``supersample`` grid of its
    area (pixel centres at integer coordinates), then blurred (``scipy.ndimage``)."""
    h, w = shape
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    n = np.array([-d[1], d[0]])
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    vv, uu = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    cover = np.zeros((h, w))
    for du in o:
        for dv in o:
            q = np.stack([uu + du - tip[0], vv + dv - tip[1]], -1)
            x, y = q @ d, q @ n
            band = (x <= 0) & (np.abs(y) <= half_width)
            ell = (x > 0) & (
                (x / max(cap, 1e-9)) ** 2 + (y / half_width) ** 2 <= 1.0 if cap > 0 else False
            )
            cover += band | ell
    cover /= supersample**2
    if blur > 0:
        cover = ndi.gaussian_filter(cover, blur, mode="nearest")
    return background + (inside - background) * cover


def fit_capsule_end(
    score: np.ndarray,
    tip,
    direction,
    half_width: float,
    *,
    cap: float = 0.0,
    behind: float = 2.5,
    ahead: float = 1.5,
    step: float = 0.5,
    max_move: float = 1.0,
    max_turn_deg: float = 60.0,
    max_blur: float = 1.9,
) -> CapsuleEnd | None:
    """The tube end near ``tip`` (u, v) fitted to the cue ``score`` (H, W) (the model of
    the module docstring).

    The window runs ``behind`` tube widths (``2 half_width``) back from ``tip`` along
    ``-direction`` and ``ahead`` widths on, ``1.5`` widths either side of the axis, sampled
    every ``step`` px (bilinear). Start: ``tip``, ``direction``, ``half_width``, ``cap``,
    blur 1 px, levels from the window's quantiles. Robust least squares (soft L1 at a tenth
    of the contrast), so another object entering the window (a crossing cable, tape) pulls
    little. Returns None when the fit does not hold one tube end in the window: the
    contrast is not positive, the end point moved over ``max_move`` widths or the axis
    turned over ``max_turn_deg`` (a tube curling at its end leaves the traced end
    direction 30-50 deg off its end's axis: dev 3886, 4016), the end face is longer than
    the half width (by 10 %: a disc seen from any side is no longer along the tube than
    across it; a longer one is the tube going on where its cue fades, dev 3750), the half width left ``[0.5, 2]`` times the start, the
    blur is over ``max_blur`` px (a clean end of real_like at 1280x720 fits 1.2-1.4 px; a
    wider blur is a cue that fades or steps along the tube, which the one level and slope
    do not describe: the end found there was 7-10 px short on dev 4048 and 4092), or the
    fit failed."""
    score = np.asarray(score, np.float64)
    t0 = np.asarray(tip, np.float64)
    d0 = np.asarray(direction, np.float64)
    r0 = float(half_width)
    if not (np.all(np.isfinite(t0)) and np.all(np.isfinite(d0)) and r0 > 0):
        return None
    nd = float(np.linalg.norm(d0))
    if nd == 0:
        return None
    d0 = d0 / nd
    n0 = np.array([-d0[1], d0[0]])
    w = 2.0 * r0
    xs = np.arange(-behind * w, ahead * w + 1e-9, step)
    ys = np.arange(-1.5 * w, 1.5 * w + 1e-9, step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    U = t0[0] + X * d0[0] + Y * n0[0]
    V = t0[1] + X * d0[1] + Y * n0[1]
    h, wd = score.shape
    g = ndi.map_coordinates(score, [V, U], order=1, mode="nearest")
    # Residuals on the window's interior (the blur at the grid's border sees the border
    # repeated) and on image pixels only.
    m = int(np.ceil(3.0 / step))
    use = (U >= 0) & (U <= wd - 1) & (V >= 0) & (V <= h - 1)
    use[:m], use[-m:], use[:, :m], use[:, -m:] = False, False, False, False
    if use.mean() < 0.4:
        return None
    s_in0 = float(np.median(g[(X < -0.5 * w) & (np.abs(Y) < 0.5 * r0) & use]))
    s_bg0 = float(np.median(g[(np.abs(Y) > 1.0 * w) & use]))
    contrast0 = s_in0 - s_bg0
    if not contrast0 > 0:
        return None
    th0 = float(np.arctan2(d0[1], d0[0]))
    # Parameters: cx, cy, theta, r, a, sigma, inside, its slope along the tube (per px,
    # behind the end), background, bend.
    p0 = np.array([t0[0], t0[1], th0, r0, float(np.clip(cap, 0.3, 0.95 * r0)), 1.0,
                   s_in0, 0.0, s_bg0, 0.0])  # fmt: skip
    # The end face's length from 0.25 px (a flat end seen edge-on; at 0 the ellipse's
    # distance is singular and the solver crawls).
    lo = np.array([-np.inf, -np.inf, th0 - np.pi / 2, 0.5 * r0, 0.25, 0.3,
                   s_bg0, -np.inf, -np.inf, -0.5 / w])  # fmt: skip
    hi = np.array([np.inf, np.inf, th0 + np.pi / 2, 2.0 * r0, 2.0 * r0, 0.6 * r0 + 0.5,
                   np.inf, np.inf, np.inf, 0.5 / w])  # fmt: skip
    gv = g[use]

    def model(p):
        c, sn = np.cos(p[2]), np.sin(p[2])
        x = c * (U - p[0]) + sn * (V - p[1])
        return p[8] + (p[6] + p[7] * np.minimum(x, 0.0) - p[8]) * _cover(p, U, V, step)

    def resid(p):
        return model(p)[use] - gv

    try:
        sol = least_squares(resid, p0, bounds=(lo, hi), loss="soft_l1",
                            f_scale=0.1 * contrast0, x_scale="jac", max_nfev=200)  # fmt: skip
    except (ValueError, np.linalg.LinAlgError):
        return None
    p = sol.x
    cx, cy, th, r, a, s, s_in, _, s_bg, k = p
    contrast = s_in - s_bg
    tip_f = np.array([cx, cy])
    d = np.array([np.cos(th), np.sin(th)])
    turn = np.degrees(np.arccos(np.clip(d @ d0, -1.0, 1.0)))
    if not (
        sol.status > 0
        and contrast > 0
        and np.linalg.norm(tip_f - t0) <= max_move * w
        and turn <= max_turn_deg
        and 0.5 * r0 < r < 2.0 * r0
        and s <= max_blur
        and a <= 1.1 * r
    ):
        return None
    rms = float(np.sqrt(np.mean(resid(p) ** 2)) / max(contrast, 1e-9))
    return CapsuleEnd(tip=tip_f, direction=d, half_width=float(r), cap=float(min(a, r)),
                      blur=float(s), inside=float(s_in), background=float(s_bg),
                      bend=float(k), rms=rms)  # fmt: skip


def with_capsule_end(trace, *, cap_from_image: bool = False):
    """``trace`` (a :class:`jaxcr.segmentation.foreground.TubeTrace`) with its tip placed
    by :func:`fit_capsule_end` on its own cue ``score``, started from its traced end
    (``tip``, ``end_dir``, ``end_half_width_px`` or half of ``width_px``, ``cap_px``): a
    copy with ``tip``, ``cap_px``, ``end_dir``, ``end_half_width_px`` and the backbone's
    last point replaced; the path is the tracer's. ``trace`` itself where it has no score
    or end direction, or the fit returns None. ``cap_from_image``: the copy is marked
    (attribute ``cap_from_image``) so that the two-view step keeps the fitted end face's
    length instead of the one from the tube's 3-D direction
    (:func:`jaxcr.stereo.pipeline.trace_stereo_tips`)."""
    from dataclasses import replace

    score = getattr(trace, "score", None)
    d = np.asarray(getattr(trace, "end_dir", np.zeros(2)), np.float64)
    if score is None or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        return trace
    hw = trace.end_half_width_px if trace.end_half_width_px > 0 else 0.5 * trace.width_px
    fit = fit_capsule_end(score, trace.tip, d, hw, cap=trace.cap_px)
    if fit is None:
        return trace
    bb = np.asarray(trace.backbone, np.float64)
    bb = np.vstack([bb[:-1], fit.tip[None]]) if len(bb) else fit.tip[None]
    out = replace(trace, tip=fit.tip.copy(), cap_px=fit.cap, end_dir=fit.direction.copy(),
                  end_half_width_px=fit.half_width, backbone=bb)  # fmt: skip
    if cap_from_image:
        out.cap_from_image = True
    return out
