"""Robot foreground on real backgrounds from a background plate (issue 16 item 2), shared by
``jaxcr segment --background plate`` and ``jaxcr stereo --segmentation trace``.

A key colour alone fails on real rigs: a dark, green-tinted tube over green cloth has the
cloth's hue, creases and static shadows are darker cloth, and where the tube crosses black
tape it matches the background completely. This module works in four steps, all numpy /
scipy on float RGB in [0, 1] (no cv2, no file I/O):

1. :func:`align_plate`: the plate (the empty scene) is registered to the frame by a
   translation, found to sub-pixel precision (cameras drift by pixels over a recording):
   phase correlation for the integer part, then weighted Gauss-Newton (Lucas-Kanade) on the
   grey images with Tukey weights, so the robot's pixels (large residuals) do not pull the
   estimate. :func:`shift_image` resamples the plate (bilinear).
2. :func:`foreground_cues`: per-pixel cues beyond the key colour, each scaled so that 1
   means "at its threshold": *darker* than the plate (``1 - Y / Y_plate``), *less
   saturated* (chroma drop relative to brightness), *different hue* (angle between the
   chroma vectors, where both are coloured) and the plain colour distance. The score is
   their maximum.
3. :func:`hysteresis`: pixels with score >= ``high`` seed the mask; pixels >= ``low``
   connected (8-neighbours) to a seed extend it (as ``skimage.filters.
   apply_hysteresis_threshold``).
4. :func:`trace_tube`: a walker follows the tube on that mask from its entry point (a given
   pixel, or found at the image border): each step picks the direction (within
   ``max_turn_deg`` of the current one) whose ray ahead is best covered by the mask and
   re-centres across the tube. Where the tube matches the background (tape, shadows,
   creases) the mask breaks; the walker then looks straight on (within
   ``gap_turn_deg``) up to ``max_gap_px`` pixels for the mask to resume and bridges the
   gap. Beyond that, the tube ends: the tip is the last mask pixel along the path (a
   walker that turned round the end face and back along the tube is cut back to its
   farthest point: a tube cannot reverse within its own width; a path that ran along one
   edge near the end is moved onto the tube's axis first, :func:`centre_end_on_axis`).
   Output: the robot mask (mask pixels near the path plus the bridges drawn at the tube's
   width), the ordered 2-D backbone and the tip pixel.

The tracing lengths are in pixels of a view where the tube is about ``tube_width_px`` wide;
:func:`plate_foreground` measures the tube's width near the entry and traces a view where it
is ``k >= 2`` times wider on the frame and plate reduced ``k`` times, refining the tip at full
resolution (:class:`PlateForegroundConfig`, "Scale").

Pixel convention: OpenCV's (u, v) = (column, row), pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

__all__ = [
    "PlateForegroundConfig",
    "TubeTrace",
    "align_plate",
    "shift_image",
    "foreground_cues",
    "cue_maps",
    "close_score",
    "hysteresis",
    "trace_tube",
    "start_alternatives",
    "border_entry",
    "refine_tip",
    "refine_tip_details",
    "centre_end_on_axis",
    "measure_tube_width",
    "downsample",
    "plate_foreground",
    "trace_alternatives",
    "end_before_hop",
    "crossing_turn",
    "crosses_through",
]


@dataclass(frozen=True)
class PlateForegroundConfig:
    """Thresholds of the plate foreground (every one is a CLI flag ``--plate-...``).

    Cue thresholds (each cue is 1 at its threshold):
        dark: relative darkening ``1 - Y/Y_plate`` of a pixel where the plate is
            achromatic (chroma < ``min_chroma``: a white board, black tape) (0.3: a grey tube on a white board darkens it by 25-45 %); on
            coloured cloth a cast shadow is the plate darkened, so darkness is no cue there.
        desat: drop of saturation ``(max - min)/max`` from plate to frame (0.25).
        hue_deg: hue change in degrees, counted where both chromas exceed ``min_chroma``
            (30).
        diff: RGB distance to the plate scaled by the best gain in [``min_gain``, 1]
            (0.25; ``min_gain`` 0.35): the old plate mode's cue made shadow-invariant.
        min_chroma: chroma ``max - min`` below which a pixel has no reliable hue (0.08).
        min_luma: darkening and saturation are relative to ``max(value, min_luma)``
            (0.2): near-black pixels (tape, deep shadow) have no reliable relative change.
    Tip: ``refine`` (True) places the tip by :func:`refine_tip` (the score's half level
    along the end direction, minus the end face's foreshortened half-ellipse, at most
    ``tip_cap`` (1.0) x the half width; 0 = the silhouette's end).
    Closing: the score is closed (grey-level, disc of ``close_px`` (2) pixels) so a tube
    seen only by its two edges is filled (0 = off).
    Hysteresis on the score (the maximum of the cues): ``high`` seeds (1.0), ``low``
    extends (0.4).
    Noise: frame and plate are smoothed with a Gaussian of ``blur_px`` (1.0) pixels.
    Alignment: ``align`` (True) registers the plate; ``max_shift_px`` (8) bounds the shift.
    Tracing: ``step_px`` (2) walker step; ``look_px`` (10) length of the ray that scores a
    direction; ``max_turn_deg`` (30) largest turn per step; ``corner_deg`` (90) where no direction
    within ``max_turn_deg`` is supported, turns up to this are tried (a projected kink or
    hook) onto mask not traced already, before a gap is searched; ``support`` (0.6) fraction of
    the ray on the mask to keep walking; ``max_gap_px`` (80) the longest stretch where the
    tube may match the background (tape, shadow, crease) that is bridged; ``gap_turn_deg``
    (12) the cone searched across a gap; ``max_width_px`` (40) the widest tube searched
    across when re-centring; ``min_seed_px`` (20) smallest mask component the walker
    accepts after a gap (noise specks are smaller); ``gap_visible`` (0.5) a gap is not
    bridged when the tube's colour (its last traced stretch) would score above ``high``
    against the plate on more than this fraction of the gap (the tube would have been
    seen there, so it ended; 1 = off); ``start_spread_deg`` (20) a given
    entry direction is also tried turned by this much either way, the longest trace kept.
    Scale: every length above (``blur_px``, ``close_px``, ``step_px``, ``look_px``,
    ``max_gap_px``, ``max_width_px``, ``min_seed_px`` (an area), ``max_shift_px`` excepted: the
    plate is aligned at full resolution) is in pixels of a view where the tube is about
    ``tube_width_px`` (7) pixels wide, the width they were set at (the ``real_like`` preset at
    640x360). :func:`plate_foreground` measures the tube's width near the entry
    (:func:`measure_tube_width`) and, where it is ``k = round(width / tube_width_px) >= 2``
    times that, finds and traces the tube on the frame and plate reduced by ``k`` (area
    average), then maps the path back and refines the tip on the full-resolution score.
    ``scale`` (0 = that automatic choice) forces the factor ``k`` (1 = full resolution).
    """

    dark: float = 0.3
    desat: float = 0.25
    hue_deg: float = 30.0
    diff: float = 0.25
    min_chroma: float = 0.08
    min_luma: float = 0.2
    close_px: float = 2.0
    min_gain: float = 0.35
    high: float = 1.0
    low: float = 0.4
    blur_px: float = 1.0
    align: bool = True
    max_shift_px: float = 8.0
    step_px: float = 2.0
    look_px: float = 10.0
    max_turn_deg: float = 30.0
    corner_deg: float = 90.0
    support: float = 0.6
    max_gap_px: float = 80.0
    gap_turn_deg: float = 12.0
    max_width_px: float = 40.0
    min_seed_px: int = 20
    gap_visible: float = 0.5
    tip_cap: float = 1.0
    refine: bool = True
    start_spread_deg: float = 20.0
    tube_width_px: float = 7.0
    scale: int = 0


@dataclass
class TubeTrace:
    """Result of :func:`plate_foreground` / :func:`trace_tube`.

    Attributes:
        mask: (H, W) bool robot pixels (the traced mask components plus bridged gaps).
        backbone: (n, 2) ordered (u, v) pixels from the entry to the tip.
        tip: (2,) (u, v) tip pixel.
        entry: (2,) (u, v) where tracing started.
        gaps: list of (start index, end index) into ``backbone`` of bridged stretches.
        shift: (2,) (du, dv) plate alignment shift applied (frame(x) ~ plate(x - shift)).
        score: (H, W) the cue score; ``seed_mask``: the hysteresis mask before tracing.
        width_px: median tube width across the traced path (pixels).
        reason: None, or why tracing stopped early (e.g. "no foreground at the entry").
        cap_px: length of the end face's half-ellipse removed by :func:`refine_tip` (px).
        scale: the factor ``k`` the tube was traced at (1 = full resolution; see
            :class:`PlateForegroundConfig`); ``measured_width_px``: the width that chose it.
        end_dir, end_half_width_px: the tube's direction (unit (u, v)) and half width at
            the tip (:func:`refine_tip_details`; the silhouette's end is
            ``tip + cap_px * end_dir``).
        junctions: (backbone index, point (u, v), direction) where a second, separate
            branch of the mask was supported ahead besides the one followed (a crossing
            cable or tool, a shadow leaving the tube), or direction None where the run
            across the tube was over 1.6 times its width (something crossing it);
            :func:`plate_foreground` follows them when the trace ran out of the image,
            :func:`trace_alternatives` when a second view disagrees.
        crossing_turn_deg: the largest turn of the path where it passes a junction (the
            angle between the tube's heading arriving there and the chord to the path two
            look lengths on, :func:`crossing_turn`): a tube passing behind a crossing
            object goes on smoothly, a trace that turned onto the object turns by the
            crossing angle.
        crossings_followed: at how many junctions the path leaves along something that
            crosses the tube there (:func:`crosses_through`: the line it leaves along is on
            the mask behind the junction too).
        departure: for an alternative of :func:`trace_alternatives`, the index into
            ``backbone`` (at the traced scale) of the junction it leaves the original
            trace at; None for a trace of :func:`plate_foreground`.
        retrace: what :func:`trace_alternatives` needs (the traced view's mask and images,
            the factor, the full-resolution score); None for traces from
            :func:`trace_tube`.
    """

    mask: np.ndarray
    backbone: np.ndarray
    tip: np.ndarray
    entry: np.ndarray
    gaps: list = field(default_factory=list)
    shift: np.ndarray = field(default_factory=lambda: np.zeros(2))
    score: np.ndarray | None = None
    seed_mask: np.ndarray | None = None
    width_px: float = 0.0
    reason: str | None = None
    cap_px: float = 0.0
    scale: int = 1
    measured_width_px: float = 0.0
    end_dir: np.ndarray = field(default_factory=lambda: np.zeros(2))
    end_half_width_px: float = 0.0
    junctions: list = field(default_factory=list)
    crossing_turn_deg: float = 0.0
    departure: int | None = None
    crossings_followed: int = 0
    retrace: object | None = field(default=None, repr=False)


# ----------------------------------------------------------------------------- alignment


def _grey(image: np.ndarray) -> np.ndarray:
    im = np.asarray(image, np.float64)
    return im @ np.array([0.299, 0.587, 0.114]) if im.ndim == 3 else im


def shift_image(image: np.ndarray, shift_uv) -> np.ndarray:
    """``out(u, v) = image(u - du, v - dv)`` by bilinear interpolation (edges clamped):
    the image content moves by ``shift_uv = (du, dv)`` pixels. A constant shift is
    separable: integer index shifts plus two linear blends."""
    im = np.asarray(image, np.float64)
    h, w = im.shape[:2]
    out = im
    for axis, n, sh in ((1, w, float(shift_uv[0])), (0, h, float(shift_uv[1]))):
        x = np.arange(n) - sh
        i0 = np.floor(x)
        t = x - i0
        i0 = i0.astype(np.int64)
        a = np.take(out, np.clip(i0, 0, n - 1), axis=axis)
        b = np.take(out, np.clip(i0 + 1, 0, n - 1), axis=axis)
        shape = [1] * im.ndim
        shape[axis] = n
        t = t.reshape(shape)
        out = a + t * (b - a)
    return out


def _phase_correlation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Integer (du, dv) with ``a(x) ~ b(x - d)`` (normalised cross-power spectrum, Hann
    window)."""
    h, w = a.shape
    win = np.outer(np.hanning(h), np.hanning(w))
    fa = np.fft.fft2((a - a.mean()) * win)
    fb = np.fft.fft2((b - b.mean()) * win)
    cp = fa * np.conj(fb)
    r = np.fft.ifft2(cp / np.maximum(np.abs(cp), 1e-12)).real
    dv, du = np.unravel_index(int(np.argmax(r)), r.shape)
    dv = dv - h if dv > h // 2 else dv
    du = du - w if du > w // 2 else du
    return np.array([du, dv], np.float64)


def align_plate(
    frame: np.ndarray,
    plate: np.ndarray,
    *,
    max_shift_px: float = 8.0,
    iterations: int = 10,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """The translation ``(du, dv)`` (pixels) with ``frame(x) ~ plate(x - d)``, i.e.
    ``shift_image(plate, d)`` lines up with the frame.

    Phase correlation gives the integer part (ignored if beyond ``max_shift_px``); then
    Gauss-Newton on the grey images (Lucas-Kanade for a translation) with Tukey weights
    (scale 4.685 x the residuals' robust sigma, MAD) so that the robot, which the plate
    lacks, does not bias the shift. ``weights`` (H, W) optionally down-weights pixels
    further (e.g. a previous robot mask). Images RGB or grey, float; a border of
    ``max_shift_px + 2`` pixels is left out.
    """
    a = ndi.gaussian_filter(_grey(frame), 1.0)
    b = ndi.gaussian_filter(_grey(plate), 1.0)
    d = _phase_correlation(a, b)
    if np.any(np.abs(d) > max_shift_px):
        d = np.zeros(2)
    m = int(np.ceil(max_shift_px)) + 2
    inner = (slice(m, -m), slice(m, -m))
    gv, gu = np.gradient(b)
    w0 = np.ones_like(a) if weights is None else np.asarray(weights, np.float64)
    for _ in range(iterations):
        bs = shift_image(b, d)[inner]
        gus = shift_image(gu, d)[inner]
        gvs = shift_image(gv, d)[inner]
        r = a[inner] - bs
        sig = 1.4826 * np.median(np.abs(r - np.median(r))) + 1e-6
        c = 4.685 * sig
        wt = np.where(np.abs(r) < c, (1 - (r / c) ** 2) ** 2, 0.0) * w0[inner]
        # d(plate(x - d))/dd = -grad plate(x - d)
        J = -np.stack([gus.ravel(), gvs.ravel()], 1)
        wr = wt.ravel()
        H = J.T @ (J * wr[:, None])
        g = J.T @ (wr * r.ravel())
        step = np.linalg.solve(H + 1e-9 * np.eye(2), g)
        d = d + step
        if np.any(np.abs(d) > max_shift_px):
            return np.clip(d, -max_shift_px, max_shift_px)
        if np.max(np.abs(step)) < 1e-4:
            break
    return d


# ----------------------------------------------------------------------------- cues


def foreground_cues(
    frame: np.ndarray, plate: np.ndarray, cfg: PlateForegroundConfig = PlateForegroundConfig()
) -> dict[str, np.ndarray]:
    """Per-pixel cues (H, W), each scaled so that 1 is at its threshold in ``cfg``, and
    ``score``, their maximum. ``frame``/``plate`` float RGB [0, 1] (H, W, 3), the plate
    already aligned."""
    f = np.asarray(frame, np.float64)
    p = np.asarray(plate, np.float64)
    if cfg.blur_px > 0:
        f = ndi.gaussian_filter(f, (cfg.blur_px, cfg.blur_px, 0))
        p = ndi.gaussian_filter(p, (cfg.blur_px, cfg.blur_px, 0))
    return cue_maps(f, p, cfg)


def cue_maps(
    f: np.ndarray, p: np.ndarray, cfg: PlateForegroundConfig = PlateForegroundConfig()
) -> dict[str, np.ndarray]:
    """The cues of :func:`foreground_cues` pixel by pixel, without smoothing: ``f``,
    ``p`` float RGB of any shape (..., 3) (broadcast); each cue of shape (...)."""
    f = np.asarray(f, np.float64)
    p = np.asarray(p, np.float64)
    f, p = np.broadcast_arrays(f, p)
    eps = 1e-3
    luma = np.array([0.299, 0.587, 0.114])
    yf, yp = f @ luma, p @ luma
    mxf, mnf = f.max(-1), f.min(-1)
    mxp, mnp = p.max(-1), p.min(-1)
    # Darkness counts on achromatic background only (white board, black tape, grey): on
    # coloured cloth a cast shadow is the plate darkened, and the tube differs from the
    # cloth by saturation, hue or shadow-invariant colour distance instead.
    # Relative changes are taken against max(value, min_luma): near black (tape, deep
    # shadow) a pixel cannot get much darker, and noise / max is large there, so darkening
    # and saturation of near-black pixels would be noise (they seeded masks along tape).
    achromatic = (mxp - mnp) < cfg.min_chroma
    floor = max(cfg.min_luma, eps)
    # Either sign: a grey metal tube on a white board is darker than the board in its body
    # and brighter in its specular highlight (shadows only darken, but on achromatic
    # background a cast shadow is as dark as a grey tube, so the sign would not help).
    dark = np.where(achromatic, np.abs(yp - yf) / np.maximum(yp, floor), 0.0)
    dark = dark / cfg.dark
    sat_f = (mxf - mnf) / np.maximum(mxf, floor)
    sat_p = (mxp - mnp) / np.maximum(mxp, floor)
    desat = np.clip(sat_p - sat_f, 0.0, None) / cfg.desat
    cf = f - f.mean(-1, keepdims=True)
    cp = p - p.mean(-1, keepdims=True)
    nf = np.linalg.norm(cf, axis=-1)
    npl = np.linalg.norm(cp, axis=-1)
    cos = np.sum(cf * cp, -1) / np.maximum(nf * npl, 1e-12)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    coloured = ((mxf - mnf) > cfg.min_chroma) & ((mxp - mnp) > cfg.min_chroma)
    hue = np.where(coloured, ang, 0.0) / cfg.hue_deg
    # Colour distance to the best-scaled plate g P, g in [min_gain, 1]: a cast shadow
    # (the plate darkened, same chromaticity) is no foreground by this cue.
    g = np.sum(f * p, -1) / np.maximum(np.sum(p * p, -1), 1e-9)
    g = np.clip(g, cfg.min_gain, 1.0)[..., None]
    diff = np.linalg.norm(f - g * p, axis=-1) / cfg.diff
    score = np.maximum(np.maximum(dark, desat), np.maximum(hue, diff))
    return {"dark": dark, "desat": desat, "hue": hue, "diff": diff, "score": score}


def close_score(score: np.ndarray, radius_px: float) -> np.ndarray:
    """Grey-level closing (dilation, then erosion) of ``score`` with a disc of
    ``radius_px``: a tube whose body matches the background (a lit metal tube on a white
    board) differs only along its two edges; the closing fills between edges up to
    ``2 radius_px`` apart, and leaves isolated peaks and steps in place."""
    r = int(np.floor(radius_px))
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = xx * xx + yy * yy <= radius_px * radius_px
    return ndi.grey_closing(score, footprint=disc, mode="nearest")


def hysteresis(score: np.ndarray, low: float, high: float) -> np.ndarray:
    """Pixels with ``score > low`` in an 8-connected component holding a pixel with
    ``score > high`` (the convention of ``skimage.filters.apply_hysteresis_threshold``)."""
    weak = score > low
    lab, n = ndi.label(weak, structure=np.ones((3, 3), bool))
    if n == 0:
        return weak
    strong_labels = np.unique(lab[(score > high) & weak])
    keep = np.zeros(n + 1, bool)
    keep[strong_labels] = True
    keep[0] = False
    return keep[lab]


# ----------------------------------------------------------------------------- tracing


def _sample(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Mask value (0/1) at the nearest pixel of each (u, v) point; 0 outside."""
    h, w = mask.shape
    c = np.floor(pts[..., 0] + 0.5).astype(np.int64)
    r = np.floor(pts[..., 1] + 0.5).astype(np.int64)
    inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    out = np.zeros(pts.shape[:-1])
    out[inside] = mask[r[inside], c[inside]]
    return out


def _unit(a: float) -> np.ndarray:
    return np.array([np.cos(a), np.sin(a)])


def _recentre(mask, p, d, max_w):
    """Centre of the mask run across direction ``d`` through ``p`` (or the run nearest to
    ``p`` within 3 px); returns (new point, run width) or (p, 0)."""
    n = np.array([-d[1], d[0]])
    offs = np.arange(-max_w / 2, max_w / 2 + 0.5, 0.5)
    vals = _sample(mask, p[None] + offs[:, None] * n[None]) > 0
    if not vals.any():
        return p, 0.0
    on = np.flatnonzero(vals)
    k0 = on[np.argmin(np.abs(offs[on]))]
    if abs(offs[k0]) > 3.0:
        return p, 0.0
    lo = k0
    while lo > 0 and vals[lo - 1]:
        lo -= 1
    hi = k0
    while hi < len(vals) - 1 and vals[hi + 1]:
        hi += 1
    centre = 0.5 * (offs[lo] + offs[hi])
    width = offs[hi] - offs[lo] + 0.5
    shift = np.clip(centre, -1.0, 1.0)
    return p + shift * n, width


def border_entry(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the robot enters the image: the mask component with the most pixels on the
    image border; returns ((u, v) mean of its border pixels, inward unit direction) or
    None if no component touches the border."""
    h, w = mask.shape
    lab, n = ndi.label(mask, structure=np.ones((3, 3), bool))
    if n == 0:
        return None
    border = np.zeros_like(mask)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    counts = np.bincount(lab[border & mask], minlength=n + 1)
    counts[0] = 0
    if counts.max() == 0:
        return None
    k = int(np.argmax(counts))
    rr, cc = np.nonzero((lab == k) & border)
    uv = np.array([cc.mean(), rr.mean()])
    # Inward direction: towards the component's pixels near the entry.
    r2, c2 = np.nonzero(lab == k)
    near = (c2 - uv[0]) ** 2 + (r2 - uv[1]) ** 2 < 30.0**2
    d = np.array([c2[near].mean(), r2[near].mean()]) - uv
    if np.linalg.norm(d) < 1e-6:
        d = np.array([w / 2, h / 2]) - uv
    return uv, d / np.linalg.norm(d)


def _initial_direction(mask: np.ndarray, entry: np.ndarray, radius: float = 25.0):
    h, w = mask.shape
    r0, r1 = int(max(entry[1] - radius, 0)), int(min(entry[1] + radius + 1, h))
    c0, c1 = int(max(entry[0] - radius, 0)), int(min(entry[0] + radius + 1, w))
    rr, cc = np.nonzero(mask[r0:r1, c0:c1])
    if len(rr) < 3:
        return None
    d = np.array([cc.mean() + c0, rr.mean() + r0]) - entry
    if np.linalg.norm(d) < 1.0:
        pts = np.stack([cc + c0, rr + r0], 1).astype(float)
        pts -= pts.mean(0)
        d = np.linalg.svd(pts, full_matrices=False)[2][0]
    return d / np.linalg.norm(d)


def _local_arc(path: list, window_px: float = 24.0) -> tuple[float, float] | None:
    """Heading (rad) and curvature (rad/px, clipped to +-0.1) at the end of the path from a
    quadratic least-squares fit of u(s), v(s) over its last ``window_px`` of arclength
    (the per-step headings jitter with the re-centring); None if the path is shorter."""
    pts = np.asarray(path[-64:], np.float64)
    if len(pts) < 5:
        return None
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s = s - s[-1]
    keep = s >= -window_px
    if keep.sum() < 5 or -s[keep][0] < 0.5 * window_px:
        return None
    cu = np.polyfit(s[keep], pts[keep, 0], 2)
    cv = np.polyfit(s[keep], pts[keep, 1], 2)
    du, dv = cu[1], cv[1]  # first derivatives at s = 0
    ddu, ddv = 2 * cu[0], 2 * cv[0]
    n = np.hypot(du, dv)
    if n < 1e-9:
        return None
    kappa = (du * ddv - dv * ddu) / n**3
    return float(np.arctan2(dv, du)), float(np.clip(kappa, -0.1, 0.1))


def _at(image: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``image`` at the nearest pixel of each (u, v) point (clamped to the image)."""
    h, w = image.shape[:2]
    c = np.clip(np.floor(pts[:, 0] + 0.5).astype(np.int64), 0, w - 1)
    r = np.clip(np.floor(pts[:, 1] + 0.5).astype(np.int64), 0, h - 1)
    return image[r, c]


def _bridge_visible(mask, frame, plate, path, p, q, cfg) -> bool:
    """Whether the tube, had it gone on from ``p`` to ``q``, would have been seen there:
    the colour of the tube's last traced stretch (median of ``frame`` on the mask along
    the last 20 px of ``path``) scored against the aligned ``plate`` with the same cues
    (:func:`cue_maps`) exceeds ``high`` on more than ``gap_visible`` of the bridge's
    off-mask pixels. A gap is bridged only where the tube can match the background (tape,
    shadow, crease); where the background differs from the tube, a missing mask is the
    tube's end. False when no ``frame``/``plate`` is given (mask-only tracing)."""
    if frame is None or plate is None or cfg.gap_visible >= 1.0:
        return False
    pts = np.asarray(path[-11:], np.float64)
    on = _sample(mask, pts) > 0
    if not on.any():
        return False
    tube = np.median(_at(frame, pts[on]), axis=0)
    dist = float(np.linalg.norm(q - p))
    t = np.arange(1.0, dist - 0.5, 1.0)
    if not len(t):
        return False
    bridge = p[None] + t[:, None] * ((q - p) / dist)[None]
    bridge = bridge[_sample(mask, bridge) == 0]
    if not len(bridge):
        return False
    score = cue_maps(tube[None], _at(plate, bridge), cfg)["score"]
    return bool(np.mean(score > cfg.high) > cfg.gap_visible)


def _trace_length(t: TubeTrace) -> float:
    return float(np.sum(np.linalg.norm(np.diff(t.backbone, axis=0), axis=1)))


def trace_tube(
    mask: np.ndarray,
    entry_uv,
    direction_uv=None,
    cfg: PlateForegroundConfig = PlateForegroundConfig(),
    *,
    frame: np.ndarray | None = None,
    plate: np.ndarray | None = None,
    _single: bool = False,
) -> TubeTrace:
    """Follow the tube on ``mask`` (H, W) bool from ``entry_uv`` (u, v) (see module
    docstring, step 4). ``direction_uv``: the initial direction (default: the axis of the
    mask pixels near the entry, traced both ways, the longer trace kept). Returns a :class:`TubeTrace` (``score``/``shift`` unset)."""
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    entry = np.asarray(entry_uv, np.float64)
    empty = TubeTrace(np.zeros_like(mask), entry[None].copy(), entry.copy(), entry.copy())
    # Start on the mask pixel nearest the entry (within 20 px).
    rr, cc = np.nonzero(mask[
        max(int(entry[1]) - 20, 0) : int(entry[1]) + 21,
        max(int(entry[0]) - 20, 0) : int(entry[0]) + 21,
    ])  # fmt: skip
    if not len(rr):
        empty.reason = "no foreground at the entry"
        return empty
    rr = rr + max(int(entry[1]) - 20, 0)
    cc = cc + max(int(entry[0]) - 20, 0)
    k = int(np.argmin((cc - entry[0]) ** 2 + (rr - entry[1]) ** 2))
    p = np.array([cc[k], rr[k]], np.float64)
    if direction_uv is None:
        # The axis of the mask near the entry, both ways (a shadow may leave the base on
        # the other side): the longer trace wins.
        d = _initial_direction(mask, p)
        if d is None:
            empty.reason = "no foreground at the entry"
            return empty
        both = [
            trace_tube(mask, entry_uv, s * d, cfg, frame=frame, plate=plate) for s in (1.0, -1.0)
        ]
        return max(
            both, key=lambda t: float(np.sum(np.linalg.norm(np.diff(t.backbone, axis=0), axis=1)))
        )
    d = np.asarray(direction_uv, np.float64) / np.linalg.norm(direction_uv)
    if cfg.start_spread_deg > 0 and not _single:
        # The given direction is a model's: also start turned by +-start_spread_deg, and
        # keep the longest trace (a shadow or crease at the base can divert one start).
        out = []
        for a in (0.0, -cfg.start_spread_deg, cfg.start_spread_deg):
            c, s_ = np.cos(np.radians(a)), np.sin(np.radians(a))
            dr = np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]])
            out.append(trace_tube(mask, entry_uv, dr, cfg, frame=frame, plate=plate, _single=True))
        best = max(out, key=_trace_length)
        # The others are branches too (the longest may follow a rod that runs past the
        # entry beside the tube): trace_alternatives offers them (docs/decisions.md S45).
        best.start_alternatives = [t for t in out if t is not best]
        return best
    theta = float(np.arctan2(d[1], d[0]))
    radii = np.arange(1.0, cfg.look_px + 0.5, 1.0)
    turn = np.radians(cfg.max_turn_deg)
    cands = theta + np.linspace(-turn, turn, 2 * int(round(cfg.max_turn_deg / 5.0)) + 1)
    path = [p.copy()]
    widths = []
    gaps = []
    seen = np.zeros((h // 4 + 1, w // 4 + 1), np.int32)
    labels, _ = ndi.label(mask, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.ravel())
    max_steps = int(4 * (h + w) / cfg.step_px)

    last_corner = -(10**9)
    on_old = 0
    junctions: list = []

    def _visited(c, keep=30.0):
        """Whether pixel c (u, v) lies on the tube already traced, except its last ``keep``
        px (the stretch the gap starts from): a gap must not land back on the shaft (a
        curled tip ending near it)."""
        pts = np.asarray(path)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        back = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])  # arclength to the end
        old = pts[back > keep]
        if not len(old):
            return False
        rad = min(np.median(widths) / 2, 8.0) + 3.0 if widths else 5.0
        return bool(np.min(np.sum((old - c[None]) ** 2, 1)) <= rad * rad)

    for _ in range(max_steps):
        cands = theta + np.linspace(-turn, turn, len(cands))
        dirs = np.stack([np.cos(cands), np.sin(cands)], 1)
        pts = p[None, None] + radii[None, :, None] * dirs[:, None]
        sup = _sample(mask, pts).mean(1)
        # Prefer straight on among near-equal supports.
        pref = sup - 0.02 * np.abs(cands - theta) / max(turn, 1e-9)
        j = int(np.argmax(pref))
        dvec = dirs[j] if sup[j] >= cfg.support else None
        if dvec is not None and len(junctions) < 8:
            _note_junction(junctions, sup, cands, j, cfg, len(path) - 1, p, dirs)
        since = len(path) - last_corner
        if (dvec is None and cfg.corner_deg > cfg.max_turn_deg and len(path) > 5
                and since * cfg.step_px >= cfg.look_px):  # fmt: skip
            # A corner (a projected kink where an inner tube leaves the outer one, or a
            # hook): turn by up to corner_deg, onto mask not traced already (more than a
            # look length and a width back: two turns would walk back along the tube's
            # other edge), at most once per look length.
            wide = np.radians(cfg.corner_deg)
            ca = theta + np.concatenate([np.arange(turn, wide + 1e-9, np.radians(5.0)),
                                         -np.arange(turn, wide + 1e-9, np.radians(5.0))])  # fmt: skip
            cd = np.stack([np.cos(ca), np.sin(ca)], 1)
            cs = _sample(mask, p[None, None] + radii[None, :, None] * cd[:, None]).mean(1)
            # Best supported first (the tube after a kink is covered along the whole
            # ray; directions into the kink's corner only partly), straighter on ties.
            for jj in np.argsort(-cs + 0.02 * np.abs(ca - theta) / wide):
                if cs[jj] < 0.5 * (1.0 + cfg.support):  # a corner needs more support
                    break
                wref = float(np.median(widths)) if widths else 5.0
                # As wide as the tube (not a crease or an edge residue leaving the tip).
                _, wl = _recentre(mask, p + 0.5 * cfg.look_px * cd[jj], cd[jj], cfg.max_width_px)
                if not 0.5 * wref <= wl <= 2.0 * wref:
                    continue
                if not _visited(p + cfg.look_px * cd[jj], keep=cfg.look_px + wref):
                    dvec = cd[jj]
                    last_corner = len(path)
                    break
        if dvec is not None:
            q0 = p + cfg.step_px * dvec
            q, wid = _recentre(mask, q0, dvec, cfg.max_width_px)
            # Re-centre only on a run no wider than 1.6 x the tube so far, and not in the
            # first 5 steps (the entry direction is given; a shadow or crease leaving the
            # base widens the run there and would pull the walker onto it).
            ref = float(np.median(widths)) if len(widths) >= 3 else None
            if len(path) < 5 or wid == 0 or (ref is not None and wid > 1.6 * ref):
                q = q0
            if wid > 0 and (ref is None or wid <= 1.6 * ref):
                widths.append(wid)
            elif ref is not None and wid > 1.6 * ref and len(junctions) < 8:
                # A run across much wider than the tube: something crosses it here (a
                # cable, a tool, a shadow); its branches are tried if the trace runs out.
                if not junctions or len(path) - 1 - junctions[-1][0] >= cfg.look_px / cfg.step_px:
                    junctions.append((len(path) - 1, p.copy(), None))
        else:
            # Gap: look on along the current arc (heading and curvature of the last few
            # steps) for the mask to resume in a big enough component, within
            # +-max(gap_turn_deg, 4 px lateral) of the predicted chord.
            arc = _local_arc(path)
            head0, kappa = (theta, 0.0) if arc is None else arc
            found = None
            for dist in np.arange(cfg.step_px, cfg.max_gap_px + 0.5, 1.0):
                tol = max(np.radians(cfg.gap_turn_deg), np.arctan(4.0 / dist))
                pred = head0 + np.clip(kappa * dist / 2.0, -np.pi / 2, np.pi / 2)
                n_ang = 2 * int(np.ceil(tol * dist / 0.7)) + 1
                gc = pred + np.linspace(-tol, tol, n_ang)
                gd = np.stack([np.cos(gc), np.sin(gc)], 1)
                pts = p[None] + dist * gd
                hits = _sample(mask, pts) > 0
                if not hits.any():
                    continue
                for i in np.flatnonzero(hits)[np.argsort(np.abs(gc[hits] - pred))]:
                    c = np.floor(pts[i] + 0.5).astype(int)
                    if sizes[labels[c[1], c[0]]] < cfg.min_seed_px or _visited(c):
                        continue
                    if widths:
                        # As wide as the tube (not a thin edge residue or a broad blob).
                        _, wl = _recentre(mask, pts[i], gd[i], cfg.max_width_px)
                        ref = float(np.median(widths))
                        if not 0.5 * ref <= wl <= 2.0 * ref:
                            continue
                    # The tube goes on from there (any direction within max_turn of the
                    # predicted heading at the landing point).
                    head = pred + np.clip(kappa * dist / 2.0, -np.pi / 2, np.pi / 2)
                    ha = head + np.linspace(-turn, turn, 7)
                    hd = np.stack([np.cos(ha), np.sin(ha)], 1)
                    ahead = pts[i][None, None] + radii[None, :, None] * hd[:, None]
                    if _sample(mask, ahead).mean(1).max() < cfg.support:
                        continue
                    if _bridge_visible(mask, frame, plate, path, p, pts[i], cfg):
                        continue
                    found = pts[i]
                    break
                if found is not None:
                    break
            if found is None:
                break
            gaps.append((len(path) - 1, len(path)))
            q = found
            dvec = (q - p) / np.linalg.norm(q - p)
        if not (0 <= q[0] <= w - 1 and 0 <= q[1] <= h - 1):
            break
        cell = (int(q[1]) // 4, int(q[0]) // 4)
        seen[cell] += 1
        if seen[cell] > 6:  # walking in circles
            break
        # Walking along the tube traced already (a hook that came back onto the shaft,
        # not a crossing, which is shorter than the tube's width): the tube ended where
        # it joined it.
        wref = float(np.median(widths)) if widths else 5.0
        if len(path) > 5 and _visited(q, keep=cfg.look_px + wref):
            on_old += 1
            if on_old * cfg.step_px > 1.5 * wref + cfg.step_px:
                del path[len(path) - on_old + 1 :]
                break
        else:
            on_old = 0
        path.append(q)
        # Heading: from the last few points (smooths the re-centring jitter).
        back = path[min(max(len(path) - 4, 0, last_corner), len(path) - 2)]
        hd = q - back
        theta = float(np.arctan2(hd[1], hd[0])) if np.linalg.norm(hd) > 1e-6 else theta
        p = q
    bb = np.array(path)
    width = float(np.median(widths)) if widths else 3.0
    cut = _turn_back_index(bb, width)
    if cut is not None:
        bb = bb[: cut + 1]
        gaps = [g for g in gaps if g[1] <= cut]
        junctions = [j for j in junctions if j[0] <= cut]
        hd = bb[-1] - bb[max(cut - 3, 0)]
        theta = float(np.arctan2(hd[1], hd[0])) if np.linalg.norm(hd) > 1e-6 else theta
    # Tip: march on along the heading while on the mask (0.25 px steps).
    tip = bb[-1].copy()
    hd = _unit(theta)
    for t in np.arange(0.25, cfg.look_px + 0.01, 0.25):
        if _sample(mask, (bb[-1] + t * hd)[None])[0] > 0:
            tip = bb[-1] + t * hd
        else:
            break
    if np.linalg.norm(tip - bb[-1]) > 1e-9:
        bb = np.vstack([bb, tip])
    out = _path_mask(mask, bb, gaps, width)
    return TubeTrace(out, bb, tip, entry, gaps, width_px=width, junctions=junctions)


def _turn_back_index(path: np.ndarray, width: float) -> int | None:
    """Where the walker turned round at the tube's end and walked back along the tube it
    had traced: the index of the path's farthest point before that, or None. A walker
    reaching the round end face of a tube wider than its look length can turn across the
    face and follow the tube's other edge back (real_like dev seeds 4016, 4073, 4139: a
    15 px tube traced at full resolution, the tip 15-25 px back). A tube cannot reverse
    within its own width: where a point's direction is opposite (over 135 deg) to that of
    an earlier point within half a width plus 1 px of it, and the path stays that near the
    path before from there to its end, the walker walked back along the tube; the path is
    cut at its farthest point along the earlier direction between the two."""
    pts = np.asarray(path, np.float64)
    n = len(pts)
    if n < 5:
        return None
    tan = pts[np.minimum(np.arange(n) + 1, n - 1)] - pts[np.maximum(np.arange(n) - 1, 0)]
    tan = tan / np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
    rad = 0.5 * width + 1.0
    for i in range(2, n):
        m = np.arange(i - 1)
        near = np.sum((pts[m] - pts[i]) ** 2, axis=1) <= rad * rad
        back = tan[m] @ tan[i] < np.cos(np.radians(135.0))
        hit = np.flatnonzero(near & back)
        if len(hit):
            j0 = int(hit[-1])
            # Back along the tube to the path's end (not onto something crossing it at a
            # sharp corner, which leaves the tube: a branch, not the end).
            rest = pts[i:]
            d2 = np.sum((rest[:, None] - pts[None, : j0 + 1]) ** 2, axis=2).min(1)
            if np.any(d2 > rad * rad):
                return None
            prog = (pts[j0 : i + 1] - pts[j0]) @ tan[j0]
            return j0 + int(np.argmax(prog))
    return None


def _note_junction(junctions, sup, cands, j, cfg, index, p, dirs) -> None:
    """Record a second branch ahead (a local maximum of the support, at least ``support``,
    20 deg or more from the chosen direction ``j``, with a direction below ``support``
    between the two: a separate branch, not the same tube's plateau), once per look
    length of path."""
    if junctions and index - junctions[-1][0] < cfg.look_px / cfg.step_px:
        return
    for i in np.argsort(-sup):
        if sup[i] < cfg.support:
            return
        if abs(cands[i] - cands[j]) < np.radians(20.0):
            continue
        lo, hi = sorted((int(i), int(j)))
        if np.min(sup[lo : hi + 1]) >= cfg.support:
            continue
        if (i > 0 and sup[i - 1] > sup[i]) or (i + 1 < len(sup) and sup[i + 1] > sup[i]):
            continue
        junctions.append((index, p.copy(), dirs[i].copy()))
        return


def _at_border(uv: np.ndarray, shape, margin: float) -> bool:
    h, w = shape[:2]
    return bool(uv[0] < margin or uv[1] < margin or uv[0] > w - 1 - margin
                or uv[1] > h - 1 - margin)  # fmt: skip


def _retrace_off_border(tr: TubeTrace, mask, cfg, frame, plate) -> TubeTrace:
    """A trace that ran out of the image followed something else at a junction (a robot
    whose tip leaves the view has no tip to find in it): each recorded junction's other
    branch (at a wide crossing: the heading turned by 15, 30 and 45 deg either way) is
    traced, and the longest trace that ends inside the image replaces it (unchanged when
    none does)."""
    margin = 2.0 * cfg.step_px
    if not tr.junctions or not _at_border(tr.tip, mask.shape, margin):
        return tr
    best, best_len = None, -1.0
    tries = []
    for i, pj, dj in tr.junctions:
        if dj is not None:
            tries.append((i, pj, dj))
            continue
        # A wide crossing: the heading there turned by 15-45 deg either way.
        hd = tr.backbone[min(i + 2, len(tr.backbone) - 1)] - tr.backbone[max(i - 2, 0)]
        th = float(np.arctan2(hd[1], hd[0]))
        for da in (15.0, -15.0, 30.0, -30.0, 45.0, -45.0):
            tries.append((i, pj, _unit(th + np.radians(da))))
    # The tube traced already, and the branch that ran out, are taken off the mask (but
    # near the junction): a re-trace must neither walk back along them nor follow them.
    bb_all = np.asarray(tr.backbone)
    near_steps = int(np.ceil(cfg.look_px / cfg.step_px))
    rad = 0.5 * tr.width_px + 1.0
    for i, pj, dj in tries:
        sub_mask = mask.copy()
        for piece in (bb_all[: max(i - near_steps, 0)], bb_all[i + near_steps + 1 :]):
            if len(piece) >= 2:
                sub_mask &= ~_path_mask(np.ones_like(mask), piece, [], 2 * rad)
        sub = trace_tube(sub_mask, pj, dj, cfg, frame=frame, plate=plate, _single=True)
        if len(sub.backbone) < 2 or _at_border(sub.tip, mask.shape, margin):
            continue
        # Onwards, not back: within 60 deg of the heading tried, two look lengths on.
        seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(sub.backbone, axis=0), axis=1))]
        far = sub.backbone[int(np.searchsorted(seg, min(2 * cfg.look_px, seg[-1])))]
        if np.linalg.norm(far - pj) > 0 and (far - pj) @ dj < 0.5 * np.linalg.norm(far - pj):
            continue
        bb = np.vstack([tr.backbone[: i + 1], sub.backbone[1:]])
        length = float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1)))
        if length > best_len:
            gaps = [g for g in tr.gaps if g[1] <= i] + [(a + i, b + i) for a, b in sub.gaps]
            best, best_len = (bb, gaps, sub), length
    if best is None:
        return tr
    bb, gaps, sub = best
    width = tr.width_px
    return TubeTrace(_path_mask(mask, bb, gaps, width), bb, bb[-1].copy(), tr.entry, gaps,
                     width_px=width, junctions=tr.junctions)  # fmt: skip


def _arc_sampler(bb: np.ndarray):
    """(arclength of each point of the polyline ``bb`` (n, 2) (n,), its length, a function
    of arclength (m,) -> points (m, 2) on it, clamped to its ends); repeated points (steps
    under 1e-9 px) are skipped and add no length."""
    seg = np.linalg.norm(np.diff(bb, axis=0), axis=1)
    keep = np.r_[True, seg > 1e-9]
    cum = np.r_[0.0, np.cumsum(np.where(keep[1:], seg, 0.0))]
    cum_k, bb_k = cum[keep], bb[keep]

    def at(a):
        a = np.clip(a, 0.0, cum_k[-1])
        return np.stack([np.interp(a, cum_k, bb_k[:, 0]), np.interp(a, cum_k, bb_k[:, 1])], -1)

    return cum, float(cum[-1]), at


def _normals(at, a: np.ndarray, w: float) -> np.ndarray:
    """Unit normals (m, 2) of the polyline sampled by ``at`` at arclengths ``a`` (m,), from
    its chord over one width ``w`` (the walker's re-centring jitter averaged out)."""
    tan = at(a + 0.5 * w) - at(a - 0.5 * w)
    tan = tan / np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
    return np.stack([-tan[:, 1], tan[:, 0]], 1)


def _run_edges(row: np.ndarray, tt: np.ndarray, level: float, c0: float, reach: float):
    """(left, right) offsets where the run of ``row`` (sampled at ascending offsets ``tt``)
    at or above ``level`` that holds the sample nearest ``c0`` within ``reach`` crosses
    ``level`` (linear interpolation); None where no such sample is on the run or the run
    is not closed on both sides."""
    on = row >= level
    near = np.flatnonzero(on & (np.abs(tt - c0) <= reach))
    if not len(near):
        return None
    i = near[np.argmin(np.abs(tt[near] - c0))]
    lo, hi = i, i
    while lo > 0 and on[lo - 1]:
        lo -= 1
    while hi < len(row) - 1 and on[hi + 1]:
        hi += 1
    if lo == 0 or hi == len(row) - 1:
        return None
    left = tt[lo - 1] + (level - row[lo - 1]) / (row[lo] - row[lo - 1]) * (tt[lo] - tt[lo - 1])
    right = tt[hi] + (row[hi] - level) / (row[hi] - row[hi + 1]) * (tt[hi + 1] - tt[hi])
    return float(left), float(right)


# centre_end_on_axis: the path's end stretch and the stretch before it (widths), the
# width agreement of a whole row (fraction of the upstream width), the largest step of
# the axis between rows (px), and the smallest / largest move (fractions of the width).
_AXIS_UP, _AXIS_END, _AXIS_NEAR = 6.0, 3.0, 0.5
_AXIS_WIDTH_TOL, _AXIS_STEP_PX = 0.15, 1.5
_AXIS_MIN_MOVE, _AXIS_MAX_MOVE = 0.25, 1.0
_AXIS_REACH = 1.5  # the last row whose axis is measured, at most this many widths back


def centre_end_on_axis(
    score: np.ndarray,
    backbone: np.ndarray,
    width_px: float,
    cfg: PlateForegroundConfig = PlateForegroundConfig(),
) -> np.ndarray:
    """The traced ``backbone`` (n, 2) (u, v) with its last three widths moved across the
    tube onto the tube's axis where the path left the axis there; else ``backbone``
    unchanged.

    A walker re-centres step by step, so near the end it can run along one edge of the
    tube (real_like dev seed 4147, view 2: 5 px across a 13 px tube), and the tip found
    along that line is as far across. A tube's silhouette is symmetric about its axis and
    of one width along a straight or gently bent stretch; the stretch the walker followed
    before (3-6 widths back from the end) shows that width and where the path lay.

    Rows across the path (its normal over one width ``w = width_px``), every 0.5 px from 6
    to half a width behind its end, are sampled (bilinear, 0.25 px) out to 2 widths either
    side. The silhouette is the score at least ``cfg.low`` over the background (the
    median beside the upstream rows, 1.5-2 widths out), the mask's own contrast, so a
    tube's weakly scored side (a shaded grey tube over a white board) is inside it. Its
    edges in a row are the crossings of that level around the path. Upstream (6-3
    widths back) the rows give the tube's width ``W`` (median), and must show one tube:
    three quarters of them within 15 % of ``W``, and the path within ``W / 4`` of their
    midpoints (else the run is not the tube, or the path was never centred: no change).
    Then, from 3 to half a width back, row by row, the axis is the midpoint of a row's
    edges when the row is whole (width within 15 % of ``W``) and within 1.5 px of the
    previous row's axis; rows that are not (touching other foreground, a one-sided end,
    the end face) are skipped, not guessed. With at least a third of the rows (and 4)
    kept, a line fitted to the axis offsets (once more without residuals over 1 px) is
    the move; the last three widths of the path move across by it (tapering to 0 over the
    width before) when it is at least ``W / 4`` at the end (smaller offsets are within
    the walker's re-centring and the edges' noise) and at most ``W``, the last row kept is
    within 1.5 widths of the end (the axis is not extrapolated over a stretch where it was
    not seen) and the moved line still runs on the silhouette."""
    bb = np.asarray(backbone, np.float64)
    w = float(max(width_px, 2.0))
    if len(bb) < 3:
        return bb
    cum, length, at = _arc_sampler(bb)
    s = np.arange(-_AXIS_UP * w, -_AXIS_NEAR * w + 1e-9, 0.5)
    s = s[s >= -length]
    up = s <= -_AXIS_END * w
    if up.sum() < 8 or (~up).sum() < 4:
        return bb
    a = length + s
    cen, nrm = at(a), _normals(at, a, w)
    tt = np.arange(-2.0 * w, 2.0 * w + 1e-9, 0.25)
    pts = cen[:, None] + tt[None, :, None] * nrm[:, None]
    g = ndi.map_coordinates(score, [pts[..., 1], pts[..., 0]], order=1, mode="nearest")
    s_bg = float(np.median(g[up][:, np.abs(tt) >= 1.5 * w]))
    level = s_bg + cfg.low
    rows_up = [_run_edges(g[k], tt, level, 0.0, 0.5 * w) for k in np.flatnonzero(up)]
    rows_up = np.array([r for r in rows_up if r is not None]).reshape(-1, 2)
    if len(rows_up) < 8:
        return bb
    widths = rows_up[:, 1] - rows_up[:, 0]
    w_ref = float(np.median(widths))
    tol = _AXIS_WIDTH_TOL * w_ref
    whole = np.abs(widths - w_ref) <= tol
    mids = rows_up[whole].mean(1)
    if whole.mean() < 0.75 or abs(float(np.median(mids))) > 0.25 * w_ref:
        return bb
    prev = float(np.median(mids[-8:]))
    ks, cs = [], []
    for k in np.flatnonzero(~up):
        r = _run_edges(g[k], tt, level, prev, 0.5 * w_ref)
        if r is None or abs(r[1] - r[0] - w_ref) > tol:
            continue
        c = 0.5 * (r[0] + r[1])
        if abs(c - prev) > _AXIS_STEP_PX:
            continue
        ks.append(k)
        cs.append(c)
        prev = c
    need = max(4, (~up).sum() / 3)
    # The axis is measured up to the end, not extrapolated over a stretch it was not seen
    # on (a thinner inner tube at the end: its rows are not whole, dev 4037 view 2).
    if len(ks) < need or s[ks[-1]] < -_AXIS_REACH * w:
        return bb
    ks, cs = np.array(ks), np.array(cs)
    fit = np.polyfit(s[ks], cs, 1)
    inl = np.abs(np.polyval(fit, s[ks]) - cs) <= 1.0
    if inl.sum() < need:
        return bb
    fit = np.polyfit(s[ks][inl], cs[inl], 1)
    move_end = abs(float(np.polyval(fit, 0.0)))
    if not _AXIS_MIN_MOVE * w_ref <= move_end <= _AXIS_MAX_MOVE * w_ref:
        return bb
    sp = cum - length  # each point's signed arclength from the end (<= 0)
    stretch = _AXIS_END * w
    taper = np.clip((sp + stretch + w) / w, 0.0, 1.0)
    move = np.polyval(fit, np.maximum(sp, -stretch)) * taper
    out = bb.copy()
    sel = taper > 0
    out[sel] = bb[sel] + move[sel, None] * _normals(at, cum[sel], w)
    # The moved line must still run on the silhouette up to half a width before the end.
    on = cen[~up] + np.polyval(fit, s[~up])[:, None] * nrm[~up]
    if np.any(ndi.map_coordinates(score, [on[:, 1], on[:, 0]], order=1, mode="nearest") < level):
        return bb
    return out


def refine_tip(
    score: np.ndarray,
    backbone: np.ndarray,
    width_px: float,
    cfg: PlateForegroundConfig = PlateForegroundConfig(),
) -> tuple[np.ndarray, float]:
    """(tip (u, v), a) of :func:`refine_tip_details` (see there)."""
    tip, a, _, _ = refine_tip_details(score, backbone, width_px, cfg)
    return tip, a


def refine_tip_details(
    score: np.ndarray,
    backbone: np.ndarray,
    width_px: float,
    cfg: PlateForegroundConfig = PlateForegroundConfig(),
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Sub-pixel tip along the tube's end direction, from the cue ``score`` (H, W) near the
    end of ``backbone`` (n, 2) (u, v), for a tube of width ``width_px``. The backbone's end
    is first moved onto the tube's axis where the path left it
    (:func:`centre_end_on_axis`).

    The score is sampled (bilinear) on a grid aligned with the end direction ``d`` (the
    quadratic fit of the last ``max(24, 3 w)`` px of the backbone), at 0.25 px steps.
    Levels: inside ``S_in`` (median on the centre line 1-3 widths behind the end) and
    background ``S_bg`` (median beside the tube). Along the centre line the silhouette's
    end ``s_end`` is where the score falls to the half level ``(S_in + S_bg)/2`` (a blurred
    step's half level is its edge, whatever the blur); where the tube's last stretch is a
    weaker cue than the stretch behind (what lies behind the tube changes), the levels are
    taken on that last width instead (comment in the body). The tube's end face is a disc: seen
    at an angle, the silhouette ends in a half-ellipse of width ``w`` and length ``a``
    beyond the end point (``a = r |sin|`` of the axis' tilt out of the image plane), so the
    end point is ``s_end - a``. ``a`` follows from the soft area ``T`` (the score
    normalised to background 0 and inside 1, clipped at 1, integrated) of the stretch from
    one width behind the end: ``T = w (s_end - a + w) + (pi/4) w a``, so
    ``a = (s_end + w - T/w) / (1 - pi/4)``, clipped to ``[0, tip_cap * w/2]``, with ``w``
    the median soft width behind the end. ``cfg.tip_cap`` (1.0) scales the largest
    correction (0 = the silhouette's end).

    Returns (tip (u, v), a, the end direction d (2,), the half width ``w/2`` (px; 0 if not
    measured)): the silhouette's end is ``tip + a d``. One view cannot tell ``a`` from a
    longer tube; a calibrated stereo rig can replace it by the foreshortening of the end
    face seen from the tube's 3-D direction
    (:func:`jaxcr.stereo.tip_geometry.end_face_lengths`)."""
    bb = np.asarray(backbone, np.float64)
    w = float(max(width_px, 2.0))
    bb = centre_end_on_axis(score, bb, w, cfg)
    arc = _local_arc(list(bb), window_px=max(24.0, 3 * w))
    if arc is None and len(bb) >= 2:
        # A path traced at a reduced scale steps k step_px at full resolution, and its last
        # step (the walk's end) can be longer still: the window may hold under five points
        # and the end would go unrefined (real_like 3947, 4334, 4388: 8-9 px beyond the
        # end, docs/decisions.md S43). The same fit on the path resampled every 2 px.
        arc = _local_arc(list(_densify_path(bb, 2.0)), window_px=max(24.0, 3 * w))
    if arc is None or len(bb) < 3:
        return bb[-1].copy(), 0.0, np.zeros(2), 0.0
    theta = arc[0]
    d = np.array([np.cos(theta), np.sin(theta)])
    n = np.array([-d[1], d[0]])
    p0 = bb[-1]
    ss = np.arange(-3 * w, w + cfg.look_px + 0.01, 0.25)
    tt = np.arange(-1.5 * w, 1.5 * w + 0.01, 0.25)
    # The grid runs straight back from the end along d where the traced path is straight
    # there (within w/4 of that line over the 3 widths behind the end); where the tube
    # curves near its end, the straight line behind it leaves the tube, and the grid is
    # laid along the traced path instead (_end_frame). Where the one finds no end, the
    # other is tried.
    cen_c, nrm_c = _end_frame(bb, ss, d, w)
    cen_s = p0[None] + ss[:, None] * d[None]
    grids = [(cen_s, np.broadcast_to(n, cen_s.shape)), (cen_c, nrm_c)]
    if np.max(np.linalg.norm((cen_c - cen_s)[ss >= -3 * w], axis=1)) > w / 4:
        grids = grids[::-1]
    for cen, nrm in grids:
        out = _refine_on_grid(score, cen, nrm, ss, tt, d, w, cfg)
        if out is not None:
            return out
    return p0.copy(), 0.0, d, 0.0


def _refine_on_grid(score, cen, nrm, ss, tt, d, w, cfg):
    """The body of :func:`refine_tip_details` on a sampling grid of centre points ``cen``
    (m, 2) at signed distances ``ss`` (m,) from the end and normals ``nrm`` (m, 2); None
    where the grid shows no end (centre line not on the tube, no half-level crossing, or no
    width measured)."""
    pts = cen[:, None] + tt[None, :, None] * nrm[:, None]
    g = ndi.map_coordinates(score, [pts[..., 1], pts[..., 0]], order=1, mode="nearest")
    centre = np.abs(tt) <= 0.5
    behind = (ss >= -3 * w) & (ss <= -w)
    s_in = float(np.median(g[behind][:, centre]))
    s_bg = float(np.median(g[behind][:, np.abs(tt) >= w]))
    # The centre line behind the end must lie on the tube (score at least the hysteresis
    # level ``low``) and above the background beside it.
    if not (s_in > s_bg and s_in >= cfg.low):
        return None
    prof = g[:, centre].mean(1)
    k0 = int(np.searchsorted(ss, -w))
    reach = int(round(w / 0.25))
    # The tube's score varies along it with what lies behind it (a grey tube is a strong
    # cue over a black dot or tape, a weak one over a white board), so the level 1-3 widths
    # back need not be the level at the end, and a step down to a weaker stretch is not the
    # end (real_like dev seeds 4104, 4116, 4119, 4133, 4143: 16-24 px short). The tube
    # goes on while the centre line stands out from the background beside it (at the same
    # distance along it) by the hysteresis level ``low``, dips that rise again within a
    # width passed. The level before that end is the lower median over 1/4-1 and 1/4-1/2
    # width back (inside the edge's blur; a weak stretch may be shorter than a width, seed
    # 4092, or hold a short strong spot, seed 4104: both are what lies behind the tube);
    # where it is still tube (over the background by ``low``, not texture) but under the
    # half level behind, the end's half level and the width are taken there.
    s_top, rows = s_in, behind
    contrast = prof - np.median(g[:, np.abs(tt) >= w], axis=1)
    k_low = _level_end(contrast, cfg.low, k0, reach) if s_bg < cfg.low else None
    if k_low is not None:
        for lo in (1.0, 0.5):
            near = (ss >= ss[k_low] - lo * w) & (ss <= ss[k_low] - 0.25 * w)
            if not near.any():
                continue
            s_loc = float(np.median(prof[near]))
            if cfg.low <= s_loc - s_bg and s_loc < min(s_top, 0.5 * (s_in + s_bg)):
                s_top, rows = s_loc, near
    half = 0.5 * (s_top + s_bg)
    k = _level_end(prof, half, k0, reach)
    if k is None:
        return None
    f = (prof[k - 1] - half) / max(prof[k - 1] - prof[k], 1e-12)
    s_end = float(ss[k - 1] + f * (ss[k] - ss[k - 1]))

    def at(s_):
        return np.array([np.interp(s_, ss, cen[:, 0]), np.interp(s_, ss, cen[:, 1])])

    soft = np.clip((g - s_bg) / (s_top - s_bg), None, 1.0)
    band = np.abs(tt) <= 0.75 * w
    w_full = float(np.median(soft[rows][:, band].sum(1) * 0.25))
    if not w_full > 0:
        return None
    if cfg.tip_cap <= 0:
        return at(s_end), 0.0, d, w_full / 2.0
    region = (ss >= -w) & (ss <= s_end + 0.5 * w)
    T = float(soft[region][:, band].sum() * 0.25 * 0.25)
    a = (s_end + w - T / w_full) / (1.0 - np.pi / 4.0)
    a = float(np.clip(a, 0.0, cfg.tip_cap * w_full / 2.0))
    return at(s_end - a), a, d, w_full / 2.0


def _level_end(prof: np.ndarray, level: float, k0: int, reach: int) -> int | None:
    """Index of the first sample below ``level`` of the centre-line profile ``prof`` from
    index ``k0`` on (the next one after the last at or above it behind ``k0`` where
    ``prof[k0]`` is below already: the path overshot the silhouette's end), passing dips
    that rise to the level again within ``reach`` samples (the score varies along the
    tube: a highlight ending, a section's step); None where there is no such crossing."""
    if prof[k0] < level:
        above = np.flatnonzero(prof[:k0] >= level)
        return int(above[-1]) + 1 if len(above) else None
    below = np.flatnonzero(prof[k0:] < level)
    if not len(below):
        return None
    k = k0 + int(below[0])
    while True:
        again = np.flatnonzero(prof[k : k + reach] >= level)
        if not len(again):
            return k
        nxt = np.flatnonzero(prof[k + int(again[-1]) :] < level)
        if not len(nxt):
            return k
        k = k + int(again[-1]) + int(nxt[0])


def _end_frame(bb: np.ndarray, ss: np.ndarray, d: np.ndarray, w: float):
    """Centre points (m, 2) and unit normals (m, 2) of the grid :func:`refine_tip_details`
    samples: at ``s < 0`` on the traced backbone ``bb`` (n, 2), ``-s`` px back from its end
    along it (a tube curving near its end leaves a straight line behind the end: seeds 3212
    and 3220 of the third round, 4-8 px off the tube 2 widths back), the normal from the
    backbone's direction over one width ``w``; at ``s >= 0`` straight on along ``d`` from the
    end. A backbone shorter than ``-s`` is continued straight back along ``-d``."""
    _, length, at = _arc_sampler(bb)
    end = at(np.array([length]))[0]  # the last point kept (a repeated end point skipped)
    n_end = np.array([-d[1], d[0]])
    back = np.minimum(ss, 0.0)
    a = length + back
    cen = np.where((ss >= 0)[:, None], end + np.maximum(ss, 0.0)[:, None] * d,
                   at(a) + np.minimum(a, 0.0)[:, None] * d)  # fmt: skip
    tan = at(a + 0.5 * w) - at(a - 0.5 * w)
    tn = np.linalg.norm(tan, axis=1, keepdims=True)
    tan = np.where(tn > 1e-9, tan / np.maximum(tn, 1e-9), d[None])
    # Behind the end the normal follows the backbone; beyond it stays the end's.
    nrm = np.where((ss < 0)[:, None], np.stack([-tan[:, 1], tan[:, 0]], 1), n_end[None])
    return cen, nrm


def _path_mask(mask, bb, gaps, width):
    """Mask pixels within ``width/2 + 2`` px of the path, plus the gaps' segments drawn at
    ``width`` (distance transform of the path sampled every 0.5 px)."""
    h, w = mask.shape

    def dense(pts):
        seg = [pts[:1]]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            n = max(int(np.ceil(np.linalg.norm(b - a) / 0.5)), 1)
            seg.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
        return np.concatenate(seg)

    def near(pts, radius):
        q = np.floor(dense(pts) + 0.5).astype(np.int64)
        ok = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        raster = np.ones((h, w), bool)
        raster[q[ok, 1], q[ok, 0]] = False
        if raster.all():
            return np.zeros((h, w), bool)
        return ndi.distance_transform_edt(raster) <= radius

    if len(bb) < 2:
        return np.zeros_like(mask)
    out = near(bb, width / 2 + 2) & mask
    for a, _ in gaps:
        out |= near(bb[a : a + 2], width / 2)
    return out


def downsample(image: np.ndarray, k: int) -> np.ndarray:
    """``image`` (H, W[, C]) reduced by the integer factor ``k`` (mean over k x k blocks;
    the last ``H % k`` rows and ``W % k`` columns are dropped). Pixel ``i`` of the result
    covers pixels ``k i .. k i + k - 1``, so its centre is at full-resolution coordinate
    ``k i + (k - 1)/2`` (:func:`_to_full`)."""
    im = np.asarray(image, np.float64)
    if k <= 1:
        return im
    h, w = im.shape[0] // k, im.shape[1] // k
    im = im[: h * k, : w * k]
    return im.reshape(h, k, w, k, *im.shape[2:]).mean(axis=(1, 3))


def _to_full(uv: np.ndarray, k: int) -> np.ndarray:
    return np.asarray(uv, np.float64) * k + (k - 1) / 2.0


def _to_low(uv: np.ndarray, k: int) -> np.ndarray:
    return (np.asarray(uv, np.float64) - (k - 1) / 2.0) / k


def measure_tube_width(mask: np.ndarray, entry_uv, *, search_px: float = 20.0) -> float:
    """Width (px) of the tube on ``mask`` (H, W) bool that starts near ``entry_uv`` (u, v):
    the median of ``2 d - 1/2`` over the ridge of the distance transform ``d`` (pixels
    whose distance to the background is a local maximum over their 8 neighbours, ``d >=
    1``) of the mask component nearest the entry (within ``search_px``). Across a band
    of ``w`` pixels the centre pixel lies ``(w + 1)/2`` from the first background pixel
    (``w`` odd; ``w/2`` for its two centre pixels when ``w`` is even), so the estimate is
    within 1/2 px of ``w`` on a clean band; the median ignores the short ridges of a blob
    or a noisy edge. 0 when no component is near the entry."""
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    e = np.asarray(entry_uv, np.float64)
    r0, r1 = int(max(e[1] - search_px, 0)), int(min(e[1] + search_px + 1, h))
    c0, c1 = int(max(e[0] - search_px, 0)), int(min(e[0] + search_px + 1, w))
    rr, cc = np.nonzero(mask[r0:r1, c0:c1])
    if not len(rr):
        return 0.0
    k = int(np.argmin((cc + c0 - e[0]) ** 2 + (rr + r0 - e[1]) ** 2))
    lab, _ = ndi.label(mask, structure=np.ones((3, 3), bool))
    comp = lab == lab[rr[k] + r0, cc[k] + c0]
    sl = ndi.find_objects(comp.astype(np.int32))[0]
    sub = np.pad(comp[sl], 1)
    d = ndi.distance_transform_edt(sub)
    ridge = (d >= 1.0) & (d >= ndi.maximum_filter(d, size=3))
    return float(np.median(2.0 * d[ridge] - 0.5))


def _scaled(cfg: PlateForegroundConfig, k: int) -> PlateForegroundConfig:
    """``cfg`` with its lengths multiplied by ``k`` (for the full-resolution steps)."""
    from dataclasses import replace

    return replace(cfg, close_px=cfg.close_px * k, look_px=cfg.look_px * k,
                   step_px=cfg.step_px * k, max_width_px=cfg.max_width_px * k)  # fmt: skip


def plate_foreground(
    frame: np.ndarray,
    plate: np.ndarray,
    entry_uv=None,
    direction_uv=None,
    cfg: PlateForegroundConfig = PlateForegroundConfig(),
) -> TubeTrace:
    """Steps 1-4 of the module docstring on one view: ``frame``, ``plate`` RGB (H, W, 3)
    (uint8 or float [0, 1]); ``entry_uv`` the pixel where the robot enters the view (None:
    found at the image border, :func:`border_entry`).

    The plate is aligned and the cues computed at full resolution; the tube's width near
    the entry (:func:`measure_tube_width` on the hysteresis mask) chooses the factor ``k``
    (``cfg.scale``, see :class:`PlateForegroundConfig`). With ``k >= 2`` the cues,
    hysteresis and tracing run again on frame and aligned plate reduced by ``k``
    (:func:`downsample`), where the tube is about ``cfg.tube_width_px`` wide as the
    lengths assume; the path is mapped back to full-resolution pixels, the mask is the
    full-resolution hysteresis mask near the path (closing ``k close_px``), and the tip is
    refined on the full-resolution score (with ``k look_px``)."""
    f = np.asarray(frame)
    p = np.asarray(plate)
    f = f.astype(np.float64) / 255.0 if f.dtype == np.uint8 else f.astype(np.float64)
    p = p.astype(np.float64) / 255.0 if p.dtype == np.uint8 else p.astype(np.float64)
    shift = align_plate(f, p, max_shift_px=cfg.max_shift_px) if cfg.align else np.zeros(2)
    pa = shift_image(p, shift) if cfg.align else p
    cues = foreground_cues(f, pa, cfg)
    raw = cues["score"]
    score = close_score(raw, cfg.close_px) if cfg.close_px > 0 else raw
    seeds = hysteresis(score, cfg.low, cfg.high)
    if entry_uv is None:
        be = border_entry(seeds)
        if be is None:
            tr = TubeTrace(np.zeros(seeds.shape, bool), np.zeros((0, 2)), np.full(2, np.nan),
                           np.full(2, np.nan), reason="no foreground touches the image border")  # fmt: skip
            tr.score, tr.seed_mask, tr.shift = score, seeds, shift
            return tr
        entry_uv, d0 = be
        direction_uv = d0 if direction_uv is None else direction_uv
    entry_uv = np.asarray(entry_uv, np.float64)
    width0 = measure_tube_width(seeds, entry_uv)
    k = int(cfg.scale) if cfg.scale > 0 else max(1, int(round(width0 / cfg.tube_width_px)))
    k = max(1, min(k, min(f.shape[:2]) // 32))  # keep at least 32 px across the reduced view
    if k > 1:
        fl, pl = downsample(f, k), downsample(pa, k)
        sl = foreground_cues(fl, pl, cfg)["score"]
        if cfg.close_px > 0:
            sl = close_score(sl, cfg.close_px)
        seeds_l = hysteresis(sl, cfg.low, cfg.high)
        if cfg.close_px > 0:  # the full-resolution score, closed across the wider tube
            score = close_score(raw, cfg.close_px * k)
            seeds = hysteresis(score, cfg.low, cfg.high)
    else:
        fl, pl, seeds_l = f, pa, seeds
    fs, ps = fl, pl
    if cfg.blur_px > 0:
        fs = ndi.gaussian_filter(fl, (cfg.blur_px, cfg.blur_px, 0))
        ps = ndi.gaussian_filter(pl, (cfg.blur_px, cfg.blur_px, 0))
    tr = trace_tube(seeds_l, _to_low(entry_uv, k), direction_uv, cfg, frame=fs, plate=ps)
    # The starts trace_tube did not keep (an attribute, not a field: a copy need not carry
    # them; trace_alternatives reads them from the retrace state's trace).
    starts = getattr(tr, "start_alternatives", [])
    tr = _retrace_off_border(tr, seeds_l, cfg, fs, ps)
    tr.start_alternatives = starts
    tr.crossing_turn_deg = _path_turn(tr.backbone, [j[0] for j in tr.junctions], cfg)
    tr.crossings_followed = _path_through(seeds_l, tr.backbone, [j[0] for j in tr.junctions],
                                          cfg, tr.width_px)  # fmt: skip
    ctx = _Retrace(seeds_l, fs, ps, k, score, seeds, shift, width0, cfg, tr)
    return _finish(tr, ctx)


@dataclass(frozen=True)
class _Retrace:
    """A :func:`plate_foreground` run's state that :func:`trace_alternatives` re-traces on:
    the traced view's mask ``seeds_l`` and smoothed frame/plate ``fs``/``ps`` (reduced by
    ``k``), the full-resolution ``score`` and hysteresis mask ``seeds``, the plate
    ``shift``, the measured entry width, the config and the trace at the traced scale."""

    seeds_l: np.ndarray
    fs: np.ndarray
    ps: np.ndarray
    k: int
    score: np.ndarray
    seeds: np.ndarray
    shift: np.ndarray
    width0: float
    cfg: PlateForegroundConfig
    low: TubeTrace


def _finish(low: TubeTrace, ctx: _Retrace) -> TubeTrace:
    """A trace at the traced scale mapped to full-resolution pixels, its mask the
    full-resolution hysteresis mask near the path, its tip refined on the full-resolution
    score (the end of :func:`plate_foreground`)."""
    from dataclasses import replace

    k, cfg = ctx.k, ctx.cfg
    tr = replace(low, backbone=low.backbone.copy(), tip=low.tip.copy(), gaps=list(low.gaps))
    if k > 1:
        tr.backbone = _to_full(tr.backbone, k)
        tr.tip, tr.entry = _to_full(tr.tip, k), _to_full(tr.entry, k)
        tr.width_px = tr.width_px * k
        tr.mask = _path_mask(ctx.seeds, tr.backbone, tr.gaps, tr.width_px)
    if cfg.refine and len(tr.backbone) >= 3:
        tip, tr.cap_px, tr.end_dir, tr.end_half_width_px = refine_tip_details(
            ctx.score, tr.backbone, tr.width_px, _scaled(cfg, k)
        )
        tr.backbone = np.vstack([tr.backbone[:-1], tip])
        tr.tip = tip
    tr.shift, tr.score, tr.seed_mask = ctx.shift, ctx.score, ctx.seeds
    tr.scale, tr.measured_width_px = k, ctx.width0
    tr.retrace = ctx
    return tr


def _heading_at(bb: np.ndarray, i: int) -> float:
    """The tube's heading (rad) arriving at ``bb[i]``: the arc fitted to the path before it
    (:func:`_local_arc`), else the chord from 5 points back."""
    arc = _local_arc(list(bb[: i + 1]))
    if arc is not None:
        return arc[0]
    d = bb[i] - bb[max(i - 5, 0)]
    if np.linalg.norm(d) < 1e-9:
        d = bb[min(i + 1, len(bb) - 1)] - bb[i]
    return float(np.arctan2(d[1], d[0]))


def crossing_turn(backbone: np.ndarray, index: int, ahead_px: float) -> float:
    """Turn (deg, in [0, 180]) of the path ``backbone`` (n, 2) at point ``index``: the
    angle between its heading arriving there (:func:`_heading_at`) and the chord from that
    point to the path ``ahead_px`` further on (or to its end). 0 when the path ends within
    ``ahead_px / 2`` (the tube's end, not a crossing: no direction to compare)."""
    bb = np.asarray(backbone, np.float64)
    if index >= len(bb) - 1:
        return 0.0
    rest = bb[index:]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(rest, axis=0), axis=1))]
    if s[-1] < ahead_px / 2:
        return 0.0
    j = int(min(np.searchsorted(s, ahead_px), len(rest) - 1))
    chord = rest[j] - rest[0]
    head = _heading_at(bb, index)
    diff = np.arctan2(chord[1], chord[0]) - head
    return float(abs(np.degrees(np.angle(np.exp(1j * diff)))))


def _path_turn(bb: np.ndarray, indices, cfg: PlateForegroundConfig) -> float:
    """The largest :func:`crossing_turn` (two look lengths on) over the junction indices."""
    turns = [crossing_turn(bb, int(i), 2.0 * cfg.look_px) for i in indices if 0 < i < len(bb)]
    return max(turns, default=0.0)


def crosses_through(mask: np.ndarray, backbone: np.ndarray, index: int, ahead_px: float,
                    width_px: float, *, support: float = 0.6) -> bool:  # fmt: skip
    """Whether the path ``backbone`` (n, 2) leaves point ``index`` along something that
    crosses the tube there: the line of its chord to the path ``ahead_px`` further on,
    continued *behind* the point (from ``ahead_px / 2`` to ``1.5 ahead_px`` back), lies on
    ``mask`` on at least ``support`` of its samples that are farther than a tube width
    (``width_px``) plus 1 px from the path before the point. A tube goes on from its own
    path; a cable or tool crossing it is seen on both sides of the crossing (an X, not a
    Y), and the tube's own path is what lies behind a straight-on continuation. False
    where fewer than a third of the samples are off the path before (no evidence)."""
    bb = np.asarray(backbone, np.float64)
    if not 0 < index < len(bb) - 1:
        return False
    rest = bb[index:]
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(rest, axis=0), axis=1))]
    if s[-1] < ahead_px / 2:
        return False
    j = int(min(np.searchsorted(s, ahead_px), len(rest) - 1))
    u = rest[j] - rest[0]
    if np.linalg.norm(u) < 1e-9:
        return False
    u = u / np.linalg.norm(u)
    t = np.arange(0.5 * ahead_px, 1.5 * ahead_px + 1e-9, 1.0)
    pts = bb[index][None] - t[:, None] * u[None]
    h, w = mask.shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    before = _densify_path(bb[: index + 1])
    d2 = np.min(np.sum((pts[:, None] - before[None]) ** 2, axis=2), axis=1)
    off = inside & (d2 > (width_px + 1.0) ** 2)
    if off.sum() < len(t) / 3:
        return False
    return bool(np.mean(_sample(mask, pts[off]) > 0) >= support)


def _densify_path(pts: np.ndarray, step: float = 1.0) -> np.ndarray:
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def _path_through(mask, bb, indices, cfg: PlateForegroundConfig, width_px: float) -> int:
    """How many of the junction indices the path leaves along a crossing object
    (:func:`crosses_through`, two look lengths on)."""
    return int(sum(crosses_through(mask, bb, int(i), 2.0 * cfg.look_px, width_px)
                   for i in indices if 0 < i < len(bb) - 1))  # fmt: skip


def _hook_apex(bb: np.ndarray, i: int, heading: float, chord: np.ndarray) -> int | None:
    """The index of ``bb`` (n, 2) beyond ``i`` farthest along ``heading`` (rad) from
    ``bb[i]``, when ``chord`` (2,) (from ``bb[i]`` to the end of a branch leaving it) runs
    against the heading (over 90 deg from it) and that point lies beyond ``bb[i]``; else
    None."""
    h = _unit(heading)
    if not float(np.asarray(chord, np.float64) @ h) < 0.0:
        return None
    prog = (bb[i:] - bb[i]) @ h
    m = int(np.argmax(prog))
    return i + m if m > 0 and prog[m] > 0.0 else None


def end_before_hop(
    trace: TubeTrace, near_uv, *, reach_widths: float = 2.0, min_widths: float = 0.25
) -> np.ndarray | None:
    """The silhouette's end (u, v) of a tube that ends before a hop of ``trace``'s path
    across background behind its point nearest ``near_uv`` (2,) (u, v), or None where the
    path hops across none there.

    A tube's silhouette is continuous up to its end. The walker steps across a short
    stretch of background where more foreground lies close ahead (its look ray needs only
    ``support`` of its length on the mask), so where a tube ends a few pixels short of a
    crossing cable or a shadow, the path hops onto that and goes on along it (real_like
    dev seed 4167, view 2: a 9 px hop, the tube's end 3 px before it). A point of the path
    beyond such a hop is not on the tube that ends there: where a second view says the
    tube ends near a point past a hop (the cut of
    :func:`jaxcr.stereo.tip_consistency.trim_unexplained_tail`), the tube ends before it.

    A hop is a run of the full-resolution ``score`` on the path (sampled every 0.5 px,
    bilinear) under the hysteresis level ``low`` of the trace's configuration, at least
    ``min_widths`` tube widths (and 2 px) long, starting at most ``reach_widths`` widths
    (``width_px``) behind the point nearest ``near_uv``, and not one of the gaps the trace
    bridged (``gaps``: the tube matching the background). The end is the last crossing,
    before the nearest such hop, of the half level between the path's median score 1-3
    widths before the hop and the hop's median (a blurred step's half level is its edge),
    linearly interpolated. It is the silhouette's end: the end face's foreshortened length
    (:func:`refine_tip_details`) is not removed."""
    if trace.score is None or len(trace.backbone) < 3:
        return None
    bb = np.asarray(trace.backbone, np.float64)
    w = float(max(trace.width_px, 2.0))
    low = trace.retrace.cfg.low if trace.retrace is not None else PlateForegroundConfig().low
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    a_near = float(
        cum[int(np.argmin(np.linalg.norm(bb - np.asarray(near_uv, np.float64), axis=1)))]
    )
    a = np.arange(max(0.0, a_near - (reach_widths + 3.0) * w), a_near + 0.25, 0.5)
    if len(a) < 4:
        return None
    pts = np.stack([np.interp(a, cum, bb[:, 0]), np.interp(a, cum, bb[:, 1])], 1)
    sc = ndi.map_coordinates(np.asarray(trace.score, np.float64), [pts[:, 1], pts[:, 0]],
                             order=1, mode="nearest")  # fmt: skip
    off = sc < low
    for g0, g1 in trace.gaps:
        g0, g1 = min(int(g0), len(cum) - 1), min(int(g1), len(cum) - 1)
        off &= ~((a >= cum[g0]) & (a <= cum[g1]))
    edges = np.diff(np.r_[0, off.astype(np.int8), 0])
    # Hops (first, last sample), with the 3 widths before each sampled for its level.
    hops = [(i, j - 1) for i, j in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1),
                                        strict=True)
            if a[j - 1] - a[i] >= max(2.0, min_widths * w)
            and a_near - reach_widths * w <= a[i] and a[i] >= a[0] + 3.0 * w]  # fmt: skip
    if not hops:
        return None
    i, j = hops[-1]
    before = (a >= a[i] - 3.0 * w) & (a <= a[i] - w)
    half = 0.5 * (float(np.median(sc[before])) + float(np.median(sc[i : j + 1])))
    above = np.flatnonzero(sc[:i] >= half)
    if not len(above):
        return None
    m = int(above[-1])
    end = a[m] + (sc[m] - half) / max(sc[m] - sc[m + 1], 1e-12) * (a[m + 1] - a[m])
    return np.array([np.interp(end, cum, bb[:, 0]), np.interp(end, cum, bb[:, 1])])


def trace_alternatives(
    tr: TubeTrace, *, turns_deg=(0.0, 15.0, -15.0, 30.0, -30.0, 45.0, -45.0)
) -> list[TubeTrace]:
    """Other ways the tube may go on at the junctions ``tr`` passed (crossing cables or
    tools, shadows), each traced to its end and refined as :func:`plate_foreground` does:
    the alternatives one view offers when another view disagrees with its tip
    (:func:`jaxcr.stereo.branch_choice.choose_branches`).

    At each junction the re-trace starts from the junction's point in the direction of its
    second branch (where one was seen) and in the tube's heading arriving there
    (:func:`_heading_at`) turned by each of ``turns_deg`` (0 first: straight on, behind the
    crossing object), on the mask with the tube traced before the junction taken off (a
    re-trace must not walk back) and the trace's own path after it taken off beyond a look
    length and a width from the junction (so the re-trace neither follows the branch the
    trace took nor is cut off from the crossing). Junctions fewer than two look lengths
    before the trace's end are skipped (the end's jitter, not a branch). Kept: traces that
    go on for two look lengths, onwards (within 60 deg of the start direction there), end
    inside the image, and end more than 1.5 px (traced scale) from every tip kept before
    (the original's included).
    A re-trace that ends behind its junction (along the heading arriving there) may be the
    way back of a hook: the tube went on along the trace to the hook's apex and came back
    beside itself, the two merged into one wide run (where the junction was seen). It is
    then offered twice: as it is (the tube turned back at the junction, a bend seen nearly
    end-on) and as the trace out to the apex (its farthest point along that heading,
    :func:`_hook_apex`) followed by the re-trace from its point nearest the apex on, so
    that a second view, which sees the whole hook, can explain it.
    Each alternative's ``departure`` is its junction's index; its ``crossing_turn_deg`` the
    largest turn at the junctions it passes. [] for a trace without ``retrace`` state or
    junctions.

    The traces from the entry's other starting directions (``start_spread_deg``), which
    :func:`trace_tube` did not keep because a longer one was found, are offered too, under
    the same conditions, with ``departure`` 0 (docs/decisions.md S45: a rod running past
    the entry beside the tube is the longer trace)."""
    ctx = tr.retrace
    starts = getattr(getattr(ctx, "low", None), "start_alternatives", [])
    if ctx is None or not (ctx.low.junctions or starts):
        return []
    low, cfg = ctx.low, ctx.cfg
    mask = ctx.seeds_l
    bb_all = np.asarray(low.backbone, np.float64)
    near_steps = int(np.ceil(cfg.look_px / cfg.step_px))
    rad = 0.5 * low.width_px + 1.0
    reach = cfg.look_px + low.width_px
    margin = 2.0 * cfg.step_px
    tips = [np.asarray(low.tip, np.float64)]
    out = []
    ones = np.ones_like(mask)
    seg_all = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb_all, axis=0), axis=1))]
    ahead_px = 2.0 * cfg.look_px
    for i, pj, dj in low.junctions:
        # A branch, not the end's jitter: the trace goes on two look lengths past the
        # junction, and so must an alternative.
        if not 0 < i < len(bb_all) or seg_all[-1] - seg_all[i] < ahead_px:
            continue
        head = _heading_at(bb_all, i)
        dirs = [] if dj is None else [np.asarray(dj, np.float64)]
        dirs += [_unit(head + np.radians(a)) for a in turns_deg]
        sub_mask = mask.copy()
        pre = bb_all[: max(i - near_steps, 0)]
        if len(pre) >= 2:
            sub_mask &= ~_path_mask(ones, pre, [], 2 * rad)
        post = bb_all[i:]
        far = np.linalg.norm(post - pj[None], axis=1) > reach
        # Runs of far points (the path may come back near the junction).
        idx = np.flatnonzero(far)
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if len(idx) else []:
            if len(run) >= 2:
                sub_mask &= ~_path_mask(ones, post[run], [], 2 * rad)
        for dv in dirs:
            sub = trace_tube(sub_mask, pj, dv, cfg, frame=ctx.fs, plate=ctx.ps, _single=True)
            if len(sub.backbone) < 2 or _at_border(sub.tip, mask.shape, margin):
                continue
            seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(sub.backbone, axis=0), axis=1))]
            if seg[-1] < ahead_px:
                continue
            ahead = sub.backbone[int(np.searchsorted(seg, min(2 * cfg.look_px, seg[-1])))]
            dn = np.linalg.norm(ahead - pj)
            if dn > 0 and (ahead - pj) @ dv < 0.5 * dn:
                continue
            if min(np.linalg.norm(sub.tip - t) for t in tips) <= 1.5:
                continue
            tips.append(sub.tip.copy())
            # Where the re-trace ends behind its junction (along the heading arriving
            # there), either the tube turned back there (a bend seen nearly end-on) or it
            # went on along the trace and came back beside itself (a hook; the way out
            # and the way back merged into the wide run where the junction was seen).
            # Both paths are offered, the second the trace out to the hook's apex (its
            # farthest point along that heading) and the re-trace from its point
            # nearest the apex on; the second view tells which it sees.
            apex = _hook_apex(bb_all, i, head, sub.backbone[-1] - pj)
            splices = [(i, 1, [(i, pj, dv)])]
            if apex is not None:
                near = int(np.argmin(np.linalg.norm(sub.backbone - bb_all[apex], axis=1)))
                splices.append((apex, near, []))
            for stop, start, first in splices:
                bb = np.vstack([bb_all[: stop + 1], sub.backbone[start:]])
                off = stop + 1 - start  # sub's index m is bb's m + off
                gaps = [g for g in low.gaps if g[1] <= stop]
                gaps += [(a + off, b + off) for a, b in sub.gaps if a >= start]
                juncs = [j for j in low.junctions if j[0] < i or (stop > i and j[0] <= stop)]
                juncs += first + [(a + off, b, c) for a, b, c in sub.junctions if a >= start]
                out.append(_alternative(ctx, bb, gaps, juncs, int(i)))
    out += start_alternatives(tr, tips=tips)
    return out


def start_alternatives(tr: TubeTrace, *, tips=()) -> list[TubeTrace]:
    """The traces of ``tr``'s view from the entry's other starting directions
    (:func:`trace_tube` with ``start_spread_deg`` keeps the longest of three), each refined as
    :func:`plate_foreground` does, with ``departure`` 0: part of
    :func:`trace_alternatives` (docs/decisions.md S45: a rod running past the entry beside
    the tube is the longer trace). Kept as the junctions' re-traces are: two look lengths
    long, ending inside the image and more than 1.5 px (traced scale) from ``tr``'s tip and
    every tip in ``tips`` (traced scale)."""
    ctx = tr.retrace
    starts = getattr(getattr(ctx, "low", None), "start_alternatives", [])
    if not starts:
        return []
    low, cfg, mask = ctx.low, ctx.cfg, ctx.seeds_l
    margin, ahead_px = 2.0 * cfg.step_px, 2.0 * cfg.look_px
    tips = [np.asarray(low.tip, np.float64)] + [np.asarray(t, np.float64) for t in tips]
    out = []
    for st in starts:
        if len(st.backbone) < 2 or _at_border(st.tip, mask.shape, margin):
            continue
        if _trace_length(st) < ahead_px or min(np.linalg.norm(st.tip - t) for t in tips) <= 1.5:
            continue
        tips.append(np.asarray(st.tip, np.float64).copy())
        out.append(_alternative(ctx, st.backbone.copy(), list(st.gaps), list(st.junctions), 0))
    return out


def _alternative(ctx: _Retrace, bb: np.ndarray, gaps: list, junctions: list, departure: int):
    """An alternative path ``bb`` (traced scale) of the trace whose retrace state is
    ``ctx`` as :func:`trace_alternatives` offers it: its mask, turn and crossings at its
    ``junctions``, ``departure``, finished (mapped to full resolution, tip refined) as
    :func:`plate_foreground` finishes a trace."""
    low, cfg, mask = ctx.low, ctx.cfg, ctx.seeds_l
    alt = TubeTrace(_path_mask(mask, bb, gaps, low.width_px), bb, bb[-1].copy(), low.entry,
                    gaps, width_px=low.width_px, junctions=junctions)  # fmt: skip
    alt.crossing_turn_deg = _path_turn(bb, [j[0] for j in junctions], cfg)
    alt.crossings_followed = _path_through(mask, bb, [j[0] for j in junctions], cfg,
                                           low.width_px)  # fmt: skip
    alt.departure = departure
    return _finish(alt, ctx)
