"""The output folder of ``jaxcr segment`` (format ``jaxcr.segment/2``): layout, atomic file
writes and the append-only ``results.jsonl`` log.

Layout of ``OUT`` (all paths in records are relative to ``OUT``)::

    run.json                         config, versions, dataset path (written first)
    results.jsonl                    one JSON object per processed frame (see below)
    masks/<camera>/<id>.png          refined full projection (255 robot, 0 elsewhere)
    nominal/<camera>/<id>.png        unoptimised projection (delta u = 0)
    background/<camera>/<id>.png     background-subtraction foreground mask M (Watson II-A)
    centrelines/<id>.npy             refined centreline points (N, 3), robot frame, metres
    centrelines_nominal/<id>.npy     nominal centreline points (N, 3), robot frame, metres
    overlays/<camera>/<id>.png       Watson Fig. 4 style 2x2 panel
    summary.json, DONE               written last, only when every frame was processed

Crash safety: every file is written to a temporary name in its destination folder, flushed,
fsynced and renamed over the destination (atomic on POSIX); a frame's JSONL line is appended
(and fsynced) only after all its files exist. An interrupted run therefore leaves complete
files and complete lines only, except possibly one truncated last line, which
:func:`read_results` ignores and :class:`ResultsLog` cuts off before appending.
"""

from __future__ import annotations

import io
import json
import math
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

RESULTS_FORMAT = "jaxcr.segment/2"  # /2: the "uncertainty" entry (docs/uncertainty.md)
RUN_FORMAT = "jaxcr.segment-run/1"
RESULTS_FILE = "results.jsonl"
RUN_FILE = "run.json"
SUMMARY_FILE = "summary.json"
DONE_FILE = "DONE"


# --------------------------------------------------------------------------- atomic writes


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, fsync,
    rename). Creates parent folders. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(err, OSError) and err.filename is None and err.errno is not None:
            # a write/fsync error (e.g. ENOSPC, a full disk) carries no file name: name the
            # file that could not be written, so the CLI's one line says which
            raise _named(err, path) from None
        raise
    return path


def _named(err: OSError, path: str | os.PathLike) -> OSError:
    """``err`` (an OSError without a file name) as the same OSError type naming ``path``."""
    try:
        return type(err)(err.errno, err.strerror or os.strerror(err.errno), str(path))
    except TypeError:
        return OSError(err.errno, err.strerror or os.strerror(err.errno), str(path))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Atomically write ``obj`` as indented JSON (non-finite floats become ``null``)."""
    return atomic_write_text(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def atomic_write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Atomically write an 8-bit PNG.

    Args:
        image: (H, W) mask (bool, or uint8) or (H, W, 3) RGB (uint8, or float in [0, 1]).
            Boolean masks are written as 0/255.
    """
    import cv2

    img = np.asarray(image)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    elif img.dtype != np.uint8:
        img = np.clip(np.rint(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    return atomic_write_bytes(path, buf.tobytes())


def atomic_write_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Atomically write a ``.npy`` file."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def read_mask_png(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit mask PNG as a boolean (H, W) array (pixel > 127).

    A missing file raises ``FileNotFoundError``; an unreadable one, or one declaring more than
    :data:`jaxcr.io.images.MAX_PIXELS` pixels (never decoded), :class:`InputError`."""
    from jaxcr.io.images import read_raw

    if not os.path.isfile(path):
        raise FileNotFoundError(str(path))
    img = read_raw(path)
    if img.ndim == 3:
        img = img[..., 0]
    if img.dtype != np.uint8:  # 16-bit masks: threshold at half range
        return img > (np.iinfo(img.dtype).max // 2)
    return img > 127


# --------------------------------------------------------------------------- JSON helpers


def to_jsonable(obj: Any) -> Any:
    """Convert numpy/JAX scalars and arrays to plain JSON types; NaN/inf become ``None``."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, (bool, np.bool_)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, Path):
        return obj.as_posix()
    if hasattr(obj, "__array__"):
        arr = np.asarray(obj)
        if arr.ndim == 0:
            return to_jsonable(arr.item())
        return [to_jsonable(v) for v in arr.tolist()]
    return obj


# --------------------------------------------------------------------------- layout


class OutputLayout:
    """Paths inside a segment output folder ``root``; ``rel`` gives the path stored in
    records (relative to ``root``, POSIX separators). ``log_dir``: where ``results.jsonl``,
    ``run.json``, ``summary.json`` and ``DONE`` go (default ``root``; a ``--shard`` run's
    ``root/shards/I-of-N``, :mod:`jaxcr.scale.shards`); frame files always go under ``root``."""

    def __init__(self, root: str | os.PathLike, log_dir: str | os.PathLike | None = None):
        self.root = Path(root)
        self.log_root = self.root if log_dir is None else Path(log_dir)

    def rel(self, *parts: str) -> str:
        return Path(*parts).as_posix()

    def abs(self, rel: str) -> Path:
        return self.root / rel

    def mask(self, camera: str, frame_id: str) -> str:
        return self.rel("masks", camera, f"{frame_id}.png")

    def nominal(self, camera: str, frame_id: str) -> str:
        return self.rel("nominal", camera, f"{frame_id}.png")

    def background(self, camera: str, frame_id: str) -> str:
        return self.rel("background", camera, f"{frame_id}.png")

    def overlay(self, camera: str, frame_id: str) -> str:
        return self.rel("overlays", camera, f"{frame_id}.png")

    def centreline(self, frame_id: str) -> str:
        return self.rel("centrelines", f"{frame_id}.npy")

    def centreline_nominal(self, frame_id: str) -> str:
        return self.rel("centrelines_nominal", f"{frame_id}.npy")

    @property
    def results(self) -> Path:
        return self.log_root / RESULTS_FILE

    @property
    def run(self) -> Path:
        return self.log_root / RUN_FILE

    @property
    def summary(self) -> Path:
        return self.log_root / SUMMARY_FILE

    @property
    def done(self) -> Path:
        return self.log_root / DONE_FILE


# --------------------------------------------------------------------------- results log


def read_run(path: str | os.PathLike) -> dict:
    """Read ``run.json`` (format ``jaxcr.segment-run/1``); an unreadable, truncated or foreign
    file raises :class:`jaxcr.errors.InputError` naming it (never a JSON traceback)."""
    from jaxcr.errors import InputError
    from jaxcr.io.jsonfile import read_json

    path = Path(path)
    info = read_json(path)
    if not isinstance(info, dict) or not isinstance(info.get("dataset"), str):
        raise InputError("not a jaxcr segment run.json (no 'dataset')", file=str(path))
    fmt = info.get("format")
    if fmt != RUN_FORMAT:
        raise InputError(
            f"unsupported format {fmt!r}; this jaxcr reads {RUN_FORMAT!r}",
            file=str(path),
            field="format",
        )
    return info


def read_results(path: str | os.PathLike) -> list[dict]:
    """Read a ``results.jsonl`` file: one dict per complete line, in file order.

    A last line without its terminating newline (a run killed while appending) is ignored;
    a malformed complete line raises ``ValueError`` naming the line. If a frame id occurs
    several times (a frame re-run), the last record wins and keeps its first position.
    """
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    lines = data.split(b"\n")
    complete = lines[:-1]  # the part after the last newline is empty or truncated
    records: dict[str, dict] = {}
    for lineno, line in enumerate(complete, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}:{lineno}: malformed JSON line ({err.msg})") from None
        if not isinstance(rec, dict) or "frame" not in rec:
            raise ValueError(f"{path}:{lineno}: not a jaxcr.segment record")
        records[str(rec["frame"])] = rec
    return list(records.values())


class ResultsLog:
    """Append-only writer of ``results.jsonl``.

    Opening cuts off a truncated last line left by an interrupted run, so the next append
    starts on a fresh line. ``append`` writes one line, flushes and fsyncs it.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            data = self.path.read_bytes()
            if data and not data.endswith(b"\n"):
                cut = data.rfind(b"\n") + 1  # 0 if no newline at all
                with open(self.path, "r+b") as f:
                    f.truncate(cut)
        self._f = open(self.path, "ab")

    def append(self, record: dict) -> None:
        self.append_many([record])

    def append_many(self, records: list[dict]) -> None:
        """Append several records with one write and one fsync (a chunk of thousands of
        ``fk`` rows; a kill mid-write leaves a cut last line, which readers ignore)."""
        if not records:
            return
        lines = [json.dumps(to_jsonable(r), separators=(",", ":"), allow_nan=False)
                 for r in records]  # fmt: skip
        try:
            self._f.write("".join(x + "\n" for x in lines).encode("utf-8"))
            self._f.flush()
            os.fsync(self._f.fileno())
        except OSError as err:
            if err.filename is None and err.errno is not None:
                raise _named(err, self.path) from None
            raise

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> ResultsLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def done_frame_ids(records: Iterable[dict], retry_failed: bool = False) -> set[str]:
    """Frame ids that need no re-run: every record present (ok or failed with a reason), or
    with ``retry_failed`` only the frames whose last record is ok (``records`` as returned by
    :func:`read_results`, one final record per frame; a re-run appends a newer record, which
    readers take as the frame's result)."""
    return {str(r["frame"]) for r in records if r.get("ok") or not retry_failed}


def output_is_complete(root: str | os.PathLike) -> bool:
    """True when a segment run finished (the ``DONE`` marker exists)."""
    return (Path(root) / DONE_FILE).exists()
