"""Stereo calibration from chessboard or circle-grid views with OpenCV, and whether the views
determine the fitted intrinsics.

:func:`calibrate_stereo` detects the target in grayscale image pairs (:func:`find_pattern`,
retried on a robot-free background plate with :func:`fill_from_plate`), fits each camera
(:func:`calibrate_camera`: ``cv2.calibrateCameraExtended`` under :class:`IntrinsicConstraints`,
with the predicted 1-sigma of every fitted intrinsic from the fit's Jacobian, marginalised over
the board poses) and the pair (``cv2.stereoCalibrateExtended`` with the intrinsics fixed).
:func:`identifiability_problems` says whether the views determine the intrinsics (Zhang 2000,
sec. 3.3: each board orientation gives two constraints on the pinhole intrinsics), with
:func:`views_summary` and :func:`advice` for the messages. Units: metres for the board,
pixels for the images; poses in the camera frame.

OpenCV on host numpy arrays, outside jit; writing the result is
:func:`jaxcr.io.calibration.save_calibration`, the command line ``jaxcr calibrate``
(:mod:`jaxcr.cli.calibrate`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


def board_points(pattern: str, cols: int, rows: int, square: float) -> np.ndarray:
    """(cols*rows, 3) object points of the calibration target (z = 0, metres), in the order
    OpenCV's detectors return them."""
    if pattern == "acircles":
        pts = [
            ((2 * c + r % 2) * square, r * square, 0.0) for r in range(rows) for c in range(cols)
        ]
        return np.array(pts, np.float32)
    g = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    return np.c_[g * square, np.zeros(len(g))].astype(np.float32)


def find_pattern(gray: np.ndarray, pattern: str, cols: int, rows: int) -> np.ndarray | None:
    """Sub-pixel image points (n, 2) of the target, or None when it is not found."""
    if pattern == "chessboard":
        ok, c = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
    else:
        flag = cv2.CALIB_CB_SYMMETRIC_GRID if pattern == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        ok, c = cv2.findCirclesGrid(gray, (cols, rows), flags=flag)
    return c.reshape(-1, 2).astype(np.float32) if ok else None


# ----------------------------------------------------------------- intrinsic constraints


@dataclass(frozen=True)
class IntrinsicConstraints:
    """Which intrinsics ``cv2.calibrateCamera`` keeps fixed (OpenCV's ``CALIB_*`` flags).

    Without an intrinsic guess OpenCV starts from the image centre ``((w-1)/2, (h-1)/2)`` and
    ``fx/fy`` of the camera matrix passed in (:func:`initial_camera_matrix`: 1), so
    ``fix_principal_point`` keeps the principal point at the image centre, and
    ``fix_aspect_ratio`` keeps ``fx = fy`` (square pixels). ``fix_k`` (subset of 1, 2, 3) and
    ``no_distortion`` keep those coefficients at 0; ``no_distortion`` also implies
    ``zero_tangent_dist`` (p1 = p2 = 0).
    """

    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    zero_tangent_dist: bool = False
    fix_k: tuple[int, ...] = ()
    no_distortion: bool = False

    def cv_flags(self) -> int:
        """The ``flags`` argument of ``cv2.calibrateCamera`` for these constraints."""
        f = 0
        if self.fix_principal_point:
            f |= cv2.CALIB_FIX_PRINCIPAL_POINT
        if self.fix_aspect_ratio:
            f |= cv2.CALIB_FIX_ASPECT_RATIO
        if self.zero_tangent_dist or self.no_distortion:
            f |= cv2.CALIB_ZERO_TANGENT_DIST
        ks = (1, 2, 3) if self.no_distortion else self.fix_k
        for k in ks:
            f |= {1: cv2.CALIB_FIX_K1, 2: cv2.CALIB_FIX_K2, 3: cv2.CALIB_FIX_K3}[k]
        return f

    def fitted(self) -> tuple[str, ...]:
        """Names of the fitted intrinsics: ``f`` (fx = fy) or ``fx, fy``; ``cx, cy``;
        the distortion coefficients left free."""
        names = ["f"] if self.fix_aspect_ratio else ["fx", "fy"]
        if not self.fix_principal_point:
            names += ["cx", "cy"]
        ks = (1, 2, 3) if self.no_distortion else self.fix_k
        for k in (1, 2):
            if k not in ks:
                names.append(f"k{k}")
        if not (self.zero_tangent_dist or self.no_distortion):
            names += ["p1", "p2"]
        if 3 not in ks:
            names.append("k3")
        return tuple(names)

    def describe(self) -> str:
        """Comma-separated flag names (``"none"`` when everything is fitted)."""
        on = [n for n in ("fix_principal_point", "fix_aspect_ratio", "zero_tangent_dist",
                          "no_distortion") if getattr(self, n)]  # fmt: skip
        on += [f"fix_k{k}" for k in self.fix_k if not self.no_distortion]
        return ",".join(on) or "none"


def initial_camera_matrix(size: tuple[int, int]) -> np.ndarray:
    """The camera matrix passed to OpenCV: fx = fy = 1 (only their ratio is used, for
    ``CALIB_FIX_ASPECT_RATIO``) and the principal point at the image centre."""
    w, h = size
    return np.array([[1.0, 0.0, (w - 1) / 2], [0.0, 1.0, (h - 1) / 2], [0.0, 0.0, 1.0]])


# -------------------------------------------------------------------- one camera's fit

# Detection noise floor (px) for the predicted uncertainties: sub-pixel corner and circle
# detectors on real images are rarely better than 0.1 px, and a fit that explains its own
# points exactly (an ill-posed one can) would otherwise look certain.
SIGMA_FLOOR_PX = 0.1
# Two board views whose normals are within this angle constrain the intrinsics alike (a
# plane's image of the absolute conic depends only on its orientation; Zhang 2000, sec. 3.3).
SAME_ORIENTATION_DEG = 5.0


@dataclass
class CameraCalibration:
    """One camera's calibration and how well its views determine it.

    ``K`` (3, 3) and ``dist`` (5,) as OpenCV returns them; ``rms`` and ``per_view_rms`` (n,)
    reprojection errors (px); ``rvecs``/``tvecs`` (n, 3) board poses (camera frame, metres);
    ``std`` maps each fitted intrinsic (:meth:`IntrinsicConstraints.fitted`) to its predicted
    1-sigma at ``sigma_px`` detection noise; ``ray_std_px`` the predicted 1-sigma (px) of where
    a fixed ray lands, worst over the image corners and centre (what a wrong focal length,
    principal point or distortion does to triangulation); ``tilt_deg`` (n,) angle between the
    board normal and the optical axis; ``distance`` (n,) distance to the board centre
    (metres); ``coverage`` fraction of the image inside the board's outline in some view;
    ``orientations`` number of distinct board orientations (normals more than
    ``SAME_ORIENTATION_DEG`` apart); ``std_intrinsics_cv`` (9,): OpenCV's own
    ``stdDeviationsIntrinsics`` of ``cv2.calibrateCameraExtended`` (fx fy cx cy k1 k2 p1 p2
    k3; 0 for a fixed parameter), which ``jaxcr calibrate`` writes to the calibration file's
    ``uncertainty`` block."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    rms: float
    per_view_rms: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    std: dict[str, float]
    sigma_px: float
    ray_std_px: float
    tilt_deg: np.ndarray
    distance: np.ndarray
    coverage: float
    orientations: int
    constraints: IntrinsicConstraints = field(default_factory=IntrinsicConstraints)
    std_intrinsics_cv: np.ndarray | None = None


def _intrinsic_map(K: np.ndarray, constraints: IntrinsicConstraints) -> np.ndarray:
    """(9, p) map from the fitted intrinsics to OpenCV's (fx fy cx cy k1 k2 p1 p2 k3)
    perturbations; with a fixed aspect ratio ``a = fx/fy`` a change d of f moves fx by a d
    and fy by d."""
    idx = {"fx": 0, "fy": 1, "cx": 2, "cy": 3, "k1": 4, "k2": 5, "p1": 6, "p2": 7, "k3": 8}
    names = constraints.fitted()
    M = np.zeros((9, len(names)))
    for j, n in enumerate(names):
        if n == "f":
            M[0, j], M[1, j] = K[0, 0] / K[1, 1], 1.0
        else:
            M[idx[n], j] = 1.0
    return M


def _marginal_std(J: np.ndarray, p: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """``(cov (p, p), free (p,))``: the covariance of the first ``p`` parameters of a
    Gauss-Newton fit with Jacobian ``J`` (rows: residuals of noise ``sigma``), marginalised
    over the rest, and which of them lie in a (numerically) unidentifiable direction."""
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    Js = J / norms
    _, s, Vt = np.linalg.svd(Js, full_matrices=False)
    # directions with singular values below 1e-9 of the largest are numerically free: float64
    # Gauss-Newton on a column-scaled Jacobian cannot tell them apart (cond^2 > 1e18 ~ 1/eps)
    good = s > 1e-9 * s[0]
    V = Vt.T
    cov = (V[:, good] / s[good] ** 2) @ V[:, good].T
    cov = cov / np.outer(norms, norms) * sigma**2
    free = np.any(np.abs(V[:p][:, ~good]) > 1e-6, axis=1)
    return cov[:p, :p], free


def calibrate_camera(
    obj: list[np.ndarray],
    img: list[np.ndarray],
    size: tuple[int, int],
    constraints: IntrinsicConstraints = IntrinsicConstraints(),  # noqa: B008 - frozen
) -> CameraCalibration:
    """``cv2.calibrateCameraExtended`` with the constraints' flags, plus the predicted
    uncertainty of the fitted intrinsics and the spread of board poses (see
    :class:`CameraCalibration`). ``obj`` (n_i, 3) board points (metres), ``img`` (n_i, 2)
    their detections (px), ``size`` (width, height)."""
    obj = [np.asarray(o, np.float32).reshape(-1, 3) for o in obj]
    img = [np.asarray(i, np.float32).reshape(-1, 2) for i in img]
    out = cv2.calibrateCameraExtended(
        obj, img, size, initial_camera_matrix(size), np.zeros(5), flags=constraints.cv_flags()
    )
    rms, K, D, rvecs, tvecs, std_cv, _, per_view = out
    D = np.asarray(D, np.float64).reshape(-1)[:5]
    rvecs = np.asarray(rvecs, np.float64).reshape(-1, 3)
    tvecs = np.asarray(tvecs, np.float64).reshape(-1, 3)
    # predicted uncertainty: J^T J of the reprojection residuals at the optimum (cv2's own
    # analytic Jacobian), intrinsics marginalised over every view's pose
    M = _intrinsic_map(K, constraints)
    p, n = M.shape[1], len(obj)
    rows = []
    for i, o in enumerate(obj):
        _, Jv = cv2.projectPoints(o, rvecs[i], tvecs[i], K, D)
        Jrow = np.zeros((Jv.shape[0], p + 6 * n))
        Jrow[:, :p] = Jv[:, 6:15] @ M
        Jrow[:, p + 6 * i : p + 6 * i + 6] = Jv[:, :6]
        rows.append(Jrow)
    J = np.concatenate(rows)
    dof = J.shape[0] - J.shape[1]
    # OpenCV's rms is per point (2-D residual norm), so per coordinate it is rms / sqrt(2);
    # sqrt(rows / dof) undoes the fit's absorption of the noise (unbiased variance)
    rms_coord = float(rms) / np.sqrt(2.0)
    sigma = max(rms_coord * np.sqrt(J.shape[0] / dof) if dof > 0 else 0.0, SIGMA_FLOOR_PX)
    cov, free = _marginal_std(J, p, sigma)
    std = {name: (np.inf if free[j] else float(np.sqrt(max(cov[j, j], 0.0))))
           for j, name in enumerate(constraints.fitted())}  # fmt: skip
    ray = _ray_std(K, D, size, M, cov, free)
    tilt, distance = _pose_spread(obj, rvecs, tvecs)
    return CameraCalibration(
        K=np.asarray(K, np.float64), dist=D, size=tuple(size), rms=float(rms),
        per_view_rms=np.asarray(per_view, np.float64).reshape(-1), rvecs=rvecs, tvecs=tvecs,
        std=std, sigma_px=sigma, ray_std_px=ray, tilt_deg=tilt, distance=distance,
        coverage=image_coverage(img, size), orientations=_n_orientations(rvecs),
        constraints=constraints,
        std_intrinsics_cv=np.asarray(std_cv, np.float64).reshape(-1)[:9],
    )  # fmt: skip


def _ray_std(K, D, size, M, cov, free) -> float:
    """Worst predicted 1-sigma (px) of the pixel a fixed ray lands on, over the image's
    corners and centre: the rays are the fitted model's own (cv2.undistortPoints)."""
    if np.any(free):
        return float("inf")
    w, h = size
    px = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2]],
                  np.float64)  # fmt: skip
    xy = cv2.undistortPoints(px.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    rays = np.c_[xy, np.ones(len(xy))]
    _, Jc = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, D)
    Jp = Jc[:, 6:15] @ M
    var = np.einsum("ij,jk,ik->i", Jp, cov, Jp).reshape(-1, 2).sum(axis=1)
    return float(np.sqrt(np.max(np.maximum(var, 0.0))))


def _pose_spread(obj, rvecs, tvecs) -> tuple[np.ndarray, np.ndarray]:
    """Per view: the angle (deg) between the board normal and the optical axis, and the
    distance (metres) from the camera to the board's centre."""
    tilt, dist = [], []
    for o, r, t in zip(obj, rvecs, tvecs, strict=True):
        R = cv2.Rodrigues(r)[0]
        n = R[:, 2]
        tilt.append(np.degrees(np.arctan2(np.hypot(n[0], n[1]), abs(n[2]))))
        dist.append(float(np.linalg.norm(R @ o.mean(axis=0) + t)))
    return np.array(tilt), np.array(dist)


def _n_orientations(rvecs) -> int:
    """Number of distinct board orientations: greedy clusters of normals (sign-free) within
    ``SAME_ORIENTATION_DEG``."""
    normals = [cv2.Rodrigues(r)[0][:, 2] for r in rvecs]
    reps: list[np.ndarray] = []
    cos_lim = np.cos(np.radians(SAME_ORIENTATION_DEG))
    for n in normals:
        if not any(abs(float(n @ m)) >= cos_lim for m in reps):
            reps.append(n)
    return len(reps)


def image_coverage(img: list[np.ndarray], size: tuple[int, int], cell: int = 4) -> float:
    """Fraction of the image inside the convex outline of the detected points in at least
    one view (rasterised at 1/``cell`` resolution)."""
    w, h = size
    mask = np.zeros(((h + cell - 1) // cell, (w + cell - 1) // cell), np.uint8)
    for pts in img:
        hull = cv2.convexHull(np.round(np.asarray(pts, np.float32) / cell).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1)
    return float(mask.mean())


# ---------------------------------------------------------------- is it determined?

MAX_STD = 0.05  # default refusal limit (--max-std): 5 % of f is a 5 % depth-scale error
WEAK_FRACTION = 0.2  # warn when an uncertainty exceeds this fraction of its refusal limit


def identifiability_problems(
    cal: CameraCalibration, max_std: float = MAX_STD
) -> tuple[list[str], list[str]]:
    """``(refusals, warnings)``, each a list of short sentences. Refused: fewer distinct
    board orientations than the fitted pinhole intrinsics need (two constraints each: two
    for fx, fy, cx, cy or f, cx, cy; one for fx, fy or f), a focal length whose predicted
    1-sigma exceeds ``max_std`` of itself, or a principal point whose 1-sigma exceeds
    ``max_std`` of the image's larger side. Warned: those above ``WEAK_FRACTION``
    of their limit, and a fixed ray's pixel at the image corners uncertain by more than
    ``WEAK_FRACTION * max_std`` of the half-diagonal (distortion extrapolated beyond the
    board's coverage: a warning, since the fitted region itself may be fine)."""
    w, h = cal.size
    checks = []
    for name, sd in cal.std.items():
        if name in ("f", "fx", "fy"):
            val = cal.K[0, 0] if name in ("f", "fx") else cal.K[1, 1]
            rel = sd / val if val > 0 else np.inf  # OpenCV can return f = 0 when it is free
            checks.append((rel, f"{name} = {val:.1f} +- {sd:.3g} px"))
        elif name in ("cx", "cy"):
            val = cal.K[0, 2] if name == "cx" else cal.K[1, 2]
            checks.append((sd / max(w, h), f"{name} = {val:.1f} +- {sd:.3g} px"))
    refuse = [t for r, t in checks if not r <= max_std]
    # Linear identifiability (Zhang 2000, sec. 3.3): each board orientation gives two
    # constraints on the pinhole intrinsics, so fx, fy, cx, cy need two distinct orientations
    # (one f with a free principal point too). Views short of that are refused even when the
    # fit's curvature looks sharp: what then pins the intrinsics is the perspective within one
    # board, a weak and noise-dependent constraint (one tilted pose seen 3 times gave fy 10 %
    # off with a 3.5 % sigma).
    c = cal.constraints
    pinhole = (1 if c.fix_aspect_ratio else 2) + (0 if c.fix_principal_point else 2)
    need = -(-pinhole // 2)
    if cal.orientations < need:
        names = ("f" if c.fix_aspect_ratio else "fx, fy") + (
            "" if c.fix_principal_point else ", cx, cy"
        )
        refuse.insert(0, f"{names} need the board in at least {need} distinct orientations "
                      f"(normals > {SAME_ORIENTATION_DEG:g} deg apart), these views have "
                      f"{cal.orientations}")  # fmt: skip
    warn = [t for r, t in checks if r <= max_std and not r <= WEAK_FRACTION * max_std]
    if not cal.ray_std_px / (0.5 * np.hypot(w, h)) <= WEAK_FRACTION * max_std:
        warn.append(f"a ray's pixel is uncertain by +- {cal.ray_std_px:.3g} px at the image "
                    "corners")  # fmt: skip
    return refuse, warn


def views_summary(cal: CameraCalibration) -> str:
    """One line: number of views, distinct orientations, tilt and distance ranges, coverage."""
    n = len(cal.per_view_rms)
    return (f"{n} view{'s' if n != 1 else ''}, {cal.orientations} distinct board "
            f"orientation{'s' if cal.orientations != 1 else ''}, tilt "
            f"{cal.tilt_deg.min():.0f}-{cal.tilt_deg.max():.0f} deg, distance "
            f"{cal.distance.min():.3g}-{cal.distance.max():.3g} m, the board covers "
            f"{100 * cal.coverage:.0f} % of the image")  # fmt: skip


def advice(cal: CameraCalibration) -> str:
    """What to do about weakly determined intrinsics, from the views' spread."""
    tips = []
    if cal.orientations < 3 or cal.tilt_deg.max() < 20:
        tips.append("add views of the board tilted by 20-45 deg about different axes")
    if cal.coverage < 0.5:
        tips.append("move the board into the image corners")
    c = cal.constraints
    fix = [f for f, on in (("--fix-principal-point", not c.fix_principal_point),
                           ("--fix-aspect-ratio", not c.fix_aspect_ratio),
                           ("--no-distortion", not c.no_distortion)) if on]  # fmt: skip
    if fix:
        tips.append("or fit fewer intrinsics (" + " ".join(fix) + ")")
    return "; ".join(tips)


# ------------------------------------------------------------------------- stereo


def calibrate_stereo(
    left: list[np.ndarray],
    right: list[np.ndarray],
    pattern: str,
    cols: int,
    rows: int,
    square: float,
    constraints: IntrinsicConstraints = IntrinsicConstraints(),  # noqa: B008 - frozen
    plates: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    plate_threshold: float = 40.0,
) -> dict:
    """Calibrate from grayscale image pairs; returns ``K1 D1 K2 D2 R T size1 size2 rms_1
    rms_2 rms_stereo per_view_rms_stereo (n, 2) cal1 cal2`` (:class:`CameraCalibration`) and
    ``used`` (indices of the pairs used) and ``via_plate`` (indices found only after filling
    from the plate, :func:`fill_from_plate`). Raises ``ValueError`` when no pair is usable."""
    obj = board_points(pattern, cols, rows, square)
    o, p1, p2, used, via_plate = [], [], [], [], []
    for k, (a, b) in enumerate(zip(left, right, strict=True)):
        ca, fa = _find_with_plate(a, plates[0], pattern, cols, rows, plate_threshold)
        cb, fb = _find_with_plate(b, plates[1], pattern, cols, rows, plate_threshold)
        if ca is not None and cb is not None:
            o.append(obj)
            p1.append(ca)
            p2.append(cb)
            used.append(k)
            if fa or fb:
                via_plate.append(k)
    if not used:
        raise ValueError("the pattern was found in no image pair (wrong --cols/--rows?)")
    s1 = (left[0].shape[1], left[0].shape[0])
    s2 = (right[0].shape[1], right[0].shape[0])
    cal1 = calibrate_camera(o, p1, s1, constraints)
    cal2 = calibrate_camera(o, p2, s2, constraints)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    out = cv2.stereoCalibrateExtended(
        o, p1, p2, cal1.K, cal1.dist, cal2.K, cal2.dist, s1, None, None,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit,
    )  # fmt: skip
    rms, K1, D1, K2, D2, R, T = out[:7]
    rvecs, tvecs = out[9], out[10]
    per_view = np.asarray(out[-1], np.float64).reshape(-1, 2)
    std_r, std_t = stereo_pose_std(o, p1, p2, K1, D1, K2, D2, R, T, rvecs, tvecs)
    return {"K1": K1, "D1": D1.ravel()[:5], "K2": K2, "D2": D2.ravel()[:5], "R": R, "T": T.ravel(),
            "size1": s1, "size2": s2, "rms_1": cal1.rms, "rms_2": cal2.rms,
            "rms_stereo": float(rms), "per_view_rms_stereo": per_view, "cal1": cal1,
            "cal2": cal2, "used": used, "via_plate": via_plate,
            "std_R_rad": std_r, "std_T": std_t}  # fmt: skip


def stereo_pose_std(obj, img1, img2, K1, D1, K2, D2, R, T, rvecs, tvecs):
    """Standard deviations of the stereo fit's ``R`` (its rotation vector, rad, per axis) and
    ``T`` (per axis, the board's unit), shapes (3,), (3,): what ``cv2.calibrateCameraExtended``
    computes for its parameters (``sigma^2 (J^T J)^-1``, ``sigma^2`` the squared residuals'
    sum over residuals minus parameters), for ``cv2.stereoCalibrate``'s fit with the
    intrinsics fixed, which OpenCV does not report: the parameters are ``R``, ``T`` and each
    view's board pose in camera 1 (``rvecs``, ``tvecs``); camera 2's pose of a board is the
    composition (``cv2.composeRT``, with its derivatives), the residuals both cameras'
    reprojections (``cv2.projectPoints``, with its Jacobian). ``obj``, ``img1``, ``img2``:
    per view (n_i, 3) board points and their (n_i, 2) detections."""
    r = cv2.Rodrigues(np.asarray(R, np.float64))[0].reshape(3)
    t = np.asarray(T, np.float64).reshape(3)
    n = len(obj)
    rows, res = [], []
    for i in range(n):
        o = np.asarray(obj[i], np.float64).reshape(-1, 3)
        rv = np.asarray(rvecs[i], np.float64).reshape(3)
        tv = np.asarray(tvecs[i], np.float64).reshape(3)
        p, J1 = cv2.projectPoints(o, rv, tv, K1, D1)
        res.append(p.reshape(-1) - np.asarray(img1[i], np.float64).reshape(-1))
        Jrow = np.zeros((J1.shape[0], 6 + 6 * n))
        Jrow[:, 6 + 6 * i : 12 + 6 * i] = J1[:, :6]
        rows.append(Jrow)
        rv2, tv2, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            rv, tv, r, t
        )
        p, J2 = cv2.projectPoints(o, rv2, tv2, K2, D2)
        res.append(p.reshape(-1) - np.asarray(img2[i], np.float64).reshape(-1))
        Jr, Jt = J2[:, :3], J2[:, 3:6]
        Jrow = np.zeros((J2.shape[0], 6 + 6 * n))
        Jrow[:, :3] = Jr @ dr3dr2 + Jt @ dt3dr2
        Jrow[:, 3:6] = Jr @ dr3dt2 + Jt @ dt3dt2
        Jrow[:, 6 + 6 * i : 9 + 6 * i] = Jr @ dr3dr1 + Jt @ dt3dr1
        Jrow[:, 9 + 6 * i : 12 + 6 * i] = Jr @ dr3dt1 + Jt @ dt3dt1
        rows.append(Jrow)
    J = np.concatenate(rows)
    e = np.concatenate(res)
    dof = J.shape[0] - J.shape[1]
    sigma = float(np.sqrt(e @ e / dof)) if dof > 0 else float("inf")
    cov, free = _marginal_std(J, 6, sigma)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std[free] = np.inf
    return std[:3], std[3:]


def fill_from_plate(gray: np.ndarray, plate: np.ndarray, threshold: float = 40.0) -> np.ndarray:
    """``gray`` with the pixels that differ from the background ``plate`` (same camera, scene
    without the robot) by more than ``threshold`` grey levels, grown by 3 px, replaced by the
    plate's: the robot crossing a board is painted out so the board can be detected. The board
    must not have moved between plate and image (its corners are then the plate's)."""
    diff = cv2.absdiff(gray, plate) > threshold
    grown = cv2.dilate(diff.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    out = gray.copy()
    out[grown] = plate[grown]
    return out


def _find_with_plate(gray, plate, pattern, cols, rows, threshold):
    c = find_pattern(gray, pattern, cols, rows)
    if c is not None or plate is None:
        return c, False
    c = find_pattern(fill_from_plate(gray, plate, threshold), pattern, cols, rows)
    return c, c is not None
