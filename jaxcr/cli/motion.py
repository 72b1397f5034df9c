"""``jaxcr motion DATASET -o OUT``: segment the object the robot moves (Motion-Likelihood).

DATASET is a ``jaxcr.motion/1`` folder (docs/motion-format.md): motion.json with P, the arm,
per-frame joints and touch flags, and the frames as a video file (any format OpenCV reads)
or an image folder. OUT receives, as they complete:

  frames.jsonl          one line per frame: used or the reason it was skipped (no touch,
                        end-effector still or out of view, unreadable/corrupt frame), timings
  prob_<model>.png/.npy probability map (eq. 16) on the evaluation frame's segments
  mask_<model>.png      the map thresholded at --threshold x its maximum
  pr_<model>.csv        precision/recall over thresholds (if the dataset has ground truth)
  mask_baseline.png     the frame-differencing + grabCut baseline's mask of the first touch
                        frame at --baseline-threshold (grabCut seeded: deterministic)
  baseline_pr.csv       the baseline over its threshold (if the dataset has ground truth)
  report.md, summary.json

A batch of videos (several DATASET folders, or one folder whose sub-folders are datasets;
docs/scale-out.md) writes each video's files above into OUT/<video>/ and one line per video
to OUT/results.jsonl (jaxcr.motion-batch/1: ok or the reason it failed, scores), then
OUT/summary.json and OUT/DONE. The unit of work is a video (M-L tracks and integrates over
the whole sequence): --resume skips recorded videos, --shard I/N takes the I-th block of the
sorted videos (records in OUT/shards/I-of-N/), --executor ray runs videos as Ray tasks.

``jaxcr motion synth -o OUT`` writes a synthetic video dataset instead (presets
pushed_static, pushed_changing, held_static, held_changing).

Examples:
  jaxcr motion synth --preset pushed_changing --seed 3 -o /tmp/push3
  jaxcr motion /tmp/push3 -o /tmp/push3_out
  jaxcr motion /tmp/push3 -o /tmp/out --model homography --lambda 20 --flow dis
  jaxcr motion /data/videos -o /shared/out --shard $SLURM_ARRAY_TASK_ID/8
  jaxcr motion /data/videos -o /shared/out --executor ray --address auto
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from jaxcr.cli._common import seed as _seed
from jaxcr.errors import InputError
from jaxcr.io import results as R


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "motion",
        help="segment the object the robot pushes or holds (Motion-Likelihood), or 'synth'",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument(
        "dataset",
        nargs="+",
        help="dataset folder (jaxcr.motion/1), or 'synth' to generate one; several folders, or "
        "a folder of dataset folders, run as a batch of videos (OUT/<video>/ each)",
    )
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument(
        "--model",
        choices=["translation", "homography", "both"],
        default="both",
        help="motion model(s) to run (default: both; each writes its own prob_/mask_ files)",
    )
    p.add_argument(
        "--lambda",
        dest="lam",
        type=float,
        default=5.0,
        help="Sigma = lambda I, px^2 (default 5, chosen on the static synthetic videos)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=0.85,
        help="fraction of the map maximum (default 0.85, chosen with lambda; paper 0.75)",
    )
    p.add_argument(
        "--superpixel-step",
        type=int,
        default=0,
        help="SLIC grid step, px (default 0: frame width / 16, the validated setting: 20 px at "
        "320x240, 40 px at 640x480)",
    )
    p.add_argument(
        "--flow-step",
        type=int,
        default=0,
        help="LK grid step, px (default 0: frame width / 80, the validated setting: 4 px at "
        "320x240, 8 px at 640x480)",
    )
    p.add_argument("--flow", choices=["lk", "dis"], default="lk", help="optical flow method")
    p.add_argument(
        "--integration",
        choices=["product", "mixture"],
        default="product",
        help="combine the before-touch and touching windows as a product (default) or pool "
        "all frames in one average (the paper's eq. 16 literally)",
    )
    p.add_argument(
        "--prior-frames",
        type=float,
        default=1.0,
        help="Beta prior of each window mean, in pseudo-frames at 1/2 (0: plain averages)",
    )
    p.add_argument(
        "--no-stabilise",
        action="store_true",
        help="do not take the flow relative to the background homography (static camera)",
    )
    p.add_argument("--no-baseline", action="store_true", help="skip the grabCut baseline")
    p.add_argument(
        "--baseline-threshold",
        type=float,
        default=40.0,
        help="the baseline's frame-difference threshold, grey levels 0-255, for "
        "mask_baseline.png and the report (default 40, chosen on the static synthetic videos "
        "like lambda; the paper's 5 leaves the mask empty on them)",
    )
    b = p.add_argument_group("batch of videos (several DATASETs or a folder of them)")
    b.add_argument(
        "--resume",
        action="store_true",
        help="continue a batch in OUT: skip the videos it already recorded",
    )
    b.add_argument(
        "--retry-failed",
        action="store_true",
        help="like --resume, but re-run the videos recorded as failed",
    )
    b.add_argument("--shard", default=None, metavar="I/N",
                   help="process only the I-th of N contiguous blocks of the batch's videos "
                   "(sorted by name; 0-based, e.g. $SLURM_ARRAY_TASK_ID/N) into the same OUT; "
                   "records go to OUT/shards/I-of-N/ (default: all videos)")  # fmt: skip
    from jaxcr.scale.executor import add_executor_arguments

    add_executor_arguments(p, "1 video")
    g = p.add_argument_group("synth (with DATASET = synth)")
    g.add_argument("--preset", default="pushed_static")
    g.add_argument("--seed", type=_seed, default=0, help="random seed of the generated scene")
    g.add_argument("--size", default="320x240", help="WIDTHxHEIGHT")
    g.add_argument("--frames", type=int, default=24)
    g.add_argument("--video", action="store_true", help="also encode video.avi and read from it")
    p.set_defaults(func=run)


def _synth(args) -> int:
    from jaxcr.synth.motion_scenes import PRESETS, generate_motion_video

    if args.preset not in PRESETS:
        raise InputError(
            f"unknown preset {args.preset!r}; choose from {', '.join(PRESETS)}", field="--preset"
        )
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise InputError("--size must be WIDTHxHEIGHT", field="--size") from None
    from jaxcr.limits import check_frames, check_size

    w, h = check_size(w, h, "--size", "motion synth", min_size=(64, 48))
    if args.frames < 6:
        raise InputError(f"need at least 6 frames, got {args.frames}", field="--frames")
    check_frames(args.frames, "--frames", lo=6)
    from jaxcr.io import outdir

    outdir.claim(args.out, "motion synth")  # new, empty or an earlier motion synth; locked
    out = generate_motion_video(
        args.out, args.preset, seed=args.seed, size=(w, h), n_frames=args.frames, video=args.video
    )
    print(f"wrote {out}")
    return 0


from jaxcr.motion.batch import timing_line  # noqa: E402,F401  (re-exported: tests, docs)


def _config(args, width_of=None):
    """The MotionConfig and VideoOptions of the arguments (bad values: InputError, exit 2)."""
    from jaxcr.limits import check_number
    from jaxcr.motion.batch import VideoOptions
    from jaxcr.motion.flow import FlowConfig
    from jaxcr.motion.pipeline import MODELS, MotionConfig

    check_number(args.prior_frames, "--prior-frames", 0.0)  # NaN/inf were accepted
    check_number(args.lam, "--lambda", 0.0, lo_open=True)
    check_number(args.threshold, "--threshold", 0.0, 1.0, lo_open=True)  # was named --lambda
    if not (0 <= args.baseline_threshold < 255):
        raise InputError(
            "--baseline-threshold must be in [0, 255) grey levels", field="--baseline-threshold"
        )
    if not (args.superpixel_step == 0 or args.superpixel_step >= 4) or args.flow_step < 0:
        raise InputError(
            "--superpixel-step must be 0 (auto) or >= 4 and --flow-step >= 0 (0: auto)",
            field="--superpixel-step",
        )
    models = MODELS if args.model == "both" else (args.model,)
    cfg = MotionConfig(
        superpixel_step=args.superpixel_step,
        flow=FlowConfig(step=args.flow_step, method=args.flow),
        models=models,
        lam=args.lam,
        threshold=args.threshold,
        stabilise=not args.no_stabilise,
        integration=args.integration,
        prior_frames=args.prior_frames,
    )
    opts = VideoOptions(args.threshold, not args.no_baseline, float(args.baseline_threshold))
    return cfg, opts


def _check_steps(args, ds) -> None:
    """A grid step over the frames' shorter side leaves one superpixel / one flow vector."""
    from jaxcr.limits import check_count

    short = min(ds.width, ds.height)
    for flag, step in (
        ("--superpixel-step", args.superpixel_step),
        ("--flow-step", args.flow_step),
    ):
        check_count(step, flag, 0, short, "the frames' shorter side; 0 = auto")


def _batch_flags(args) -> list[str]:
    given = []
    if args.shard is not None:
        given.append("--shard")
    if args.executor != "local":
        given.append("--executor " + args.executor)
    for flag in ("chunk", "workers", "address"):
        if getattr(args, flag) is not None:
            given.append("--" + flag)
    if args.resume or args.retry_failed:
        given.append("--resume" if args.resume else "--retry-failed")
    return given


def run(args) -> int:
    if args.dataset == ["synth"]:
        return _synth(args)
    if "synth" in args.dataset:
        raise InputError("'synth' generates one dataset: give it alone", field="dataset")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    from jaxcr.motion.batch import find_videos

    cfg, opts = _config(args)
    first = Path(args.dataset[0])
    # one dataset folder (or a motion.json, or a missing path: the loader names the problem)
    # is a single video; several, or a folder of dataset folders, are a batch
    single = len(args.dataset) == 1 and (not first.is_dir() or (first / "motion.json").exists())
    if not single:
        return _run_batch(args, find_videos(args.dataset), cfg, opts)
    given = _batch_flags(args)
    if given:
        raise InputError(
            f"{given[0]} needs a batch of videos (several DATASET folders or a folder of them):"
            " one video is one tracked sequence and runs in one process",
            field=given[0].split()[0][2:],
        )
    return _run_single(args, args.dataset[0], cfg, opts)


def _run_single(args, dataset: str, cfg, opts) -> int:
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.motion.batch import motion_video, video_failure
    from jaxcr.progress import progress

    ds = load_motion_dataset(dataset)
    _check_steps(args, ds)
    # the scored frame's ground-truth mask, before OUT is claimed (motion_video reads it
    # again before the work; a PNG mask is cheap)
    from jaxcr.motion.run import eval_frame_index

    ds.mask(eval_frame_index(ds))
    out = Path(args.out)
    from jaxcr.io import outdir

    # new, empty or an earlier motion run (whose results are replaced), never another command's
    # folder; locked until exit
    outdir.claim(out, "motion", recognise=lambda o: (o / "frames.jsonl").exists())
    bar = progress(total=len(ds), desc="motion", unit="frame")
    try:
        summary, report = motion_video(dataset, out, cfg, opts, ds=ds,
                                       on_step=lambda rec: bar.update(1))  # fmt: skip
    finally:
        bar.close()
    print(report, end="")
    # Frames the reader could not use (unreadable, corrupt, wrong size) are failed frames: the
    # run went on without them but exits 1 (README exit codes). Pairs the method itself does not
    # use (first frame, end-effector still or out of view, no valid flow) are not failures.
    failed = summary["failed"]
    if failed:
        print(f"jaxcr motion: {video_failure(summary)}; all listed in {out / 'summary.json'}",
              file=sys.stderr)  # fmt: skip
    return 0 if summary["used"] and not failed else 1


def _run_batch(args, videos: dict, cfg, opts) -> int:
    """Several videos (docs/scale-out.md, "motion"): one item per video."""
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.motion import batch as B
    from jaxcr.progress import progress
    from jaxcr.scale.executor import WorkerSpec, executor_config, run_frames
    from jaxcr.scale.shards import parse_shard

    shard = parse_shard(args.shard)
    executor = executor_config(args)
    if args.retry_failed:
        args.resume = True
    # bad input is found before any work: every video's motion.json and the grid steps
    for path in videos.values():
        _check_steps(args, load_motion_dataset(path))
    out = Path(args.out)
    run_info = {
        "format": B.BATCH_RUN_FORMAT,
        "videos": {k: str(Path(v).resolve()) for k, v in videos.items()},
        "config": R.to_jsonable(_asdict(cfg)),
        "options": _asdict(opts),
    }
    previous, log_dir, lock = _prepare_batch(out, shard, run_info, args.resume)
    ids = list(videos)
    scope = ids if shard is None else shard.select(ids)
    done = {str(r["video"]) for r in previous if r.get("ok") or not args.retry_failed}
    todo = [v for v in scope if v not in done]
    worker = B.MotionWorker({k: str(v) for k, v in videos.items()}, out, cfg, opts)
    spec = WorkerSpec(B.build_motion_worker,
                      ({k: str(v) for k, v in videos.items()}, str(out), cfg, opts))  # fmt: skip
    bar = progress(total=len(todo), desc="motion", unit="video") if todo else None
    t0 = time.time()
    with R.ResultsLog(log_dir / "results.jsonl") as log:
        stats = run_frames(spec, todo, log, executor, chunk=1, key="video",
                           local_worker=worker,
                           on_record=None if bar is None else lambda r: bar.update(1))  # fmt: skip
    if bar is not None:
        bar.close()
    if executor.kind != "local" and shard is None:
        from jaxcr.io.outdir import clean_leftovers

        clean_leftovers(out)  # temp files of a worker killed mid-write (OUT is locked, all done)
    merged = {str(r["video"]): r for r in _all_records(out)}
    recs = [merged[v] for v in scope if v in merged]
    failed = [r for r in recs if not r.get("ok")]
    summary = {
        "format": B.BATCH_FORMAT,
        "videos": len(recs),
        "ok": len(recs) - len(failed),
        "failed": len(failed),
        "failures": {r["video"]: r.get("reason") for r in failed},
        "missing": [v for v in scope if v not in merged],
        "shard": None if shard is None else str(shard),
        "executor": stats.executor,
        "run_s": stats.run_s,
        "wall_s": time.time() - t0,
    }
    R.atomic_write_json(log_dir / "summary.json", summary)
    R.atomic_write_text(log_dir / "DONE", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()) + "\n")
    what = "" if shard is None else f" (shard {shard})"
    print(f"jaxcr motion: {summary['ok']}/{len(recs)} videos ok{what} -> {out}")
    for r in failed:
        print(f"  {r['video']}: {r.get('reason')}", file=sys.stderr)
    return 1 if failed else 0


def _asdict(obj) -> dict:
    import dataclasses

    return dataclasses.asdict(obj)


def _all_records(out: Path) -> list[dict]:
    from jaxcr.motion.batch import read_video_records
    from jaxcr.scale.shards import read_all_records

    return read_all_records(out, read_video_records, key="video")


def _prepare_batch(out: Path, shard, run_info: dict, resume: bool):
    """Lock OUT (or the shard's folder), check that every part of the job ran with the same
    videos and options, and return (records this run skips, the folder of its results.jsonl,
    the lock). Without --resume an OUT that already holds this part's records is refused."""
    from jaxcr.io import outdir
    from jaxcr.scale import shards as S

    lock = S.claim_output(out, "motion", shard, marker=R.RUN_FILE)
    log_dir = out if shard is None else S.shard_dir(out, shard)
    try:
        if (out / "frames.jsonl").exists():
            raise InputError("output folder holds a single-video motion run; choose a new "
                             "folder for a batch", file=str(out))  # fmt: skip
        for other in [out / R.RUN_FILE] + [d / R.RUN_FILE for _, d in S.shard_dirs(out)]:
            if other.exists():
                prev = json.loads(other.read_text())
                if {k: prev.get(k) for k in run_info} != run_info:
                    raise InputError(
                        "another part of this job ran with other videos or options "
                        f"({other}); use the same arguments or a new folder",
                        file=str(out),
                    )
        from jaxcr.motion.batch import read_video_records

        own = read_video_records(log_dir / "results.jsonl")
        if own and not resume:
            raise InputError(
                f"output folder already holds {len(own)} video record(s) of this job; add "
                "--resume to continue it (--retry-failed to re-run failed videos) or choose a "
                "new folder",
                file=str(log_dir / "results.jsonl"),
            )
        (log_dir / "summary.json").unlink(missing_ok=True)
        (log_dir / "DONE").unlink(missing_ok=True)
        R.atomic_write_json(log_dir / R.RUN_FILE, run_info)
        # every part's records: a shard never redoes another part's video
        previous = _all_records(out)
    except BaseException:
        outdir.release(lock)
        raise
    return previous, log_dir, lock
