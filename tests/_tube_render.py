"""Independent tube renderer shared by the refinement tests (not jaxcr's rasteriser).

Watson eq. 7 surface points are projected with the camera, the convex hull of each pair of
consecutive rings (OpenCV) is filled at pixel centres (scikit-image), and the tube is drawn
grey over a noisy red background.
"""

import cv2
import numpy as np
from skimage.draw import polygon

from jaxcr.camera import project_points, surface_points


def render_tube(cl, cam, seed: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Image (h, w, 3) float32 in [0, 1] and tube mask (h, w) bool for centreline ``cl``."""
    W, H = size
    pts = surface_points(cl, 16)
    uv, _ = project_points(cam, pts.reshape(-1, 3))
    uv = np.asarray(uv).reshape(pts.shape[0], 16, 2)
    mask = np.zeros((H, W), bool)
    for i in range(pts.shape[0] - 1):
        hull = cv2.convexHull(np.concatenate([uv[i], uv[i + 1]]).astype(np.float32))[:, 0]
        rr, cc = polygon(hull[:, 1], hull[:, 0], mask.shape)
        mask[rr, cc] = True
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3), np.float32)
    img[:] = [0.70, 0.25, 0.25]
    img += rng.normal(0, 0.05, img.shape).astype(np.float32)
    img[mask] = [0.6, 0.6, 0.62]
    img[mask] += rng.normal(0, 0.03, (mask.sum(), 3)).astype(np.float32)
    return np.clip(img, 0, 1), mask
