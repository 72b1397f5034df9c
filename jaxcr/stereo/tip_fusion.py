"""The tube's end fused from both views along the tube (issue 16 item 2, docs/decisions.md S40).

Each view's tip is a measurement of one 3-D point, the tube's end: precise across the tube
(the two edges fix it), imprecise along it (where the end face is: shading, blur, a
background of the tube's colour). Model each view's tip ``x_k`` (undistorted pixels) as the
projection of the end ``X`` plus a Gaussian error of covariance

    C_k = s_along_k^2 d_k d_k^T + s_across^2 n_k n_k^T + s_cal_k^2 I

(``d_k`` the unit end direction in the image, ``n_k`` its normal; ``s_cal_k`` the rig's
calibration error seen as pixel noise in view ``k``, from
:func:`jaxcr.stereo.epipolar_tolerance.epipolar_sigma_px`). The end is the ``X``
minimising the Mahalanobis reprojection error ``sum_k r_k^T C_k^-1 r_k``, ``r_k =
pi_k(X) - x_k`` (:func:`mahalanobis_triangulate`).

The fused tips are not the end's projections through the calibrated cameras: those are
epipolar-consistent under the calibration, while the true tips are not (the rig's
calibration error puts right tips 1.5 px median, p90 3.5 px, off each other's epipolar
lines on the real_like preset, S27), so reprojecting moves right tips by the calibration's
own offset. Each view's residual ``x_k - pi_k(X)`` is the calibration's offset plus the
tip's placement error, independent and Gaussian in the model; the fused tip is the
measured one minus the placement error's estimate, ``x_k - C_meas,k C_k^-1 (x_k -
pi_k(X))`` (``output="noise_removed"``; ``"reprojected"`` is kept for comparison).

What it can and cannot do. Two views give four coordinates of three unknowns: one
redundancy, the epipolar residual. To first order the fused tips differ from the measured
ones only by moving each view along ``C_k m_k`` (``m_k`` the epipolar line's normal in view
``k``) until the residual is shared out in proportion to ``m_k^T C_k m_k``. A view whose
end line crosses the epipolar lines at angle ``theta_k`` turns an along-tube error ``e``
into a residual ``e sin theta_k``; with the along variance dominant it is moved back along
the tube by up to ``e`` (the other view's along-tube evidence, carried through the 3-D
tube). Where the tube runs along the epipolar lines (``theta -> 0``) the along-tube
disagreement leaves no residual and nothing moves: not observable. The calibration term
bounds what the fusion does with the residual the calibration error makes itself: a right
pair with an epipolar residual ``r`` is moved along the tube by at most about
``s_along / 4 * r / s_cal`` (at ``sin theta = s_cal / s_along``), not ``r / sin theta``.

This differs from :mod:`jaxcr.stereo.joint_end` (S27, lost 163 -> 144 on development): that
fit carried the other view's end along the 3-D axis with an L1 cost where one view decides,
and no term for the calibration error, so a right view inherited the rig's epipolar error
divided by ``sin theta`` (3.2 px median). Here the calibration error is in each view's
covariance and the cost is quadratic: the views compromise in proportion to their
variances, and a small angle damps the move instead of amplifying it.

Pixels are undistorted (pinhole) inside; :func:`fuse_tips` takes and returns distorted
pixels. Poses ``T_cam_world`` (4, 4), any world frame shared by both cameras. Numpy float64,
host side, one frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.epipolar_tolerance import CalibrationUncertainty, epipolar_sigma_px
from jaxcr.stereo.tip_consistency import _distort, undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses

__all__ = [
    "FusedTips",
    "end_covariance",
    "end_falloff_px",
    "mahalanobis_triangulate",
    "fuse_tips",
    "fuse_traced_tips",
]


def end_covariance(direction, sigma_along: float, sigma_across: float, sigma_iso: float = 0.0):
    """The 2x2 pixel covariance of a tube's end: ``sigma_along`` (px) along the unit image
    direction ``direction`` (2,), ``sigma_across`` across it, plus ``sigma_iso^2 I``."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    n = np.array([-d[1], d[0]])
    return (sigma_along**2 * np.outer(d, d) + sigma_across**2 * np.outer(n, n)
            + sigma_iso**2 * np.eye(2))  # fmt: skip


def _dlt(Ps, xs) -> np.ndarray:
    A = np.concatenate(
        [[x[0] * P[2] - P[0], x[1] * P[2] - P[1]] for P, x in zip(Ps, xs, strict=True)]
    )
    X = np.linalg.svd(A)[2][-1]
    return X[:3] / X[3]


def _project_jac(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pixel (2,) of ``X`` and its Jacobian (2, 3) with respect to ``X``."""
    p = K @ (T[:3, :3] @ X + T[:3, 3])
    uv = p[:2] / p[2]
    KR = K @ T[:3, :3]
    J = (KR[:2] - uv[:, None] * KR[2][None]) / p[2]
    return uv, J


def mahalanobis_triangulate(Ks, Ts, xs, covs, *, iters: int = 50, tol: float = 1e-12):
    """The 3-D point ``X`` minimising ``sum_k (pi_k(X) - x_k)^T C_k^-1 (pi_k(X) - x_k)``.

    ``Ks`` (3, 3) intrinsics and ``Ts`` (4, 4) ``T_cam_world`` of the views, ``xs`` their
    undistorted pixels (2,), ``covs`` the pixels' covariances (2, 2) (positive definite).
    Gauss-Newton from the linear (DLT) point, Levenberg-damped where a step does not lower
    the cost. Returns ``(X, cost)`` (world frame; the minimised sum, a chi-square with one
    degree of freedom for two views under the model)."""
    Ks = [np.asarray(K, np.float64) for K in Ks]
    Ts = [np.asarray(T, np.float64) for T in Ts]
    xs = [np.asarray(x, np.float64) for x in xs]
    Ws = [np.linalg.inv(np.asarray(C, np.float64)) for C in covs]
    X = _dlt([K @ T[:3] for K, T in zip(Ks, Ts, strict=True)], xs)

    def cost_of(X):
        c = 0.0
        for K, T, x, W in zip(Ks, Ts, xs, Ws, strict=True):
            r = _project_jac(K, T, X)[0] - x
            c += float(r @ W @ r)
        return c

    cost, lam = cost_of(X), 0.0
    for _ in range(iters):
        H, g = np.zeros((3, 3)), np.zeros(3)
        for K, T, x, W in zip(Ks, Ts, xs, Ws, strict=True):
            uv, J = _project_jac(K, T, X)
            H += J.T @ W @ J
            g += J.T @ W @ (uv - x)
        while True:
            step = np.linalg.solve(H + lam * np.diag(np.diag(H)), -g)
            new = cost_of(X + step)
            if new <= cost or lam > 1e8:
                break
            lam = max(10.0 * lam, 1e-6)
        if new > cost:
            break
        done = cost - new <= tol * max(cost, 1e-30) or np.linalg.norm(step) <= 1e-15 * (
            1.0 + np.linalg.norm(X)
        )
        X, cost, lam = X + step, new, lam * 0.1
        if done:
            break
    return X, cost


def end_falloff_px(score: np.ndarray, tip, direction, half_width: float, *, step: float = 0.5):
    """How sharply the cue ``score`` (H, W) falls off at a view's end, in px: the score
    averaged over the central half width, sampled along ``direction`` (unit, out of the
    tip) from 3 widths behind ``tip`` to 2.5 past (distorted pixels, as the trace's score),
    and the 20-80 % rise distance of that profile between its inside level (1-2.5 widths
    behind) and its outside level (1.5-2.5 widths past), the crossing points taken from the
    outside in. NaN where the profile has no step (inside not above outside)."""
    from scipy import ndimage as ndi

    tip, d = np.asarray(tip, np.float64), np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    n = np.array([-d[1], d[0]])
    w = 2.0 * half_width
    tau = np.arange(-3.0 * w, 2.5 * w + 1e-9, step)
    tt = np.linspace(-0.5, 0.5, 5) * half_width
    pts = tip[None, None] + tau[:, None, None] * d + tt[None, :, None] * n
    sc = ndi.map_coordinates(np.asarray(score, np.float64), [pts[..., 1].ravel(),
                             pts[..., 0].ravel()], order=1, mode="nearest")  # fmt: skip
    prof = sc.reshape(len(tau), len(tt)).mean(1)
    inside = float(np.median(prof[(tau >= -2.5 * w) & (tau <= -w)]))
    outside = float(np.median(prof[tau >= 1.5 * w]))
    if not inside > outside:
        return float("nan")
    f = (prof - outside) / (inside - outside)

    # From the outside in: the last sample (largest tau) above each level.
    def last_above(level):
        idx = np.flatnonzero(f >= level)
        if not len(idx) or idx[-1] + 1 >= len(tau):
            return float("nan")
        i = idx[-1]
        a, b = f[i], f[i + 1]
        return float(tau[i] + step * (a - level) / max(a - b, 1e-12))

    return float(last_above(0.2) - last_above(0.8))


@dataclass
class FusedTips:
    """Result of :func:`fuse_tips`: ``tips`` [(2,), (2,)] the fused end's projections
    (distorted pixels), ``point`` (3,) the end (the cameras' world frame), ``chi2`` the
    minimised Mahalanobis cost, ``moved_px`` (2,) how far each view's tip moved, ``sin``
    (2,) the sine of each view's end line's angle to the epipolar line through its tip,
    ``sigma_along`` (2,) the along-tube standard deviations used (px), ``sigma_cal`` (2,)
    the calibration's pixel noise per view, ``applied`` whether ``tips`` replaced the
    input (False: a gate kept them; ``reason`` says which)."""

    tips: list
    point: np.ndarray
    chi2: float
    moved_px: np.ndarray
    sin: np.ndarray
    sigma_along: np.ndarray
    sigma_cal: np.ndarray
    applied: bool
    reason: str


def _epipolar_sines(Ks, Ts, xs, dirs) -> np.ndarray:
    F = fundamental_from_poses(Ks[0], Ts[0], Ks[1], Ts[1])
    lines = [F.T @ np.r_[xs[1], 1.0], F @ np.r_[xs[0], 1.0]]  # epiline in view 0, view 1
    out = []
    for ln, d in zip(lines, dirs, strict=True):
        m = ln[:2] / np.hypot(ln[0], ln[1])  # the line's normal
        out.append(abs(float(m @ d)))
    return np.array(out)


def fuse_tips(
    cams, tips, dirs, *, sigma_along, calibration: CalibrationUncertainty,
    sigma_across: float = 0.5, min_sin: float = 0.0, max_chi2: float = float("inf"),
    output: str = "noise_removed",
) -> FusedTips | None:  # fmt: skip
    """The two views' tips corrected by the end triangulated with each view's along/across
    covariance (module docstring).

    ``output``: ``"reprojected"``, the end's projections through the calibrated cameras
    (epipolar-consistent under the calibration, so a right pair is moved by the
    calibration's own epipolar offset); ``"noise_removed"`` (default), each tip minus its
    placement error's estimate ``C_meas,k C_k^-1 (x_k - pi_k(X))`` (the residual shared
    between the calibration's offset and the placement error by their covariances: the
    Gaussian posterior mean of the true pixel, to first order).

    ``cams``: the two calibrated cameras (``K``, ``dist``, ``T_cam_robot``); ``tips``: the
    two tips (distorted (u, v)), consistent within the rig's epipolar tolerance (the caller
    checks); ``dirs``: each view's unit end direction (distorted image, out of the tip);
    ``sigma_along``: (2,) each view's along-tube standard deviation (px);
    ``calibration``: the rig's calibration uncertainty, whose epipolar standard deviation
    per image (tips' placement removed) is split evenly between the views as isotropic
    pixel noise; ``sigma_across``: the across-tube standard deviation (px). Gates (the
    input tips kept, ``applied`` False): an end line within ``asin(min_sin)`` of its
    epipolar line in either view, or a chi-square over ``max_chi2`` (the views disagree
    beyond the model: one is off by more than its covariance says). None when a tip or
    direction is not finite or the point is not in front of both cameras."""
    tips = [np.asarray(t, np.float64) for t in tips]
    dirs = [np.asarray(d, np.float64) for d in dirs]
    sig_a = np.asarray(sigma_along, np.float64)
    if not all(np.all(np.isfinite(v)) for v in [*tips, *dirs, sig_a]):
        return None
    if any(np.linalg.norm(d) == 0 for d in dirs):
        return None
    Ks = [np.asarray(c.K, np.float64) for c in cams]
    Ts = [np.asarray(c.T_cam_robot, np.float64) for c in cams]
    xs = [undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True)]
    du = []
    for c, t, d, x in zip(cams, tips, dirs, xs, strict=True):
        v = undistort_pixels(c, t + 5.0 * d / np.linalg.norm(d))[0] - x
        du.append(v / np.linalg.norm(v))
    sig = epipolar_sigma_px(cams, tips, calibration)
    if sig is None:
        return None
    # Each image's epipolar variance, the two tips' placement taken out, shared by the views.
    s_cal = np.sqrt(np.maximum(np.max(sig) ** 2 - 2.0 * calibration.tip_px**2, 0.0) / 2.0)
    s_cal = np.array([s_cal, s_cal])
    meas = [end_covariance(d, a, sigma_across) for d, a in zip(du, sig_a, strict=True)]
    covs = [C + c**2 * np.eye(2) for C, c in zip(meas, s_cal, strict=True)]
    X, chi2 = mahalanobis_triangulate(Ks, Ts, xs, covs)
    if not all((T[:3, :3] @ X + T[:3, 3])[2] > 0 for T in Ts):
        return None
    sin = _epipolar_sines(Ks, Ts, xs, du)
    proj = [_project_jac(K, T, X)[0] for K, T in zip(Ks, Ts, strict=True)]
    if output == "reprojected":
        est = proj
    elif output == "noise_removed":
        # The residual x_k - pi_k(X) is the calibration's offset plus the tip's placement
        # error; only the latter's estimate (its share by covariance) is taken out.
        est = [x - Cm @ np.linalg.solve(Ct, x - p)
               for x, p, Cm, Ct in zip(xs, proj, meas, covs, strict=True)]  # fmt: skip
    else:
        raise ValueError(f"output must be 'noise_removed' or 'reprojected', not {output!r}")
    new = [_distort(c, p[None])[0] for c, p in zip(cams, est, strict=True)]
    moved = np.array([np.linalg.norm(a - b) for a, b in zip(new, tips, strict=True)])
    reason = "fused"
    if np.min(sin) < min_sin:
        reason = "along_epipolar"
    elif chi2 > max_chi2:
        reason = "disagree"
    applied = reason == "fused"
    return FusedTips(new if applied else tips, X, float(chi2), moved, sin, sig_a, s_cal,
                     applied, reason)  # fmt: skip


#: The along-tube standard deviation (px) where a view's cue has no step at the end.
NO_STEP_PX = 8.0


def fuse_traced_tips(
    cams, traces, tips, calibration: CalibrationUncertainty, *, sigma_along_px: float | None = 8.0,
    sigma_across_px: float = 1.0, falloff_gain: float = 1.0, floor_px: float = 1.0,
    min_sin: float = 0.1, max_chi2: float = float("inf"), output: str = "noise_removed",
) -> FusedTips | None:  # fmt: skip
    """:func:`fuse_tips` for two traced views (as :func:`jaxcr.stereo.pipeline.
    traced_stereo_tips` calls it on tips it found consistent). Each view's along-tube
    standard deviation is ``sigma_along_px``, or, where None, ``hypot(floor_px,
    falloff_gain * falloff)`` with ``falloff`` the cue's fall-off at its end
    (:func:`end_falloff_px` on the trace's ``score``; ``NO_STEP_PX`` where there is no
    step). The defaults (8 px along, 1 px across, both end lines at least asin 0.1 from the
    epipolar lines) are the variant chosen on the even development seeds
    (docs/decisions.md S40; the fall-off's weights lost there). ``traces``: objects with
    ``score``, ``end_dir`` and ``end_half_width_px``
    (:class:`jaxcr.segmentation.foreground.TubeTrace`)."""
    dirs, sig = [], []
    for t, p in zip(traces, tips, strict=True):
        d = np.asarray(t.end_dir, np.float64)
        dirs.append(d)
        if sigma_along_px is not None:
            sig.append(float(sigma_along_px))
            continue
        f = float("nan")
        if t.score is not None and t.end_half_width_px > 0 and np.linalg.norm(d) > 0:
            f = end_falloff_px(t.score, p, d, t.end_half_width_px)
        sig.append(float(np.hypot(floor_px, falloff_gain * (f if np.isfinite(f) else NO_STEP_PX))))
    return fuse_tips(cams, tips, dirs, sigma_along=sig, calibration=calibration,
                     sigma_across=sigma_across_px, min_sin=min_sin, max_chi2=max_chi2,
                     output=output)  # fmt: skip
