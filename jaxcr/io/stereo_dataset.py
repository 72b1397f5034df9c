"""``stereo.json``: the stereo dataset format ``jaxcr.stereo/1`` (docs/stereo-format.md) and its
reader. ``load_stereo_dataset`` parses and validates a dataset (one-line InputErrors naming file,
frame and field); ``read_rgb`` reads one view. Used by ``jaxcr stereo``, tests and experiments."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.jsonfile import read_json

FORMAT = "jaxcr.stereo/1"
# stereo.json's keys ("base": the marker-free base of issue 16 item 1, parsed by parse_base)
STEREO_JSON_KEYS = ("format", "calibration", "cameras", "markers", "robot_base", "base",
                    "background", "background_plates", "frames", "meta", "unit")  # fmt: skip


def _read_rgb(path: Path, frame=None, size=None, field=None) -> np.ndarray:
    """8-bit RGB (H, W, 3) (grey, RGBA and 16-bit files are converted by OpenCV); ``size``
    (width, height) is checked when given. InputError naming the file otherwise."""
    from jaxcr.io.images import read_image

    try:
        img = read_image(path)  # float RGB in [0, 1]; one-line errors for missing/corrupt
    except InputError as err:
        raise InputError(err.message, file=err.file, frame=frame, field=field) from None
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise InputError(
            f"image is {img.shape[1]}x{img.shape[0]}, the calibration is {size[0]}x{size[1]}",
            file=str(path),
            frame=frame,
            field=field,
        )
    return np.round(img * 255.0).astype(np.uint8)


def _finite_tuple(v, n: int, file: str, field: str) -> tuple[float, ...]:
    """``v`` as a tuple of ``n`` finite floats, else InputError naming ``field``."""
    if (
        not isinstance(v, list)
        or len(v) != n
        or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v)
        or not all(np.isfinite(v))
    ):
        raise InputError(f"expected {n} finite numbers, got {v!r}", file=file, field=field)
    return tuple(float(x) for x in v)


BASE_FORMS = ("T_cam_base", "entry_px", "markers")
# The two entry pixels must be images of one point: their rays pass within this many pixels
# (reprojection error of the triangulated point) -- a few pixels of clicking error pass,
# a swapped camera order or a wrong point does not.
ENTRY_MAX_RESIDUAL_PX = 10.0
# The base of a robot camera 1 sees is at least this far from its centre (metres).
BASE_MIN_DISTANCE_M = 0.01


def parse_base(base, file: str, names: list[str], cam1, cam2, scale: float = 1.0):
    """``stereo.json``'s ``"base"`` (None: the markers) as a
    :class:`jaxcr.stereo.base_frame.BaseSpec`; InputError naming ``base.<field>``.
    ``scale``: metres per unit of the file's lengths (its top-level ``unit``), applied to
    ``T_cam_base``'s translation before its plausibility check."""
    from jaxcr.stereo.base_frame import BaseSpec, triangulate_entry

    if base is None:
        if len(names) == 1:
            raise InputError(
                "a one-camera dataset needs base.entry_px or base.T_cam_base (no stereo "
                "marker pose from one view)",
                file=file,
                field="base",
            )
        return BaseSpec()
    if not isinstance(base, dict) or len(base) != 1 or next(iter(base)) not in BASE_FORMS:
        keys = list(base) if isinstance(base, dict) else base
        raise InputError(
            f"expected an object with exactly one of {list(BASE_FORMS)}, got {keys!r}",
            file=file,
            field="base",
        )
    ((kind, value),) = base.items()
    if kind == "markers":
        if len(names) == 1:
            raise InputError(
                "one camera cannot give the base from markers; use entry_px or T_cam_base",
                file=file,
                field="base.markers",
            )
        return BaseSpec()
    if kind == "T_cam_base":
        from jaxcr.io.calibration import check_transform
        from jaxcr.io.units import check_length

        # The translation is a length in the file's unit: convert it before the 5 m check,
        # so a file in mm that says so is not refused with advice to say so.
        T = check_transform(value, file, "base.T_cam_base", scale)
        # A base nearer than 1 cm to camera 1's centre cannot be seen by it: almost always
        # metres written under "unit": "mm" (or cm).
        check_length(float(np.linalg.norm(T[:3, 3])), "base translation", scale, file,
                     "base.T_cam_base", lo=BASE_MIN_DISTANCE_M)  # fmt: skip
        return BaseSpec("T_cam_base", T_cam1_base=T)
    if not isinstance(value, dict) or set(value) != set(names):
        got = sorted(value) if isinstance(value, dict) else value
        raise InputError(
            f"expected {{camera: [u, v]}} for the cameras {names}, got {got!r}",
            file=file,
            field="base.entry_px",
        )
    px = []
    for n, cam in zip(names, (cam1, cam2), strict=False):
        uv = _finite_tuple(value[n], 2, file, f"base.entry_px.{n}")
        if not (-0.5 <= uv[0] <= cam.width - 0.5 and -0.5 <= uv[1] <= cam.height - 0.5):
            raise InputError(
                f"pixel {list(uv)} is outside the {cam.width}x{cam.height} image",
                file=file,
                field=f"base.entry_px.{n}",
            )
        px.append(uv)
    if len(names) == 2:
        _, residual, depths = triangulate_entry(cam1, cam2, px[0], px[1])
        if min(depths) <= 0 or residual > ENTRY_MAX_RESIDUAL_PX:
            raise InputError(
                "the entry pixels are not images of one point in front of both cameras "
                f"(reprojection {residual:.1f} px, limit {ENTRY_MAX_RESIDUAL_PX:g}); check "
                "the pixels and the camera order",
                file=file,
                field="base.entry_px",
            )
    return BaseSpec("entry_px", entry_px=tuple(px))


def load_stereo_dataset(folder: str | os.PathLike) -> dict:
    """Parse ``stereo.json`` (see module docstring): returns ``{"root", "meta", "cam1",
    "cam2", "config", "plates", "frames"}`` (``config.calibration``: the calibration file's
    ``uncertainty`` block, :func:`jaxcr.io.calibration.load_stereo_uncertainty`, or None).
    Bad input raises :class:`InputError`."""
    from jaxcr.io.calibration import load_stereo
    from jaxcr.io.dataset import is_safe_frame_id
    from jaxcr.stereo.aruco import MarkerLayout
    from jaxcr.stereo.chroma import KEY_COLOURS
    from jaxcr.stereo.pipeline import StereoConfig

    root = Path(folder)
    path = root / "stereo.json" if root.is_dir() else root
    root = path.parent
    file = str(path)
    if not path.exists():
        raise InputError("no stereo.json found", file=file)
    meta = read_json(path)
    if not isinstance(meta, dict):
        raise InputError("expected a JSON object at the top level", file=file)
    if meta.get("format") != FORMAT:
        raise InputError(
            f"expected format {FORMAT!r}, got {meta.get('format')!r}", file=file, field="format"
        )
    if not isinstance(meta.get("calibration"), str):
        raise InputError("missing required key (a path string)", file=file, field="calibration")
    from jaxcr.io.units import check_known_keys, check_length, unit_scale

    check_known_keys(meta, STEREO_JSON_KEYS, file)
    scale = unit_scale(meta, file)
    names = meta.get("cameras", ["cam1", "cam2"])
    if (
        not isinstance(names, list)
        or len(names) not in (1, 2)
        or not all(isinstance(n, str) and n for n in names)
        or len(set(names)) != len(names)
    ):
        raise InputError("expected one or two distinct camera names", file=file, field="cameras")
    calibration = None
    if len(names) == 2:
        from jaxcr.io.calibration import load_stereo_uncertainty

        cam1, cam2 = load_stereo(root / meta["calibration"])
        # the calibration file's "uncertainty" block (jaxcr calibrate writes it): the tips'
        # re-search under --segmentation trace is flagged by it (docs/decisions.md S37)
        calibration = load_stereo_uncertainty(root / meta["calibration"])
    else:
        from jaxcr.io.calibration import load_camera

        cam1, cam2 = load_camera(root / meta["calibration"]), None
    markers = meta.get("markers")
    base = meta.get("base")
    if isinstance(base, dict) and "markers" in base:
        if markers is not None:
            raise InputError(
                "the marker layout is given twice (top-level 'markers' and base.markers)",
                file=file,
                field="base.markers",
            )
        markers = base["markers"]
    field_m = "base.markers" if isinstance(base, dict) and "markers" in base else "markers"
    try:
        layout = MarkerLayout.from_dict(markers) if markers is not None else MarkerLayout()
    except (AttributeError, KeyError, TypeError, ValueError, IndexError):
        raise InputError(
            "bad marker layout (expected {'centres': {id: [x, y]}, 'size': metres})",
            file=file,
            field=field_m,
        ) from None
    if markers is not None:
        if not all(np.isfinite(v) for c in layout.centres.values() for v in c) or not np.isfinite(
            layout.size
        ):
            raise InputError("marker layout has NaN or infinite values", file=file, field=field_m)
        layout = MarkerLayout(
            {k: (c[0] * scale, c[1] * scale) for k, c in layout.centres.items()},
            layout.size * scale,
            layout.dictionary,
        )
        check_length(
            layout.size,
            "marker size",
            scale,
            file,
            f"{field_m}.size",
            lo=1e-3,
            hi=1.0,
            typical=0.02,
        )
        for k, c in layout.centres.items():
            check_length(float(np.hypot(*c)), "marker centre distance", scale, file,
                         f"{field_m}.centres.{k}")  # fmt: skip
    spec = parse_base(base, file, names, cam1, cam2, scale)
    bg = meta.get("background", {})
    if not isinstance(bg, dict):
        raise InputError("expected an object", file=file, field="background")
    if "key_rgb" in bg:
        key = _finite_tuple(bg["key_rgb"], 3, file, "background.key_rgb")
    else:
        name = bg.get("key", "green")
        if not isinstance(name, str) or name not in KEY_COLOURS:
            raise InputError(f"unknown key colour {name!r}", file=file, field="background.key")
        key = KEY_COLOURS[name]
    cfg = StereoConfig(layout=layout, key_rgb=key, base=spec, calibration=calibration)
    if meta.get("robot_base") is not None:
        base_xyz = tuple(
            v * scale for v in _finite_tuple(meta["robot_base"], 3, file, "robot_base")
        )
        check_length(
            float(np.linalg.norm(base_xyz)), "robot_base distance", scale, file, "robot_base"
        )
        cfg.robot_base = base_xyz
        if spec.mode == "entry_px":
            raise InputError(
                "robot_base has no meaning with base.entry_px (the base origin is the "
                "triangulated entry point); remove it",
                file=file,
                field="robot_base",
            )
    sizes = {n: (c.width, c.height) for n, c in zip(names, (cam1, cam2), strict=False)}
    plates = None
    if meta.get("background_plates"):
        bp = meta["background_plates"]
        if not isinstance(bp, dict) or any(not isinstance(bp.get(n), str) for n in names):
            missing = [
                n for n in names if not isinstance(bp, dict) or not isinstance(bp.get(n), str)
            ]
            raise InputError(
                f"expected {{camera: path}} for cameras {names}; no plate path for "
                + ", ".join(repr(n) for n in missing),
                file=file,
                field="background_plates",
            )
        plates = tuple(
            _read_rgb(root / bp[n], size=sizes[n], field=f"background_plates.{n}") for n in names
        )
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError("no frames", file=file, field="frames")
    seen: set[str] = set()
    for k, fr in enumerate(frames):
        if (
            not isinstance(fr, dict)
            or "id" not in fr
            or not isinstance(fr.get("images"), dict)
            or any(not isinstance(fr["images"].get(n), str) for n in names)
        ):
            raise InputError(
                f"frame {k} needs an id and images for {names}", file=file, field="frames"
            )
        fid = fr["id"]
        if isinstance(fid, bool) or not isinstance(fid, str | int) or not str(fid).strip():
            raise InputError(f"expected a string id, got {fid!r}", file=file, frame=k, field="id")
        if not is_safe_frame_id(str(fid)):
            raise InputError(
                f"frame id {str(fid)!r} is not usable as a file name (no '/', '\\', control "
                "characters, '.' or '..')",
                file=file,
                frame=k,
                field="id",
            )
        if str(fid) in seen:
            raise InputError(f"duplicate frame id {str(fid)!r}", file=file, frame=k, field="id")
        seen.add(str(fid))
    return {"root": root, "meta": meta, "names": names, "cam1": cam1, "cam2": cam2,
            "config": cfg, "plates": plates, "frames": frames}  # fmt: skip


# ------------------------------------------------------------------------------ outputs


read_rgb = _read_rgb
