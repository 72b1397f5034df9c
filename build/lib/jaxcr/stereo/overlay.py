"""Overlay images of a stereo reconstruction: the ordered skeleton (thin grey), the 3-D
backbone reprojected and coloured by segment, segment boundaries (white circles), the base
seed (yellow cross) and the base frame axes (X red, Y green, Z blue, 20 mm). cv2 drawing at
the edge; RGB uint8 in and out."""

from __future__ import annotations

import cv2
import numpy as np

from jaxcr.camera import Camera
from jaxcr.stereo.pipeline import _project_np

__all__ = ["draw_overlay", "SEGMENT_COLOURS"]

SEGMENT_COLOURS = [(255, 80, 80), (80, 160, 255), (255, 220, 60), (220, 80, 255), (80, 255, 200)]


def draw_overlay(
    image: np.ndarray, cam: Camera, result: dict, view: int, scale: int = 2
) -> np.ndarray:
    """Overlay of ``result`` (from :func:`jaxcr.stereo.pipeline.reconstruct_pair`) on
    ``image`` (H, W, 3) RGB uint8 of view ``view`` (0 or 1), upscaled by ``scale``."""
    img = image if image.dtype == np.uint8 else np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8)
    h, w = img.shape[:2]
    out = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
    sh = 4  # fixed-point shift for sub-pixel drawing
    f = scale * (1 << sh)

    def pt(uv):
        return (
            int(round((uv[0] + 0.5) * f - (1 << (sh - 1)))),
            int(round((uv[1] + 0.5) * f - (1 << (sh - 1)))),
        )

    T = np.asarray(result["T_cam1_base"] if view == 0 else result["T_cam2_base"], np.float64)
    rc = result["skeleton_rc"][view]
    for r, c in rc:
        cv2.circle(out, pt((c, r)), 1, (150, 150, 150), -1, cv2.LINE_AA, sh)
    uv = _project_np(cam, result["p"], T)
    s = result["s"]
    bounds = list(result["boundary_s"])
    seg = np.searchsorted(np.asarray(bounds), s)
    for k in range(len(uv) - 1):
        col = SEGMENT_COLOURS[int(seg[k]) % len(SEGMENT_COLOURS)]
        cv2.line(out, pt(uv[k]), pt(uv[k + 1]), col, 2, cv2.LINE_AA, sh)
    for bp in _project_np(cam, result["boundary_p"], T) if len(bounds) else []:
        cv2.circle(out, pt(bp), 5 * scale * (1 << sh) // 2, (255, 255, 255), 2, cv2.LINE_AA, sh)
    sr, sc = result["seed_rc"][view]
    cv2.drawMarker(out, (int(sc * scale), int(sr * scale)), (255, 255, 0), cv2.MARKER_CROSS, 14, 2)
    axes = _project_np(cam, np.array([[0, 0, 0], [0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.02]]), T)
    for k, col in enumerate([(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
        cv2.line(out, pt(axes[0]), pt(axes[k + 1]), col, 2, cv2.LINE_AA, sh)
    return out
