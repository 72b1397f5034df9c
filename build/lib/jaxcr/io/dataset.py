"""Datasets in the ``jaxcr.dataset/1`` format (docs/dataset-format.md): validation, lazy
loading and writing.

* :func:`validate_dataset` checks everything up front and returns *every* problem as an
  :class:`~jaxcr.errors.InputError` naming the file, the frame id and the field.
* :func:`load_dataset` returns a :class:`Dataset`; frames with problems are listed in
  ``Dataset.bad_frames`` (id -> message) so a batch can record them as failed and go on
  (``strict=True`` raises :class:`~jaxcr.errors.InputErrors` instead). Dataset-level problems
  (no dataset.json, wrong format, bad robot or camera) always raise.
* :class:`DatasetWriter` writes images/masks as frames are added and ``dataset.json`` last,
  atomically, so an interrupted write never looks like a complete dataset.

Images are read lazily (``frame.load_image(camera_name)``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jaxcr.camera import Camera
from jaxcr.errors import InputError, InputErrors
from jaxcr.io.calibration import (
    camera_from_dict,
    camera_from_stereo_entry,
    camera_to_dict,
    load_camera,
)
from jaxcr.io.images import file_header_size, image_size, read_image, read_mask, write_png
from jaxcr.io.units import MAX_LENGTH_M, nearest_key
from jaxcr.kinematics.robots import robot_to_dict

FORMAT = "jaxcr.dataset/1"
DATASET_FILE = "dataset.json"
IMAGE_KINDS = ("images", "masks", "full_masks", "occluders")
_FRAME_KEYS = {"id", "q", *IMAGE_KINDS, "tags", "truth", "meta"}
_TOP_KEYS = {"format", "name", "robot", "cameras", "frames", "background_images", "meta"}
_ROBOT_KINDS = ("constant_curvature", "single_segment", "ctr")


def _unknown_key_message(key: str, known) -> str:
    """``unknown key (did you mean 'x'?)`` with the nearest known key (difflib)."""
    if key in ("unit", "units"):
        return (
            "unknown key: dataset.json has no file-wide unit (robot, q and truth are SI); "
            'give "unit" inside each camera entry (cameras.<name>.unit)'
        )
    near = nearest_key(key, sorted(known))
    return f"unknown key (did you mean {near!r}?)" if near else "unknown key (typo?)"


# ------------------------------------------------------------------------------ data types


@dataclass
class Frame:
    """One time instant: joint values and, per camera, image (and optional mask) paths.

    Paths are absolute. ``truth`` maps a name to an absolute ``Path`` (for ``.npy`` files
    given as strings in dataset.json) or to the inline JSON value.
    """

    id: str
    q: np.ndarray
    images: dict[str, Path]
    masks: dict[str, Path] = field(default_factory=dict)
    full_masks: dict[str, Path] = field(default_factory=dict)
    occluders: dict[str, Path] = field(default_factory=dict)
    tags: list[str] = field(default_factory=list)
    truth: dict[str, Any] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def load_image(self, camera: str) -> np.ndarray:
        """RGB float32 (H, W, 3) in [0, 1] seen by ``camera``."""
        if camera not in self.images:
            raise InputError(f"no image for camera {camera!r}", frame=self.id, field="images")
        try:
            return read_image(self.images[camera])
        except InputError as e:
            raise InputError(
                e.message, file=e.file, frame=self.id, field=f"images.{camera}"
            ) from None

    def _load_mask(self, kind: str, camera: str) -> np.ndarray | None:
        paths = getattr(self, kind)
        if camera not in paths:
            return None
        try:
            return read_mask(paths[camera])
        except InputError as e:
            raise InputError(
                e.message, file=e.file, frame=self.id, field=f"{kind}.{camera}"
            ) from None

    def load_mask(self, camera: str) -> np.ndarray | None:
        """Visible robot pixels (bool (H, W)), or None if the frame has no mask there."""
        return self._load_mask("masks", camera)

    def load_full_mask(self, camera: str) -> np.ndarray | None:
        """Robot pixels including occluded parts, or None."""
        return self._load_mask("full_masks", camera)

    def load_occluder(self, camera: str) -> np.ndarray | None:
        """Pixels of something in front of the robot, or None."""
        return self._load_mask("occluders", camera)

    def load_truth(self, name: str = "centreline") -> Any:
        """A ground-truth entry: ``.npy`` files are loaded (e.g. centreline (N, 3), robot frame,
        metres); inline values are returned as stored. None if absent."""
        v = self.truth.get(name)
        if isinstance(v, Path):
            try:
                return np.load(v, allow_pickle=False)  # a pickle could run code: never
            except (ValueError, OSError) as err:
                msg = " ".join(str(err).split())
                raise InputError(f"not a readable .npy file ({msg})", file=str(v),
                                 field=f"truth.{name}") from None  # fmt: skip
        return v


@dataclass
class Dataset:
    """A loaded dataset. ``frames`` holds the usable frames in file order; ``bad_frames``
    maps the id of each unusable frame (``"#<index>"`` if it had no id) to its problems."""

    root: Path
    name: str
    robot: Any  # RobotModel, or None if its kind is not implemented in this build
    robot_dict: dict[str, Any]
    cameras: dict[str, Camera]
    frames: list[Frame]
    bad_frames: dict[str, str] = field(default_factory=dict)
    background_images: dict[str, list[Path]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    def frame(self, frame_id: str) -> Frame:
        for f in self.frames:
            if f.id == frame_id:
                return f
        raise KeyError(frame_id)

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)


# ------------------------------------------------------------------------------- checking


def is_safe_frame_id(fid: str) -> bool:
    """True when a frame id can be used as a file name inside an output folder: no path
    separators, no control characters, not ``.`` or ``..``."""
    return (
        fid not in (".", "..")
        and "/" not in fid
        and "\\" not in fid
        and not any(ord(c) < 32 or ord(c) == 127 for c in fid)
    )


def _robot_from_dict(d: Mapping[str, Any], file: str):
    """The robot model, or None when the kind is valid but its module is not available in
    this build (then only ``kind`` is validated)."""
    try:
        from jaxcr.kinematics.robots import robot_from_dict
    except ImportError:
        robot_from_dict = None
    if robot_from_dict is not None:
        try:
            return robot_from_dict(d, file=file)
        except ImportError:
            pass  # e.g. the CTR module is not in this build yet
    kind = d.get("kind") if isinstance(d, Mapping) else None
    if kind is None:
        raise InputError("missing required key", file=file, field="robot.kind")
    if kind not in _ROBOT_KINDS:
        raise InputError(
            f"unknown robot kind {kind!r}; expected one of {list(_ROBOT_KINDS)}",
            file=file,
            field="robot.kind",
        )
    return None


class _Scan:
    """Collects problems while reading dataset.json (dataset-level and per frame)."""

    def __init__(self, root: Path, json_path: Path, decode_images: bool, progress=None):
        self.progress = progress
        self.n_frames = 0
        self.root = root
        self.json_path = json_path
        self.file = str(json_path)
        self.decode = decode_images
        self.errors: list[InputError] = []  # dataset-level
        self.frame_errors: dict[str, list[InputError]] = {}
        self.name = root.name
        self.robot = None
        self.robot_dict: dict[str, Any] = {}
        self.cameras: dict[str, Camera] = {}
        self.bad_cameras: set[str] = set()
        self.frames: list[Frame] = []
        self.background: dict[str, list[Path]] = {}
        self.meta: dict[str, Any] = {}
        self._size_cache: dict[Path, tuple[int, int] | InputError] = {}

    def err(self, message, field=None, file=None):
        self.errors.append(InputError(message, file=file or self.file, field=field))

    # -- pieces ---------------------------------------------------------------------------

    def read_json(self) -> dict | None:
        if not self.json_path.exists():
            msg = f"missing {DATASET_FILE}{other_format_hint(self.root)}"
            self.errors.append(InputError(msg, file=str(self.root)))
            return None
        try:
            # utf-8-sig: a byte-order mark (Windows editors write one) is skipped
            with open(self.json_path, encoding="utf-8-sig") as fh:
                d = json.load(fh)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            self.err(f"not valid JSON ({e})")
            return None
        except RecursionError:
            self.err("not valid JSON (nested too deeply)")
            return None
        except OSError as e:
            self.err(f"cannot read ({e.strerror})")
            return None
        if not isinstance(d, dict):
            self.err("expected a JSON object at the top level")
            return None
        return d

    def check_top(self, d: dict) -> None:
        fmt = d.get("format")
        if fmt is None:
            self.err(f"missing required key (expected {FORMAT!r})", field="format")
        elif fmt != FORMAT:
            self.err(f"unsupported format {fmt!r}; this jaxcr reads {FORMAT!r}", field="format")
        for k in sorted(set(d) - _TOP_KEYS):
            self.err(_unknown_key_message(k, _TOP_KEYS), field=k)
        name = d.get("name", self.root.name)
        if not isinstance(name, str):
            self.err("expected a string", field="name")
        else:
            self.name = name
        meta = d.get("meta", {})
        if not isinstance(meta, dict):
            self.err("expected an object", field="meta")
        else:
            self.meta = meta

    def check_robot(self, d: dict) -> None:
        if "robot" not in d:
            self.err("missing required key", field="robot")
            return
        robot = d["robot"]
        file = self.file
        if isinstance(robot, str):
            path = self.root / robot
            file = str(path)
            try:
                with open(path, encoding="utf-8") as fh:
                    robot = json.load(fh)
            except FileNotFoundError:
                self.err(f"robot file not found: {robot}", field="robot")
                return
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                self.err(f"not valid JSON ({e})", file=file)
                return
            except OSError as e:
                self.err(f"cannot read robot file ({e.strerror})", file=file)
                return
        if not isinstance(robot, dict):
            self.err("expected a robot description object or a path to robot.json", field="robot")
            return
        self.robot_dict = robot
        try:
            self.robot = _robot_from_dict(robot, file)
        except InputError as e:
            if file == self.file and e.field and not e.field.startswith("robot"):
                e = InputError(e.message, file=e.file, frame=e.frame, field=f"robot.{e.field}")
            self.errors.append(e)

    def check_cameras(self, d: dict) -> None:
        cams = d.get("cameras")
        if cams is None:
            self.err("missing required key", field="cameras")
            return
        if not isinstance(cams, dict) or not cams:
            self.err("expected a non-empty object {name: camera}", field="cameras")
            return
        for name, entry in cams.items():
            try:
                if isinstance(entry, str):
                    path = self.root / entry
                    if not path.exists():
                        raise InputError(
                            f"camera file not found: {entry}",
                            file=self.file,
                            field=f"cameras.{name}",
                        )
                    self.cameras[name] = load_camera(path)
                elif isinstance(entry, dict) and "stereo" in entry:
                    self.cameras[name] = camera_from_stereo_entry(
                        entry, self.root, file=self.file, prefix=f"cameras.{name}."
                    )
                else:
                    self.cameras[name] = camera_from_dict(
                        entry, file=self.file, prefix=f"cameras.{name}."
                    )
            except InputError as e:
                self.errors.append(e)
                self.bad_cameras.add(name)

    def _image_size(self, path: Path, kind: str, expected=None) -> tuple[int, int] | InputError:
        if path in self._size_cache:
            return self._size_cache[path]
        head = file_header_size(path)
        if head is not None and expected is not None and head != expected:
            return head  # the caller reports the mismatch; never decode a wrong-size file
        try:
            if head is not None and not self.decode:
                size = head
            elif self.decode:
                if kind == "images":
                    a = read_image(path)
                else:
                    a = read_mask(path)
                size = (a.shape[1], a.shape[0])
            else:
                size = image_size(path)
        except InputError as e:
            size = e
        self._size_cache[path] = size
        return size

    def check_frame(self, i: int, fr: Any, seen: set[str], n_joints: int | None) -> None:
        label = f"#{i}"
        errs: list[InputError] = []

        def ferr(message, fld=None, file=None):
            errs.append(InputError(message, file=file or self.file, frame=label, field=fld))

        if not isinstance(fr, dict):
            ferr("expected a frame object", f"frames[{i}]")
            self.frame_errors[label] = errs
            return
        fid = fr.get("id")
        if fid is None or (isinstance(fid, str) and not fid.strip()):
            ferr("missing frame id", "id")
        elif not isinstance(fid, str | int) or isinstance(fid, bool):
            ferr(f"expected a string id, got {fid!r}", "id")
        elif not is_safe_frame_id(str(fid)):
            # ids name output files (segment's masks/<cam>/<id>.png): never a path
            ferr(
                f"frame id {str(fid)!r} is not usable as a file name "
                "(no '/', '\\', control characters, '.' or '..')",
                "id",
            )
        else:
            fid = str(fid)
            if fid in seen:
                label = f"{fid} (#{i})"
                ferr(f"duplicate frame id {fid!r}", "id")
            else:
                label = fid
                seen.add(fid)
        for k in sorted(set(fr) - _FRAME_KEYS):
            ferr(_unknown_key_message(k, _FRAME_KEYS), k)

        q = None
        if "q" not in fr:
            ferr("missing required key", "q")
        else:
            raw = fr["q"]
            if not isinstance(raw, list) or not all(
                isinstance(x, int | float) and not isinstance(x, bool) for x in raw
            ):
                ferr("expected a list of numbers", "q")
            else:
                q = np.asarray(raw, np.float64)
                bad = [j for j, x in enumerate(raw) if not math.isfinite(x)]
                if bad:
                    ferr(f"non-finite joint value(s) at index {bad}", "q")
                    q = None
                if n_joints is not None and len(raw) != n_joints:
                    ferr(f"expected {n_joints} joint values for this robot, got {len(raw)}", "q")
                    q = None

        paths: dict[str, dict[str, Path]] = {k: {} for k in IMAGE_KINDS}
        bad_cams_used: set[str] = set()
        if "images" not in fr:
            ferr("missing required key", "images")
        for kind in IMAGE_KINDS:
            entry = fr.get(kind)
            if entry is None:
                continue
            if not isinstance(entry, dict) or (kind == "images" and not entry):
                ferr("expected a non-empty object {camera: path}", kind)
                continue
            for cam, rel in entry.items():
                fld = f"{kind}.{cam}"
                if cam not in self.cameras and cam not in self.bad_cameras:
                    ferr(f"unknown camera {cam!r} (cameras: {sorted(self.cameras)})", fld)
                    continue
                if not isinstance(rel, str):
                    ferr("expected a path string", fld)
                    continue
                path = self.root / rel
                if not path.is_file():
                    ferr(f"file not found: {rel}", fld)
                    continue
                paths[kind][cam] = path.resolve()
                cam_obj = self.cameras.get(cam)
                want = None if cam_obj is None else (cam_obj.width, cam_obj.height)
                size = self._image_size(path, kind, want)
                if isinstance(size, InputError):
                    ferr(size.message, fld, file=str(path))
                    continue
                if cam_obj is not None and size != (cam_obj.width, cam_obj.height):
                    ferr(
                        f"size {size[0]}x{size[1]} does not match camera {cam!r} "
                        f"({cam_obj.width}x{cam_obj.height})",
                        fld,
                        file=str(path),
                    )
                if cam in self.bad_cameras and cam not in bad_cams_used:
                    # once per frame and camera (not per image kind); validate folds these
                    # into one line per camera (DatasetCheck.report_errors)
                    bad_cams_used.add(cam)
                    ferr(f"camera {cam!r} {_BAD_CAMERA_SUFFIX}", f"cameras.{cam}")

        tags = fr.get("tags", [])
        if not isinstance(tags, list) or not all(isinstance(t, str) for t in tags):
            ferr("expected a list of strings", "tags")
            tags = []
        truth: dict[str, Any] = {}
        traw = fr.get("truth", {})
        if not isinstance(traw, dict):
            ferr("expected an object {name: path or value}", "truth")
        else:
            for k, v in traw.items():
                if isinstance(v, str):
                    path = self.root / v
                    if not path.is_file():
                        ferr(f"file not found: {v}", f"truth.{k}")
                        continue
                    if path.suffix == ".npy":
                        try:
                            arr = np.load(path, mmap_mode="r", allow_pickle=False)
                        except (ValueError, OSError) as e:
                            ferr(f"not a readable .npy file ({e})", f"truth.{k}", file=str(path))
                            continue
                        if k == "centreline" and (arr.ndim != 2 or arr.shape[1] != 3):
                            ferr(
                                f"expected an (N, 3) array, got shape {arr.shape}",
                                f"truth.{k}",
                                file=str(path),
                            )
                            continue
                        if k == "centreline" and not (
                            np.issubdtype(arr.dtype, np.number)
                            and arr.shape[0] >= 2
                            and np.all(np.isfinite(arr))
                        ):
                            ferr(
                                "expected at least 2 finite points (NaN, inf or non-numbers found)",
                                f"truth.{k}",
                                file=str(path),
                            )
                            continue
                        if k == "centreline":
                            reach = float(np.max(np.linalg.norm(arr, axis=1)))
                            if reach > MAX_LENGTH_M:
                                hint = (
                                    f" (millimetres? {reach:.4g} mm = {reach * 1e-3:.4g} m)"
                                    if reach * 1e-3 <= MAX_LENGTH_M
                                    else ""
                                )
                                ferr(
                                    f"centreline reaches {reach:.4g} m from the robot base, "
                                    f"implausible (over {MAX_LENGTH_M:g} m); truth is in "
                                    f"metres{hint}",
                                    f"truth.{k}",
                                    file=str(path),
                                )
                                continue
                    truth[k] = path.resolve()
                else:
                    truth[k] = v
        fmeta = fr.get("meta", {})
        if not isinstance(fmeta, dict):
            ferr("expected an object", "meta")
            fmeta = {}

        # Relabel problems found before the id was known (label may have changed).
        errs = [InputError(e.message, file=e.file, frame=label, field=e.field) for e in errs]
        if errs:
            self.frame_errors[label] = errs
            return
        self.frames.append(
            Frame(
                id=label,
                q=q,
                images=paths["images"],
                masks=paths["masks"],
                full_masks=paths["full_masks"],
                occluders=paths["occluders"],
                tags=list(tags),
                truth=truth,
                meta=fmeta,
            )
        )

    def check_frames(self, d: dict) -> None:
        frames = d.get("frames")
        if frames is None:
            self.err("missing required key", field="frames")
            return
        if not isinstance(frames, list):
            self.err("expected a list of frames", field="frames")
            return
        n_joints = None
        if self.robot is not None:
            try:
                n_joints = int(self.robot.n_joints)
            except Exception:  # noqa: BLE001 - a model without n_joints: skip the length check
                n_joints = None
        seen: set[str] = set()
        self.n_frames = len(frames)
        for i, fr in enumerate(frames):
            self.check_frame(i, fr, seen, n_joints)
            if self.progress is not None:
                self.progress(i + 1, len(frames))

    def check_background(self, d: dict) -> None:
        bg = d.get("background_images")
        if bg is None:
            return
        if not isinstance(bg, dict):
            self.err("expected an object {camera: [paths]}", field="background_images")
            return
        for cam, lst in bg.items():
            fld = f"background_images.{cam}"
            if cam not in self.cameras and cam not in self.bad_cameras:
                self.err(f"unknown camera {cam!r}", field=fld)
                continue
            if not isinstance(lst, list) or not all(isinstance(p, str) for p in lst):
                self.err("expected a list of paths", field=fld)
                continue
            out = []
            for rel in lst:
                path = self.root / rel
                if not path.is_file():
                    self.err(f"file not found: {rel}", field=fld)
                    continue
                c = self.cameras.get(cam)
                size = self._image_size(path, "images", None if c is None else (c.width, c.height))
                if isinstance(size, InputError):
                    self.errors.append(InputError(size.message, file=str(path), field=fld))
                    continue
                if c is not None and size != (c.width, c.height):
                    self.err(
                        f"size {size[0]}x{size[1]} does not match camera {cam!r} ({c.width}x{c.height})",
                        field=fld,
                        file=str(path),
                    )
                    continue
                out.append(path.resolve())
            self.background[cam] = out

    def run(self) -> _Scan:
        d = self.read_json()
        if d is None:
            return self
        self.check_top(d)
        self.check_robot(d)
        self.check_cameras(d)
        self.check_frames(d)
        self.check_background(d)
        return self


# folders of jaxcr's other formats, recognised to say what a folder without dataset.json is
_OTHER_FORMATS = (
    ("stereo.json", "a jaxcr.stereo/1 stereo dataset, read by jaxcr stereo"),
    ("motion.json", "a jaxcr.motion/1 motion dataset, read by jaxcr motion"),
    ("scene.json", "a jaxcr.rgbd_scene/1 RGB-D scene, read by jaxcr model-object"),
    ("run.json", "a jaxcr segment output folder, read by jaxcr evaluate"),
)


def other_format_hint(folder: str | os.PathLike) -> str:
    """`` (this folder has stereo.json: a jaxcr.stereo/1 ..., read by jaxcr stereo)`` when
    ``folder`` holds another jaxcr format instead of a dataset.json, else ``""``."""
    folder = Path(folder)
    for name, what in _OTHER_FORMATS:
        if (folder / name).is_file():
            return f" (this folder has {name}: {what})"
    return ""


def _locate(path: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(path)
    if p.is_file() or p.name == DATASET_FILE:
        return p.parent, p
    return p, p / DATASET_FILE


def _scan(path, decode_images: bool, progress=None) -> _Scan:
    root, json_path = _locate(path)
    if not root.exists():
        s = _Scan(root, json_path, decode_images)
        s.errors.append(InputError("dataset folder not found", file=str(root)))
        return s
    return _Scan(root, json_path, decode_images, progress).run()


_BAD_CAMERA_SUFFIX = "has an invalid calibration"


def fold_camera_consequences(errors: list[InputError]) -> list[InputError]:
    """``errors`` with the per-frame "camera X has an invalid calibration" consequences of one
    broken camera folded into one line naming how many frames (and which) use that camera.

    One broken calibration file is one problem, not one per frame: this is the list
    ``jaxcr validate`` prints and whose length the loader's "(and N more problems)" counts.
    """
    out: list[InputError | list] = []
    folded: dict[str | None, list] = {}
    for e in errors:
        if e.frame is not None and e.message.endswith(_BAD_CAMERA_SUFFIX):
            if e.field in folded:
                folded[e.field][1].append(e.frame)
                continue
            folded[e.field] = [e, [e.frame]]
            out.append(folded[e.field])
        else:
            out.append(e)
    result = []
    for item in out:
        if isinstance(item, InputError):
            result.append(item)
            continue
        e, frames = item
        shown = ", ".join(str(f) for f in frames[:5])
        more = f" and {len(frames) - 5} more" if len(frames) > 5 else ""
        result.append(
            InputError(
                f"{e.message}: {len(frames)} frame(s) use it and cannot be processed "
                f"({shown}{more})",
                file=e.file,
                field=e.field,
            )
        )
    return result


@dataclass
class DatasetCheck:
    """Outcome of :func:`check_dataset`: dataset-level ``errors``, per-frame problems
    ``frame_errors`` (frame label -> errors, in file order), and counts for a report."""

    path: Path
    name: str
    robot_kind: str | None
    cameras: list[str]
    n_frames: int
    errors: list[InputError]
    frame_errors: dict[str, list[InputError]]

    @property
    def all_errors(self) -> list[InputError]:
        return list(self.errors) + [e for es in self.frame_errors.values() for e in es]

    @property
    def report_errors(self) -> list[InputError]:
        """:attr:`all_errors` for a report: the per-frame "camera has an invalid calibration"
        consequences of one broken camera are folded into one line naming how many frames
        (and which) use that camera; the camera's own error is reported as it is."""
        return fold_camera_consequences(self.all_errors)

    @property
    def n_bad_frames(self) -> int:
        return len(self.frame_errors)

    @property
    def ok(self) -> bool:
        return not self.errors and not self.frame_errors


def check_dataset(
    path: str | os.PathLike, decode_images: bool = True, progress=None
) -> DatasetCheck:
    """Validate the dataset at ``path`` and summarise it (see :func:`validate_dataset`).

    ``progress``: optional callback ``progress(done_frames, total_frames)``.
    """
    s = _scan(path, decode_images, progress)
    kind = s.robot_dict.get("kind") if isinstance(s.robot_dict, dict) else None
    return DatasetCheck(
        path=s.json_path,
        name=s.name,
        robot_kind=kind if isinstance(kind, str) else None,
        cameras=sorted(set(s.cameras) | s.bad_cameras),
        n_frames=s.n_frames,
        errors=list(s.errors),
        frame_errors=dict(s.frame_errors),
    )


def validate_dataset(path: str | os.PathLike, decode_images: bool = True) -> list[InputError]:
    """Every problem of the dataset at ``path`` (folder or its dataset.json); [] if clean.

    Dataset-level problems come first, then per-frame problems in file order. With
    ``decode_images`` (default) every image and mask is fully decoded, so corrupt files are
    found; otherwise only PNG/JPEG headers are read (sizes), which is much faster.
    """
    return check_dataset(path, decode_images).all_errors


def load_dataset(
    path: str | os.PathLike, *, strict: bool = False, decode_images: bool = False
) -> Dataset:
    """Load the dataset at ``path`` (folder or its dataset.json).

    Dataset-level problems raise :class:`InputErrors`. Frame-level problems put the frame in
    ``bad_frames`` (id -> "; "-joined messages), or raise with ``strict=True``. Images are not
    decoded here (only PNG/JPEG headers are read for the size check) unless ``decode_images``.
    The format is docs/dataset-format.md (``jaxcr.dataset/1``).

    Parameters
    ----------
    path : str or os.PathLike
        the dataset folder or its dataset.json.
    strict : bool
        raise for frame-level problems too, instead of listing them in ``bad_frames``.
    decode_images : bool
        decode every image while checking (slow; catches corrupt image data).

    Returns
    -------
    Dataset
        ``name``, ``robot`` (a model), ``cameras`` ({name: Camera}), ``frames`` (the good
        frames: ``id``, ``q``, ``tags``, image/mask paths, loaders), ``bad_frames``.

    Examples
    --------
    >>> import jaxcr as jcr
    >>> ds = jcr.load_dataset("my_dataset")  # e.g. written by `jaxcr synth`  # doctest: +SKIP
    >>> [f.id for f in ds.frames][:2], list(ds.cameras)  # doctest: +SKIP
    (['000000', '000001'], ['main'])
    """
    s = _scan(path, decode_images)
    if s.errors or (strict and s.frame_errors):
        errs = list(s.errors) + [e for es in s.frame_errors.values() for e in es]
        raise InputErrors(
            fold_camera_consequences(errs), where=f"jaxcr validate {s.root} lists them all"
        )
    bad = {k: "; ".join(e.format() for e in es) for k, es in s.frame_errors.items()}
    return Dataset(
        root=s.root.resolve(),
        name=s.name,
        robot=s.robot,
        robot_dict=s.robot_dict,
        cameras=s.cameras,
        frames=s.frames,
        bad_frames=bad,
        background_images=s.background,
        meta=s.meta,
    )


# --------------------------------------------------------------------------------- writing


def _dumps_dataset(d: dict[str, Any]) -> str:
    """dataset.json text: readable at the top level, one line per frame (compact for long
    datasets, still diff-friendly)."""
    parts = []
    for k, v in d.items():
        if k == "cameras" and isinstance(v, dict) and v:
            rows = ",\n".join(
                f"  {json.dumps(n)}: {json.dumps(c, allow_nan=False)}" for n, c in v.items()
            )
            parts.append(f' "cameras": {{\n{rows}\n }}')
        elif k == "frames":
            rows = ",\n".join("  " + json.dumps(f, allow_nan=False) for f in v)
            parts.append(f' "frames": [\n{rows}\n ]' if v else ' "frames": []')
        else:
            body = json.dumps(v, indent=1, allow_nan=False).replace("\n", "\n ")
            parts.append(f" {json.dumps(k)}: {body}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


def _frame_id(frame_id: str | int) -> str:
    if isinstance(frame_id, bool):
        raise ValueError("frame id must be a string or an int")
    if isinstance(frame_id, int):
        return f"{frame_id:06d}"
    if not isinstance(frame_id, str) or not frame_id or "/" in frame_id or "\\" in frame_id:
        raise ValueError(f"invalid frame id {frame_id!r}")
    return frame_id


class DatasetWriter:
    """Write a ``jaxcr.dataset/1`` dataset frame by frame.

    Signature (stable; ``jaxcr synth`` relies on it)::

        w = DatasetWriter(root, name, robot_dict, cameras, meta=None, overwrite=False)
        w.add_frame(frame_id, q, images, masks=None, full_masks=None, occluders=None,
                    tags=None, truth=None, meta=None) -> str          # the stored id
        w.add_background(camera, image) -> str                         # relative path
        w.close() -> Path                                              # path of dataset.json

    Args:
        root: output folder (created). If it already holds a dataset.json, ``overwrite=True``
            is required; that dataset.json is then removed first, so the folder never looks
            complete until :meth:`close`.
        name: dataset name.
        robot_dict: robot description (``robot_to_dict(model)``), or a model with ``to_dict``.
        cameras: ``{name: Camera}`` (stored inline) or ``{name: "calib/x.yaml"}`` (a
            calibration file already inside ``root``, stored as that relative path).
        meta: free-form JSON-able dict (generator, seed, ...).

    ``add_frame``: ``frame_id`` str (no slashes) or int (stored zero-padded to 6 digits);
    ``q`` (n_joints,) finite; ``images`` ``{camera: (H, W, 3) RGB}`` as float in [0, 1], uint8
    or uint16 (size must equal the camera's); ``masks``/``full_masks``/``occluders``
    ``{camera: bool (H, W)}``; ``truth`` ``{name: array}`` saved as ``truth/<id>[_name].npy``
    (``centreline`` -> ``truth/<id>.npy``) or a JSON-able scalar/list stored inline. Files go
    to ``images/<cam>/<id>.png``, ``masks/<cam>/<id>.png``, ``full/<cam>/<id>.png``,
    ``occluders/<cam>/<id>.png``, each written atomically.

    Usable as a context manager: ``close()`` runs on normal exit only.
    """

    _DIRS = {"images": "images", "masks": "masks", "full_masks": "full", "occluders": "occluders"}

    def __init__(
        self,
        root: str | os.PathLike,
        name: str,
        robot_dict: Mapping[str, Any] | Any,
        cameras: Mapping[str, Camera | str],
        meta: Mapping[str, Any] | None = None,
        overwrite: bool = False,
    ):
        self.root = Path(root)
        self.name = name
        if hasattr(robot_dict, "to_dict") and not isinstance(robot_dict, Mapping):
            robot_dict = robot_to_dict(robot_dict)
        self.robot_dict = dict(robot_dict)
        self.meta = dict(meta or {})
        json_path = self.root / DATASET_FILE
        if json_path.exists():
            if not overwrite:
                raise FileExistsError(f"{json_path} exists (pass overwrite=True to replace it)")
            json_path.unlink()
        self.root.mkdir(parents=True, exist_ok=True)
        self._cam_entries: dict[str, Any] = {}
        self.cameras: dict[str, Camera] = {}
        for cname, cam in cameras.items():
            if isinstance(cam, str):
                self.cameras[cname] = load_camera(self.root / cam)
                self._cam_entries[cname] = cam
            else:
                self.cameras[cname] = cam
                self._cam_entries[cname] = camera_to_dict(cam)
        self._frames: list[dict[str, Any]] = []
        self._ids: set[str] = set()
        self._background: dict[str, list[str]] = {}
        self._closed = False

    def _write_image(self, kind: str, cam: str, rel: str, array) -> str:
        if cam not in self.cameras:
            raise ValueError(f"{kind}: unknown camera {cam!r} (cameras: {sorted(self.cameras)})")
        a = np.asarray(array)
        c = self.cameras[cam]
        if a.shape[:2] != (c.height, c.width):
            raise ValueError(
                f"{kind}.{cam}: array of shape {a.shape} does not match camera size "
                f"{c.width}x{c.height} (expected (H, W, ...) = ({c.height}, {c.width}, ...))"
            )
        if kind != "images" and a.ndim != 2:
            raise ValueError(f"{kind}.{cam}: masks must be (H, W), got {a.shape}")
        if kind != "images":
            a = np.asarray(a, bool)
        write_png(self.root / rel, a)
        return rel

    def add_frame(
        self,
        frame_id: str | int,
        q: Sequence[float] | np.ndarray,
        images: Mapping[str, np.ndarray],
        masks: Mapping[str, np.ndarray] | None = None,
        full_masks: Mapping[str, np.ndarray] | None = None,
        occluders: Mapping[str, np.ndarray] | None = None,
        tags: Sequence[str] | None = None,
        truth: Mapping[str, Any] | None = None,
        meta: Mapping[str, Any] | None = None,
    ) -> str:
        """Write one frame's files and record it; returns the stored frame id."""
        if self._closed:
            raise RuntimeError("DatasetWriter is closed")
        fid = _frame_id(frame_id)
        if fid in self._ids:
            raise ValueError(f"duplicate frame id {fid!r}")
        qa = np.asarray(q, np.float64).reshape(-1)
        if not np.all(np.isfinite(qa)):
            raise ValueError(f"frame {fid}: q contains NaN or infinity")
        if not images:
            raise ValueError(f"frame {fid}: at least one image is required")
        entry: dict[str, Any] = {"id": fid, "q": qa.tolist()}
        for kind, maps in (
            ("images", images),
            ("masks", masks),
            ("full_masks", full_masks),
            ("occluders", occluders),
        ):
            if maps:
                entry[kind] = {
                    cam: self._write_image(kind, cam, f"{self._DIRS[kind]}/{cam}/{fid}.png", a)
                    for cam, a in maps.items()
                }
        if tags:
            entry["tags"] = [str(t) for t in tags]
        if truth:
            tr: dict[str, Any] = {}
            for k, v in truth.items():
                if isinstance(v, np.ndarray) or (
                    hasattr(v, "__array__") and not isinstance(v, list)
                ):
                    rel = f"truth/{fid}.npy" if k == "centreline" else f"truth/{fid}_{k}.npy"
                    path = self.root / rel
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.npy")
                    np.save(tmp, np.asarray(v))
                    os.replace(tmp, path)
                    tr[k] = rel
                else:
                    tr[k] = v
            entry["truth"] = tr
        if meta:
            entry["meta"] = dict(meta)
        self._frames.append(entry)
        self._ids.add(fid)
        return fid

    def add_background(self, camera: str, image: np.ndarray) -> str:
        """Write a robot-free view for ``camera``; returns its relative path."""
        if camera not in self.cameras:
            raise ValueError(f"background: unknown camera {camera!r}")
        lst = self._background.setdefault(camera, [])
        rel = self._write_image("images", camera, f"background/{camera}/{len(lst):04d}.png", image)
        lst.append(rel)
        return rel

    def to_dict(self) -> dict[str, Any]:
        """The dataset.json content as it would be written now."""
        d: dict[str, Any] = {
            "format": FORMAT,
            "name": self.name,
            "robot": self.robot_dict,
            "cameras": self._cam_entries,
            "frames": self._frames,
        }
        if self._background:
            d["background_images"] = self._background
        if self.meta:
            d["meta"] = self.meta
        return d

    def close(self) -> Path:
        """Write dataset.json (atomically: temp file then rename) and return its path."""
        path = self.root / DATASET_FILE
        tmp = self.root / f".{DATASET_FILE}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(_dumps_dataset(self.to_dict()))
        os.replace(tmp, path)
        self._closed = True
        return path

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and not self._closed:
            self.close()
