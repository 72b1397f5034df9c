"""Image and mask files at the edge of the pipeline (OpenCV I/O).

* :func:`read_image` -> float32 RGB in [0, 1], shape (H, W, 3). 8-bit images are divided by
  255, 16-bit by 65535; grey images are replicated to three channels, alpha is dropped.
* :func:`read_mask` -> bool (H, W): ``True`` where the pixel value is above half the range
  (so 255/0 masks, 1/0 masks written as 8-bit are *not* accepted as robot pixels: a value
  of 1 in an 8-bit mask is below 128 and reads as background; masks are 255 on robot pixels,
  see docs/dataset-format.md).
* :func:`write_png` writes atomically (temporary file in the same folder, then rename).

Unreadable or corrupt files raise :class:`jaxcr.errors.InputError` naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from jaxcr.errors import InputError


def _quiet_decode(data: np.ndarray, flags: int) -> np.ndarray | None:
    # OpenCV logs its own WARN/ERROR lines for corrupt files; we report one InputError instead.
    from cv2.utils import logging as cvlog

    level = cvlog.getLogLevel()
    cvlog.setLogLevel(cvlog.LOG_LEVEL_SILENT)
    try:
        return cv2.imdecode(data, flags)
    except cv2.error:
        return None
    finally:
        cvlog.setLogLevel(level)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"  # the end chunk's type and CRC


def _imread(path: str | os.PathLike, flags: int) -> np.ndarray:
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError("image file not found", file=path)
    if os.path.isdir(path):
        raise InputError("is a directory, expected an image file", file=path)
    try:
        # np.fromfile + imdecode: works for any path (cv2.imread mishandles some unicode paths)
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as err:
        raise InputError(f"cannot read image ({err.strerror})", file=path) from None
    if data.size == 0:
        raise InputError("image file is empty", file=path)
    if data[:8].tobytes() == _PNG_SIGNATURE and _PNG_IEND not in data.tobytes():
        # caught here: libpng would print its own "libpng error" line on stderr
        raise InputError("truncated PNG file (no IEND chunk)", file=path)
    img = _quiet_decode(data, flags)
    if img is None:
        raise InputError("not a readable image (corrupt or unsupported format)", file=path)
    return img


def _to_unit_float(img: np.ndarray, path: str) -> np.ndarray:
    if img.dtype == np.uint8:
        return img.astype(np.float32) / np.float32(255.0)
    if img.dtype == np.uint16:
        return img.astype(np.float32) / np.float32(65535.0)
    if img.dtype == np.float32:
        return img
    raise InputError(f"unsupported image sample type {img.dtype}", file=path)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG/JPEG (8 or 16 bit, grey/RGB/RGBA) as float32 RGB in [0, 1], shape (H, W, 3)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    path = os.fspath(path)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 3:
        img = img[:, :, ::-1]  # BGR -> RGB
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, 2::-1]  # BGRA -> RGB (alpha dropped)
    else:
        raise InputError(f"unsupported image layout {img.shape}", file=path)
    return np.ascontiguousarray(_to_unit_float(img, path))


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a single-channel mask PNG as bool (H, W): ``True`` above half the value range
    (>= 128 for 8-bit, >= 32768 for 16-bit). Colour masks are accepted if all channels are
    equal (a grey image saved as RGB); otherwise InputError."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    path = os.fspath(path)
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        if not np.all(img == img[:, :, :1]):
            raise InputError("mask must be single-channel (grey), got a colour image", file=path)
        img = img[:, :, 0]
    if img.dtype == np.uint8:
        return img >= 128
    if img.dtype == np.uint16:
        return img >= 32768
    raise InputError(f"unsupported mask sample type {img.dtype}", file=path)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file (decodes it: also checks it is readable)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    return int(img.shape[1]), int(img.shape[0])


def _to_png_array(array: np.ndarray) -> np.ndarray:
    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise ValueError("write_png: image contains NaN or infinity")
        a = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    elif a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"write_png: unsupported dtype {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 3:
        a = a[:, :, ::-1]  # RGB -> BGR for OpenCV
    elif a.ndim == 3 and a.shape[2] == 4:
        a = a[:, :, [2, 1, 0, 3]]
    elif not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1)):
        raise ValueError(f"write_png: unsupported shape {a.shape}")
    return np.ascontiguousarray(a)


def write_png(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write ``array`` as PNG, atomically (temp file in the same folder, then ``os.replace``).

    Accepts bool (H, W) masks (-> 0/255), uint8/uint16 grey (H, W) or RGB(A) (H, W, 3|4),
    and float arrays in [0, 1] (clipped, rounded to 8 bit). RGB order, as returned by
    :func:`read_image`. Creates parent folders. Returns the path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    a = _to_png_array(array)
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
