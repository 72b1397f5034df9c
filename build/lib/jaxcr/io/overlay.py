"""Overlay panels in the style of Watson et al. Fig. 4 (numpy + OpenCV drawing).

The panel is 2x2: (a) the raw image, (b) the background-subtracted image ``I' = I o M``,
(c) the nominal (unoptimised, delta u = 0) projection as a transparent white overlay on the
background-subtracted image with the true robot outline in blue, (d) the same for the refined
(optimised) projection. Without ground truth, panels (c) and (d) carry no blue outline.

Large frames (:func:`robot_crop`): a robot covering 1 % of a 1280x720 frame is invisible in a
2560x1440 panel, so all four tiles are cropped to the same box around the robot (the union of
the nominal, refined and true masks, grown by a margin of ``max(16 px, 25 %`` of the box's
larger side), at least ``MIN_CROP`` px a side) and tile (a) carries a full-frame thumbnail
(``THUMB_FRACTION`` of the tile width) with the crop rectangle in yellow, in the corner
farthest from the robot. No crop is made when the box would cover at least
``NO_CROP_FRACTION`` of the frame's width and height (the tiles are then the full frame, as
before). Finally tiles larger than ``MAX_TILE`` px a side are shrunk (area interpolation), so a
panel is at most ``2 MAX_TILE`` px a side; frames of at most ``MAX_TILE`` px a side whose robot
fills them are unchanged.
"""

from __future__ import annotations

import numpy as np

WHITE = (255, 255, 255)
BLUE = (40, 110, 255)  # RGB
YELLOW = (255, 220, 0)
PROJECTION_ALPHA = 0.5
MIN_CROP = 96
NO_CROP_FRACTION = 0.6
THUMB_FRACTION = 0.3
MAX_TILE = 800


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


def robot_crop(
    masks: list[np.ndarray | None], min_size: int = MIN_CROP
) -> tuple[int, int, int, int] | None:
    """Crop box ``(x0, y0, x1, y1)`` (x1, y1 exclusive) around every true pixel of ``masks``
    (same-size (H, W) bools; ``None`` entries skipped), grown by the margin of the module
    docstring, at least ``min_size`` a side, inside the frame. ``None`` when no crop is
    needed (empty masks, or the box covers ``NO_CROP_FRACTION`` of both sides)."""
    ms = [np.asarray(m, bool) for m in masks if m is not None]
    if not ms:
        return None
    h, w = ms[0].shape
    union = np.logical_or.reduce(ms)
    ys, xs = np.nonzero(union)
    if ys.size == 0:
        return None
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    margin = max(16, int(np.ceil(0.25 * max(x1 - x0, y1 - y0))))
    x0, y0, x1, y1 = x0 - margin, y0 - margin, x1 + margin, y1 + margin

    def grow(a, b, size, limit):
        size = min(size, limit)
        if b - a < size:
            c = (a + b) // 2
            a, b = c - size // 2, c - size // 2 + size
        a, b = max(0, a), min(limit, b)
        if b - a < size:  # pushed against an edge: extend the other way
            a, b = (0, size) if a == 0 else (limit - size, limit)
        return int(a), int(b)

    x0, x1 = grow(x0, x1, min_size, w)
    y0, y1 = grow(y0, y1, min_size, h)
    if x1 - x0 >= NO_CROP_FRACTION * w and y1 - y0 >= NO_CROP_FRACTION * h:
        return None
    return x0, y0, x1, y1


def _with_thumbnail(tile: np.ndarray, full: np.ndarray, box, robot_centre) -> np.ndarray:
    """``tile`` with the full frame shrunk to ``THUMB_FRACTION`` of its width, the crop ``box``
    drawn on it, in the corner of ``tile`` farthest from ``robot_centre`` (tile pixels)."""
    import cv2

    th, tw = tile.shape[:2]
    fh, fw = full.shape[:2]
    scale = max(1, int(THUMB_FRACTION * tw)) / fw
    sw, sh = max(1, int(round(fw * scale))), max(1, int(round(fh * scale)))
    if sh > th // 2:  # a very tall frame: bound the height instead
        scale = (th // 2) / fh
        sw, sh = max(1, int(round(fw * scale))), max(1, th // 2)
    thumb = cv2.resize(full, (sw, sh), interpolation=cv2.INTER_AREA)
    x0, y0, x1, y1 = box
    p0 = (int(x0 * scale), int(y0 * scale))
    p1 = (
        max(p0[0] + 1, int(np.ceil(x1 * scale)) - 1),
        max(p0[1] + 1, int(np.ceil(y1 * scale)) - 1),
    )
    thumb = np.ascontiguousarray(thumb)
    cv2.rectangle(thumb, p0, p1, YELLOW, 1)
    cv2.rectangle(thumb, (0, 0), (sw - 1, sh - 1), WHITE, 1)
    cx, cy = robot_centre
    right = cx < tw / 2  # put it on the side away from the robot
    bottom = cy < th / 2
    ox = tw - sw if right else 0
    oy = th - sh if bottom else 0
    out = tile.copy()
    out[oy : oy + sh, ox : ox + sw] = thumb
    return out


def _shrink_tile(tile: np.ndarray, max_tile: int) -> np.ndarray:
    import cv2

    h, w = tile.shape[:2]
    if max(h, w) <= max_tile:
        return tile
    s = max_tile / max(h, w)
    size = (max(1, int(round(w * s))), max(1, int(round(h * s))))
    return cv2.resize(tile, size, interpolation=cv2.INTER_AREA)


def fig4_panel(
    image: np.ndarray,
    foreground: np.ndarray,
    nominal_mask: np.ndarray,
    refined_mask: np.ndarray,
    truth_mask: np.ndarray | None = None,
    labels: bool = True,
    crop: bool = True,
    max_tile: int = MAX_TILE,
) -> np.ndarray:
    """Compose the 2x2 Fig. 4 panel.

    Args:
        image: (H, W, 3) raw RGB image (float in [0, 1] or uint8).
        foreground: (H, W) bool background-subtraction mask M (True = kept, robot-like).
        nominal_mask, refined_mask: (H, W) bool projections (full robot).
        truth_mask: (H, W) bool true visible robot pixels, or None.
        labels: draw "(a) raw" ... captions.
        crop: crop the tiles to the robot with a full-frame thumbnail (module docstring).
        max_tile: shrink tiles larger than this many pixels a side.

    Returns:
        (2h, 2w, 3) uint8 RGB panel: [[raw, subtracted], [nominal, refined]]; (h, w) is the
        crop's size (the frame's without a crop), shrunk to at most ``max_tile`` a side.
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
    box = robot_crop([nominal_mask, refined_mask, truth_mask]) if crop else None
    if box is not None:
        x0, y0, x1, y1 = box
        tiles = [t[y0:y1, x0:x1] for t in tiles]
        union = np.asarray(nominal_mask, bool) | np.asarray(refined_mask, bool)
        ys, xs = np.nonzero(union[y0:y1, x0:x1])
        centre = (xs.mean(), ys.mean()) if xs.size else ((x1 - x0) / 2, (y1 - y0) / 2)
        tiles[0] = _with_thumbnail(tiles[0], raw, box, centre)
    tiles = [_shrink_tile(t, max_tile) for t in tiles]
    if labels:
        names = ["(a) raw", "(b) background subtracted", "(c) nominal", "(d) refined"]
        tiles = [_label(t, n) for t, n in zip(tiles, names, strict=True)]
    top = np.concatenate(tiles[:2], axis=1)
    bottom = np.concatenate(tiles[2:], axis=1)
    return np.concatenate([top, bottom], axis=0)
