"""Overlay panels in the style of Watson et al. Fig. 4 (numpy + OpenCV drawing).

The panel is 2x2: (a) the raw image, (b) the background-subtracted image ``I' = I o M``,
(c) the nominal (unoptimised, delta u = 0) projection as a transparent white overlay on the
background-subtracted image with the true robot outline in blue, (d) the same for the refined
(optimised) projection. Without ground truth, panels (c) and (d) carry no blue outline.
"""

from __future__ import annotations

import numpy as np

WHITE = (255, 255, 255)
BLUE = (40, 110, 255)  # RGB
PROJECTION_ALPHA = 0.5


def to_uint8_rgb(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB float in [0, 1] or uint8 (or (H, W) grey) -> (H, W, 3) uint8."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.dtype != np.uint8:
        img = np.clip(np.rint(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img[..., :3])


def blend_mask(image: np.ndarray, mask: np.ndarray, colour=WHITE, alpha=PROJECTION_ALPHA):
    """Blend ``colour`` over ``image`` (uint8 RGB) where ``mask`` is true, with opacity
    ``alpha``; returns a new uint8 image."""
    out = image.astype(np.float32)
    m = np.asarray(mask, bool)
    out[m] = (1.0 - alpha) * out[m] + alpha * np.asarray(colour, np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def draw_contour(image: np.ndarray, mask: np.ndarray, colour=BLUE, thickness: int = 1):
    """Draw the outer and inner boundaries of a binary ``mask`` on a copy of ``image``."""
    import cv2

    out = np.ascontiguousarray(image.copy())
    m = np.asarray(mask, np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, tuple(int(c) for c in colour), thickness)
    return out


def _label(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = np.ascontiguousarray(image.copy())
    h = out.shape[0]
    scale = max(0.3, min(1.0, h / 480.0))
    org = (4, int(4 + 14 * scale))
    thick = max(1, int(round(2 * scale)))
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thick + 2, cv2.LINE_AA)
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, WHITE, thick, cv2.LINE_AA)
    return out


def fig4_panel(
    image: np.ndarray,
    foreground: np.ndarray,
    nominal_mask: np.ndarray,
    refined_mask: np.ndarray,
    truth_mask: np.ndarray | None = None,
    labels: bool = True,
) -> np.ndarray:
    """Compose the 2x2 Fig. 4 panel.

    Args:
        image: (H, W, 3) raw RGB image (float in [0, 1] or uint8).
        foreground: (H, W) bool background-subtraction mask M (True = kept, robot-like).
        nominal_mask, refined_mask: (H, W) bool projections (full robot).
        truth_mask: (H, W) bool true visible robot pixels, or None.
        labels: draw "(a) raw" ... captions.

    Returns:
        (2H, 2W, 3) uint8 RGB panel: [[raw, subtracted], [nominal, refined]].
    """
    raw = to_uint8_rgb(image)
    fg = np.asarray(foreground, bool)
    sub = raw * fg[..., None].astype(np.uint8)
    c = blend_mask(sub, nominal_mask)
    d = blend_mask(sub, refined_mask)
    if truth_mask is not None:
        c = draw_contour(c, truth_mask)
        d = draw_contour(d, truth_mask)
    tiles = [raw, sub, c, d]
    if labels:
        names = ["(a) raw", "(b) background subtracted", "(c) nominal", "(d) refined"]
        tiles = [_label(t, n) for t, n in zip(tiles, names, strict=True)]
    top = np.concatenate(tiles[:2], axis=1)
    bottom = np.concatenate(tiles[2:], axis=1)
    return np.concatenate([top, bottom], axis=0)
