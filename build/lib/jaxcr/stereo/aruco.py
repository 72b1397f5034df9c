"""Base frame from four ArUco markers (stereo report sec. 2), OpenCV 5 object API.

The base frame: origin at the centre of marker ``origin_id`` (2), X and Y in the plate,
Z perpendicular (out of the plate, towards the robot). The marker layout (centres and side
length, metres) is part of the rig description (:class:`MarkerLayout`).

Per camera, markers are found with ``cv2.aruco.ArucoDetector`` (sub-pixel corner
refinement) and the pose of the base frame is solved with ``cv2.solvePnP`` (SQPNP) on all
corners of all found markers. Robust combination: when the joint fit leaves more than
1 px RMS, a marker whose removal makes the others consistent (RMS below a third) is dropped
and the pose re-solved. With both
views, :func:`stereo_base_pose` refines one pose ``T_cam1_base`` by Gauss-Newton (float64, through
``cv2.projectPoints``) over the
reprojection errors of all corners in both images (the stereo extrinsics are fixed), and
reports the marker reprojection RMS in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from jaxcr.camera import Camera

__all__ = [
    "MarkerLayout",
    "detect_markers",
    "marker_object_corners",
    "camera_base_pose",
    "stereo_base_pose",
    "reprojection_rms",
]


@dataclass(frozen=True)
class MarkerLayout:
    """Four (or more) markers on the base plate. ``centres`` maps marker id -> (x, y) of its
    centre in the base frame (metres, z = 0); ``size`` the black square's side (metres)."""

    centres: dict[int, tuple[float, float]] = field(
        default_factory=lambda: {2: (0.0, 0.0), 3: (0.06, 0.0), 0: (0.0, 0.06), 1: (0.06, 0.06)}
    )
    size: float = 0.024
    dictionary: str = "DICT_4X4_50"

    @property
    def base_centre(self) -> np.ndarray:
        """Centre of the marker centres (the report's "base centre"), base frame (3,)."""
        c = np.array(list(self.centres.values()), float)
        return np.array([c[:, 0].mean(), c[:, 1].mean(), 0.0])

    def to_dict(self) -> dict:
        return {
            "centres": {str(k): list(v) for k, v in self.centres.items()},
            "size": self.size,
            "dictionary": self.dictionary,
        }

    @classmethod
    def from_dict(cls, d: dict) -> MarkerLayout:
        return cls(
            {int(k): (float(v[0]), float(v[1])) for k, v in d["centres"].items()},
            float(d["size"]),
            str(d.get("dictionary", "DICT_4X4_50")),
        )


def marker_object_corners(layout: MarkerLayout, marker_id: int) -> np.ndarray:
    """(4, 3) corners of one marker in the base frame, in OpenCV's detection order
    (top-left, top-right, bottom-right, bottom-left of the marker image), with the marker
    image's top towards +Y and its right towards +X."""
    cx, cy = layout.centres[marker_id]
    h = layout.size / 2
    return np.array(
        [[cx - h, cy + h, 0], [cx + h, cy + h, 0], [cx + h, cy - h, 0], [cx - h, cy - h, 0]],
        float,
    )


def _detector(layout: MarkerLayout) -> cv2.aruco.ArucoDetector:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, layout.dictionary))
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    # Markers seen at grazing angles come out small and close together in the image; the
    # default minimum distance (0.125 of the perimeter) drops some of them.
    p.minMarkerDistanceRate = 0.01
    return cv2.aruco.ArucoDetector(d, p)


def detect_markers(image: np.ndarray, layout: MarkerLayout) -> dict[int, np.ndarray]:
    """Detected markers of the layout in an image (H, W, 3) RGB float [0, 1] or uint8:
    ``{id: (4, 2) corner pixels}``. Ids not in the layout are ignored."""
    img = image if image.dtype == np.uint8 else np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    corners, ids, _ = _detector(layout).detectMarkers(gray)
    out: dict[int, np.ndarray] = {}
    if ids is None:
        return out
    for c, i in zip(corners, ids.ravel(), strict=True):
        if int(i) in layout.centres and int(i) not in out:
            out[int(i)] = np.asarray(c, np.float64).reshape(4, 2)
    return out


def _cv_pose(camera: Camera, obj: np.ndarray, img: np.ndarray):
    K = np.asarray(camera.K, np.float64)
    D = np.asarray(camera.dist, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, D, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, D, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


def _per_marker_rms(camera, T, layout, det):
    K = np.asarray(camera.K, np.float64)
    D = np.asarray(camera.dist, np.float64)
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    out = {}
    for i, c in det.items():
        uv, _ = cv2.projectPoints(marker_object_corners(layout, i), rvec, T[:3, 3], K, D)
        out[i] = float(np.sqrt(np.mean(np.sum((uv.reshape(4, 2) - c) ** 2, axis=1))))
    return out


def _fit_rms(camera, layout, det) -> tuple[np.ndarray | None, float]:
    """Pose from the markers ``det`` and its reprojection RMS over the same corners (px)."""
    ids = sorted(det)
    obj = np.concatenate([marker_object_corners(layout, i) for i in ids])
    img = np.concatenate([det[i] for i in ids])
    T = _cv_pose(camera, obj, img)
    if T is None:
        return None, np.inf
    r = _per_marker_rms(camera, T, layout, det)
    return T, float(np.sqrt(np.mean(np.square(list(r.values())))))


def camera_base_pose(
    camera: Camera, detections: dict[int, np.ndarray], layout: MarkerLayout
) -> tuple[np.ndarray, dict[int, np.ndarray]] | None:
    """``T_cam_base`` (4, 4) of one camera from its detections (SQPNP on all corners plus
    Levenberg-Marquardt refinement) and the detections kept; ``None`` without markers.

    Robust combination: with three or more markers whose joint fit leaves more than 1 px
    RMS, the marker whose removal makes the others consistent (their fit RMS drops below a
    third) is dropped; this repeats while three markers remain."""
    det = dict(detections)
    if not det:
        return None
    T, rms = _fit_rms(camera, layout, det)
    while len(det) >= 3 and rms > 1.0:
        trials = {
            i: _fit_rms(camera, layout, {k: v for k, v in det.items() if k != i}) for i in det
        }
        best = min(trials, key=lambda i: trials[i][1])
        if trials[best][1] < rms / 3.0:
            det.pop(best)
            T, rms = trials[best]
        else:
            break
    if T is None:
        return None
    return T, det


def _project_cv(camera: Camera, T: np.ndarray, obj: np.ndarray) -> np.ndarray:
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    uv, _ = cv2.projectPoints(
        obj, rvec, T[:3, 3], np.asarray(camera.K, np.float64), np.asarray(camera.dist, np.float64)
    )
    return uv.reshape(-1, 2)


def _twist(xi: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(xi[3:].reshape(3, 1))[0]
    T[:3, 3] = xi[:3]
    return T


def reprojection_rms(cameras, T_cam_bases, detections, layout) -> float:
    """RMS (pixels) of all marker corners over the given views."""
    sq, n = 0.0, 0
    for cam, T, det in zip(cameras, T_cam_bases, detections, strict=True):
        for i, c in det.items():
            uv = _project_cv(cam, np.asarray(T, np.float64), marker_object_corners(layout, i))
            sq += float(np.sum((uv - c) ** 2))
            n += 4
    return float(np.sqrt(sq / max(n, 1)))


def stereo_base_pose(
    cam1: Camera,
    cam2: Camera,
    det1: dict[int, np.ndarray],
    det2: dict[int, np.ndarray],
    layout: MarkerLayout,
    iterations: int = 8,
) -> dict:
    """Base pose from both views. Cameras carry their calibration extrinsics
    (``T_cam_robot``, any common frame: camera 1's frame for a stereo file). Returns
    ``{"T_cam1_base", "T_cam2_base", "rms_px", "n_markers": (n1, n2), "markers": (ids1,
    ids2)}``; raises ``ValueError`` when no view sees a marker."""
    T1w = np.asarray(cam1.T_cam_robot, np.float64)
    T2w = np.asarray(cam2.T_cam_robot, np.float64)
    r1 = camera_base_pose(cam1, det1, layout)
    r2 = camera_base_pose(cam2, det2, layout)
    if r1 is None and r2 is None:
        raise ValueError("no ArUco marker of the base plate found in either view")
    det1 = r1[1] if r1 else {}
    det2 = r2[1] if r2 else {}
    # Initial pose of the base in the common calibration frame w.
    if r1 is not None and (r2 is None or len(det1) >= len(det2)):
        T_w_base = np.linalg.inv(T1w) @ r1[0]
    else:
        T_w_base = np.linalg.inv(T2w) @ r2[0]
    views = [(T1w, cam1, det1), (T2w, cam2, det2)]
    views = [
        (
            Tw,
            cam,
            np.concatenate([marker_object_corners(layout, i) for i in sorted(det)]),
            np.concatenate([det[i] for i in sorted(det)]),
        )
        for Tw, cam, det in views
        if det
    ]

    def residuals(T_wb):
        return np.concatenate(
            [(_project_cv(cam, Tw @ T_wb, obj) - img).ravel() for Tw, cam, obj, img in views]
        )

    # Gauss-Newton on a left increment exp(xi) T (forward-difference Jacobian through
    # cv2.projectPoints, float64).
    for _ in range(iterations):
        r = residuals(T_w_base)
        J = np.empty((len(r), 6))
        h = 1e-7
        for k in range(6):
            xi = np.zeros(6)
            xi[k] = h
            J[:, k] = (residuals(_twist(xi) @ T_w_base) - r) / h
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        T_w_base = _twist(step) @ T_w_base
        if np.linalg.norm(step) < 1e-10:
            break
    U, _, Vt = np.linalg.svd(T_w_base[:3, :3])
    T_w_base[:3, :3] = U @ Vt
    T1b, T2b = T1w @ T_w_base, T2w @ T_w_base
    rms = reprojection_rms([cam1, cam2], [T1b, T2b], [det1, det2], layout)
    return {
        "T_cam1_base": T1b,
        "T_cam2_base": T2b,
        "T_calib_base": T_w_base,
        "rms_px": rms,
        "n_markers": (len(det1), len(det2)),
        "markers": (sorted(det1), sorted(det2)),
    }
