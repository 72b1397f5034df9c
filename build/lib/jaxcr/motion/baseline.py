"""The baseline M-L is compared with (Fitzpatrick & Metta 2003, as described in M-L section
5.1): background subtraction by frame differencing around the touch event, an arm model from
the frame before the touch, and graph-cut segmentation (OpenCV's grabCut, Boykov-Kolmogorov
style) of the touch frame with the arm-model pixels fixed as background.

The free parameter is the difference threshold in grey levels (0-255); the paper's optimum
was 5. Also here: "M-L + GraphCuts", grabCut seeded by the M-L mask (section 5.1).
"""

from __future__ import annotations

import cv2
import numpy as np


def difference_image(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel maximum over channels of |a - b| for uint8 images, float32 grey levels."""
    d = np.abs(a.astype(np.int16) - b.astype(np.int16))
    return (d.max(axis=2) if d.ndim == 3 else d).astype(np.float32)


def _grabcut(image: np.ndarray, mask: np.ndarray, iters: int, seed: int = 0) -> np.ndarray:
    """grabCut from ``mask`` (GC_* labels). Its GMMs start from k-means++ centres drawn from
    OpenCV's global RNG, so the cut depended on whatever had used that RNG before (a few to
    hundreds of pixels on the synthetic videos): the RNG is seeded with ``seed`` first."""
    fg = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    bg = (mask == cv2.GC_BGD) | (mask == cv2.GC_PR_BGD)
    if not fg.any() or not bg.any():  # grabCut needs both models: nothing to cut
        return fg
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    m = mask.copy()
    cv2.setRNGSeed(int(seed))
    cv2.grabCut(image, m, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    return (m == cv2.GC_FGD) | (m == cv2.GC_PR_FGD)


def fitzpatrick_segment(
    before_touch2: np.ndarray,
    before_touch: np.ndarray,
    touch: np.ndarray,
    threshold: float = 5.0,
    iters: int = 3,
    seed: int = 0,
) -> np.ndarray:
    """Object mask of the touch frame (bool (H, W)).

    ``touch`` is the first frame with contact, ``before_touch`` the one before it and
    ``before_touch2`` the one before that (uint8 RGB). Pixels changing between
    ``before_touch`` and ``touch`` by more than ``threshold`` are the moving foreground; the
    arm model is the change between the two frames before the touch (the arm moving alone),
    classed as definite background; grabCut on the touch frame decides the rest (its RNG
    seeded with ``seed``: the same frames give the same mask)."""
    change = difference_image(before_touch, touch) > threshold
    arm = difference_image(before_touch2, before_touch) > threshold
    arm = cv2.dilate(arm.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    mask = np.full(change.shape, cv2.GC_PR_BGD, np.uint8)
    mask[change] = cv2.GC_PR_FGD
    mask[arm] = cv2.GC_BGD
    bgr = cv2.cvtColor(touch, cv2.COLOR_RGB2BGR)
    return _grabcut(bgr, mask, iters, seed)


def ml_graphcut(
    image: np.ndarray, ml_mask: np.ndarray, iters: int = 3, seed: int = 0
) -> np.ndarray:
    """ "M-L + GraphCuts": grabCut on ``image`` (uint8 RGB) seeded with the M-L object mask as
    probable foreground and everything else as probable background."""
    mask = np.where(ml_mask, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    return _grabcut(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), mask, iters, seed)
