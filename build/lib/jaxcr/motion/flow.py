"""Optical flow for M-L step 2: pyramidal Lucas-Kanade (Bouguet 1999, OpenCV) on a regular
grid of points, with OpenCV's DIS as a denser option. OpenCV is called here (not in the
jitted core) because the paper's flow *is* OpenCV's; everything after it is JAX.

Grid points sit at ``k * step + (step - 1) / 2`` so that ``cv2.resize`` of the (rows, cols)
grid of flow vectors with bilinear interpolation is exactly aligned with the pixel grid
(:func:`dense_from_grid`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class FlowConfig:
    """Flow settings: grid step (px; 0: :func:`auto_step` of the frame width), LK window (px),
    pyramid levels, forward-backward check threshold (px; 0 disables it), method "lk" or
    "dis", and LK's minimum eigenvalue of the gradient matrix (OpenCV's minEigThreshold; points
    in textureless areas, whose flow the aperture problem leaves undetermined, are marked
    invalid).

    The default (grid step W / 80, window 15 px, 3 levels) is the setting the accuracy
    experiments validate: 4 px on their 320x240 videos (experiments/results/motion/motion_report.md),
    8 px at 640x480 (experiments/results/motion/motion_bench.md), i.e. 80 x 60 points per frame."""

    step: int = 0
    window: int = 15
    levels: int = 3
    fb_threshold: float = 0.0
    method: str = "lk"
    min_eig: float = 1e-3


def grid_points(height: int, width: int, step: int) -> np.ndarray:
    """(rows * cols, 2) float32 (x, y) pixel positions of the flow grid, row-major."""
    gh, gw = grid_dims(height, width, step)
    ys = np.arange(gh, dtype=np.float32) * step + (step - 1) / 2
    xs = np.arange(gw, dtype=np.float32) * step + (step - 1) / 2
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float32)


def auto_step(width: int) -> int:
    """Default grid step for a frame ``width`` px wide: W / 80 rounded, at least 1 px (80
    points across the frame, as in the validated setting: 4 px at 320 px, 8 px at 640 px)."""
    return max(1, round(width / 80))


def grid_dims(height: int, width: int, step: int) -> tuple[int, int]:
    """(rows, cols) of the flow grid: one point per whole step x step cell."""
    return height // step, width // step


def to_gray_u8(rgb: np.ndarray) -> np.ndarray:
    """uint8 grey image from float RGB in [0, 1] or uint8 RGB."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        # saturating round(255 a), as np.clip(np.round(a * 255), 0, 255) but 25x faster
        a = cv2.convertScaleAbs(np.clip(a, 0.0, None).astype(np.float32, copy=False), alpha=255.0)
    return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a


def grid_flow(
    prev_gray: np.ndarray, next_gray: np.ndarray, cfg: FlowConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flow from ``prev`` to ``next`` at the grid points.

    Returns (points (n, 2) xy, flow (n, 2) px, valid (n,) bool). Invalid points (LK lost
    track, left the image or failed the forward-backward check) have zero flow.
    """
    cfg = cfg or FlowConfig()
    h, w = prev_gray.shape
    pts = grid_points(h, w, cfg.step or auto_step(w))
    if cfg.method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
        dense = dis.calc(prev_gray, next_gray, None)
        xi = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
        flow = dense[yi, xi].astype(np.float32)
        valid = np.isfinite(flow).all(axis=1)
        return pts, np.where(valid[:, None], flow, 0.0).astype(np.float32), valid
    if cfg.method != "lk":
        raise ValueError(f"unknown flow method {cfg.method!r}")
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
    lk = dict(
        winSize=(cfg.window, cfg.window),
        maxLevel=cfg.levels,
        criteria=crit,
        minEigThreshold=cfg.min_eig,
    )
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev_gray, next_gray, pts[:, None, :], None, **lk)
    nxt = nxt.reshape(-1, 2)
    valid = status.reshape(-1).astype(bool)
    if cfg.fb_threshold > 0:
        back, st2, _ = cv2.calcOpticalFlowPyrLK(next_gray, prev_gray, nxt[:, None, :], None, **lk)
        fb = np.linalg.norm(back.reshape(-1, 2) - pts, axis=1)
        valid &= st2.reshape(-1).astype(bool) & (fb < cfg.fb_threshold)
    valid &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= w - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= h - 1)
    valid &= np.isfinite(nxt).all(axis=1)
    flow = np.where(valid[:, None], nxt - pts, 0.0).astype(np.float32)
    return pts, flow, valid


def dense_from_grid(
    flow: np.ndarray, valid: np.ndarray, height: int, width: int, step: int, scale: int = 1
) -> np.ndarray:
    """Dense flow by normalised bilinear interpolation of the valid grid vectors (invalid
    points are filled from their neighbours).

    With ``scale`` > 1 the field is given at the working resolution of the superpixels,
    (ceil(H / scale), ceil(W / scale), 2), in working pixels (flow / scale); ``step`` must then
    be a multiple of ``scale`` so that the grid stays aligned with the working pixels.
    Returns (H, W, 2) float32 for ``scale`` = 1.
    """
    if scale < 1 or step % scale:
        raise ValueError(f"flow grid step {step} is not a multiple of the working scale {scale}")
    gh, gw = grid_dims(height, width, step)
    f = flow.reshape(gh, gw, 2) * valid.reshape(gh, gw, 1)
    v = valid.reshape(gh, gw).astype(np.float32)
    fb = cv2.GaussianBlur(f, (3, 3), 0.8)
    vb = cv2.GaussianBlur(v, (3, 3), 0.8)
    fill = fb / np.maximum(vb, 1e-6)[..., None]
    f = np.where(v[..., None] > 0, f, fill)
    cell = step // scale
    dense = cv2.resize(f, (gw * cell, gh * cell), interpolation=cv2.INTER_LINEAR)
    if scale != 1:
        dense = dense / np.float32(scale)
    h, w = -(-height // scale), -(-width // scale)
    pad = ((0, h - gh * cell), (0, w - gw * cell), (0, 0))
    return np.ascontiguousarray(np.pad(dense, pad, mode="edge"), dtype=np.float32)
