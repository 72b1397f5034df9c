"""Shape buckets: image sizes padded to a few standard sizes, so that new sizes reuse compiled
programs (issue 18, docs/decisions.md S29).

Every program of ``jaxcr segment`` whose shapes depend on the image size (the background
mask, the refinement, the covariance) is compiled for the arrays it is given. With shape
buckets the frames of a camera of ``width x height`` pixels are padded at the bottom and the
right to the **bucket** :func:`bucket_shape` (each side rounded up to the next entry of
:data:`LADDER`), and the refinement is told the real size as a traced value: a dataset at
600x450 then runs the program compiled for 640x480, and 1280x700 the one of 1280x720.

Padded pixels carry zero weight everywhere (:func:`jaxcr.segmentation.refine.refine_frame`
with ``sizes``): they are neither data nor background in the region sums and the variance
normalisation, no band tile lies in the padding, the pyramid's 2x2 averages see them as the
zero-weight pixels they already add for odd sizes, the projection clamps to the real image,
and the masks are cut back to the real size. Pixel coordinates are unchanged (the padding
is at the bottom/right; the principal point does not move).

The ladder holds the common camera sides (240, 320, 480, 640, 720, 1080, 1280, 1920, 2160,
3840, ...) so that a common size is its own bucket and pays nothing, with rungs in between
at most 1.25x apart from 64 px up (1.34x below): from 64 px up a side grows by less than a
quarter and the area by less than 1.56x (600x450 -> 640x480: +13.8 %).
"""

from __future__ import annotations

import numpy as np

#: the standard side lengths (pixels, multiples of 8 = the refinement's default tile):
#: each side of an image is rounded up to the next one; beyond the last, to a multiple of
#: :data:`LADDER_STEP_BEYOND`
LADDER = (
    32, 40, 48, 64, 80, 96, 120, 128, 160, 192, 240, 256, 320, 384, 480, 512, 640, 720, 800,
    960, 1080, 1280, 1440, 1600, 1920, 2160, 2560, 3072, 3840, 4096,
)  # fmt: skip
LADDER_STEP_BEYOND = 1024

#: ``jaxcr segment --shape-buckets`` choices
MODES = ("on", "off")


def bucket_side(n: int) -> int:
    """The ladder's side for an image side of ``n`` pixels (>= n)."""
    n = int(n)
    for s in LADDER:
        if s >= n:
            return s
    return -(-n // LADDER_STEP_BEYOND) * LADDER_STEP_BEYOND


def bucket_shape(height: int, width: int) -> tuple[int, int]:
    """The bucket (H, W) >= (height, width) of an image: each side rounded up to the ladder
    (:data:`LADDER`). A size on the ladder is its own bucket."""
    return bucket_side(height), bucket_side(width)


def pad_frames(images: np.ndarray, shape: tuple[int, int], fill=0) -> np.ndarray:
    """``images`` (F, h, w, ...) padded at the bottom and right to ``shape`` = (H, W) with
    ``fill`` (the padded pixels' values never count: the refinement weighs them zero)."""
    h, w = images.shape[1:3]
    H, W = shape
    if (h, w) == (H, W):
        return images
    if H < h or W < w:
        raise ValueError(f"cannot pad {w}x{h} images to a smaller {W}x{H}")
    pad = [(0, 0), (0, H - h), (0, W - w)] + [(0, 0)] * (images.ndim - 3)
    return np.pad(images, pad, constant_values=fill)


def padded_fraction(height: int, width: int) -> float:
    """Pixels added by the bucket, as a fraction of the image's own (0 on the ladder)."""
    H, W = bucket_shape(height, width)
    return H * W / (height * width) - 1.0
