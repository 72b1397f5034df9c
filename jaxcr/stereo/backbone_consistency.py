"""Whether two views' traced backbones are images of one 3-D curve (issue 16 item 2: a
trace that took a wrong branch, stopped at a hook or ran on past the tube's end in one view).

The tip's epipolar check (:func:`jaxcr.stereo.pipeline.traced_stereo_tips`) looks at one
point of each trace; a wrong path whose end meets the other tip's epipolar line by chance
passes it, and a right path that the check flags cannot be told from a wrong one by its tip
alone. Here the whole backbones are compared. Both run from the robot's entry to its tip,
so corresponding points keep their order: they are matched by a monotone (dynamic time
warping) path through the symmetric epipolar distances of all sample pairs, from the two
entries to the two tips (:func:`jaxcr.stereo.correspondence.dtw_path`), each pair
of the path is triangulated (linear DLT, :func:`triangulate_pixels`) and reprojected into
both views. A backbone part that the other view cannot explain (a branch the other view
does not see, a stretch past the other view's end) is matched with a large reprojection
error; ``inconsistent_px`` is the length of such parts, in both views. Where a backbone
runs along the epipolar lines the matching is ambiguous but consistent, so it costs
nothing (the check is blind there, not wrong).

Pixels are distorted (as the camera records them) at the interface and undistorted inside
(:func:`jaxcr.stereo.tip_consistency.undistort_pixels`). Numpy float64 and cv2
(undistortion), per frame, at the edge of the stereo pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.correspondence import dtw_path, dtw_path_costs_np
from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses

__all__ = [
    "BackboneConsistency", "backbone_consistency", "fold_back_tip", "open_end_tails", "triangulate_pixels",
    "resample_polyline",
]  # fmt: skip


@dataclass
class BackboneConsistency:
    """Result of :func:`backbone_consistency`.

    ``pairs`` (p, 2) sample indices (view 1, view 2) of the monotone matching, from the
    entries to the tips; ``points`` (p, 3) their triangulated points (the cameras' shared
    frame, metres when the poses are; inf/NaN at infinity); ``reprojection_px`` (p,) the
    larger of the two views' reprojection errors of each pair (undistorted px);
    ``residual_px`` [(n1,), (n2,)] per sample of each view the smallest reprojection error
    of the pairs it is in; ``inconsistent_px`` the length (px, both views summed) of the
    samples whose residual exceeds ``tol_px``; ``length_px`` (2,) the two resampled
    backbones' lengths (undistorted); ``samples`` [(n1, 2), (n2, 2)] the resampled
    backbones (distorted pixels, what ``pairs`` and ``residual_px`` index); ``steps_px``
    (2,) their resampling steps."""

    pairs: np.ndarray
    points: np.ndarray
    reprojection_px: np.ndarray
    residual_px: list
    inconsistent_px: float
    length_px: np.ndarray
    samples: list
    steps_px: np.ndarray


def resample_polyline(line, step: float) -> np.ndarray:
    """The polyline ``line`` (n, 2) resampled at ``step`` (px) along its length, both ends
    kept; (m, 2), m >= 1."""
    line = np.asarray(line, np.float64).reshape(-1, 2)
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if len(line) < 2 or s[-1] <= 0:
        return line[:1].copy()
    t = np.arange(0.0, s[-1], step)
    t = np.r_[t, s[-1]]
    return np.stack([np.interp(t, s, line[:, 0]), np.interp(t, s, line[:, 1])], 1)


def _triangulate_h(P1, P2, x1, x2) -> np.ndarray:
    """(n, 4) unit homogeneous DLT points of the pixel pairs (:func:`triangulate_pixels`)."""
    P1, P2 = np.asarray(P1, np.float64), np.asarray(P2, np.float64)
    x1, x2 = np.asarray(x1, np.float64), np.asarray(x2, np.float64)
    A = np.stack(
        [
            x1[:, :1] * P1[2] - P1[0],
            x1[:, 1:] * P1[2] - P1[1],
            x2[:, :1] * P2[2] - P2[0],
            x2[:, 1:] * P2[2] - P2[1],
        ],
        axis=1,
    )  # (n, 4, 4)
    # Rows scaled to unit norm: the same null vector, better conditioned in float64.
    A = A / np.maximum(np.linalg.norm(A, axis=2, keepdims=True), 1e-300)
    _, _, vt = np.linalg.svd(A)
    return vt[:, -1]


def triangulate_pixels(P1, P2, x1, x2) -> np.ndarray:
    """Linear (DLT) triangulation of pixel pairs: ``P1``, ``P2`` (3, 4) projection matrices
    (``K [R | t]``), ``x1``, ``x2`` (n, 2) undistorted pixels; (n, 3) points, the smallest
    right singular vector of each pair's 4 x 4 system (as OpenCV ``triangulatePoints``);
    inf/NaN for a pair whose rays are parallel (a point at infinity)."""
    X = _triangulate_h(P1, P2, x1, x2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:]


def _project_h(P, Xh) -> np.ndarray:
    """Pixels (n, 2) of homogeneous points (n, 4): finite for points at infinity too
    (their image is the vanishing point of their direction)."""
    x = Xh @ np.asarray(P, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return x[:, :2] / x[:, 2:]


def _symmetric_epipolar(F, a, b) -> np.ndarray:
    """(n, m) the larger of the two point-to-epiline distances (px) of every pair of
    undistorted pixels ``a`` (n, 2) of view 1 and ``b`` (m, 2) of view 2."""
    ha = np.c_[a, np.ones(len(a))]
    hb = np.c_[b, np.ones(len(b))]
    l2 = ha @ F.T  # epilines in view 2 of a's points
    l1 = hb @ F  # epilines in view 1 of b's points
    l2 = l2 / np.maximum(np.hypot(l2[:, :1], l2[:, 1:2]), 1e-300)
    l1 = l1 / np.maximum(np.hypot(l1[:, :1], l1[:, 1:2]), 1e-300)
    d2 = np.abs(l2 @ hb.T)  # (n, m): b_j to the line of a_i
    d1 = np.abs(ha @ l1.T)  # (n, m): a_i to the line of b_j
    return np.maximum(d1, d2)


def backbone_consistency(
    cams, backbone1, backbone2, *, step_px: float = 2.0, tol_px: float = 3.0,
    cap_px: float = 50.0, max_samples: int = 600,
) -> BackboneConsistency:  # fmt: skip
    """How well two traced backbones are the two views of one 3-D curve (module docstring).

    ``cams``: two calibrated cameras (``K``, ``dist``, ``T_cam_robot``, one shared frame).
    ``backbone1``, ``backbone2``: (n, 2) distorted (u, v) pixels, each from the robot's
    entry to its tip. Both are resampled every ``step_px`` along their length (coarser if
    that gives more than ``max_samples`` samples); the matching's cost is the symmetric
    epipolar distance clipped at ``cap_px`` (a wrong stretch costs the same however far
    off it is). ``tol_px``: the reprojection error above which a sample is inconsistent
    (3 px: the tips' epipolar flag of 5 px split over two views, plus the calibration
    error's half pixel or so)."""
    ys, steps, samples = [], [], []
    for cam, bb in zip(cams, (backbone1, backbone2), strict=True):
        bb = np.asarray(bb, np.float64).reshape(-1, 2)
        length = float(np.sum(np.linalg.norm(np.diff(bb, axis=0), axis=1))) if len(bb) > 1 else 0.0
        st = max(step_px, length / max(max_samples - 1, 1))
        steps.append(st)
        samples.append(resample_polyline(bb, st))
        ys.append(undistort_pixels(cam, samples[-1]))
    K1, K2 = (np.asarray(c.K, np.float64) for c in cams)
    T1, T2 = (np.asarray(c.T_cam_robot, np.float64) for c in cams)
    F = fundamental_from_poses(K1, T1, K2, T2)
    cost = np.minimum(_symmetric_epipolar(F, ys[0], ys[1]), cap_px)
    pairs = dtw_path(cost)
    P1, P2 = K1 @ T1[:3], K2 @ T2[:3]
    Xh = _triangulate_h(P1, P2, ys[0][pairs[:, 0]], ys[1][pairs[:, 1]])
    # Reprojected from the homogeneous points: a pair of parallel rays (zero disparity,
    # a point at infinity) reprojects exactly, as it should.
    err = np.maximum(
        np.linalg.norm(_project_h(P1, Xh) - ys[0][pairs[:, 0]], axis=1),
        np.linalg.norm(_project_h(P2, Xh) - ys[1][pairs[:, 1]], axis=1),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:]
    err = np.where(np.isfinite(err), err, np.inf)
    residual = []
    for k in range(2):
        r = np.full(len(ys[k]), np.inf)
        np.minimum.at(r, pairs[:, k], err)
        residual.append(r)
    # Each sample stands for one step of its backbone (distorted and undistorted lengths
    # differ by the distortion's few per cent; the step is the distorted one).
    bad = sum(float(np.sum(r > tol_px)) * st for r, st in zip(residual, steps, strict=True))
    lengths = np.array([np.sum(np.linalg.norm(np.diff(y, axis=0), axis=1)) for y in ys])
    return BackboneConsistency(pairs, X, err, residual, bad, lengths, samples, np.array(steps))


def open_end_tails(
    cams, consistency: BackboneConsistency, *, tol_px: float = 3.0, cap_px: float = 50.0
) -> list[tuple[int, float, float]]:  # fmt: skip
    """Per view ``k``: where ``k``'s backbone stops being explained when the other view's
    backbone is matched whole, ``(i, tail_px, cost)``: ``i`` the last sample of ``k`` (an
    index into ``consistency.samples[k]``), ``tail_px`` the length of ``k`` beyond it and
    ``cost`` the match's (below; the smaller of the two views' is the better
    explanation: the other view's unexplained stretch, forced into the match, costs
    there).

    :func:`backbone_consistency` matches the two backbones from end to end, so a stretch
    that one view does not see is partly paired diagonally with the other view's last
    samples, and its unexplained length is shared between the two views' ends. Here the
    match is *open-ended* in ``k``: the monotone path runs from the entries to the other
    view's tip and to any sample ``i`` of ``k``, and each of ``k``'s samples beyond ``i``
    costs ``2 tol_px`` (a pair over twice the inconsistency level is better left
    unmatched; matched pairs cost their symmetric epipolar distance clipped at
    ``cap_px``, as in :func:`backbone_consistency`). ``i`` minimises the path's cost plus
    that tail cost (a standard open-end DTW on the same cost matrix)."""
    ys = [undistort_pixels(c, s) for c, s in zip(cams, consistency.samples, strict=True)]
    K1, K2 = (np.asarray(c.K, np.float64) for c in cams)
    T1, T2 = (np.asarray(c.T_cam_robot, np.float64) for c in cams)
    F = fundamental_from_poses(K1, T1, K2, T2)
    D, _ = dtw_path_costs_np(np.minimum(_symmetric_epipolar(F, ys[0], ys[1]), cap_px))
    pen = 2.0 * tol_px
    out = []
    for k in range(2):
        last = D[:, -1] if k == 0 else D[-1, :]  # k cut at i, the other view whole
        n = len(last)
        total = last + pen * (n - 1 - np.arange(n))
        i = int(np.argmin(total))
        out.append((i, float(consistency.steps_px[k]) * (n - 1 - i), float(total[i])))
    return out


def fold_back_tip(
    cams, consistency: BackboneConsistency, widths, *, tol_px: float = 3.0,
    cap_px: float = 50.0,
) -> tuple[int, np.ndarray, float] | None:  # fmt: skip
    """A view whose tube hooks back over its own silhouette: the view ``j`` and its tip
    (distorted (u, v)) on the way back, or None.

    Where the tube bends back towards a camera, its return runs over its outgoing part in
    that view's image, so the tracer stops at the fold and the tip lies inside the traced
    silhouette; the other view ``k`` sees the whole tube, whose end then has no partner
    on ``j``'s traced backbone. Hypothesis: ``j``'s tube goes on back along its own
    backbone (its samples followed by the same samples in reverse). ``k``'s whole backbone
    is matched (as in :func:`open_end_tails`) with ``j``'s backbone and its reverse, the
    match ending anywhere on the way back at least a tube width (``widths[j]``, px) past
    the fold. The fold is taken when that match costs less than the best explanation
    without it (either view's unexplained tail left unmatched at ``2 tol_px`` a sample,
    :func:`open_end_tails`) by more than a tube width of unmatched samples of ``k``, and
    explains ``k`` whole (the samples of ``k`` whose best pair along it is over
    ``tol_px`` from the epipolar line add up to at most ``widths[k]``), and the way back
    in ``j`` is no longer than the stretch of ``k`` that ``j``'s trace leaves unexplained
    (:func:`open_end_tails`: the return runs along camera ``j``'s rays, that is why it
    hides, so ``j`` sees it foreshortened; a long way back that ``k`` sees short is a
    chance match, and an overshoot of ``k`` the likelier story); the tip is ``j``'s sample
    where the match ends. Returns ``(j, tip, gain)`` for the larger
    gain (in the cost's px units) of the two views, None when neither passes."""
    ys = [undistort_pixels(c, s) for c, s in zip(cams, consistency.samples, strict=True)]
    K1, K2 = (np.asarray(c.K, np.float64) for c in cams)
    T1, T2 = (np.asarray(c.T_cam_robot, np.float64) for c in cams)
    F = fundamental_from_poses(K1, T1, K2, T2)
    pen = 2.0 * tol_px
    best = None
    for j in range(2):
        k = 1 - j
        n_j, n_k = len(ys[j]), len(ys[k])
        if n_j < 3:
            continue
        yj = np.vstack([ys[j], ys[j][-2::-1]])  # there and back
        a, b = (ys[k], yj) if k == 0 else (yj, ys[k])
        D, _ = dtw_path_costs_np(np.minimum(_symmetric_epipolar(F, a, b), cap_px))
        Dk = D[-1, :] if k == 0 else D[:, -1]  # k whole, j' open-ended
        Dj = D[:, n_j - 1] if k == 0 else D[n_j - 1, :]  # j whole (no fold), k open
        tail_k = Dj + pen * (n_k - 1 - np.arange(n_k))  # k cut, j whole
        nofold = min(float(np.min(Dk[:n_j] + pen * (n_j - 1 - np.arange(n_j)))),
                     float(np.min(tail_k)))  # fmt: skip
        tail_k_px = (n_k - 1 - int(np.argmin(tail_k))) * float(consistency.steps_px[k])
        first = n_j - 1 + int(np.ceil(float(widths[j]) / float(consistency.steps_px[j])))
        if first >= len(yj):
            continue
        i = first + int(np.argmin(Dk[first:]))
        gain = nofold - float(Dk[i])
        margin = pen * float(widths[k]) / float(consistency.steps_px[k])
        # The fold must explain k whole: along the folded match, k's samples whose best
        # pair is over tol_px off add up to at most a tube width.
        C = np.minimum(_symmetric_epipolar(F, a[: i + 1] if k == 1 else a,
                                           b if k == 1 else b[: i + 1]), cap_px)  # fmt: skip
        path = dtw_path(C)
        resid = np.full(n_k, np.inf)
        np.minimum.at(resid, path[:, 0 if k == 0 else 1], C[path[:, 0], path[:, 1]])
        left = float(np.sum(resid > tol_px)) * float(consistency.steps_px[k])
        back_px = (i - (n_j - 1)) * float(consistency.steps_px[j])
        if (
            gain > margin and left <= float(widths[k]) and back_px <= tail_k_px
            and (best is None or gain > best[2])
        ):  # fmt: skip
            src = consistency.samples[j]
            tip = np.vstack([src, src[-2::-1]])[i]
            best = (j, np.asarray(tip, np.float64), gain)
    return best
