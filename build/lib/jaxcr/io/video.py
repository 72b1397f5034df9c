"""Video files at the edge of the pipeline (OpenCV VideoCapture, FFmpeg backend).

OpenCV's video backends write straight to the process's standard error (file descriptor 2):
FFmpeg's decoder errors (``[mjpeg @ 0x...] overread 8`` for a frame cut short), OpenCV's own
AVI reader (``Unexpected element. Expected: LIST. Got: <raw bytes>`` for a damaged header) and
VideoCapture warnings. None of it goes through Python, so it cannot be caught as an exception
and ``cv2.utils.logging`` silences only part of it. :class:`VideoReader` therefore

* refuses, as one :class:`jaxcr.errors.InputError` naming the file, what is not a video: a
  still image whatever its extension (FFmpeg would read a PNG renamed ``.avi`` as a one-frame
  video), an empty file, a file no backend opens (unknown container, header cut off);
* opens with the FFmpeg backend when it is available (the container is recognised by its
  content, so an ``.mp4`` renamed ``.avi`` decodes correctly; OpenCV's fallback AVI reader,
  which prints raw bytes, is not tried);
* reads each frame with file descriptor 2 redirected to a temporary file: what the decoder
  wrote while decoding that frame is not shown, it marks the frame as damaged instead (a frame
  cut short by a truncated file is decoded by FFmpeg with grey or smeared blocks and an error
  message, never silently used);
* reports a RIFF/AVI file shorter than its header declares (a truncated copy) in the reasons
  of the frames missing from it.

Limits: OpenCV's FFmpeg wrapper logs errors only by default (``OPENCV_FFMPEG_LOGLEVEL``
changes that); with a more verbose level set by the user, informational lines would mark
frames as damaged. A decoder that decodes several frames in parallel (frame threading, e.g.
H.264) may report a damaged frame one or a few reads late, so the frame failed can be a
neighbour of the damaged one (MJPEG, as written by ``jaxcr motion synth --video``, decodes
each frame on its own read). Anything another thread writes to stderr during a read is
swallowed with the decoder's output.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from pathlib import Path

import cv2

from jaxcr.errors import InputError

# still-image signatures (first bytes): a video container never starts with these
_IMAGE_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"\xff\xd8\xff", "JPEG"),
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"BM", "BMP"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
)


def image_format(head: bytes) -> str | None:
    """The still-image format whose signature ``head`` (a file's first bytes) starts with,
    or None (WebP is RIFF with form type ``WEBP``)."""
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    for magic, name in _IMAGE_MAGIC:
        if head.startswith(magic):
            return name
    return None


def riff_truncation(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(actual, declared)`` file sizes in bytes when ``path`` is a RIFF file (AVI) shorter
    than its RIFF header declares (a truncated copy), else None."""
    with open(path, "rb") as fh:
        head = fh.read(12)
        size = os.fstat(fh.fileno()).st_size
    if len(head) < 12 or head[:4] != b"RIFF":
        return None
    declared = int.from_bytes(head[4:8], "little") + 8
    return (size, declared) if size < declared else None


@contextlib.contextmanager
def captured_native_stderr():
    """Redirect file descriptor 2 (where C libraries write) to a temporary file for the
    duration; yields a list that receives the captured text (decoded, possibly empty) on exit.

    Python's ``sys.stderr`` is flushed first, so nothing written before is lost. If fd 2
    cannot be duplicated (closed), nothing is redirected and the list stays empty.
    """
    captured: list[str] = []
    try:
        sys.stderr.flush()
    except (AttributeError, ValueError):
        pass
    try:
        saved = os.dup(2)
    except OSError:
        yield captured
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            captured.append(tmp.read().decode("utf-8", "replace"))


def decoder_message(text: str) -> str:
    """First line of native decoder output as printable text, e.g. ``mjpeg: overread 8``."""
    for line in text.splitlines():
        line = re.sub(r"\[(\w+) @ 0x[0-9a-fA-F]+\] ", r"\1: ", line)
        line = "".join(c if c.isprintable() else "?" for c in line).strip()
        if line:
            return line[:120]
    return ""


class VideoReader:
    """Frames of a video file, read quietly (see the module docstring).

    Args:
        path: the video file.
        field: the field that named it (for messages), e.g. ``"source.video"``.

    Raises:
        InputError: the file is missing, empty, a still image, or no backend opens it.
    """

    def __init__(self, path: str | os.PathLike, field: str | None = None):
        self.path = Path(path)
        self.field = field
        where = {"file": str(self.path), "field": field}
        if not self.path.is_file():
            raise InputError("video file not found", **where)
        with open(self.path, "rb") as fh:
            head = fh.read(16)
        if not head:
            raise InputError("video file is empty", **where)
        kind = image_format(head)
        if kind is not None:
            raise InputError(
                f"is a {kind} image, not a video (whatever its extension); give an image "
                "folder as source.images instead",
                **where,
            )
        self.truncated = riff_truncation(self.path)
        ffmpeg = cv2.CAP_FFMPEG in cv2.videoio_registry.getBackends()
        from cv2.utils import logging as cvlog

        level = cvlog.getLogLevel()
        cvlog.setLogLevel(cvlog.LOG_LEVEL_SILENT)
        try:
            with captured_native_stderr():
                self._cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG if ffmpeg else 0)
        finally:
            cvlog.setLogLevel(level)
        if not self._cap.isOpened():
            self._cap.release()
            why = "unknown container or damaged header"
            if self.truncated:
                why = f"the file is truncated ({self.truncated[0]} of {self.truncated[1]} bytes)"
            raise InputError(f"not a readable video ({why})", **where)
        self.width = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.n_read = 0

    def read(self):
        """``(bgr uint8 (H, W, 3), "")`` for the next frame, or ``(None, reason)`` when it is
        missing (the video ended) or the decoder reported an error while decoding it."""
        with captured_native_stderr() as text:
            ok, bgr = self._cap.read()
        msg = decoder_message(text[0] if text else "")
        if not ok or bgr is None:
            reason = f"no such frame: the video ends after {self.n_read} frame(s)"
            if self.truncated:
                reason += f" (file truncated: {self.truncated[0]} of {self.truncated[1]} bytes)"
            return None, reason
        self.n_read += 1
        if msg:
            return None, f"corrupt video frame (decoder: {msg})"
        return bgr, ""

    def release(self) -> None:
        self._cap.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.release()
