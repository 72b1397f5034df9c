"""``jaxcr stereo DATASET -o OUT``: 3-D backbone shape sensing from calibrated stereo pairs
(base frame, chroma key, thinning, triangulation, diameters, segments, plane and arc fits;
see :mod:`jaxcr.stereo.pipeline`), or the 2-D results of one camera. ``jaxcr stereo synth
-o OUT`` writes a synthetic stereo set (:mod:`jaxcr.synth.stereo_ctr`).

DATASET is a folder with ``stereo.json`` (format ``jaxcr.stereo/1``)::

    {"format": "jaxcr.stereo/1", "calibration": "calib/stereo.yaml",
     "cameras": ["cam1", "cam2"],                   # or one camera: ["cam1"]
     "base": {"T_cam_base": 4x4} | {"entry_px": {"cam1": [u, v], "cam2": [u, v]}}
             | {"markers": {...}},                  # optional, default: the markers
     "markers": {"centres": {"2": [0, 0], "3": [0.06, 0], ...}, "size": 0.024,
                 "dictionary": "DICT_4X4_50"},      # the ArUco layout (or in base.markers)
     "robot_base": [x, y, z],                       # optional, base frame (unit)
     "background": {"key": "green"} | {"key_rgb": [r, g, b]},
     "background_plates": {"cam1": "background/cam1.png", ...},   # optional
     "frames": [{"id": "000", "images": {"cam1": "...png", "cam2": "...png"}}, ...],
     "unit": "m"}                                   # optional: "m", "cm" or "mm"

``unit`` (default ``"m"``) is the unit of the lengths in stereo.json (marker centres and size,
``robot_base``, ``T_cam_base``'s translation); they are converted to metres. The calibration
file has its own ``unit``. An unknown top-level key is refused with the nearest known key, and
implausible lengths (marker size outside 1 mm..1 m, positions over 5 m, a base under 10 mm
from camera 1) are refused with a suggested unit.

The base frame ("base"; docs/stereo-format.md):

- ``{"markers": layout}`` or no "base": four ArUco markers on the base plate (origin at
  marker 2's centre, z out of the plate); the robot leaves the plate at ``robot_base``
  (default: the layout's base centre).
- ``{"T_cam_base": 4x4}``: the base frame in camera 1's frame (base -> camera 1, in unit),
  fixed; the robot enters at ``robot_base`` (default: the base origin).
- ``{"entry_px": {cam: [u, v]}}``: the pixel where the robot enters each view (OpenCV
  pixels: the centre of pixel (0, 0) is (0, 0); distorted image). Origin: that point
  triangulated (the two pixels must reproject within 10 px); z: the tube's initial
  direction, per frame, from the refined backbone's first 12 mm (a quadratic through
  the origin); x: camera 1's x axis (image right) made perpendicular to z (camera 1's y
  axis when z is within 18 deg of it); y = z x x. ``robot_base`` is not allowed.

The calibration is an OpenCV FileStorage stereo file as ``cv2.stereoCalibrate`` users
save it (``K1 D1 K2 D2 R T [E F]``, image sizes; read by :mod:`jaxcr.io.calibration`); with
one camera, a single-camera file (``camera_matrix``, ``distortion_coefficients``, size).
A stereo file's optional ``uncertainty`` block (``jaxcr calibrate`` writes it) or
``--calibration-sigma`` gives the tips' re-search under ``--segmentation trace`` its
tolerance (docs/stereo-format.md, "The calibration's uncertainty"; without either: 5 px).
One camera gives the 2-D results alone (tip pixel and backbone polyline, no triangulation,
no segments); its base must be ``entry_px`` or ``T_cam_base`` (projected). With
``--segmentation trace`` its tip is the view's own traced tip (``tip_source`` ``"trace"``).
With the chroma key and no second view to check it, a run whose key mask looks like a real
background (:func:`jaxcr.stereo.key_check.key_mask_check`) prints one WARNING line naming
the frames.

Segmentation (``--segmentation``, default ``auto``): ``trace`` when stereo.json gives
``background_plates`` (the plate foreground, made for real backgrounds: creases, shadows,
tape, a dark tube), else ``chroma``; a rerun into an earlier OUT keeps the mode its
run.json recorded. The first line printed names the mode and why
(``segmentation: trace (auto: background plates given)``).

Outputs in OUT (written as frames complete; a rerun into the same OUT skips frames already
done, and is refused if the dataset or options differ from ``OUT/run.json``):

- ``results.jsonl`` (records ``jaxcr.stereo-results/2``): one line per frame: ``format``,
  ``id``, ``segmentation`` (the mode used), ``ok``, ``reason`` and ``message`` on failure (``calibration_size``, ``markers``,
  ``base``, ``robot_not_found``, ``correspondence``, ``image``); on success ``views``:
  per camera ``{"tip_px": [u, v], "backbone_px": [[u, v], ...]}`` (OpenCV pixels, the
  view's ordered skeleton from the base every 2 px, ending at the tip pixel, where the
  skeleton continued straight leaves the robot's mask), and for two cameras ``base_mode``,
  marker RMS, ``entry_residual_px``, number of segments, ``single_view_mm`` (the tail
  seen by one view only), stage timings;
- ``frames/<id>.json`` (``jaxcr.stereo-frame/2``) and ``frames/<id>.npz``: the 3-D
  backbone (base frame, metres: ``s``, ``p``, ``diameter``, ``single_view`` flags: True
  where one view alone saw the tube and the joint chain fit gave the point), boundaries,
  the per-segment table, the base pose, ``views``; one camera: ``views`` and ``base_px``;
- ``overlays/<id>_<cam>.png``: backbone coloured by segment on the views;
- ``segments.csv`` and ``segments.md``: the per-segment parameter table of all frames
  (``single_view_mm``: the part of the segment from the single-view tail).

``--shard I/N`` (Slurm arrays, docs/scale-out.md): only the I-th of N contiguous frame
blocks; ``frames/`` and ``overlays/`` go to OUT, ``results.jsonl``, ``run.json`` and the
shard's ``segments.csv``/``.md`` to ``OUT/shards/I-of-N/``.

Exit code 0 when every frame succeeded, 1 when any frame failed, 2 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from jaxcr.cli._common import seed as _seed
from jaxcr.cli._plate import add_plate_arguments, plate_config, plate_flags_given
from jaxcr.errors import InputError
from jaxcr.io.exported import cached_call
from jaxcr.io.stereo_dataset import (  # noqa: F401  (re-exported for existing callers)
    FORMAT,
    STEREO_JSON_KEYS,
    _finite_tuple,
    _read_rgb,
    load_stereo_dataset,
    parse_base,
)

# Output record formats (v2: per-camera 2-D results, base mode, the single-view tail).
RESULTS_FORMAT = "jaxcr.stereo-results/2"
FRAME_FORMAT = "jaxcr.stereo-frame/2"
TABLE_FIELDS = [
    "frame", "segment", "s_start_mm", "s_end_mm", "length_mm", "diameter_mm",
    "phi_xy_deg", "phi_zx_deg", "phi_yz_deg", "curvature_1pm", "arc_length_fit_mm",
    "arc_rms_mm", "single_view_mm",
]  # fmt: skip


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "stereo",
        help="3-D backbone shape sensing from stereo pairs (or 'synth' for a synthetic set)",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("dataset", help="stereo dataset folder (stereo.json), or 'synth'")
    p.add_argument("-o", "--out", required=True, help="output folder (created if missing)")
    p.add_argument(
        "--segmentation",
        choices=["auto", *SEGMENTATIONS],
        default=None,
        help="auto (default): trace when stereo.json gives background_plates, else chroma "
        "(a rerun into an earlier OUT keeps the mode recorded in its run.json); chroma key, "
        "plate difference, plate after the best shadow gain, both, or trace: the plate "
        "foreground for real backgrounds (aligned plate, cues beyond the key colour, the tube "
        "traced from the robot base with gaps bridged; see the --plate-... flags; each "
        "view's tip_px is the traced tip corrected for the end face with both views, its "
        "tip_source recorded: docs/stereo-format.md). The mode used is printed first and "
        "recorded in run.json and every results.jsonl record (segmentation)",
    )
    p.add_argument("--tolerance", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="chroma-key score ramp (default 0.5 0.8)")  # fmt: skip
    p.add_argument("--segments", type=int, default=None, help="number of tubes if known")
    p.add_argument("--no-overlays", action="store_true", help="skip the overlay PNGs")
    p.add_argument("--frames", type=int, default=8, help="synth: number of frames")
    p.add_argument("--seed", type=_seed, default=0, help="synth: random seed")
    p.add_argument("--size", default="640x480",
                   help="synth: image size WxH (at least 64x48, height >= 9/16 width)")  # fmt: skip
    p.add_argument("--background", choices=["green", "blue"], default="green",
                   help="synth: chroma cloth colour")  # fmt: skip
    from jaxcr.scale.executor import add_executor_arguments
    from jaxcr.scale.shards import add_shard_argument

    add_shard_argument(p)
    add_executor_arguments(p, "1 frame")
    p.add_argument(
        "--calibration-sigma",
        default=None,
        metavar="SPEC",
        help="the rig's calibration uncertainty, for --segmentation trace: the tips' "
        "re-search acts only on tips further from each other's epipolar lines than 3 "
        "standard deviations of right tips' distance under it (at least 5 px; "
        "docs/decisions.md S37). Default: the calibration file's 'uncertainty' block "
        "(jaxcr calibrate writes it), or, without one, none: the fixed 5 px. 'none': the "
        "fixed 5 px. Or by hand, standard deviations: "
        "focal_rel=0.002,principal_px=1,rotation_deg=0.05,translation_mm=0.3 (focal "
        "lengths relative; principal point px; the rotation and translation between the "
        "two cameras, R and T, per axis; translation_m/_cm/_mm)",
    )
    add_plate_arguments(p, "--segmentation trace, or auto with background_plates")
    p.set_defaults(func=run)


# ------------------------------------------------------------------------------ loading


def _atomic_write(path: Path, data: bytes) -> None:
    from jaxcr.io.results import atomic_write_bytes

    atomic_write_bytes(path, data)  # temporary name + rename; a failed write names the file


FRAME_DESCRIPTIONS = {
    "markers": "base (origin: centre of ArUco marker 2; metres)",
    "T_cam_base": "base (the given T_cam_base; metres)",
    "entry_px": "base (origin: the triangulated entry point; z: the tube's initial direction; "
    "x: camera 1's x axis made perpendicular to z; metres)",
}


def _frame_json(fid: str, r: dict, names) -> dict:
    views = {n: v for n, v in zip(names, r["views_px"], strict=True)}
    if "p" not in r:  # one camera: the 2-D results alone
        return {"format": FRAME_FORMAT, "id": fid, "cameras": list(names),
                "base_px": r["base_px"], "views": views}  # fmt: skip
    return {
        "format": FRAME_FORMAT,
        "id": fid,
        "frame": FRAME_DESCRIPTIONS[r["base_mode"]],
        "base_mode": r["base_mode"],
        "s": r["s"].tolist(),
        "p": r["p"].tolist(),
        "single_view": r["single_view"].tolist(),
        "s_stereo_end": r["s_stereo_end"],
        "diameter": r["diameter"].tolist(),
        "boundary_s": r["boundary_s"].tolist(),
        "boundary_p": r["boundary_p"].tolist(),
        "segments": r["segments"],
        "T_cam1_base": np.asarray(r["T_cam1_base"]).tolist(),
        "T_cam2_base": np.asarray(r["T_cam2_base"]).tolist(),
        "marker_rms_px": r["marker_rms_px"],
        "entry_residual_px": r["entry_residual_px"],
        "views": views,
    }


def _write_frame(out: Path, fid: str, r: dict, names) -> None:
    (out / "frames").mkdir(exist_ok=True)
    if "p" in r:
        buf = io.BytesIO()
        np.savez(buf, s=r["s"], p=r["p"], single_view=r["single_view"], diameter=r["diameter"],
                 diameter_views=r["diameter_views"], diameter_report=r["diameter_report"],
                 boundary_s=r["boundary_s"], boundary_p=r["boundary_p"],
                 T_cam1_base=r["T_cam1_base"], T_cam2_base=r["T_cam2_base"])  # fmt: skip
        _atomic_write(out / "frames" / f"{fid}.npz", buf.getvalue())
    data = json.dumps(_frame_json(fid, r, names)) + "\n"
    _atomic_write(out / "frames" / f"{fid}.json", data.encode())


def _write_overlays(out: Path, fid: str, names, images, cams, r) -> None:
    from jaxcr.stereo.overlay import draw_overlay

    (out / "overlays").mkdir(exist_ok=True)
    for k, (n, im, cam) in enumerate(zip(names, images, cams, strict=False)):
        if "p" in r:
            ov = draw_overlay(im, cam, r, k, scale=1)
        else:  # one camera: the 2-D backbone and the tip
            ov = np.ascontiguousarray(im).copy()
            line = np.round(np.asarray(r["views_px"][k]["backbone_px"]) * 16).astype(np.int32)
            cv2.polylines(ov, [line], False, (255, 0, 255), 2, cv2.LINE_AA, 4)
            tip = np.round(np.asarray(r["views_px"][k]["tip_px"])).astype(int)
            cv2.drawMarker(ov, (int(tip[0]), int(tip[1])), (255, 255, 0), cv2.MARKER_CROSS, 14, 1)
        ok, png = cv2.imencode(".png", cv2.cvtColor(ov, cv2.COLOR_RGB2BGR))
        _atomic_write(out / "overlays" / f"{fid}_{n}.png", png.tobytes())


def _read_log_list(path: Path) -> list[dict]:
    return list(_read_log(path).values())


def _read_log(path: Path) -> dict[str, dict]:
    done: dict[str, dict] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by an interrupted run
            done[rec["id"]] = rec
    return done


def write_tables(out: Path, frame_ids: list[str], table_dir: Path | None = None) -> int:
    """Collect ``frames/<id>.json`` into ``segments.csv`` and ``segments.md`` (in
    ``table_dir``, default ``out``); returns rows."""
    table_dir = out if table_dir is None else table_dir
    rows = []
    for fid in frame_ids:
        f = out / "frames" / f"{fid}.json"
        if f.exists():
            for seg in json.loads(f.read_text()).get("segments", []):
                rows.append({"frame": fid, **{k: seg[k] for k in TABLE_FIELDS if k != "frame"}})
    sio = io.StringIO()
    w = csv.DictWriter(sio, fieldnames=TABLE_FIELDS, lineterminator="\n")
    w.writeheader()
    for row in rows:
        w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()})
    _atomic_write(table_dir / "segments.csv", sio.getvalue().encode())
    md = ["| " + " | ".join(TABLE_FIELDS) + " |", "|" + "---|" * len(TABLE_FIELDS)]
    for row in rows:
        md.append(
            "| "
            + " | ".join(
                f"{row[k]:.3f}" if isinstance(row[k], float) else str(row[k]) for k in TABLE_FIELDS
            )
            + " |"
        )
    _atomic_write(table_dir / "segments.md", ("\n".join(md) + "\n").encode())
    return len(rows)


# ------------------------------------------------------------------------------ running


RUN_FORMAT = "jaxcr.stereo-run/2"

#: The segmentation modes of :class:`jaxcr.stereo.pipeline.StereoConfig` (``--segmentation``
#: also takes ``auto``, resolved by :func:`segmentation_mode`).
SEGMENTATIONS = ("chroma", "plate", "plate_shadow", "both", "trace")


def recorded_segmentation(out: str | os.PathLike) -> tuple[str, Path] | None:
    """The segmentation recorded by an earlier run in OUT (``OUT/run.json`` or a shard's),
    with the file it was read from; None when OUT holds no stereo run."""
    from jaxcr.scale.shards import shard_dirs

    out = Path(out)
    if not out.is_dir():
        return None
    for f in [out / "run.json"] + [d / "run.json" for _, d in shard_dirs(out)]:
        try:
            prev = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError):
            continue
        if isinstance(prev, dict) and prev.get("format") == RUN_FORMAT:
            seg = (prev.get("options") or {}).get("segmentation")
            if seg in SEGMENTATIONS:
                return seg, f
    return None


def segmentation_mode(
    requested: str | None, plates_given: bool, out: str | os.PathLike
) -> tuple[str, str]:
    """``--segmentation`` resolved: ``(mode, why)``. A mode other than ``auto`` is used as
    given. ``auto`` (or no flag): the mode an earlier run recorded in OUT's run.json (a
    rerun continues it, also one written before ``auto`` existed, whose default was chroma);
    else ``trace`` when the dataset gives background plates (the plate foreground for real
    backgrounds: docs/decisions.md S32), else ``chroma``."""
    if requested not in (None, "auto"):
        return requested, f"--segmentation {requested}"
    rec = recorded_segmentation(out)
    if rec is not None:
        return rec[0], f"auto: recorded by the earlier run in {rec[1]}"
    if plates_given:
        return "trace", "auto: background plates given"
    return "chroma", "auto: no background plates in stereo.json"


def _check_run(out: Path, dataset: dict, log_dir: Path | None = None) -> None:
    """Write ``OUT/run.json`` (dataset and options) on the first run; a rerun into the same
    OUT continues it only with the same dataset and options (frames already in results.jsonl
    are skipped, so different options would silently mix two configurations)."""
    from jaxcr.io import results as R

    cfg = dataset["config"]
    info = {
        "format": RUN_FORMAT,
        "dataset": str(Path(dataset["root"]).resolve()),
        # how the mode in options was chosen (not compared on a rerun: options are)
        "segmentation_choice": dataset.get("segmentation_choice"),
        "options": {
            "segmentation": cfg.segmentation,
            "tolerance": [cfg.tol_lo, cfg.tol_hi],
            "segments": cfg.n_segments,
        },
    }
    if cfg.segmentation == "trace":
        import dataclasses

        info["options"]["plate"] = dataclasses.asdict(cfg.plate_foreground)
        if cfg.calibration is not None:  # (absent: the fixed 5 px, as before S37)
            info["options"]["calibration_sigma"] = dataclasses.asdict(cfg.calibration)
    from jaxcr.scale.shards import shard_dirs

    log_dir = out if log_dir is None else log_dir
    path = log_dir / "run.json"
    # every part of one job (OUT's own run, each shard's) has the same dataset and options
    for other in [out / "run.json"] + [d / "run.json" for _, d in shard_dirs(out)]:
        if other != path and other.exists():
            _same_run(other, info)
    if path.exists():
        _same_run(path, info)
        return
    if (log_dir / "results.jsonl").exists() or (log_dir == out and (out / "frames").exists()):
        raise InputError(
            "OUT holds stereo results without run.json (an older jaxcr); choose a new -o",
            file=str(out),
        )
    R.atomic_write_json(path, info)


def _same_run(path: Path, info: dict) -> None:
    """Refuse when the run.json at ``path`` has another dataset or options than ``info``."""
    from jaxcr.io import results as R

    try:
        prev = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        prev = None
    if not isinstance(prev, dict) or prev.get("format") != RUN_FORMAT:
        raise InputError("not a jaxcr stereo run.json; choose another -o", file=str(path))
    for key in ("dataset", "options"):
        if R.to_jsonable(prev.get(key)) != R.to_jsonable(info[key]):
            raise InputError(
                f"OUT holds a run with different {key} ({prev.get(key)!r} vs {info[key]!r}); "
                "choose a new -o or delete it",
                file=str(path),
                field=key,
            )


class StereoWorker:
    """Reconstructs frames of a loaded dataset into ``out`` (files written atomically) and
    returns their records: the worker of :func:`jaxcr.scale.executor.run_frames`."""

    def __init__(self, dataset: dict, out: str | os.PathLike, overlays: bool = True):
        self.dataset, self.out, self.overlays = dataset, Path(out), overlays
        self.frames = {str(fr["id"]): fr for fr in dataset["frames"]}
        self.compile_s = self.run_s = 0.0

    def failed_record(self, fid: str, reason: str) -> dict:
        return {"format": RESULTS_FORMAT, "id": fid,
                "segmentation": self.dataset["config"].segmentation, "ok": False,
                "reason": "worker", "message": reason}  # fmt: skip

    def process(self, frame_ids: list[str]) -> Iterator[dict]:
        """Yield each frame's record as soon as its files are written (the caller appends it
        to results.jsonl at once, so an interrupted run keeps every finished frame)."""
        import time

        for fid in frame_ids:
            t0 = time.perf_counter()
            rec = self._frame(self.frames[fid])
            self.run_s += time.perf_counter() - t0
            yield rec

    def _frame(self, fr: dict) -> dict:
        from jaxcr.stereo.pipeline import StereoFailure, reconstruct_pair
        from jaxcr.stereo.single_view import reconstruct_view

        dataset, out, overlays = self.dataset, self.out, self.overlays
        names = dataset["names"]
        cams = (dataset["cam1"], dataset["cam2"])[: len(names)]
        fid = str(fr["id"])
        rec: dict = {"format": RESULTS_FORMAT, "id": fid,
                     "segmentation": dataset["config"].segmentation}  # fmt: skip
        try:
            images = [
                _read_rgb(dataset["root"] / fr["images"][n], fid, field=f"images.{n}")
                for n in names
            ]
            plates = dataset["plates"]
            if len(names) == 2:
                # the large compiled stages through stored traced programs (a second
                # process does not trace them again; docs/decisions.md S23)
                r = reconstruct_pair(
                    images[0], images[1], cams[0], cams[1], dataset["config"], plates,
                    jit_call=cached_call,
                )  # fmt: skip
            else:
                r = reconstruct_view(
                    images[0], cams[0], config=dataset["config"],
                    plate=plates[0] if plates else None,
                )  # fmt: skip
            _write_frame(out, fid, r, names)
            if overlays:
                _write_overlays(out, fid, names, images, cams, r)
            rec["ok"] = True
            rec["views"] = {n: v for n, v in zip(names, r["views_px"], strict=True)}
            if "p" in r:
                rec.update(base_mode=r["base_mode"], marker_rms_px=r["marker_rms_px"],
                           n_markers=list(r["n_markers"]),
                           entry_residual_px=r["entry_residual_px"],
                           n_segments=len(r["segments"]),
                           single_view_mm=1e3 * float(r["s"][-1] - r["s_stereo_end"]),
                           tip_epipolar_px=r["tip_epipolar_px"],
                           camera_order_suspect=r["camera_order_suspect"],
                           camera_order_px=r["camera_order_px"],
                           camera_order_tip_px=r.get("camera_order_tip_px"))  # fmt: skip
            if r.get("key_check") is not None:
                kc = r["key_check"]
                rec["key_check"] = {"robot_fraction": kc.robot_fraction,
                                    "border_fraction": kc.border_fraction,
                                    "suspect": kc.suspect}  # fmt: skip
            if r.get("trace_check") is not None:
                tc = r["trace_check"]
                rec["trace_check"] = {"length_px": tc.length_px, "width_px": tc.width_px,
                                      "edge_px": tc.edge_px, "suspect": tc.suspect}  # fmt: skip
            rec["timings"] = r["timings"]
        except StereoFailure as err:
            rec.update(ok=False, reason=err.reason, message=str(err))
        except InputError as err:
            rec.update(ok=False, reason="image", message=str(err))
        return rec


def build_stereo_worker(dataset: str, config, out: str, overlays: bool) -> StereoWorker:
    """A :class:`StereoWorker` from picklable arguments (a Ray worker loads the dataset)."""
    ds = load_stereo_dataset(dataset)
    ds["config"] = config
    return StereoWorker(ds, out, overlays)


def run_batch(
    dataset: dict, out: str | os.PathLike, overlays: bool = True, progress: bool = True,
    shard=None, executor=None, announce=None,
) -> list[dict]:  # fmt: skip
    """Reconstruct every frame of a loaded dataset into ``out`` (see module docstring);
    returns the log records of all frames (including ones done by an earlier run).
    ``shard`` (:class:`jaxcr.scale.shards.Shard`): only its block of frames, its log, run.json
    and tables in ``out/shards/I-of-N`` (frames recorded by other shards are skipped).
    ``executor``: :class:`jaxcr.scale.executor.ExecutorConfig` (default local; ``ray``: the
    frames as tasks, one per ``--chunk`` frames, default 1). ``announce``: called once the
    dataset and options are accepted for ``out`` (before any frame)."""
    from jaxcr.io import results as R
    from jaxcr.scale.shards import read_all_records, shard_dir

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log_dir = out if shard is None else shard_dir(out, shard)
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / "results.jsonl"
    _check_run(out, dataset, log_dir)
    if announce is not None:
        announce()  # the run is accepted: say how (jaxcr stereo prints the segmentation)
    done = {str(r["id"]): r for r in read_all_records(out, _read_log_list, key="id")}
    done.update(_read_log(log_path))
    # the tables are rebuilt at the end: none is left over that looks like this run's
    for name in ("segments.csv", "segments.md"):
        (log_dir / name).unlink(missing_ok=True)
    frames = dataset["frames"] if shard is None else shard.select(dataset["frames"])
    todo = [
        fr
        for fr in frames
        if str(fr["id"]) not in done
        or not (out / "frames" / f"{fr['id']}.json").exists()
        and done[str(fr["id"])].get("ok")
    ]
    from jaxcr.scale.executor import ExecutorConfig, WorkerSpec, run_frames

    executor = executor or ExecutorConfig()
    worker = StereoWorker(dataset, out, overlays)
    spec = WorkerSpec(build_stereo_worker, (str(dataset["root"]), dataset["config"], str(out),
                                            overlays))  # fmt: skip
    bar = None
    if progress and todo:
        from jaxcr.progress import progress as progress_bar

        bar = progress_bar(total=len(todo), desc="stereo", unit="pair")
    with R.ResultsLog(log_path) as log:  # cuts a line left half-written by a killed run
        stats = run_frames(spec, [str(fr["id"]) for fr in todo], log, executor, chunk=1,
                           key="id", local_worker=worker,
                           on_record=None if bar is None else lambda r: bar.update(1))  # fmt: skip
    if bar is not None:
        bar.close()
    if executor is not None and executor.kind != "local" and shard is None:
        from jaxcr.io.outdir import clean_leftovers

        clean_leftovers(out)  # temp files of a worker killed mid-write (OUT is locked, all done)
    for rec in stats.records:
        done[str(rec["id"])] = rec
    write_tables(out, [str(fr["id"]) for fr in frames], log_dir)
    return [done[str(fr["id"])] for fr in frames]


MERGE_FORMAT = "jaxcr.stereo-merge/1"


def is_stereo_output(out: str | os.PathLike) -> bool:
    """True when OUT was written by ``jaxcr stereo`` (its owner file, or a stereo run.json in
    OUT or one of its shards)."""
    from jaxcr.io import outdir
    from jaxcr.scale.shards import shard_dirs

    out = Path(out)
    if outdir.owner(out) is not None:
        return outdir.owner(out) == "stereo"
    for f in [out / "run.json"] + [d / "run.json" for _, d in shard_dirs(out)]:
        try:
            if json.loads(f.read_text(encoding="utf-8")).get("format") == RUN_FORMAT:
                return True
        except (OSError, ValueError, AttributeError):
            continue
    return False


def merge_outputs(out: str | os.PathLike, write: bool = True) -> dict:
    """Merge a stereo OUT written by shards (and/or unsharded runs): the records of
    ``OUT/results.jsonl`` and every ``OUT/shards/*/results.jsonl`` (a later file's record of a
    frame wins), the dataset's frames that have no record, and the shards without ``DONE``.
    With ``write``, ``OUT/segments.csv``/``.md`` over every recorded frame and
    ``OUT/merge.json`` (``jaxcr.stereo-merge/1``: ``frames``, ``ok``, ``failed`` (id ->
    message), ``missing`` (ids), ``unfinished_shards``). Returns the merge.json content."""
    from jaxcr.io import results as R
    from jaxcr.scale.shards import read_all_records, shard_dirs

    out = Path(out)
    runs = [f for f in [out / "run.json"] + [d / "run.json" for _, d in shard_dirs(out)]
            if f.exists()]  # fmt: skip
    if not runs:
        raise InputError("no run.json: not a jaxcr stereo output", file=str(out))
    try:
        dataset = json.loads(runs[0].read_text(encoding="utf-8"))["dataset"]
    except (UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise InputError("not a jaxcr stereo run.json", file=str(runs[0])) from None
    ids = [str(fr["id"]) for fr in load_stereo_dataset(dataset)["frames"]]
    recs = {str(r["id"]): r for r in read_all_records(out, _read_log_list, key="id")}
    recorded = [i for i in ids if i in recs]
    # a shard is unfinished when it has no DONE-equivalent: its block of frames is incomplete
    from jaxcr.scale.shards import Shard

    counts = sorted({s.count for s, _ in shard_dirs(out)})
    unfinished = [str(Shard(i, n)) for n in counts for i in range(n)
                  if any(f not in recs for f in Shard(i, n).select(ids))]  # fmt: skip
    info = {
        "format": MERGE_FORMAT,
        "dataset": dataset,
        "frames": len(ids),
        "ok": sum(1 for i in recorded if recs[i].get("ok")),
        "failed": {i: failure_line(recs[i]) for i in recorded if not recs[i].get("ok")},
        "missing": [i for i in ids if i not in recs],
        "unfinished_shards": unfinished,
    }
    if write:
        write_tables(out, recorded, out)
        R.atomic_write_json(out / "merge.json", info)
    return info


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"bad size {text!r}, expected WxH", field="--size") from None
    from jaxcr.limits import check_size as check_limits
    from jaxcr.synth.stereo_ctr import check_size

    return check_limits(*check_size((w, h), field="--size"), "--size", "stereo synth")


def _claim(out: str, command: str, recognise=None) -> None:
    """OUT must be new, empty or an earlier run of ``command``; held (locked) until exit."""
    from jaxcr.io import outdir

    outdir.claim(out, command, recognise=recognise)


def failure_line(rec: dict) -> str:
    """One failed frame's line: ``frame ID: message`` (an image error's message, which names
    the frame already, as it is)."""
    msg = rec["message"]
    return msg if f"frame {rec['id']}:" in msg else f"frame {rec['id']}: {msg}"


def run(args) -> int:
    if args.dataset == "synth":
        from jaxcr.limits import check_frames
        from jaxcr.synth.stereo_ctr import generate_stereo_set

        check_frames(args.frames, "--frames")
        size = _parse_size(args.size)
        _claim(args.out, "stereo synth")
        path = generate_stereo_set(args.out, args.frames, args.seed, size,
                                   args.background, progress=True)  # fmt: skip
        print(f"wrote {path / 'stereo.json'}")
        return 0
    from jaxcr.scale.executor import executor_config
    from jaxcr.scale.shards import claim_output, parse_shard

    shard = parse_shard(args.shard)  # bad --shard: one line, before reading anything
    executor = executor_config(args)
    ds = load_stereo_dataset(args.dataset)
    mode, why = segmentation_mode(args.segmentation, ds["plates"] is not None, args.out)
    ds["config"].segmentation = mode
    ds["segmentation_choice"] = why
    if args.tolerance is not None:
        from jaxcr.limits import check_number

        lo, hi = (check_number(v, "--tolerance", 0.0, 1.0) for v in args.tolerance)
        if not lo < hi:
            raise InputError(f"needs LO < HI, got {lo:g} {hi:g}", field="--tolerance")
        ds["config"].tol_lo, ds["config"].tol_hi = args.tolerance
    if args.segments is not None:
        from jaxcr.limits import MAX_SEGMENTS, check_count

        check_count(args.segments, "--segments", 1, MAX_SEGMENTS)
        ds["config"].n_segments = args.segments
    given = plate_flags_given(args)
    if given and mode != "trace":
        raise InputError(
            f"{given[0]} needs --segmentation trace"
            + ("" if why.startswith("--") else f" (segmentation is {mode}, {why})"),
            field=given[0],
        )
    if args.calibration_sigma is not None:
        from jaxcr.io.calibration import parse_calibration_sigma

        if mode != "trace":
            raise InputError(f"needs --segmentation trace (segmentation is {mode}, {why})",
                             field="--calibration-sigma")  # fmt: skip
        ds["config"].calibration = parse_calibration_sigma(args.calibration_sigma)
        sigma_from = "--calibration-sigma"
    else:
        sigma_from = f"the calibration file's uncertainty block ({ds['meta']['calibration']})"
    tips_line = (
        "tips' re-search: fixed 5 px (no calibration uncertainty; see --calibration-sigma)"
        if ds["config"].calibration is None
        else f"tips' re-search: 3 sigma of the epipolar distance under {sigma_from}"
    )
    if mode == "trace":
        ds["config"].plate_foreground = plate_config(args)
    if mode != "chroma" and ds["plates"] is None:
        raise InputError(f"--segmentation {mode} needs background_plates in stereo.json")

    claim_output(args.out, "stereo", shard, marker="run.json")
    recs = run_batch(ds, args.out, overlays=not args.no_overlays, shard=shard,
                     executor=executor,
                     announce=lambda: print(f"segmentation: {mode} ({why})"
                                            + (f"\n{tips_line}" if mode == "trace" else ""),
                                            flush=True))  # fmt: skip
    for line in summary_lines(recs, args.out):
        print(line)
    return 0 if all(r["ok"] for r in recs) else 1


#: A reconstructed frame whose two tips lie further than this from each other's epipolar
#: lines (undistorted px) is reported with a WARNING line: twice the 5 px at which the
#: trace segmentation re-checks its tips; the same tip seen in both views of a calibrated
#: rig lies within a few pixels (docs/stereo-format.md, tip_epipolar_px).
TIP_EPIPOLAR_WARN_PX = 10.0
#: Frames named in the one-camera chroma-key WARNING line (the rest are counted).
MAX_NAMED = 10


def summary_lines(recs: list[dict], out) -> list[str]:
    """What ``jaxcr stereo`` prints after a run: the count, one line per failed frame, and a
    WARNING per reconstructed frame whose two tips disagree (``tip_epipolar_px`` over
    :data:`TIP_EPIPOLAR_WARN_PX`: one view lost the tip or segmented something else, and its
    3-D tip and that view's ``tip_px`` are not to be trusted), and one per frame whose two
    backbones the exchanged camera order explains much better (``camera_order_suspect``,
    :mod:`jaxcr.stereo.camera_order`); and one WARNING line for the whole run naming the
    one-camera chroma-key frames whose mask looks like a real background (``key_check``,
    :mod:`jaxcr.stereo.key_check`); for one-camera traced frames, one WARNING line naming
    those whose trace stopped at the entry or ran out of the image and one NOTE line counting the rest, whose tips
    nothing checks (``trace_check``, :mod:`jaxcr.stereo.trace_check`)."""
    n_ok = sum(r["ok"] for r in recs)
    lines = [f"{n_ok}/{len(recs)} frames reconstructed; results in {out}"
             + (f" (failed frames listed below and in {Path(out) / 'results.jsonl'})"
                if n_ok < len(recs) else "")]  # fmt: skip
    lines += [f"  {failure_line(r)}" for r in recs if not r["ok"]]
    suspect = [r for r in recs if r["ok"] and (r.get("key_check") or {}).get("suspect")]
    if suspect:
        from jaxcr.stereo.key_check import BORDER_FRACTION_MAX, ROBOT_FRACTION_MAX

        ids = [str(r["id"]) for r in suspect]
        named = ", ".join(ids[:MAX_NAMED]) + (f" and {len(ids) - MAX_NAMED} more"
                                              if len(ids) > MAX_NAMED else "")  # fmt: skip
        rf = max(r["key_check"]["robot_fraction"] for r in suspect)
        bf = max(r["key_check"]["border_fraction"] for r in suspect)
        lines.append(
            f"WARNING: {len(ids)} frame(s) ({named}): the chroma key's mask looks like a real "
            f"background (robot region up to {rf:.0%} of the frame, non-key border up to "
            f"{bf:.0%}; a key-coloured backdrop stays under {ROBOT_FRACTION_MAX:.0%} and "
            f"{BORDER_FRACTION_MAX:.0%}) and one camera has no second view to check it: "
            "their tip_px and backbone_px are unchecked; with background plates in "
            "stereo.json use --segmentation trace (docs/stereo-format.md, key_check)"
        )
    traced = [r for r in recs if r["ok"] and r.get("trace_check") is not None]
    if traced:
        # One camera, traced (S33): no second view checks the tip. A trace that stopped
        # at the entry or ran out of the image is named; every other traced tip is said to
        # be unchecked.
        from jaxcr.stereo.trace_check import STUB_WIDTHS

        stub = [str(r["id"]) for r in traced if r["trace_check"]["suspect"]]
        if stub:
            named = ", ".join(stub[:MAX_NAMED]) + (f" and {len(stub) - MAX_NAMED} more"
                                                   if len(stub) > MAX_NAMED else "")  # fmt: skip
            lines.append(
                f"WARNING: {len(stub)} frame(s) ({named}): one camera, the trace stopped within "
                f"{STUB_WIDTHS:g} tube widths of the entry or ran out of the image: their tip_px "
                "is not the tube's end; check the overlays and the entry pixel "
                "(docs/stereo-format.md, trace_check)"
            )
        rest = len(traced) - len(stub)
        if rest:
            lines.append(
                f"NOTE: one camera: the traced tip_px of {rest} frame(s) is unchecked (no second "
                "view; a trace that followed an object crossing the tube is not detected): "
                "check the overlays (docs/stereo-format.md, One camera)"
            )
    for r in recs:
        e = r.get("tip_epipolar_px") if r["ok"] else None
        if e is not None and e > TIP_EPIPOLAR_WARN_PX:
            # the trace hint only where the frame was not traced already (a traced view
            # that followed a crossing cable got "try trace" before: S32, seed 4005)
            hint = (
                "; the traces may have followed an object crossing the tube"
                if r.get("segmentation") == "trace"
                else " (on a real background try --segmentation trace)"
            )
            lines.append(
                f"WARNING: frame {r['id']}: the two views' tips are {e:.0f} px from each "
                f"other's epipolar lines (over {TIP_EPIPOLAR_WARN_PX:g} px): one view lost the "
                f"tip or found something else; check its overlay{hint}"
            )
        if r["ok"] and r.get("camera_order_suspect"):
            given, exchanged, total = r["camera_order_px"]
            lines.append(
                f"WARNING: frame {r['id']}: the camera order looks swapped: with the "
                f"calibration as given {given:.0f} of the two backbones' {total:.0f} px do not "
                f"triangulate consistently, with the two cameras exchanged {exchanged:.0f} px; "
                'check that "cameras" in stereo.json lists camera 1 of the calibration first '
                "(docs/stereo-format.md, camera_order_suspect)"
            )
    return lines
