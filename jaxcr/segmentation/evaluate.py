"""Evaluation of ``jaxcr segment`` output folders against the dataset's ground truth
(Watson et al. Table II): per-frame metric rows, their aggregation into a report folder.

Reads each segment output folder (``results.jsonl`` and its masks/centrelines) and the
dataset's ground truth (visible robot masks, occluder masks, true centrelines), and reports
per column (the frames' tag set for one OUT, e.g. "orthogonal occluded"; the dataset name for
several OUTs) the mean ± std IoU (eq. 8) of background subtraction, the unoptimised and the
optimised projection, with the adjusted IoU (predicted pixels inside occluded regions removed,
Sec. III-B) after "|" where occlusion masks exist; tip and mean centreline errors (mm) of the
nominal and refined shapes; median solver steps and time per frame; failed frame counts.

:func:`write_report` writes ``table2.md``, ``table2.csv`` (long format), ``per_frame.csv`` and
``iou.png``. A frame whose outputs are missing, damaged or mis-sized is a failed row with the
reason (the rest go on); the command line (``jaxcr evaluate``, :mod:`jaxcr.cli.evaluate`)
turns the counts into messages and the exit code.

This is a driver (it reads files through :mod:`jaxcr.io`), not part of the jitted core; the
metrics themselves are :mod:`jaxcr.segmentation.metrics`.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io import report as rep
from jaxcr.io import results as R

PER_FRAME_FIELDS = [
    "dataset", "group", "frame", "camera", "ok", "reason",
    "iou_background", "iou_nominal", "iou_refined", "adj_iou_nominal", "adj_iou_refined",
    "tip_nominal_mm", "tip_refined_mm", "cl_nominal_mm", "cl_refined_mm",
    "tip_lateral_nominal_mm", "tip_lateral_refined_mm", "tip_depth_nominal_mm",
    "tip_depth_refined_mm",
    "sigma_depth_mm", "sigma_image_mm", "sigma_image_px", "depth_ambiguous",
    "num_steps", "time_s",
]  # fmt: skip
_METRIC_FIELDS = PER_FRAME_FIELDS[6:19]


# --------------------------------------------------------------------------- per-frame metrics


def _occluded_region(frame, camera: str, visible):
    """Occluded pixels for the adjusted IoU: the occluder mask, else (full robot mask minus the
    visible one); None when the dataset has neither."""
    occ = frame.load_occluder(camera) if camera in frame.occluders else None
    if occ is not None:
        return occ
    full = frame.load_full_mask(camera) if camera in frame.full_masks else None
    if full is not None and visible is not None:
        return full & ~visible
    return None


#: kinds of ``files`` in a results.jsonl record: per camera ({camera: path}) or one path
_PER_CAMERA_FILES = ("masks", "nominal", "background", "overlays")
_SINGLE_FILES = ("centreline", "centreline_nominal")


def _check_files(files, results: Path, line: int | None, fid: str) -> dict:
    """A record's ``files`` field as written by segment (``{kind: {camera: path}}`` for masks,
    ``{kind: path}`` for centrelines; relative paths inside OUT), else an InputError naming
    results.jsonl, the line, the frame and the field (that frame then fails, the rest go on)."""
    where = f" (line {line})" if line is not None else ""

    def bad(field: str, what: str):
        return InputError(f"{what}{where}", file=str(results), frame=fid, field=field)

    def check_path(field: str, rel) -> None:
        if not isinstance(rel, str) or not rel:
            raise bad(field, f"expected a relative path string, got {rel!r}")
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise bad(field, f"path {rel!r} is outside the output folder")

    if not isinstance(files, dict):
        raise bad("files", f"expected an object {{kind: paths}}, got {type(files).__name__}")
    for kind, v in files.items():
        if kind in _PER_CAMERA_FILES:
            if not isinstance(v, dict):
                raise bad(f"files.{kind}", f"expected {{camera: path}}, got {v!r}")
            for cam, rel in v.items():
                check_path(f"files.{kind}.{cam}", rel)
        elif kind in _SINGLE_FILES:
            check_path(f"files.{kind}", v)
    return files


def _record_lines(path: Path) -> dict[str, int]:
    """Line number (1-based) of each frame's last record in results.jsonl, for messages."""
    lines: dict[str, int] = {}
    try:
        data = path.read_bytes().split(b"\n")
    except OSError:
        return lines
    for k, raw in enumerate(data, start=1):
        try:
            rec = json.loads(raw)
        except ValueError:
            continue
        if isinstance(rec, dict) and "frame" in rec:
            lines[str(rec["frame"])] = k
    return lines


def _load_pred(out: Path, files: dict, kind: str, camera: str):
    rel = files.get(kind, {}).get(camera)
    if rel is None:
        return None
    try:
        return R.read_mask_png(out / rel)
    except FileNotFoundError:
        raise InputError(f"missing output file {rel}", file=str(out)) from None


def _load_centreline(out: Path, rel: str) -> np.ndarray:
    """An output centreline (N, 3); InputError naming the file when missing or unreadable."""
    try:
        arr = np.load(out / rel, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(f"missing output file {rel}", file=str(out)) from None
    except (OSError, ValueError, EOFError) as err:
        raise InputError(f"not a readable .npy file ({err})", file=str(out / rel)) from None
    # N >= 2: a tip and a mean error need points (an empty (0, 3) array was an IndexError
    # traceback in the audit, experiments/contract_audit.py item 4)
    if (
        arr.ndim != 2
        or arr.shape[1] != 3
        or arr.shape[0] < 2
        or not np.issubdtype(arr.dtype, np.number)
    ):
        raise InputError(f"expected an (N, 3) array with N >= 2, got {arr.dtype} {arr.shape}",
                         file=str(out / rel))  # fmt: skip
    if not np.all(np.isfinite(arr)):
        # a NaN/inf centreline has no error to average: the frame fails (never a NaN that the
        # means would silently skip)
        n = int((~np.isfinite(arr)).any(axis=1).sum())
        raise InputError(f"{n} of {len(arr)} centreline points are not finite (NaN or inf)",
                         file=str(out / rel))  # fmt: skip
    return arr


class OutputEvaluator:
    """The evaluation of one segment output folder, frame by frame: reads OUT's run.json and
    records (every shard's merged), and the dataset's ground truth; :meth:`frame` gives one
    record's per-camera metric rows. Built from paths only, so a Ray worker builds its own
    (``jaxcr evaluate --executor ray``: OUT and the dataset on a filesystem the workers share).

    Args:
        group_by: ``"tags"`` (column = the frame's tags joined by spaces, or the dataset name
            when untagged) or ``"dataset"`` (column = dataset name).
    """

    def __init__(self, out: str | Path, group_by: str = "tags"):
        from jaxcr.io.dataset import load_dataset
        from jaxcr.scale import shards as S

        out = Path(out)
        self.out, self.group_by = out, group_by
        self.layout = R.OutputLayout(out)
        if not out.is_dir():
            raise InputError("not a segment output folder", file=str(out))
        # a --shard run keeps run.json and results.jsonl in OUT/shards/I-of-N: merge them all
        runs = [self.layout.run] + [d / R.RUN_FILE for _, d in S.shard_dirs(out)]
        runs = [p for p in runs if p.exists()]
        if not runs:
            raise InputError("no run.json: not a jaxcr segment output folder", file=str(out))
        self.run_info = R.read_run(runs[0])
        try:
            self.records = S.read_all_records(out)
        except ValueError as err:
            raise InputError(str(err)) from None
        ds_path = Path(self.run_info["dataset"])
        if not ds_path.exists():
            raise InputError("the dataset of this run is gone", file=str(ds_path))
        self.ds = load_dataset(ds_path)
        self.name = self.run_info.get("dataset_name") or self.ds.name
        self.cams = self.run_info.get("cameras") or list(self.ds.cameras)
        self.frames = {f.id: f for f in self.ds.frames}
        self.record_lines = _record_lines(self.layout.results)

    def frame(self, rec: dict) -> tuple[list[dict], str | None]:
        """One record's rows (one per camera) and None; or, when its outputs cannot be
        compared with its ground truth (missing, damaged, mis-sized), failed rows (NaN
        metrics, the reason) and the reason: that frame fails, the report goes on."""
        import jax.numpy as jnp

        from jaxcr.segmentation import metrics

        def m(x):
            return float(x) if x is not None else math.nan

        out, layout, ds, cams = self.out, self.layout, self.ds, self.cams
        fid = str(rec["frame"])
        frame = self.frames.get(fid)
        tags = rec.get("tags") or (list(frame.tags) if frame is not None else [])
        group = self.name if self.group_by == "dataset" or not tags else " ".join(tags)
        files = rec.get("files") or {}
        truth_cl = frame.load_truth("centreline") if frame is not None else None
        e3 = {k: math.nan for k in _METRIC_FIELDS[5:]}
        bad = None  # set when this frame's outputs cannot be compared with its ground truth
        rows: list[dict] = []
        try:  # a damaged output file of this frame fails this frame only
            line = self.record_lines.get(fid)
            # a failed record of an unknown frame too (the audit, item 4: `{"frame": 3}` was a
            # failed frame without a reason); the dataset's bad frames have records of their own
            if frame is None and (rec.get("ok") or fid not in ds.bad_frames):
                where = f" (line {line})" if line is not None else ""
                ok = "an ok" if rec.get("ok") else "a"
                raise InputError(f"{ok} record of a frame the dataset does not have{where}",
                                 file=str(layout.results), frame=fid, field="frame")  # fmt: skip
            if rec.get("ok") and not rec.get("files"):  # missing, null or {} (audit item 4)
                where = f" (line {line})" if line is not None else ""
                raise InputError(f"an ok record without its output files{where}",
                                 file=str(layout.results), frame=fid, field="files")  # fmt: skip
            files = _check_files(files, layout.results, line, fid)
            if rec.get("ok") and truth_cl is not None and "centreline" in files:
                t = jnp.asarray(np.asarray(truth_cl, np.float64), jnp.float32)
                for tag, key in (("refined", "centreline"), ("nominal", "centreline_nominal")):
                    if key in files:
                        p = jnp.asarray(_load_centreline(out, files[key]), jnp.float32)
                        e3[f"tip_{tag}_mm"] = 1e3 * float(metrics.tip_error(p, t))
                        e3[f"cl_{tag}_mm"] = 1e3 * float(metrics.mean_centreline_error(p, t))
                        if cams and cams[0] in ds.cameras:
                            lat, dep = metrics.tip_error_components(p, t, ds.cameras[cams[0]].R)
                            e3[f"tip_lateral_{tag}_mm"] = 1e3 * float(lat)
                            e3[f"tip_depth_{tag}_mm"] = 1e3 * float(dep)
            for cam in cams:
                row = {
                    "out": str(out),
                    "dataset": self.name,
                    "group": group,
                    "frame": fid,
                    "camera": cam,
                    "ok": bool(rec.get("ok")),
                    "reason": rec.get("reason"),
                    "num_steps": rec.get("num_steps"),
                    "time_s": rec.get("time_s"),
                    **{k: math.nan for k in _METRIC_FIELDS},
                }
                row.update(e3)
                row.update(_uncertainty_fields(rec, cam))
                visible = frame.load_mask(cam) if frame is not None and cam in frame.masks else None
                if rec.get("ok") and visible is not None:
                    occ = _occluded_region(frame, cam, visible)
                    vj = jnp.asarray(visible)
                    for kind, key in (("background", "background"), ("nominal", "nominal"),
                                      ("refined", "masks")):  # fmt: skip
                        pred = _load_pred(out, files, key, cam)
                        if pred is None:
                            continue
                        if pred.shape != visible.shape:
                            bad = (f"evaluate: mask {key}/{cam} is {pred.shape}, ground truth "
                                   f"{visible.shape}")  # fmt: skip
                            break
                        pj = jnp.asarray(pred)
                        row[f"iou_{kind}"] = m(metrics.iou(pj, vj))
                        if occ is not None and kind != "background":
                            row[f"adj_iou_{kind}"] = m(
                                metrics.adjusted_iou(pj, vj, jnp.asarray(occ))
                            )
                rows.append(row)
                if bad is not None:
                    break
        except InputError as err:
            bad = f"evaluate: {err.format()}"
        if bad is not None:
            return self.failed_rows(rec, bad), bad
        return rows, None

    def failed_rows(self, rec: dict, reason: str) -> list[dict]:
        """The rows of a frame that could not be evaluated: every camera, NaN metrics, the
        reason."""
        fid = str(rec["frame"])
        frame = self.frames.get(fid)
        tags = rec.get("tags") or (list(frame.tags) if frame is not None else [])
        group = self.name if self.group_by == "dataset" or not tags else " ".join(tags)
        return [{
            "out": str(self.out), "dataset": self.name, "group": group, "frame": fid,
            "camera": cam, "ok": False, "reason": reason, "num_steps": rec.get("num_steps"),
            "time_s": rec.get("time_s"), **{k: math.nan for k in _METRIC_FIELDS},
        } for cam in self.cams]  # fmt: skip

    def info(self, failed: dict[str, str]) -> dict:
        """run.json with the evaluation's counts added (``evaluate_expected``,
        ``evaluate_missing``, ``evaluate_unknown``, ``evaluate_failed``: see
        :func:`frame_rows`)."""
        # frames of the dataset without a record (an interrupted or --limit run, or a dataset
        # that grew since): the report covers fewer frames than the dataset has
        expected = list(self.ds.bad_frames) + [f.id for f in self.ds.frames]
        have = {str(r["frame"]) for r in self.records}
        known = set(expected)
        return {**self.run_info, "evaluate_expected": len(expected),
                "evaluate_missing": [f for f in expected if f not in have],
                # records of frames the dataset does not have (failed records, never
                # counted among the dataset's frames)
                "evaluate_unknown": sorted(f for f in have if f not in known),
                "evaluate_out": str(self.out),
                # frames whose outputs could not be evaluated ({frame: reason}); the CLI warns
                "evaluate_failed": failed}  # fmt: skip


#: frames per task of ``jaxcr evaluate --executor ray`` (each reads a few PNGs per camera)
EVALUATE_CHUNK = 64


class EvaluateWorker:
    """The worker of ``jaxcr evaluate --executor ray`` (:mod:`jaxcr.scale.executor`): one
    record per frame, ``{"frame", "rows", "bad"}`` (its metric rows, and the reason when its
    outputs could not be evaluated). Nothing is written: the driver assembles the report."""

    compile_s = 0.0

    def __init__(self, out: str, group_by: str = "tags"):
        self.evaluator = OutputEvaluator(out, group_by)
        self.by_id = {str(r["frame"]): r for r in self.evaluator.records}
        self.run_s = 0.0

    def process(self, frame_ids: list[str]) -> list[dict]:
        import time

        t0 = time.perf_counter()
        recs = []
        for fid in frame_ids:
            rows, bad = self.evaluator.frame(self.by_id[fid])
            recs.append({"frame": fid, "rows": rows, "bad": bad})
        self.run_s += time.perf_counter() - t0
        return recs

    def failed_record(self, frame_id: str, reason: str) -> dict:
        bad = f"evaluate: {reason}"
        return {"frame": frame_id, "rows": self.evaluator.failed_rows(self.by_id[frame_id], bad),
                "bad": bad}  # fmt: skip


class _Collect:
    """A results log that keeps the records in memory (evaluate writes its report at the
    end, not per frame)."""

    def __init__(self):
        self.records: list[dict] = []

    def append(self, record: dict) -> None:
        self.records.append(record)

    def append_many(self, records: list[dict]) -> None:
        self.records += records


def frame_rows(out: str | Path, group_by: str = "tags",
               executor=None) -> tuple[list[dict], dict]:  # fmt: skip
    """Per-frame, per-camera metric rows of one segment output folder (see
    :mod:`jaxcr.io.report`), and its run.json with the evaluation's counts added
    (``evaluate_expected``: frames in the dataset; ``evaluate_missing``: their ids without a
    record; ``evaluate_unknown``: ids of records of frames the dataset does not have (each a
    failed record, not one of the dataset's frames); ``evaluate_failed``: {frame: reason} of
    frames whose outputs could not be
    evaluated).

    Args:
        group_by: ``"tags"`` (column = the frame's tags joined by spaces, or the dataset name
            when untagged) or ``"dataset"`` (column = dataset name).
        executor: None or a local :class:`jaxcr.scale.executor.ExecutorConfig`: in this
            process, with a progress bar; ``kind="ray"``: the frames in chunks as Ray tasks
            (the same rows, in the same order).
    """
    if executor is not None and executor.kind != "local":
        from jaxcr.scale.executor import WorkerSpec, run_frames

        worker = EvaluateWorker(str(out), group_by)
        ids = [str(r["frame"]) for r in worker.evaluator.records]
        log = _Collect()
        spec = WorkerSpec(EvaluateWorker, (str(out), group_by))
        run_frames(spec, ids, log, executor, chunk=EVALUATE_CHUNK, local_worker=worker)
        by_id = {r["frame"]: r for r in log.records}
        rows, failed = [], {}
        for fid in ids:  # the local run's order
            rows += by_id[fid]["rows"]
            if by_id[fid]["bad"] is not None:
                failed[fid] = by_id[fid]["bad"]
        return rows, worker.evaluator.info(failed)
    from jaxcr.progress import progress

    ev = OutputEvaluator(out, group_by)
    rows: list[dict] = []
    failed: dict[str, str] = {}
    # reading masks of long runs takes a while: a bar on a terminal, plain lines in a log
    for rec in progress(ev.records, desc=f"evaluate {ev.out.name}", unit="frame", leave=False):
        frame_rows_, bad = ev.frame(rec)
        rows += frame_rows_
        if bad is not None:
            failed[str(rec["frame"])] = bad
    return rows, ev.info(failed)


def _uncertainty_fields(rec: dict, cam: str) -> dict:
    """The per-camera tip uncertainty of a record (format jaxcr.segment/2, docs/uncertainty.md):
    NaN where the record has none (older runs, --no-uncertainty, failed frames), inf where the
    images do not bound it (JSON null)."""
    u = (rec.get("uncertainty") or {}).get("cameras", {}).get(cam)
    if not rec.get("ok") or not isinstance(u, dict):
        return {"sigma_depth_mm": math.nan, "sigma_image_mm": math.nan,
                "sigma_image_px": math.nan, "depth_ambiguous": ""}  # fmt: skip

    def val(k):
        v = u.get(k)
        return math.inf if v is None else float(v)

    return {"sigma_depth_mm": val("sigma_depth_mm"), "sigma_image_mm": val("sigma_image_mm"),
            "sigma_image_px": val("sigma_image_px"),
            "depth_ambiguous": bool(u.get("depth_ambiguous"))}  # fmt: skip


def uncertainty_markdown(rows: list[dict]) -> list[str]:
    """Report lines: per group and camera, the median 1-sigma tip uncertainty (Laplace,
    docs/uncertainty.md), the depth-ambiguous frames and, where the dataset has the true
    centreline, how often the refined tip's depth error (first camera) is within 1 and 2
    predicted sigma. Empty when no row has an uncertainty."""
    have = [r for r in rows if r.get("ok") and r.get("depth_ambiguous") != ""]
    if not have:
        return []

    def med(v):
        v = [x for x in v if not math.isnan(x)]
        return f"{float(np.median(v)):.3g}" if v else "-"

    first_cam = {}
    for r in rows:
        first_cam.setdefault(r["out"], r["camera"])
    lines = ["Tip uncertainty (1 sigma, Laplace covariance of the refined shape, "
             "docs/uncertainty.md; medians over ok frames; inf = not bounded by the images):",
             "", "| group | camera | frames | depth (mm) | image plane (mm) | image plane (px) "
             "| depth-ambiguous | depth error within 1 / 2 sigma |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    keys = sorted({(r["group"], r["camera"]) for r in have})
    for g, c in keys:
        rs = [r for r in have if r["group"] == g and r["camera"] == c]
        cover = "-"
        ev = [r for r in rs if r["camera"] == first_cam[r["out"]]
              and math.isfinite(r.get("tip_depth_refined_mm", math.nan))]  # fmt: skip
        if ev:
            n1 = sum(abs(r["tip_depth_refined_mm"]) <= r["sigma_depth_mm"] for r in ev)
            n2 = sum(abs(r["tip_depth_refined_mm"]) <= 2 * r["sigma_depth_mm"] for r in ev)
            cover = f"{n1 / len(ev):.0%} / {n2 / len(ev):.0%} of {len(ev)}"
        lines.append(
            f"| {g} | {c} | {len(rs)} | {med(r['sigma_depth_mm'] for r in rs)} | "
            f"{med(r['sigma_image_mm'] for r in rs)} | {med(r['sigma_image_px'] for r in rs)} | "
            f"{sum(bool(r['depth_ambiguous']) for r in rs)} | {cover} |"
        )
    return lines + [""]


def evaluate_outputs(outs: list[str | Path], executor=None) -> tuple[list[dict], list[dict]]:
    """Rows of several output folders (grouped by dataset name when more than one; folder
    names disambiguate equal dataset names) and their run.json dicts. ``executor``: as
    :func:`frame_rows`."""
    all_rows, infos = [], []
    group_by = "tags" if len(outs) == 1 else "dataset"
    seen: dict[str, str] = {}
    for out in outs:
        rows, info = frame_rows(out, group_by=group_by, executor=executor)
        if group_by == "dataset" and rows:
            nm = rows[0]["dataset"]
            if nm in seen and seen[nm] != str(out):
                for r in rows:
                    r["group"] = f"{nm} ({Path(out).name})"
            seen.setdefault(nm, str(out))
        all_rows += rows
        infos.append(info)
    return all_rows, infos


# --------------------------------------------------------------------------- outputs


def per_frame_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=PER_FRAME_FIELDS, extrasaction="ignore",
                       lineterminator="\n")  # fmt: skip
    w.writeheader()
    for r in rows:
        # NaN (no value) as an empty cell; inf (an unbounded sigma) as "inf"
        w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v)
                    for k, v in r.items()})  # fmt: skip
    return buf.getvalue()


def iou_plot(rows: list[dict], path: Path) -> None:
    """Histogram of per-frame IoUs per method and IoU per frame (refined vs nominal)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    bins = np.linspace(0, 1, 21)
    for key, label in (("iou_background", "background subtraction"),
                       ("iou_nominal", "unoptimised projection"),
                       ("iou_refined", "optimised projection")):  # fmt: skip
        v = np.array([r[key] for r in rows], float)
        v = v[np.isfinite(v)]
        if v.size:
            ax1.hist(v, bins=bins, alpha=0.5, label=f"{label} (mean {v.mean():.3f})")
    ax1.set_xlabel("IoU")
    ax1.set_ylabel("frames")
    ax1.legend(fontsize=8)
    ax1.set_title("IoU histogram")
    groups = list(dict.fromkeys(r["group"] for r in rows))
    for gi, g in enumerate(groups):
        gr = [r for r in rows if r["group"] == g]
        x = np.arange(len(gr))
        c = f"C{gi % 10}"
        ax2.plot(x, [r["iou_refined"] for r in gr], "o-", color=c, label=f"{g}: optimised")
        ax2.plot(x, [r["iou_nominal"] for r in gr], "x--", color=c, alpha=0.6,
                 label=f"{g}: unoptimised")  # fmt: skip
    from matplotlib.ticker import MaxNLocator

    ax2.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax2.set_xlabel("frame (per column, in run order)")
    ax2.set_ylabel("IoU")
    ax2.set_ylim(0, 1)
    ax2.legend(fontsize=7)
    ax2.set_title("IoU per frame")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    R.atomic_write_bytes(path, buf.getvalue())


def write_report(rows, infos, report_dir: Path, title: str | None = None, plot: bool = True,
                 incomplete=()):  # fmt: skip
    """Write table2.md/csv, per_frame.csv (and iou.png); return the :class:`Table2`.

    ``incomplete``: output folders without a DONE marker (interrupted or ``--limit`` runs);
    table2.md then says so at the top, so a partial report never reads as a complete one.
    """
    table = rep.build_table2(rows)
    report_dir.mkdir(parents=True, exist_ok=True)
    title = title or "Kinematic-prior segmentation (Watson et al. Table II layout)"
    lines = [f"# {title}", ""]
    for o in incomplete:
        n = len({r["frame"] for r in rows if r.get("out") == str(o)})
        lines.append(f"**INCOMPLETE RUN**: `{o}` has no DONE marker (interrupted or --limit); "
                     f"only its {n} processed frames are in this report.")  # fmt: skip
        lines.append("")
    for info in infos:
        missing, n_ds = info.get("evaluate_missing") or [], info.get("evaluate_expected")
        if missing:
            lines.append(f"**MISSING FRAMES**: {len(missing)} of the dataset's {n_ds} frames "
                         f"are missing from `{info.get('dataset')}`'s run (no record).")  # fmt: skip
            lines.append("")
    unknown = {(info.get("evaluate_out"), f) for info in infos
               for f in info.get("evaluate_unknown") or []}  # fmt: skip
    frames = {(r.get("out"), r["frame"]): bool(r.get("ok")) for r in rows
              if (r.get("out"), r["frame"]) not in unknown}  # fmt: skip
    n_ok = sum(frames.values())
    n_failed = len(frames) - n_ok
    lines.append("IoU mean ± std over frames (raw | adjusted where occlusion masks exist); the "
                 f"averages are over {n_ok} of {len(frames)} frames"
                 + (f" ({n_failed} failed)" if n_failed else "")
                 + (f" ({len(unknown)} record(s) of frames the dataset does not have, failed)"
                    if unknown else "")
                 + " (a cell over fewer has its count in table2.csv, column n).")  # fmt: skip
    lines.append("")
    lines.append(rep.table2_markdown(table))
    lines.append("Published (Watson et al. Table II, real images, 20 frames per set):")
    lines.append("")
    lines.append(rep.paper_table2_markdown())
    lines += uncertainty_markdown(rows)
    lines.append("Runs:")
    lines.append("")
    for info in infos:
        v = info.get("versions", {})
        lines.append(
            f"- `{info.get('dataset')}` ({info.get('dataset_name')}): cameras "
            f"{info.get('cameras')}, background {info.get('background')}, jaxcr "
            f"{v.get('jaxcr')} commit {str(v.get('git_commit'))[:10]}, jax {v.get('jax')}"
        )
    R.atomic_write_text(report_dir / "table2.md", "\n".join(lines) + "\n")
    R.atomic_write_text(report_dir / "table2.csv", rep.table2_csv(table))
    R.atomic_write_text(report_dir / "per_frame.csv", per_frame_csv(rows))
    if plot and rows:
        iou_plot(rows, report_dir / "iou.png")
    return table
