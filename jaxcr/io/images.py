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
import threading
from pathlib import Path

import cv2
import numpy as np

from jaxcr.errors import InputError

_DECODE_LOCK = threading.Lock()  # fd 2 is process-wide: one redirected decode at a time
# libjpeg's messages for a damaged file (the decoder then fills the rest with grey): the file
# is refused rather than used. Other native output (libpng warnings such as "iCCP: known
# incorrect sRGB profile", about metadata, not pixels) is dropped.
_JPEG_DAMAGED = ("Corrupt JPEG data", "Premature end of JPEG file")


def _quiet_decode(data: np.ndarray, flags: int) -> np.ndarray | None:
    # OpenCV logs its own WARN/ERROR lines for corrupt files, and libpng/libjpeg write warnings
    # straight to file descriptor 2: we report one InputError instead (or nothing).
    from cv2.utils import logging as cvlog

    from jaxcr.io.video import captured_native_stderr

    with _DECODE_LOCK:
        level = cvlog.getLogLevel()
        cvlog.setLogLevel(cvlog.LOG_LEVEL_SILENT)
        try:
            with captured_native_stderr() as text:
                try:
                    img = cv2.imdecode(data, flags)
                except cv2.error:
                    img = None
        finally:
            cvlog.setLogLevel(level)
    native = "".join(text)
    for line in native.splitlines():
        if line.startswith(_JPEG_DAMAGED):
            raise InputError(f"damaged JPEG ({line.strip()})")  # the caller names the file
    return img


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"  # the end chunk's type and CRC


#: Largest image decoded (pixels), checked on the file header before decoding: a float32 RGB
#: copy of it is 1.6 GB. A PNG can declare 30000x30000 zero pixels in under 1 MB of file
#: (a "decompression bomb"); decoding it would take ~11 GB on this path.
MAX_PIXELS = 1 << 27


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF segment, or None if not found."""
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            if i + 9 > len(data):
                return None
            h = int.from_bytes(data[i + 5 : i + 7], "big")
            w = int.from_bytes(data[i + 7 : i + 9], "big")
            return w, h
        i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    return None


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) declared in a PNG or JPEG header, without decoding; None for other
    formats or an unreadable header."""
    if data[:8] == _PNG_SIGNATURE and len(data) >= 24 and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return _jpeg_size(data)


def file_header_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) from a PNG/JPEG file's header (first MB), or None (other format,
    unreadable). Does not decode."""
    try:
        with open(path, "rb") as fh:
            return header_size(fh.read(1 << 20))
    except OSError:
        return None


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
        raise InputError("not a readable image (truncated PNG: no IEND chunk)", file=path)
    size = header_size(data[: 1 << 20].tobytes())
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise InputError(
            f"image of {size[0]}x{size[1]} pixels exceeds the {MAX_PIXELS} pixel limit",
            file=path,
        )
    try:
        img = _quiet_decode(data, flags)
    except InputError as err:
        raise InputError(err.message, file=path) from None
    if img is None:
        raise InputError("not a readable image (corrupt or unsupported format)", file=path)
    return img


def read_raw(path: str | os.PathLike, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """``cv2.imread(path, flags)`` with the checks of :func:`read_image`: a missing, empty,
    truncated, corrupt file, or one whose PNG/JPEG header declares more than
    :data:`MAX_PIXELS` pixels (never decoded), raises :class:`InputError` naming the file.
    For callers that need OpenCV's own layout (BGR, grey uint8, 16-bit)."""
    return _imread(path, flags)


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
    # ".NAME.PID.tmp": the pattern a later claim of OUT deletes after a kill -9 (jaxcr.io.outdir)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())
        os.replace(tmp, path)
    except OSError as err:
        if err.filename is None and err.errno is not None:
            # a full disk (ENOSPC) names no file: name it, so the CLI's one line says which
            # (the audit, experiments/contract_audit.py item 6: "file system: No space left")
            raise OSError(err.errno, err.strerror, str(path)) from None
        raise
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
