"""M-L over one video into an output folder, and over many videos as a batch (shards, Ray).

:func:`motion_video` runs one ``jaxcr.motion/1`` dataset and writes its outputs (the files
``jaxcr motion DATASET -o OUT`` documents: frames.jsonl, prob_/mask_/pr_ per model, the
baseline, summary.json, report.md last). It returns the summary and the report's text; it
prints nothing (the CLI prints).

A batch's unit of work is a **video**: M-L tracks its superpixels and integrates each
segment's evidence over the whole sequence (the evaluation frame needs every frame before it),
so a video cannot be split into frame ranges without changing the result. :class:`MotionWorker`
is the per-video worker of :func:`jaxcr.scale.executor.run_frames` (``--executor local|ray``,
``--shard I/N`` selects contiguous blocks of the sorted video list): each video's files go to
``OUT/<video>/`` (written as in a single run, summary.json last, atomically), and the driver
appends one record per video to ``results.jsonl`` (:func:`video_record`).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io import results as R
from jaxcr.motion.pipeline import MotionConfig, StepRecord, resolve_steps

#: format of a batch's results.jsonl records and summary.json
BATCH_FORMAT = "jaxcr.motion-batch/1"
#: format of a batch's run.json (the options every part of one job must share)
BATCH_RUN_FORMAT = "jaxcr.motion-batch-run/1"
#: files of one video's output, removed before it is re-run (summary.json and report.md are
#: written last: a folder without them is not a finished video)
VIDEO_OUTPUTS = ("summary.json", "report.md", "baseline_pr.csv", "mask_baseline.png")
VIDEO_PATTERNS = ("prob_*.npy", "prob_*.png", "mask_*.png", "pr_*.csv")


@dataclass(frozen=True)
class VideoOptions:
    """Per-video output options of ``jaxcr motion``: the mask ``threshold`` (fraction of the
    map maximum), whether to run the baseline, and its difference threshold (grey levels)."""

    threshold: float = 0.85
    baseline: bool = True
    baseline_threshold: float = 40.0


def clear_video_outputs(out: Path) -> None:
    """Remove an earlier run's results from ``out`` (one video's folder)."""
    for stale in VIDEO_OUTPUTS:
        (out / stale).unlink(missing_ok=True)
    for pattern in VIDEO_PATTERNS:
        for f in out.glob(pattern):
            f.unlink()


def timing_line(timing: dict) -> str:
    """The report's median per-frame times (ms, one decimal; '-' without used frames)."""
    parts = []
    for k in ("flow", "segmentation", "likelihood"):
        v = timing.get(f"{k}_ms")
        parts.append(f"{k} -" if v is None else f"{k} {v:.1f} ms")
    return "Median per-frame time: " + ", ".join(parts) + "."


def motion_video(
    dataset: str | os.PathLike,
    out: str | os.PathLike,
    cfg: MotionConfig,
    options: VideoOptions | None = None,
    *,
    ds=None,
    on_step: Callable[[StepRecord], None] | None = None,
) -> tuple[dict, str]:
    """Run M-L (and the baseline) on one video and write its outputs into ``out`` (created).

    ``ds``: the already loaded :class:`~jaxcr.io.motion_dataset.MotionDataset` of
    ``dataset`` (default: loaded here). Returns (summary, report text). The summary's
    ``failed`` maps frames the reader could not use to the reason; ``used`` counts the frame
    pairs M-L used. A video without any readable frame is an :class:`InputError`."""
    from jaxcr.io.images import write_png
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.motion import metrics as mt
    from jaxcr.motion import run as motion_run

    opts = options or VideoOptions()
    ds = ds if ds is not None else load_motion_dataset(dataset)
    # the scored frame's ground-truth mask is read before any frame is processed: a missing
    # or unreadable one is bad input (exit 2) at once, not after the whole video (issue 17)
    ev = motion_run.eval_frame_index(ds)
    gt = ds.mask(ev)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # An earlier run's results must not sit beside this run's partial log if it stops early:
    # remove them now; summary.json and report.md (last) are written only when it completes.
    clear_video_outputs(out)
    t0 = time.time()
    with open(out / "frames.jsonl", "w") as log:

        def step(rec):
            log.write(
                json.dumps(
                    {k: (round(v, 3) if isinstance(v, float) else v) for k, v in vars(rec).items()}
                )
                + "\n"
            )
            log.flush()
            if on_step is not None:
                on_step(rec)

        try:
            res = motion_run.run_motion(ds, cfg, on_step=step)
        except RuntimeError as err:  # no readable frame
            raise InputError(str(err), file=str(dataset)) from None
    models = cfg.models
    ths = np.round(np.linspace(0.05, 1.0, 20), 3)
    summary = {
        "dataset": str(dataset),
        "eval_frame": res.eval_frame,
        "first_touch": motion_run.first_touch(ds),
        "warnings": res.warnings,
        "models": {},
    }
    for m in models:
        pm = res.maps[m]
        norm = pm / max(float(pm.max()), 1e-12)
        R.atomic_write_npy(out / f"prob_{m}.npy", pm)
        write_png(out / f"prob_{m}.png", np.clip(np.round(norm * 255), 0, 255).astype(np.uint8))
        mask = norm >= opts.threshold
        write_png(out / f"mask_{m}.png", mask)
        info = {"max_probability": float(pm.max())}
        if gt is not None:
            import jax.numpy as jnp

            pr, re = mt.pr_curve(jnp.asarray(norm), jnp.asarray(gt), jnp.asarray(ths))
            pr, re = np.asarray(pr), np.asarray(re)
            R.atomic_write_text(out / f"pr_{m}.csv", _csv(
                "threshold,precision,recall", np.stack([ths, pr, re], 1)))  # fmt: skip
            k, tbest = mt.optimal_threshold(ths, pr, re)
            info.update(
                tanimoto=float(mt.tanimoto_distance(jnp.asarray(mask), jnp.asarray(gt))),
                l2=float(mt.l2_distance(jnp.asarray(mask), jnp.asarray(gt))),
                optimal_threshold=tbest,
                optimal_precision=float(pr[k]),
                optimal_recall=float(re[k]),
            )
        summary["models"][m] = info
    if opts.baseline:
        _baseline(ds, gt, out, summary, float(opts.baseline_threshold))
    recs = res.records
    used = [r for r in recs if r.used]
    skipped = [r for r in recs if not r.used and r.reason != "first frame"]
    timing = {
        k: float(np.median([getattr(r, k) for r in used])) if used else None
        for k in ("flow_ms", "segmentation_ms", "likelihood_ms")
    }
    sp, scale, flow_step = resolve_steps(cfg, ds.width)
    settings = {
        "superpixel_step_px": sp,
        "superpixel_working_scale": scale,
        "flow": cfg.flow.method,
        "flow_step_px": flow_step,
        "lk_window_px": cfg.flow.window,
        "lk_levels": cfg.flow.levels,
        "lambda_px2": cfg.lam,
        "threshold": opts.threshold,
    }
    summary.update(
        settings=settings,
        frames=len(ds),
        used=len(used),
        skipped=len(skipped),
        failed={str(k): v for k, v in sorted(res.failed.items())},
        median_ms=timing,
        wall_s=time.time() - t0,
    )
    R.atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    report = _report(dataset, ds, res, cfg, summary, skipped, used, settings, timing)
    R.atomic_write_text(out / "report.md", report)
    return summary, report


def _csv(header: str, rows: np.ndarray) -> str:
    import io

    buf = io.StringIO()
    np.savetxt(buf, rows, delimiter=",", header=header, comments="", fmt="%.5f")
    return buf.getvalue()


def _baseline(ds, gt, out: Path, summary: dict, bth: float) -> None:
    import jax.numpy as jnp

    from jaxcr.io.images import write_png
    from jaxcr.motion import metrics as mt
    from jaxcr.motion.run import run_baseline

    bths = sorted({2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, bth})
    bl = run_baseline(ds, bths if gt is not None else [bth])
    if bl is None:
        summary["warnings"].append(
            "baseline skipped: no touch event at frame >= 2 with readable frames"
        )
        return
    write_png(out / "mask_baseline.png", bl[bth])
    summary["baseline"] = {"threshold": bth, "mask_pixels": int(bl[bth].sum())}
    if gt is None:
        return
    rows = []
    for th, msk in bl.items():
        p_, r_ = mt.precision_recall(jnp.asarray(msk), jnp.asarray(gt))
        tani = float(mt.tanimoto_distance(jnp.asarray(msk), jnp.asarray(gt)))
        rows.append([th, float(p_), float(r_), tani])
    R.atomic_write_text(out / "baseline_pr.csv", _csv(
        "threshold,precision,recall,tanimoto", np.array(rows)))  # fmt: skip
    by_th = {r[0]: r for r in rows}
    best = min(rows, key=lambda r: r[3])
    summary["baseline"].update(
        tanimoto=by_th[bth][3],
        precision=by_th[bth][1],
        recall=by_th[bth][2],
        tanimoto_at_5=by_th[5.0][3],
        best_tanimoto=best[3],
        best_threshold=best[0],
    )


def _report(dataset, ds, res, cfg, summary, skipped, used, settings, timing) -> str:
    from jaxcr.motion.run import first_touch

    sp, scale = settings["superpixel_step_px"], settings["superpixel_working_scale"]
    lines = [
        f"# Motion-Likelihood: {dataset}",
        "",
        f"{len(ds)} frames, {len(used)} frame pairs used, {len(skipped)} skipped; evaluation "
        f"frame {res.eval_frame} (first touch {first_touch(ds)}).",
        "",
        f"Settings: superpixel step {sp} px (SLIC on the frame shrunk {scale}x), "
        f"{cfg.flow.method.upper()} flow on a {settings['flow_step_px']}-px grid (window "
        f"{cfg.flow.window} px, {cfg.flow.levels} levels), lambda {cfg.lam:g} px^2, threshold "
        f"{settings['threshold']:g} x the map maximum.",
        "",
    ]
    for w in res.warnings:
        lines.append(f"**warning:** {w}")
    if skipped:
        lines += ["", "| frame | reason |", "|---|---|"] + [
            f"| {r.index} | {r.reason} |" for r in skipped
        ]
    lines += [
        "",
        "| model | Tanimoto (eq. 20) | L2 (eq. 19) | P-R optimum (threshold, Pr, Re) |",
        "|---|---|---|---|",
    ]
    for m, info in summary["models"].items():
        if "tanimoto" in info:
            lines.append(
                f"| {m} | {info['tanimoto']:.3f} | {info['l2']:.2e} | "
                f"{info['optimal_threshold']:.2f}, {info['optimal_precision']:.2f}, "
                f"{info['optimal_recall']:.2f} |"
            )
        else:
            lines.append(f"| {m} | (no ground truth) | | |")
    if "tanimoto" in summary.get("baseline", {}):
        b = summary["baseline"]
        lines += [
            f"| baseline (diff > {b['threshold']:g} + grabCut; mask_baseline.png) | "
            f"{b['tanimoto']:.3f} | | {b['threshold']:g}, {b['precision']:.2f}, "
            f"{b['recall']:.2f} |",
            f"| baseline at the paper's threshold 5 | {b['tanimoto_at_5']:.3f} | | |",
            f"| baseline at its best threshold for this video ({b['best_threshold']:g}; chosen "
            f"with the ground truth, an upper bound) | {b['best_tanimoto']:.3f} | | |",
        ]
    lines += ["", timing_line(timing)]
    return "\n".join(lines) + "\n"


def video_failure(summary: dict) -> str:
    """Why a finished video counts as failed ('' if it did not): frames the reader could not
    use, or no usable frame pair (the exit-1 cases of a single-video run)."""
    failed = summary.get("failed") or {}
    if failed:
        i, why = next(iter(failed.items()))
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        return f"{len(failed)} frame(s) failed: frame {i}: {why}{more}"
    if not summary.get("used"):
        return "no frame pair was usable (end-effector still or out of view)"
    return ""


def video_record(video: str, summary: dict, time_s: float) -> dict:
    """One video's line of a batch's results.jsonl (``format`` :data:`BATCH_FORMAT`): its
    name, ``ok`` and the ``reason`` when not, the frame counts, the per-model scores and the
    baseline's, and ``time_s`` (wall seconds, the only timing)."""
    reason = video_failure(summary)
    rec = {"format": BATCH_FORMAT, "video": video, "ok": not reason}
    if reason:
        rec["reason"] = reason
    rec.update(
        eval_frame=summary["eval_frame"],
        frames=summary["frames"],
        used=summary["used"],
        skipped=summary["skipped"],
        failed_frames=summary["failed"],
        models=summary["models"],
        baseline=summary.get("baseline"),
        warnings=summary["warnings"],
        time_s=round(time_s, 3),
    )
    return rec


def failed_video_record(video: str, reason: str) -> dict:
    """The record of a video that produced no outputs (its folder holds no summary.json)."""
    return {"format": BATCH_FORMAT, "video": video, "ok": False, "reason": reason}


def find_videos(paths: list[str | os.PathLike]) -> dict[str, Path]:
    """The videos of a batch, ``{name: dataset folder}`` in name order: each path is a dataset
    folder (with motion.json; named by the folder) or a folder whose sub-folders with a
    motion.json are the videos. Names must be unique; the list must not be empty
    (:class:`InputError` otherwise)."""
    found: dict[str, Path] = {}
    for p in map(Path, paths):
        if (p / "motion.json").is_file():
            items = [p]
        elif p.is_dir():
            items = sorted(d for d in p.iterdir() if (d / "motion.json").is_file())
            if not items:
                raise InputError("no motion.json in the folder or its sub-folders (expected "
                                 "jaxcr.motion/1 dataset folders)", file=str(p))  # fmt: skip
        else:
            raise InputError("no such dataset folder", file=str(p))
        for d in items:
            name = d.resolve().name
            if name in found and found[name].resolve() != d.resolve():
                raise InputError(f"two videos are named {name!r} ({found[name]} and {d}); "
                                 "video folder names must be unique", file=str(d))  # fmt: skip
            found[name] = d
    return dict(sorted(found.items()))


class MotionWorker:
    """Runs videos of a batch into ``OUT/<video>/`` and returns one record per video: the
    worker of :func:`jaxcr.scale.executor.run_frames` (ids are video names)."""

    def __init__(
        self,
        videos: dict[str, str],
        out: str | os.PathLike,
        cfg: MotionConfig,
        options: VideoOptions,
        on_step: Callable[[StepRecord], None] | None = None,
    ):
        self.videos, self.out, self.cfg, self.options = videos, Path(out), cfg, options
        self.on_step = on_step
        self.compile_s = self.run_s = 0.0

    def failed_record(self, video: str, reason: str) -> dict:
        return failed_video_record(video, reason)

    def process(self, ids: list[str]) -> Iterator[dict]:
        """Yield each video's record as soon as its files are written."""
        for vid in ids:
            t0 = time.perf_counter()
            try:
                summary, _ = motion_video(
                    self.videos[vid], self.out / vid, self.cfg, self.options,
                    on_step=self.on_step,
                )  # fmt: skip
                rec = video_record(vid, summary, time.perf_counter() - t0)
            except InputError as err:  # damaged video: recorded failed, the batch goes on
                rec = failed_video_record(vid, str(err))
            self.run_s += time.perf_counter() - t0
            yield rec


def build_motion_worker(videos: dict[str, str], out: str, cfg: MotionConfig,
                        options: VideoOptions) -> MotionWorker:  # fmt: skip
    """A :class:`MotionWorker` from picklable arguments (a Ray actor builds its own)."""
    return MotionWorker(videos, out, cfg, options)


def read_video_records(path: str | os.PathLike) -> list[dict]:
    """A batch's results.jsonl: one record per video (the last line of a video wins, in
    first-seen order); a truncated last line (a killed run) is ignored."""
    from jaxcr.scale.job import read_keyed

    return read_keyed(path, "video")
