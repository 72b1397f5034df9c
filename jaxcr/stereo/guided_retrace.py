"""One view's tube re-traced along the other view's backbone (issue 16 item 2, round 14,
docs/decisions.md S35).

Where the two views of ``jaxcr stereo --segmentation trace`` disagree, one view's tracer
usually took a wrong way at a junction (a crossing cable, a hook over the tube's own
silhouette) while the other followed the tube; the re-traces from a view's own junctions
(:func:`jaxcr.segmentation.foreground.trace_alternatives`) often do not hold the right way
either (S31: in 22 of 26 failing development frames no candidate pair was right). Here the
view that is right is used as the *anchor*, and the other view is searched again along it.

The anchor's backbone (entry to tip) is resampled every ``step_widths`` tube widths; each
sample's epipolar line in the other view is the set of pixels where the same 3-D point can
be, so the other view's backbone visits these lines in the anchor's order. On each line the
foreground evidence (the trace's cue score, clipped at ``high`` and blurred by a quarter
width, :func:`evidence_map`) is sampled, and its runs over a half are the candidate points
(a run longer than 1.5 widths, where the tube runs along the line, gives a candidate every
half width). A dynamic programme over the lines in order chooses one candidate per line
(lines may be skipped: a stretch the other view cannot see, tape or shadow), from the
other view's entry pixel: a step costs the length of its straight segment off the evidence
(``off_cost``), the anchor length of the lines it skips (``skip_cost``), a little of its
own length (``length_cost``, preferring the direct way among equally supported ones), and
``stall_cost`` per px by which it is shorter than ``stall_ratio`` times the anchor length
it covers (where the other view's tube runs along the epipolar lines, one stretch of it
meets many lines, and a path could stay there while the anchor goes on; a tube pointing
at one camera is foreshortened in that view, so this is a soft prior). The path may end
before the anchor's last line (the anchor's tail then unexplained, at ``skip_cost``), and
an end where the evidence goes on beyond it (along the path's chord over its last 1.5
widths, 0.75-2 widths ahead, the fraction over the level) costs ``beyond_cost`` widths: the
tube ends where the anchor's tip's epipolar line meets the end of the evidence, and a path
that stops on a structure going on (a cable, a crease) is the trace of something else.

:func:`guided_candidates` is what :func:`jaxcr.stereo.pipeline.traced_stereo_tips` calls
on frames whose tips the epipolar test flags and where the views' own candidates give no
pair whose backbones explain each other: both views in turn as the anchor, each candidate
offered under the gates in its docstring.

:func:`guided_retrace` returns the path (:class:`GuidedPath`); :func:`guided_candidate`
turns it into a :class:`jaxcr.segmentation.foreground.TubeTrace` of the re-traced view (the
tip refined on the score as the tracer does) to be offered to the branch choice
(:func:`jaxcr.stereo.branch_choice.choose_branches`).

Pixels are distorted (as the camera records them) at the interface; the epipolar lines are
built on undistorted pixels and their samples distorted back. Numpy/scipy float64 and cv2
(undistortion), per frame, at the edge of the stereo pipeline: nothing here is jitted.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import erf, sqrt

import numpy as np
from scipy import ndimage as ndi

from jaxcr.stereo.backbone_consistency import resample_polyline
from jaxcr.stereo.tip_consistency import _distort, undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses
from jaxcr.stereo.trace3d import _sample  # bilinear samples, 0 outside the image or at NaN

__all__ = [
    "GuidedPath",
    "epipolar_lines",
    "evidence_map",
    "guided_retrace",
    "guided_candidate",
    "guided_candidates",
]


@dataclass
class GuidedPath:
    """Result of :func:`guided_retrace`.

    ``backbone`` (m, 2) the re-traced view's path (distorted (u, v)), from its entry pixel
    to its end; ``anchor_index`` (m,) the anchor sample each point lies on the epipolar line
    of (-1 for the entry); ``gaps`` (index, index + 1) pairs of ``backbone`` whose segment
    crosses background; ``cost`` the programme's total; ``off_px`` the path's length off the
    evidence; ``unexplained_px`` the anchor length of skipped lines plus its unexplained tail;
    ``tail_px`` that tail alone (anchor px after the last matched line); ``beyond`` the
    fraction of the evidence over ``level`` 0.75-2 widths beyond the end (0: the
    evidence ends there)."""

    backbone: np.ndarray
    anchor_index: np.ndarray
    gaps: list
    cost: float
    off_px: float
    unexplained_px: float
    tail_px: float
    beyond: float


def evidence_map(score, *, high: float = 1.0, width_px: float = 8.0) -> np.ndarray:
    """The cue ``score`` (H, W) clipped at ``high``, scaled to [0, 1] and blurred by a
    Gaussian of a quarter ``width_px``, divided by the blurred level on a tube's axis
    (``erf(sqrt(2))``), so that a tube's axis reads 1 and its edges about a half."""
    e = np.clip(np.asarray(score, np.float32) / np.float32(high), 0.0, 1.0)
    e = ndi.gaussian_filter(e, 0.25 * float(width_px))
    return np.minimum(e / np.float32(erf(1.0 / (2.0 * sqrt(2.0) * 0.25))), 1.0)


def epipolar_lines(cams, uv, from_view: int) -> np.ndarray:
    """The epipolar lines (n, 3) ``(a, b, c)``, ``a^2 + b^2 = 1``, in the other view's
    undistorted pixels, of the distorted pixels ``uv`` (n, 2) of view ``from_view`` (0 or 1)
    of the calibrated pair ``cams`` (``K``, ``dist``, ``T_cam_robot`` in one frame): the
    undistorted pixel ``x`` of the other view is on the line of ``uv[i]`` when
    ``a u + b v + c = 0`` (OpenCV ``computeCorrespondEpilines``' convention)."""
    K0, K1 = (np.asarray(c.K, np.float64) for c in cams)
    F = fundamental_from_poses(K0, cams[0].T_cam_robot, K1, cams[1].T_cam_robot)
    x = undistort_pixels(cams[from_view], uv)
    h = np.c_[x, np.ones(len(x))]
    ln = h @ (F.T if from_view == 0 else F)
    return ln / np.maximum(np.hypot(ln[:, :1], ln[:, 1:2]), 1e-300)


def _line_samples(cam, lines, shape, step: float = 1.0, margin: float = 40.0):
    """Per line, points every ``step`` px (undistorted) across the image rectangle (plus
    ``margin``), distorted to ``cam``'s pixels: (n, L, 2), NaN beyond each line's part."""
    h, w = shape
    n = len(lines)
    a, b, c = lines[:, 0], lines[:, 1], lines[:, 2]
    d = np.stack([-b, a], 1)  # direction along the line
    x0 = -c[:, None] * np.stack([a, b], 1)  # the line's point nearest the origin
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    for k, (mn, mx) in enumerate(((-margin, w + margin), (-margin, h + margin))):
        dk, xk = d[:, k], x0[:, k]
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (mn - xk) / dk, (mx - xk) / dk
        par = np.abs(dk) < 1e-12
        inside = (xk >= mn) & (xk <= mx)
        t1 = np.where(par, np.where(inside, -np.inf, np.inf), t1)
        t2 = np.where(par, np.where(inside, np.inf, -np.inf), t2)
        lo = np.maximum(lo, np.minimum(t1, t2))
        hi = np.minimum(hi, np.maximum(t1, t2))
    length = np.maximum(hi - lo, 0.0)
    m = int(np.ceil(np.max(length, initial=0.0) / step)) + 1
    t = lo[:, None] + step * np.arange(m)[None]
    ok = (t <= hi[:, None]) & (length[:, None] > 0)
    pts = x0[:, None] + t[..., None] * d[:, None]
    pts = np.where(ok[..., None], pts, 0.0)
    out = _distort(cam, pts.reshape(-1, 2)).reshape(n, m, 2)
    out[~ok] = np.nan
    return out


def _candidates(pts, ev, level: float, width: float) -> np.ndarray:
    """Candidate points (k, 2) of one line: per run of ``ev > level`` its centre, or for a run
    over 1.5 widths long, points every half width along it."""
    on = np.isfinite(pts[:, 0]) & (ev > level)
    if not on.any():
        return np.zeros((0, 2))
    idx = np.flatnonzero(on)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    out = []
    for r in runs:
        seg = pts[r]
        ln = float(np.sum(np.linalg.norm(np.diff(seg, axis=0), axis=1))) if len(r) > 1 else 0.0
        if ln <= 1.5 * width:
            wts = ev[r] - level
            out.append((seg * wts[:, None]).sum(0) / max(wts.sum(), 1e-12))
        else:
            k = int(np.floor((ln - 0.5 * width) / (0.5 * width))) + 1
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))]
            for q in 0.25 * width + 0.5 * width * np.arange(k):
                out.append([np.interp(q, s, seg[:, 0]), np.interp(q, s, seg[:, 1])])
    return np.asarray(out, np.float64).reshape(-1, 2)


def _off_length(E, p, q, level: float, n: int = 12) -> np.ndarray:
    """For every pair of ``p`` (a, 2) and ``q`` (b, 2): the length (a, b) of the straight
    segment ``p -> q`` whose evidence is at most ``level`` (``n`` interior samples)."""
    f = (np.arange(n) + 0.5) / n
    seg = p[:, None, None] + (q[None, :, None] - p[:, None, None]) * f[None, None, :, None]
    ev = _sample(E, seg)
    length = np.linalg.norm(q[None] - p[:, None], axis=2)
    return np.mean(ev <= level, axis=2) * length


def _beyond(E, q, d, width: float, level: float) -> float:
    """Fraction of the evidence over ``level`` from 0.75 to 2 widths ahead of ``q`` along
    the unit ``d``."""
    t = np.linspace(0.75 * width, 2.0 * width, 11)
    return float(np.mean(_sample(E, q[None] + t[:, None] * d[None]) > level))


def _point_back(cands, back, entry, j: int, k: int, dist: float) -> np.ndarray:
    """The first point of the programme's path ending at candidate ``k`` of line ``j`` that
    lies at least ``dist`` px back from it (the entry if none): the end's direction is
    taken over that chord, not over the last step (candidates jitter across the tube)."""
    q = cands[j][k]
    while back[j][k, 0] >= 0:
        j, k = int(back[j][k, 0]), int(back[j][k, 1])
        if np.linalg.norm(cands[j][k] - q) >= dist:
            return cands[j][k]
    return entry


def guided_retrace(
    cams, anchor_view: int, anchor_backbone, evidence, entry_px, width_px: float, *,
    level: float = 0.5, step_widths: float = 0.5, max_skip_widths: float = 8.0,
    off_cost: float = 1.0, skip_cost: float = 0.5, length_cost: float = 0.05,
    beyond_cost: float = 2.0, stall_ratio: float = 0.33, stall_cost: float = 1.0,
) -> GuidedPath | None:  # fmt: skip
    """The other view's backbone found along the anchor's (module docstring).

    ``cams``: the calibrated pair. ``anchor_view`` (0 or 1) the view whose
    ``anchor_backbone`` (n, 2) (distorted, entry to tip) guides; ``evidence`` (H, W) the
    other view's foreground evidence in [0, 1] (:func:`evidence_map`), ``entry_px`` (2,)
    its entry pixel (distorted) and ``width_px`` its tube width. The anchor is resampled
    every ``step_widths * width_px``; at most ``max_skip_widths * width_px`` of anchor is
    skipped in one step. Costs (px of the re-traced view, except ``skip_cost`` per anchor
    px and ``beyond_cost`` per width): see the module docstring. None when the anchor is
    under two samples long or no line holds a candidate."""
    w = float(max(width_px, 2.0))
    h_step = step_widths * w
    a = resample_polyline(anchor_backbone, h_step)
    if len(a) < 2:
        return None
    # The anchor's actual spacing (its last step may be shorter).
    da = np.r_[np.linalg.norm(np.diff(a, axis=0), axis=1), 0.0]
    lines = epipolar_lines(cams, a, anchor_view)
    other = cams[1 - anchor_view]
    E = np.asarray(evidence, np.float64)
    pts = _line_samples(other, lines, E.shape)
    ev = _sample(E, pts)
    cands = [_candidates(pts[i], ev[i], level, w) for i in range(len(a))]
    if not any(len(c) for c in cands):
        return None
    n = len(a)
    kmax = max(1, int(np.ceil(max_skip_widths * w / h_step)))
    s_anchor = np.r_[0.0, np.cumsum(da[:-1])]
    entry = np.asarray(entry_px, np.float64).reshape(1, 2)
    D = [np.full(len(c), np.inf) for c in cands]
    back = [np.full((len(c), 2), -1, np.int64) for c in cands]  # (line, candidate); -1: entry
    for j in range(n):
        q = cands[j]
        if not len(q):
            continue
        if j < kmax:  # from the entry, skipping the anchor's first j samples
            c = (off_cost * _off_length(E, entry, q, level)[0]
                 + length_cost * np.linalg.norm(q - entry, axis=1)
                 + skip_cost * s_anchor[j])  # fmt: skip
            better = c < D[j]
            D[j][better] = c[better]
            back[j][better] = -1
        for i in range(max(0, j - kmax), j):
            p = cands[i]
            if not len(p) or not np.isfinite(D[i]).any():
                continue
            skipped = s_anchor[j] - s_anchor[i] - da[i]
            dq = np.linalg.norm(q[None] - p[:, None], axis=2)
            c = (D[i][:, None] + off_cost * _off_length(E, p, q, level) + length_cost * dq
                 + stall_cost * np.maximum(stall_ratio * (s_anchor[j] - s_anchor[i]) - dq, 0.0)
                 + skip_cost * skipped)  # fmt: skip
            arg = np.argmin(c, axis=0)
            best = c[arg, np.arange(len(q))]
            better = best < D[j]
            D[j][better] = best[better]
            back[j][better, 0] = i
            back[j][better, 1] = arg[better]

    def path_of(j, k):
        out = [(j, k)]
        while back[j][k, 0] >= 0:
            j, k = int(back[j][k, 0]), int(back[j][k, 1])
            out.append((j, k))
        return out[::-1]

    best = None
    for j in range(n):
        tail = s_anchor[-1] - s_anchor[j]
        for k in np.flatnonzero(np.isfinite(D[j])):
            total = D[j][k] + skip_cost * tail
            if best is not None and total >= best[0]:
                continue  # the beyond term only adds
            q = cands[j][k]
            prev = _point_back(cands, back, entry[0], j, int(k), 1.5 * w)
            d = q - prev
            nd = float(np.linalg.norm(d))
            bey = _beyond(E, q, d / nd, w, level) if nd > 0 else 1.0
            total += beyond_cost * w * bey
            if best is None or total < best[0]:
                best = (total, j, int(k), bey, tail)
    if best is None:
        return None
    total, j, k, bey, tail = best
    steps = path_of(j, k)
    bb = np.vstack([entry, [cands[i][c] for i, c in steps]])
    idx = np.r_[-1, [i for i, _ in steps]]
    off_seg = np.array([_off_length(E, p[None], q[None], level)[0, 0]
                        for p, q in zip(bb[:-1], bb[1:], strict=True)])  # fmt: skip
    seg_len = np.linalg.norm(np.diff(bb, axis=0), axis=1)
    gaps = [(m, m + 1) for m in range(len(seg_len)) if off_seg[m] > 0.5 * seg_len[m]]
    skipped = (
        sum(s_anchor[b] - s_anchor[a] - da[a] for a, b in zip(idx[1:-1], idx[2:], strict=True))
        + s_anchor[idx[1]]
    )
    return GuidedPath(bb, idx, gaps, float(total), float(np.sum(off_seg)),
                      float(skipped + tail), float(tail), float(bey))  # fmt: skip


def _densified(bb: np.ndarray, gaps, step: float) -> tuple[np.ndarray, list]:
    """``bb`` with every non-gap segment densified to ``step`` px; the gaps re-indexed."""
    gap_set = {a for a, _ in gaps}
    out, new_gaps = [bb[:1]], []
    for m in range(len(bb) - 1):
        p, q = bb[m], bb[m + 1]
        if m in gap_set:
            new_gaps.append((sum(len(o) for o in out) - 1, sum(len(o) for o in out)))
            out.append(q[None])
            continue
        k = max(int(np.ceil(np.linalg.norm(q - p) / step)), 1)
        out.append(p + (q - p) * (np.arange(1, k + 1) / k)[:, None])
    return np.concatenate(out), new_gaps


def _on_axis(E, bb: np.ndarray, width: float, level: float, passes: int = 2) -> np.ndarray:
    """``bb`` (n, 2) with each point moved across the path onto the centre of the evidence
    run through it (profile of ``E`` along the path's normal, +-1.5 widths, 0.5 px steps),
    where that run is at most 1.6 widths wide (a run wider than the tube is a crossing or
    the tube's own fold: left alone); the path is smoothed over half a width after each
    pass. The programme's points are run centres on the epipolar lines, which lie off the
    tube's axis where it runs along the lines (a long run is cut into points every half
    width) and at its end (the end face cuts the run)."""
    bb = np.asarray(bb, np.float64).copy()
    if len(bb) < 3:
        return bb
    t = np.arange(-1.5 * width, 1.5 * width + 1e-9, 0.5)
    mid = len(t) // 2
    for _ in range(passes):
        tan = np.gradient(bb, axis=0)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
        nrm = np.stack([-tan[:, 1], tan[:, 0]], 1)
        prof = _sample(E, bb[:, None] + t[None, :, None] * nrm[:, None])  # (n, m)
        on = prof > level
        shift = np.zeros(len(bb))
        for i in range(len(bb)):
            if not on[i, mid]:
                continue
            lo = mid
            while lo > 0 and on[i, lo - 1]:
                lo -= 1
            hi = mid
            while hi < len(t) - 1 and on[i, hi + 1]:
                hi += 1
            if lo == 0 or hi == len(t) - 1 or t[hi] - t[lo] > 1.6 * width:
                continue
            wts = prof[i, lo : hi + 1] - level
            shift[i] = float(np.sum(wts * t[lo : hi + 1]) / max(np.sum(wts), 1e-12))
        bb = bb + shift[:, None] * nrm
        # Smooth along the path (ends kept).
        sig = max(
            1.0, 0.5 * width / max(np.median(np.linalg.norm(np.diff(bb, axis=0), axis=1)), 1e-6)
        )
        sm = ndi.gaussian_filter1d(bb, sig, axis=0, mode="nearest")
        sm[0], sm[-1] = bb[0], bb[-1]
        bb = sm
    return bb


def guided_candidate(
    cams,
    anchor_view: int,
    anchor,
    other,
    *,
    evidence=None,
    tip_mode: str = "refine",
    recentre: bool = True,
    **kw,
):
    """The other view's trace re-traced along ``anchor`` (:func:`guided_retrace`), as a
    :class:`jaxcr.segmentation.foreground.TubeTrace` with its tip refined on the score
    (:func:`jaxcr.segmentation.foreground.refine_tip_details`, with the settings and scale
    the trace was made with), or None.

    ``anchor``, ``other``: the two views' :class:`TubeTrace` (``other`` with ``score``,
    ``seed_mask``, ``entry``, ``width_px`` and, for the tip, ``retrace``).
    ``evidence``: :func:`evidence_map` of ``other.score`` (computed when None; pass it when
    several anchors guide the same view). ``tip_mode``: ``"refine"`` (the tip refined on
    the score, as the tracer does) or ``"line"`` (the path's end, where the anchor tip's
    epipolar line meets the tube's axis, taken as the tip; ``cap_px`` and
    ``end_half_width_px`` 0, so :func:`jaxcr.stereo.pipeline.trace_stereo_tips` leaves the
    pair's tips as they are). ``recentre``: the path moved onto the tube's axis first
    (:func:`_on_axis`). The candidate's ``crossings_followed`` and
    ``crossing_turn_deg`` are ``other``'s (the branch choice's gate and ranking treat it as
    neither smoother nor rougher than the trace it may replace), its ``departure`` is -1
    and ``guided`` holds the :class:`GuidedPath`. Keyword arguments go to
    :func:`guided_retrace`."""
    from jaxcr.segmentation.foreground import (
        PlateForegroundConfig,
        TubeTrace,
        _path_mask,
        _scaled,
        refine_tip_details,
    )

    w = float(other.width_px)
    if other.score is None or not np.all(np.isfinite(np.asarray(other.entry, np.float64))):
        return None
    if evidence is None:
        evidence = evidence_map(other.score, width_px=w)
    gp = guided_retrace(cams, anchor_view, anchor.backbone, evidence, other.entry, w, **kw)
    if gp is None or len(gp.backbone) < 3:
        return None
    ctx = getattr(other, "retrace", None)
    cfg = ctx.cfg if ctx is not None else PlateForegroundConfig()
    k = ctx.k if ctx is not None else 1
    bb, gaps = _densified(gp.backbone, gp.gaps, cfg.step_px * k)
    if recentre:
        bb = _on_axis(evidence, bb, w, 0.5)
    tip, cap, end_dir, half = bb[-1].copy(), 0.0, np.zeros(2), 0.0
    if tip_mode == "refine" and cfg.refine and len(bb) >= 3:
        tip, cap, end_dir, half = refine_tip_details(other.score, bb, w, _scaled(cfg, k))
        bb = np.vstack([bb[:-1], tip])
    elif tip_mode == "line":
        # The end on the anchor tip's epipolar line is the tip itself (no end face to
        # take off); the direction the chord over the last 1.5 widths.
        back = bb[np.linalg.norm(bb - bb[-1], axis=1) >= 1.5 * w]
        chord = bb[-1] - (back[-1] if len(back) else bb[0])
        n = float(np.linalg.norm(chord))
        end_dir = chord / n if n > 0 else np.zeros(2)
    mask = other.seed_mask if other.seed_mask is not None else other.score >= cfg.low
    tr = TubeTrace(_path_mask(mask, bb, gaps, w), bb, np.asarray(tip, np.float64),
                   np.asarray(other.entry, np.float64), gaps, shift=other.shift,
                   score=other.score, seed_mask=other.seed_mask, width_px=w, cap_px=cap,
                   scale=other.scale, measured_width_px=other.measured_width_px,
                   end_dir=np.asarray(end_dir, np.float64), end_half_width_px=half)  # fmt: skip
    tr.crossing_turn_deg = float(other.crossing_turn_deg)
    tr.crossings_followed = int(getattr(other, "crossings_followed", 0))
    tr.departure = -1
    tr.guided = gp
    return tr


def _within(path, line, dist: float) -> bool:
    """Whether every point of ``path`` (densified to 1 px) lies within ``dist`` px of the
    polyline ``line`` (densified to 1 px)."""
    a = resample_polyline(path, 1.0)
    b = resample_polyline(line, 1.0)
    if len(b) < 2:
        return False
    from scipy.spatial import cKDTree

    d, _ = cKDTree(b).query(a)
    return bool(np.all(d <= dist))


def guided_candidates(
    cams, traces, *, max_tail_widths: float = 2.0, absent: float = 0.3, low: float = 0.4,
    probe_widths: float = 2.0, prefix_widths: float = 0.75, cut_back: list | None = None,
    **kw,
) -> list[list]:  # fmt: skip
    """Per view, the candidates re-traced along the other view's trace (each view in turn
    the anchor; :func:`guided_candidate`): ``[[view 0 guided by view 1], [view 1 guided by
    view 0]]``, each list empty or one trace. Kept only when the anchor and the candidate
    both end where their tube ends (on the arc continuing each path's last stretch, 0.75 to
    ``0.75 + probe_widths`` widths beyond its tip, under ``absent`` of the score's samples
    reach ``low``, as :func:`jaxcr.stereo.tip_consistency.trim_unexplained_tail` tests an
    end) and the path explains the anchor to within ``max_tail_widths`` widths of its tip:
    an anchor that stopped at a junction with its tube going on, or a path along a wrong
    anchor that stops on a structure going on, is not offered. Nor is a path that lies
    along the view's own trace (every point within ``prefix_widths`` widths of it): it
    is that trace cut back, which the trim after the branch choice decides with its own
    evidence test (a wrong anchor that ran on past the tube's end finds the other view's
    trace cut short). ``cut_back``: a list, given, gets ``(j, path)`` for each view ``j``
    whose path along the other view's trace explains that trace to its end (within
    ``max_tail_widths``), the anchor ending where its tube ends, and lies along ``j``'s own
    trace (the path, not offered for that reason; :mod:`jaxcr.stereo.run_on` reads it)."""
    from jaxcr.stereo.tip_consistency import _beyond_evidence

    out = [[], []]
    for anchor_view in (0, 1):
        j = 1 - anchor_view
        anchor = traces[anchor_view]
        if not _beyond_evidence(anchor, anchor.tip, low, probe_widths) < absent:
            continue
        cand = guided_candidate(cams, anchor_view, anchor, traces[j], **kw)
        if cand is None:
            continue
        explained = cand.guided.tail_px <= max_tail_widths * float(anchor.width_px)
        along = _within(cand.backbone, traces[j].backbone, prefix_widths * cand.width_px)
        if explained and along and cut_back is not None:
            cut_back.append((j, cand))
        if explained and _beyond_evidence(cand, cand.tip, low, probe_widths) < absent and not along:
            out[j].append(cand)
    return out
