"""Reading motion-segmentation datasets (format ``jaxcr.motion/1``, docs/motion-format.md).

A dataset is a folder with ``motion.json``; the frames come from a video file (any format
OpenCV's VideoCapture reads, through :class:`jaxcr.io.video.VideoReader`) or an image folder
(PNG/JPEG, sorted by name). Unreadable frames (a damaged image, a video frame the decoder
reported damaged, frames missing from a truncated video) are reported per frame (``None``
from :meth:`MotionDataset.frames` plus a reason), never fatal; malformed metadata, and a
video file that is no video at all (a still image under a video extension, a container no
backend opens), raise :class:`jaxcr.errors.InputError` naming file and field.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.images import MAX_PIXELS, file_header_size, read_raw
from jaxcr.io.jsonfile import read_json
from jaxcr.io.video import VideoReader
from jaxcr.motion.arm import ArmModel, arm_from_dict

FORMAT = "jaxcr.motion/1"
_IMAGE_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass
class MotionDataset:
    """A loaded dataset. ``x`` (n, 5) joints (rad), ``touch`` (n,) bool, ``P`` (3, 4),
    ``masks`` per frame (path or None), ``eval_frame`` (ground-truth frame used for scoring;
    default the first touch frame), ``scene`` free-form metadata."""

    root: Path
    P: np.ndarray
    arm: ArmModel
    x: np.ndarray
    touch: np.ndarray
    masks: list[Path | None]
    eval_frame: int | None
    scene: dict
    width: int
    height: int
    _images: list[Path] | None
    _video: Path | None
    _cache: dict

    def __len__(self) -> int:
        return len(self.x)

    def frames(self, indices=None):
        """Yield ``(index, rgb float32 (H, W, 3) in [0, 1] or None, reason)`` for every frame in
        order, or only for the frames in ``indices`` (an iterable of frame indices, yielded in
        increasing order): an image folder decodes only those, a video stops after the last
        one (a video is read sequentially, so earlier frames are still decoded).

        ``rgb`` is None for a frame that cannot be used (unreadable, damaged, wrong size), with
        the reason; never raises for a bad frame. Raises ``ValueError`` for an index outside
        ``[0, len(self))``.
        """
        wanted = None
        if indices is not None:
            wanted = sorted({int(i) for i in indices})
            bad = [i for i in wanted if not 0 <= i < len(self)]
            if bad:
                raise ValueError(f"frame index {bad[0]} outside [0, {len(self)})")
        yield from self._frames(wanted)

    def _frames(self, wanted: list[int] | None):
        last = len(self) - 1 if wanted is None else (wanted[-1] if wanted else -1)
        want = None if wanted is None else set(wanted)
        if self._images is not None:
            for i, p in enumerate(self._images[: last + 1]):
                if want is not None and i not in want:
                    continue
                size = file_header_size(p)  # a wrong-size file is never decoded
                if size is not None and size != (self.width, self.height):
                    yield i, None, f"image size {size[0]}x{size[1]} != {self.width}x{self.height}"
                    continue
                try:
                    img = _read_rgb(p)
                except InputError as err:
                    yield i, None, f"unreadable image {p.name}: {err.message}"
                    continue
                if img.shape[:2] != (self.height, self.width):
                    yield (
                        i,
                        None,
                        f"image size {img.shape[1]}x{img.shape[0]} != {self.width}x{self.height}",
                    )
                else:
                    yield i, img, ""
            return
        # quiet reader: no native library output on stderr; a frame the decoder reported
        # damaged, or missing from a truncated file, is a failed frame with the reason
        reader = VideoReader(self._video, field="source.video")
        try:
            vw, vh = reader.width, reader.height
            if vw * vh > MAX_PIXELS:  # declared by the container: no frame is decoded
                for i in range(last + 1):
                    if want is None or i in want:
                        yield (
                            i,
                            None,
                            f"video frame size {vw}x{vh} exceeds the {MAX_PIXELS} pixel limit",
                        )
                return
            for i in range(last + 1):
                bgr, why = reader.read()
                if want is not None and i not in want:
                    continue
                if bgr is None:
                    yield i, None, why
                    continue
                if bgr.shape[:2] != (self.height, self.width):
                    yield (
                        i,
                        None,
                        f"frame size {bgr.shape[1]}x{bgr.shape[0]} != {self.width}x{self.height}",
                    )
                    continue
                yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0, ""
        finally:
            reader.release()

    def mask(self, i: int) -> np.ndarray | None:
        p = self.masks[i]
        if p is None:
            return None
        try:
            m = read_raw(p, cv2.IMREAD_GRAYSCALE)
        except InputError as err:
            raise InputError(
                f"unreadable ground-truth mask: {err.message}",
                file=str(p),
                frame=i,
                field=f"frames[{i}].mask",
            ) from None
        return m >= 128


def _read_rgb(path: Path) -> np.ndarray:
    """Float RGB in [0, 1]; InputError when unreadable or over the MAX_PIXELS limit."""
    bgr = read_raw(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def _matrix(v, shape, file, field, max_abs: float | None = None, frame=None) -> np.ndarray:
    """A finite float64 array of ``shape`` whose values fit float32 (the core's precision), at
    most ``max_abs`` in magnitude when given (jaxcr.limits)."""
    from jaxcr.limits import FLOAT32_MAX, check_finite_float32

    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"must be a {'x'.join(map(str, shape))} number array", file=file, field=field
        ) from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(
            f"must be a finite {'x'.join(map(str, shape))} array", file=file, field=field
        )
    return check_finite_float32(a, file, field, frame=frame, max_abs=max_abs or FLOAT32_MAX)


def load_motion_dataset(path: str | os.PathLike) -> MotionDataset:
    """Load ``path`` (the folder or its motion.json)."""
    from jaxcr.limits import MAX_ANGLE

    path = Path(path)
    meta_path = path / "motion.json" if path.is_dir() else path
    root = meta_path.parent
    if not meta_path.exists():
        raise InputError(
            "no motion.json (expected a jaxcr.motion/1 dataset folder)", file=str(path)
        )
    f = str(meta_path)
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"format must be '{FORMAT}'", file=f, field="format")
    P = _matrix(meta.get("P"), (3, 4), f, "P")
    if np.linalg.matrix_rank(P[:, :3]) < 3:
        raise InputError("P[:, :3] must be invertible", file=f, field="P")
    arm = arm_from_dict(meta.get("arm"), file=f)
    frames = meta.get("frames")
    if not isinstance(frames, list) or len(frames) < 2:
        raise InputError("needs a list of at least 2 frames", file=f, field="frames")
    xs, touch, masks = [], [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise InputError("frame entry must be an object", file=f, frame=i, field="frames")
        xs.append(_matrix(fr.get("x"), (5,), f, f"frames[{i}].x", max_abs=MAX_ANGLE, frame=i))
        t = fr.get("touch", False)
        if not isinstance(t, bool):
            raise InputError("touch must be true or false", file=f, frame=i, field="touch")
        touch.append(t)
        m = fr.get("mask")
        masks.append(None if m is None else root / m)
    try:
        width, height = int(meta["width"]), int(meta["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError("width and height (pixels) are required", file=f, field="width") from None
    if width < 16 or height < 16:
        raise InputError("image size must be at least 16x16", file=f, field="width")
    if width * height > MAX_PIXELS:
        raise InputError(
            f"image size {width}x{height} exceeds the {MAX_PIXELS} pixel limit",
            file=f,
            field="width",
        )
    src = meta.get("source")
    images = video = None
    if isinstance(src, dict) and "video" in src:
        video = root / src["video"]
        # refused here (exit 2) when it is no video at all: missing, empty, a still image
        # under a video extension, a container no backend opens
        VideoReader(video, field="source.video").release()
    elif isinstance(src, dict) and "images" in src:
        folder = root / src["images"]
        if not folder.is_dir():
            raise InputError("image folder not found", file=str(folder), field="source.images")
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXT)
        if len(images) < len(frames):
            raise InputError(
                f"{len(images)} images for {len(frames)} frames",
                file=str(folder),
                field="source.images",
            )
    else:
        raise InputError(
            "source must be {'video': file} or {'images': folder}", file=f, field="source"
        )
    ev = meta.get("eval_frame")
    if ev is not None and not (
        isinstance(ev, int) and not isinstance(ev, bool) and 0 <= ev < len(frames)
    ):
        raise InputError("eval_frame must be a frame index", file=f, field="eval_frame")
    return MotionDataset(
        root,
        P,
        arm,
        np.asarray(xs),
        np.asarray(touch, bool),
        masks,
        ev,
        meta.get("scene", {}),
        width,
        height,
        images,
        video,
        {},
    )
