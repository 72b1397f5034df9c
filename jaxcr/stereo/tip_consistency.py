"""Two views' tip pixels made epipolar-consistent by re-searching along the traced tubes
(issue 16 item 2, open item a: what to do when ``tip_epipolar_px`` flags a frame).

Each view's tracer (:func:`jaxcr.segmentation.foreground.plate_foreground`) follows the tube
on its own. When the two tips are more than ``flag_px`` from each other's epipolar lines,
one view's trace went past the tube's end (onto a shadow, a crease, a cable touching the
tip) or stopped short of it (the tube matching the background at its end). Which one is
decided by the images, not by a preference for either view:

* the *longer* view ``k`` is the one whose traced backbone crosses the epipolar line of the
  other view's tip (the last crossing along it, away from the end by more than
  ``min_cut_px``); the shorter view ``j``'s backbone does not reach the epipolar line of
  ``k``'s tip;
* in view ``j`` the tube's path beyond its tip is predicted by the arc of its last traced
  stretch (heading and curvature), up to where it meets the epipolar line of ``k``'s tip;
  the fraction of that path (past 0.75 tube widths from the tip, where the silhouette's
  rounded end lies; at least 3 px of it, else no decision) on which ``j``'s cue score is at
  least ``low`` (the hysteresis level) is the evidence that the tube goes on there;
* evidence below ``absent`` (0.3): the tube is absent beyond ``j``'s tip, so ``k``
  overshot: ``k``'s tip moves back along its own backbone to the crossing; evidence at or
  above ``present`` (0.6): ``j`` stopped short: ``j``'s tip moves on along the predicted
  path to the epipolar line of ``k``'s tip; between the two the tips are kept (and stay
  flagged).

A crossing where the backbone runs within ``min_angle_deg`` of the epipolar line is not
used (the tube lies near the epipolar plane there; the crossing is ill-conditioned).

Pixels are distorted (as the camera records them) at the interface and undistorted
inside. Numpy float64 and cv2 (undistortion) at the edge of the stereo pipeline, per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from jaxcr.segmentation.foreground import TubeTrace, end_before_hop
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses

__all__ = ["TipConsistency", "reconcile_tips", "trim_unexplained_tail"]


@dataclass
class TipConsistency:
    """Result of :func:`reconcile_tips`: ``tips`` [(2,), (2,)] distorted (u, v) pixels;
    ``action`` one of ``"consistent"``, ``"cut"`` (the longer view moved back), ``"extended"``
    (the shorter view moved on), ``"kept"`` (flagged, no decision), ``"no_crossing"``;
    ``"trimmed"`` and ``"rebranched"`` (the other view's end re-decided;
    :func:`trim_unexplained_tail`) and ``"folded"``
    (:func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
    :func:`jaxcr.stereo.backbone_consistency.fold_back_tip`);
    ``view`` the view (0 or 1) whose tip moved (None if none); ``evidence`` the fraction
    of the shorter view's predicted path with tube score (NaN if not measured);
    ``epipolar_px`` before and after."""

    tips: list
    action: str
    view: int | None
    evidence: float
    epipolar_before_px: float
    epipolar_after_px: float


def undistort_pixels(cam, uv) -> np.ndarray:
    """Pixels (..., 2) of ``cam`` with its lens distortion removed, as pixels of the same
    K (OpenCV ``undistortPoints`` with ``P=K``; host side, float64); shape (n, 2)."""
    pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
    K = np.asarray(cam.K, np.float64)
    return cv2.undistortPoints(pts, K, np.asarray(cam.dist, np.float64), P=K).reshape(-1, 2)


def _distort(cam, uv) -> np.ndarray:
    """Distorted pixels of undistorted pixels ``uv`` (n, 2) through ``cam``."""
    K = np.asarray(cam.K, np.float64)
    x = np.linalg.solve(K, np.c_[np.asarray(uv, np.float64), np.ones(len(uv))].T).T
    out, _ = cv2.projectPoints(x.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                               np.asarray(cam.dist, np.float64))  # fmt: skip
    return out.reshape(-1, 2)


def _densify(line: np.ndarray, step: float = 0.5) -> np.ndarray:
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if s[-1] <= 0:
        return line[:1].copy()
    t = np.arange(0.0, s[-1] + 1e-9, step)
    t = np.r_[t, s[-1]] if t[-1] < s[-1] else t
    return np.stack([np.interp(t, s, line[:, 0]), np.interp(t, s, line[:, 1])], 1)


def _epiline(F: np.ndarray, x: np.ndarray, to_second: bool) -> np.ndarray:
    """Normalised line (a, b, c) (a^2 + b^2 = 1) in the other image of undistorted ``x``."""
    h = np.r_[x, 1.0]
    ln = F @ h if to_second else F.T @ h
    return ln / np.hypot(ln[0], ln[1])


def _last_crossing(line_u: np.ndarray, ep: np.ndarray, min_angle: float):
    """Index position (float) of the last crossing of the polyline ``line_u`` (n, 2) with
    the line ``ep``, or None (none, or at a grazing angle)."""
    sd = line_u @ ep[:2] + ep[2]
    sign = np.sign(sd)
    idx = np.flatnonzero(sign[:-1] * sign[1:] <= 0)
    if not len(idx):
        return None
    i = int(idx[-1])
    seg = line_u[i + 1] - line_u[i]
    n = np.linalg.norm(seg)
    if n == 0:
        return float(i)
    if abs(seg @ ep[:2]) / n < np.sin(min_angle):  # grazing: along the epipolar line
        return None
    f = sd[i] / (sd[i] - sd[i + 1]) if sd[i] != sd[i + 1] else 0.0
    return i + float(np.clip(f, 0.0, 1.0))


def _predicted_path(bb: np.ndarray, window_px: float, length: float, step: float = 0.5):
    """Points (m, 2) continuing the polyline ``bb`` beyond its end on the circle fitted to its
    last ``window_px`` (heading and curvature), ``length`` px long (distorted pixels)."""
    d = _densify(bb, 0.5)
    seg = np.linalg.norm(np.diff(d, axis=0), axis=1)
    back = np.r_[np.cumsum(seg[::-1])[::-1], 0.0]
    tail = d[back <= window_px]
    if len(tail) < 3:
        tail = d[-3:]
    head = tail[-1] - tail[max(len(tail) - 5, 0)]
    theta = float(np.arctan2(head[1], head[0]))
    # Curvature from the turn of the tail's heading over its length.
    h0 = tail[min(4, len(tail) - 1)] - tail[0]
    turn = np.angle(np.exp(1j * (theta - np.arctan2(h0[1], h0[0]))))
    span = max(float(np.sum(np.linalg.norm(np.diff(tail, axis=0), axis=1))), 1e-9)
    kappa = turn / span
    s = np.arange(step, length + 1e-9, step)
    ang = theta + kappa * s
    pts = tail[-1] + np.cumsum(step * np.stack([np.cos(ang), np.sin(ang)], 1), axis=0)
    return pts


def reconcile_tips(
    cams, traces, tips, *, flag_px: float = 5.0, low: float = 0.4, absent: float = 0.3,
    present: float = 0.6, min_cut_px: float = 3.0, min_angle_deg: float = 20.0,
    max_extend_px: float = 80.0,
) -> TipConsistency:  # fmt: skip
    """Make the two views' tips epipolar-consistent (module docstring).

    ``cams``: two calibrated cameras (``K``, ``dist``, ``T_cam_robot`` in one frame).
    ``traces``: per view an object with ``backbone`` (n, 2) (u, v) from the entry to the tip
    and ``score`` (H, W) the cue score (as :class:`jaxcr.segmentation.foreground.TubeTrace`).
    ``tips``: the two current tips (distorted (u, v); e.g. :func:`jaxcr.stereo.pipeline.
    trace_stereo_tips`). ``flag_px``: epipolar distance above which a frame is re-searched;
    ``low``: the score level of tube pixels; ``absent``/``present``: evidence levels;
    ``min_cut_px``: a crossing nearer the tip than this is no overshoot; ``max_extend_px``:
    the longest extension searched."""
    tips = [np.asarray(t, np.float64) for t in tips]
    K0, K1 = (np.asarray(c.K, np.float64) for c in cams)
    T0, T1 = (np.asarray(c.T_cam_robot, np.float64) for c in cams)
    F = fundamental_from_poses(K0, T0, K1, T1)

    e0 = epipolar_gap_px(cams, tips)
    if not np.isfinite(e0) or e0 <= flag_px:
        return TipConsistency(tips, "consistent" if np.isfinite(e0) else "kept", None,
                              float("nan"), e0, e0)  # fmt: skip
    min_angle = np.radians(min_angle_deg)
    tu = [undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True)]
    # Epiline in view k of the other view's tip.
    lines = [_epiline(F, tu[1], to_second=False), _epiline(F, tu[0], to_second=True)]
    cross = []
    for k in range(2):
        bb = _densify(np.asarray(traces[k].backbone, np.float64), 0.5)
        bb = np.vstack([bb[:-1], tips[k]]) if len(bb) > 1 else tips[k][None]
        pos = _last_crossing(undistort_pixels(cams[k], bb), lines[k], min_angle)
        if pos is not None:
            i = int(np.floor(pos))
            f = pos - i
            pt = bb[i] if i + 1 >= len(bb) else (1 - f) * bb[i] + f * bb[i + 1]
            seg = np.linalg.norm(np.diff(bb, axis=0), axis=1)
            s_cross = float(np.sum(seg[:i]) + f * (seg[i] if i < len(seg) else 0.0))
            cut = float(np.sum(seg)) - s_cross
            cross.append((pt, cut) if cut > min_cut_px else None)
        else:
            cross.append(None)
    longer = [k for k in range(2) if cross[k] is not None]
    if len(longer) != 1:
        return TipConsistency(tips, "no_crossing" if not longer else "kept", None,
                              float("nan"), e0, e0)  # fmt: skip
    k = longer[0]
    j = 1 - k
    # The shorter view's predicted continuation up to the epiline of k's tip.
    bbj = np.asarray(traces[j].backbone, np.float64)
    bbj = np.vstack([bbj[:-1], tips[j]]) if len(bbj) > 1 else tips[j][None]
    w = 24.0
    path = _predicted_path(bbj, w, max_extend_px)
    sd = undistort_pixels(cams[j], path) @ lines[j][:2] + lines[j][2]
    s0 = float(undistort_pixels(cams[j], tips[j][None])[0] @ lines[j][:2] + lines[j][2])
    hit = np.flatnonzero(np.sign(sd) != np.sign(s0))
    if not len(hit):  # the predicted path never reaches the line: no decision
        return TipConsistency(tips, "kept", None, float("nan"), e0, e0)
    path = path[: int(hit[0]) + 1]
    # The silhouette's rounded end covers the first half width or so beyond the tip: the
    # evidence is taken past 0.75 widths, on at least 3 px.
    skip = int(np.ceil(0.75 * float(getattr(traces[j], "width_px", 5.0)) / 0.5))
    probe = path[skip:]
    if len(probe) < 6:
        return TipConsistency(tips, "kept", None, float("nan"), e0, e0)
    sc = ndi.map_coordinates(np.asarray(traces[j].score, np.float64),
                             [probe[:, 1], probe[:, 0]], order=1, mode="nearest")  # fmt: skip
    evidence = float(np.mean(sc >= low))
    new = [t.copy() for t in tips]
    if evidence < absent:
        new[k] = cross[k][0]
        action, view = "cut", k
    elif evidence >= present:
        new[j] = path[-1]
        action, view = "extended", j
    else:
        return TipConsistency(tips, "kept", None, evidence, e0, e0)
    return TipConsistency(new, action, view, evidence, e0, epipolar_gap_px(cams, new))


def trim_unexplained_tail(
    cams, traces, tips, consistency, *, tol_px: float = 3.0, low: float = 0.4,
    absent: float = 0.3, probe_widths: float = 2.0, tails=None,
) -> TipConsistency | None:  # fmt: skip
    """A view's trace that ran on past the tube's end, cut where the other view's tube
    ends, told by the two whole backbones (issue 16 item 2: an overshoot along a shadow,
    a crease or a crossing object that comes back near the other tip's epipolar line, so
    that the tips' own check cannot place the cut).

    ``consistency``: :func:`jaxcr.stereo.backbone_consistency.backbone_consistency` of the
    two backbones ending at ``tips`` (distorted (u, v)). Its monotone matching pairs the
    last sample of view ``j``'s backbone with a stretch of view ``k``'s: from the first
    sample paired with it to ``k``'s end. That stretch is ``k``'s *unexplained tail* when
    it is longer than ``k``'s tube width and over half of its samples reproject more than
    ``tol_px`` off (a tube pointing at camera ``j`` also pairs a stretch of ``k`` with
    ``j``'s last sample, but consistently: its points lie on ``j``'s ray through the tip).
    Exactly one view with such a tail, and no tube beyond ``j``'s tip (on the arc
    continuing ``j``'s last traced stretch, from 0.75 to ``0.75 + probe_widths`` tube
    widths beyond the tip, under ``absent`` of the samples have a cue score of at least
    ``low``, as in :func:`reconcile_tips`): ``k``'s tip moves back to the first sample
    paired with ``j``'s tip (action ``"trimmed"``). Else None (nothing decided).

    ``tails``: per view ``(i, tail_px, cost)`` from the open-ended match
    (:func:`jaxcr.stereo.backbone_consistency.open_end_tails`, which places an unseen
    stretch in the view that has it instead of sharing it between the two ends). Given,
    a view ``k`` has an unexplained tail when ``tail_px`` exceeds its tube width; of the
    views with one and no tube beyond the other view's tip (the test above), the one whose
    open-ended match costs less is cut back to its sample ``i`` (the better
    explanation of the two backbones), or, where its path hops across background within
    two tube widths behind that sample, to the silhouette's end before the hop
    (:func:`jaxcr.segmentation.foreground.end_before_hop`: a point past the hop is not on
    the tube; docs/decisions.md S17). Where instead ``k``'s path passes no junction and no
    bridged gap from two widths behind that sample to its end (a tracer leaves a tube only
    at a junction, across a gap or by such a hop), ``k``'s tip is taken as right and the
    other view's end is re-decided: the end of the branch of its mask, near its traced end,
    that crosses the epipolar line of ``k``'s tip and makes the two whole backbones
    consistent (action ``"rebranched"``, the other view moved; docs/decisions.md S19);
    where no branch does, ``k`` is cut as above."""
    if tails is not None:
        return _trim_open_end(cams, traces, tips, consistency, tails, low=low, absent=absent,
                              probe_widths=probe_widths)  # fmt: skip
    tips = [np.asarray(t, np.float64) for t in tips]
    pairs = np.asarray(consistency.pairs)
    tails = []
    for k in range(2):
        j = 1 - k
        n_j = len(consistency.samples[j])
        first = int(np.min(pairs[pairs[:, j] == n_j - 1, k]))
        res = np.asarray(consistency.residual_px[k])[first:]
        length = float(consistency.steps_px[k]) * (len(res) - 1)
        width = float(getattr(traces[k], "width_px", 5.0))
        unexplained = length > width and float(np.mean(res > tol_px)) > 0.5
        tails.append(first if unexplained else None)
    longer = [k for k in range(2) if tails[k] is not None]
    if len(longer) != 1:
        return None
    k = longer[0]
    j = 1 - k
    evidence = _beyond_evidence(traces[j], tips[j], low, probe_widths)
    if not evidence < absent:
        return None

    new = [t.copy() for t in tips]
    new[k] = np.asarray(consistency.samples[k][tails[k]], np.float64)
    return TipConsistency(
        new, "trimmed", k, evidence, epipolar_gap_px(cams, tips), epipolar_gap_px(cams, new)
    )


def epipolar_gap_px(cams, tips) -> float:
    """The larger distance (px) of each of two tips from the other's epipolar line, with the
    lens distortion removed: ``tips`` are distorted (u, v) in the two calibrated views
    ``cams``; inf when a tip is not finite."""
    if not all(np.all(np.isfinite(t)) for t in tips):
        return float("inf")
    K0, K1 = (np.asarray(c.K, np.float64) for c in cams)
    F = fundamental_from_poses(K0, cams[0].T_cam_robot, K1, cams[1].T_cam_robot)
    a, b = (undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True))
    return float(max(epipolar_distances(F, a, b)))


def _beyond_evidence(trace, tip, low: float, probe_widths: float) -> float:
    """Fraction of the arc continuing ``trace``'s last traced stretch beyond ``tip``, from
    0.75 to ``0.75 + probe_widths`` tube widths, with a cue score of at least ``low``; NaN
    when under 3 px of it lies in the image (no decision)."""
    tip = np.asarray(tip, np.float64)
    bb = np.asarray(trace.backbone, np.float64)
    bb = np.vstack([bb[:-1], tip]) if len(bb) > 1 else tip[None]
    w = float(getattr(trace, "width_px", 5.0))
    path = _predicted_path(bb, 24.0, (0.75 + probe_widths) * w)
    probe = path[int(np.ceil(0.75 * w / 0.5)) :]
    if len(probe) < 6:
        return float("nan")
    sc = ndi.map_coordinates(np.asarray(trace.score, np.float64),
                             [probe[:, 1], probe[:, 0]], order=1, mode="nearest")  # fmt: skip
    return float(np.mean(sc >= low))


def _trim_open_end(cams, traces, tips, consistency, tails, *, low, absent, probe_widths):
    """:func:`trim_unexplained_tail` with the open-ended tails (its docstring)."""
    tips = [np.asarray(t, np.float64) for t in tips]
    best = None
    for k in range(2):
        i, tail, cost = tails[k]
        if not tail > float(getattr(traces[k], "width_px", 5.0)):
            continue
        ev = _beyond_evidence(traces[1 - k], tips[1 - k], low, probe_widths)
        if ev < absent and (best is None or cost < best[2]):
            best = (k, i, cost, ev)
    if best is None:
        return None
    k, i, _, evidence = best

    new = [t.copy() for t in tips]
    new[k] = np.asarray(consistency.samples[k][i], np.float64)
    # A cut past a hop of the path across background: the tube ended before the hop.
    hop = end_before_hop(traces[k], new[k]) if isinstance(traces[k], TubeTrace) else None
    if hop is not None:
        new[k] = np.asarray(hop, np.float64)
    elif isinstance(traces[k], TubeTrace) and _tail_is_clean(traces[k], new[k]):
        # k's trace left no tube on the way to its tip: the other view's end is the wrong
        # one (docs/decisions.md S19).
        redo = _end_on_epiline(cams, traces, tips, 1 - k)
        if redo is not None:
            new = [t.copy() for t in tips]
            new[1 - k] = redo
            return TipConsistency(new, "rebranched", 1 - k, evidence,
                                  epipolar_gap_px(cams, tips), epipolar_gap_px(cams, new))  # fmt: skip
    return TipConsistency(
        new, "trimmed", k, evidence, epipolar_gap_px(cams, tips), epipolar_gap_px(cams, new)
    )


def _tail_is_clean(trace, cut_uv, *, behind_widths: float = 2.0) -> bool:
    """Whether ``trace``'s path beyond its point nearest ``cut_uv`` (and ``behind_widths``
    tube widths behind it) passes no junction and no bridged gap: a tracer leaves a tube
    only where something else touches it (a junction, :class:`jaxcr.segmentation.
    foreground.TubeTrace`), across background (a gap it bridged), or by a hop onto
    something just beyond the end (:func:`jaxcr.segmentation.foreground.end_before_hop`,
    tested by the caller). Junctions within two look lengths of the trace's end are the
    end's jitter, not branches (as :func:`jaxcr.segmentation.foreground.trace_alternatives`
    skips them)."""
    bb = np.asarray(trace.backbone, np.float64)
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    i_cut = int(np.argmin(np.linalg.norm(bb - np.asarray(cut_uv, np.float64)[None], axis=1)))
    w = float(max(trace.width_px, 2.0))
    start = cum[i_cut] - behind_widths * w
    ctx = getattr(trace, "retrace", None)
    look = (ctx.cfg.look_px if ctx is not None else 10.0) * int(getattr(trace, "scale", 1))
    for jn in trace.junctions:
        s = cum[min(int(jn[0]), len(cum) - 1)]
        if s >= start and cum[-1] - s >= 2.0 * look:
            return False
    return not any(cum[min(int(g[1]), len(cum) - 1)] >= start for g in trace.gaps)


def _mask_paths_from(mask: np.ndarray, sources: np.ndarray, limit: float):
    """Geodesic distances (8-neighbour steps of 1 and sqrt 2) inside ``mask`` (h, w) bool
    from the nearest of ``sources`` (m, 2) (row, col) pixels of it, up to ``limit``, and the
    predecessor of each pixel (negative at a source or unreached); flat indices."""
    h, w = mask.shape
    idx = np.arange(h * w).reshape(h, w)
    pad = np.pad(mask, 1)
    ipad = np.pad(idx, 1, constant_values=-1)
    rows, cols, wts = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ok = mask & pad[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w]
        rows.append(idx[ok])
        cols.append(ipad[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w][ok])
        wts.append(np.full(int(ok.sum()), np.hypot(dr, dc)))
    r, c, v = (np.concatenate(x) for x in (rows, cols, wts))
    graph = coo_matrix((v, (r, c)), shape=(h * w, h * w)).tocsr()
    src = np.unique(sources[:, 0] * w + sources[:, 1])
    dist, pred, _ = dijkstra(graph, directed=False, indices=src, min_only=True,
                          return_predecessors=True, limit=limit)  # fmt: skip
    return dist.reshape(h, w), pred


def _end_on_epiline(cams, traces, tips, j, *, reach_widths: float = 4.0,
                    extent_widths: float = 6.0, end_widths: float = 1.0,
                    min_angle_deg: float = 20.0):  # fmt: skip
    """View ``j``'s tube end re-decided by the other view ``k``'s tip (docs/decisions.md
    S19): the tip (2,) (distorted (u, v)), or None.

    ``k``'s tip is taken as right (its trace left no tube on the way, :func:`_tail_is_clean`),
    so the tube's end in ``j`` lies on the epipolar line of ``k``'s tip, at an end of ``j``'s
    silhouette. The branches of ``j``'s hysteresis mask (``seed_mask``) near its traced end
    are the geodesic paths inside the mask from ``j``'s path up to ``reach_widths`` tube
    widths before its end (the branch the trace took, the one it missed at a junction, the
    hook it stopped at) to the mask's extremities (local maxima of the geodesic distance
    over half a width, beyond one width from the path, within ``reach_widths +
    extent_widths`` widths). A branch is a candidate when its last crossing with the
    epipolar line (undistorted; the path's direction over a width at least
    ``min_angle_deg`` off the line, as in :func:`reconcile_tips`) is within
    ``end_widths`` widths of its extremity (the tube ends there: the end face's cap is
    under half a width, the rest is the calibration's error). Its tip is that crossing; of
    the candidates whose whole backbone, with ``k``'s, leaves neither view a stretch longer
    than its tube width unexplained (:func:`jaxcr.stereo.backbone_consistency.
    open_end_tails`: the 3-D lengths agree), the one with the least inconsistent length
    wins."""
    # backbone_consistency imports this module (undistort_pixels): imported here.
    from jaxcr.stereo.backbone_consistency import backbone_consistency, open_end_tails

    tr, k = traces[j], 1 - j
    if tr.seed_mask is None or len(tr.backbone) < 3:
        return None
    mask = np.asarray(tr.seed_mask, bool)
    H, W = mask.shape
    w = float(max(tr.width_px, 2.0))
    bb = np.vstack([np.asarray(tr.backbone, np.float64)[:-1], np.asarray(tips[j], np.float64)])
    bb = _densify(bb, 0.5)
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(bb, axis=0), axis=1))]
    keep = cum <= cum[-1] - reach_widths * w
    if keep.sum() < 2:
        return None
    limit = (reach_widths + extent_widths) * w
    near = bb[~keep]
    r0, c0 = (int(max(np.floor(near[:, a].min() - limit), 0)) for a in (1, 0))
    r1 = int(min(np.ceil(near[:, 1].max() + limit) + 1, H))
    c1 = int(min(np.ceil(near[:, 0].max() + limit) + 1, W))
    sub = mask[r0:r1, c0:c1]
    src = np.round(bb[keep][:, ::-1]).astype(int) - [r0, c0]
    inside = (src >= 0).all(1) & (src < sub.shape).all(1)
    src = src[inside]
    src = src[sub[src[:, 0], src[:, 1]]]
    if not len(src):
        return None
    dist, pred = _mask_paths_from(sub, src, limit)
    g = np.where(np.isfinite(dist), dist, -1.0)
    rad = max(int(round(0.5 * w)), 1)
    yy, xx = np.mgrid[-rad : rad + 1, -rad : rad + 1]
    peak = (g >= ndi.maximum_filter(g, footprint=yy**2 + xx**2 <= rad**2)) & (g > w)
    # A crop's cut edge (not the image's) makes false extremities.
    edge = np.zeros_like(peak)
    edge[:2, :] |= r0 > 0
    edge[-2:, :] |= r1 < H
    edge[:, :2] |= c0 > 0
    edge[:, -2:] |= c1 < W
    lab, n = ndi.label(peak & ~edge, structure=np.ones((3, 3)))
    if not n:
        return None
    ends = ndi.maximum_position(g, lab, np.arange(1, n + 1))
    K0, K1 = (np.asarray(c.K, np.float64) for c in cams)
    F = fundamental_from_poses(K0, cams[0].T_cam_robot, K1, cams[1].T_cam_robot)
    line = _epiline(F, undistort_pixels(cams[k], tips[k])[0], to_second=(j == 1))
    sin_min = np.sin(np.radians(min_angle_deg))
    flat_src = set((src[:, 0] * sub.shape[1] + src[:, 1]).tolist())
    best = None
    for e in ends:
        node, path = int(e[0] * sub.shape[1] + e[1]), []
        while node >= 0:
            path.append(node)
            if node in flat_src:
                break
            node = int(pred[node])
        path = np.array(path[::-1])
        uv = np.c_[path % sub.shape[1] + c0, path // sub.shape[1] + r0].astype(np.float64)
        if len(uv) < 3:
            continue
        uv = _densify(uv, 0.5)
        sd = undistort_pixels(cams[j], uv) @ line[:2] + line[2]
        cross = np.flatnonzero(np.sign(sd[:-1]) * np.sign(sd[1:]) <= 0)
        if not len(cross):
            continue
        i = int(cross[-1])
        seg = np.linalg.norm(np.diff(uv, axis=0), axis=1)
        if float(np.sum(seg[i:])) > end_widths * w:
            continue
        h = max(int(round(w)), 1)  # the direction over a width (a pixel path is a staircase)
        d = uv[min(i + h, len(uv) - 1)] - uv[max(i - h, 0)]
        if abs(d @ line[:2]) < sin_min * max(np.linalg.norm(d), 1e-9):
            continue
        f = sd[i] / (sd[i] - sd[i + 1]) if sd[i] != sd[i + 1] else 0.0
        tip = (1 - f) * uv[i] + f * uv[i + 1]
        # The new backbone: j's path to the branch's source, then the branch to the tip.
        i_src = int(np.argmin(np.linalg.norm(bb[keep] - uv[0][None], axis=1)))
        new_bb = np.vstack([bb[keep][: i_src + 1], uv[: i + 1], tip[None]])
        pair = [None, None]
        pair[j] = new_bb
        pair[k] = np.vstack([np.asarray(traces[k].backbone, np.float64)[:-1], tips[k]])
        bc = backbone_consistency(cams, pair[0], pair[1])
        tails = open_end_tails(cams, bc)
        widths = [float(max(t.width_px, 2.0)) for t in traces]
        if any(tails[v][1] > widths[v] for v in range(2)):
            continue
        if best is None or bc.inconsistent_px < best[1]:
            best = (tip, float(bc.inconsistent_px))
    return None if best is None else best[0]
