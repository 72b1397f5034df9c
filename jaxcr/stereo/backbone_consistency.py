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

from jaxcr.stereo.correspondence import dtw_path
from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses

__all__ = ["BackboneConsistency", "backbone_consistency", "triangulate_pixels", "resample_polyline"]


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
