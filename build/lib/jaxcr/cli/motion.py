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

``jaxcr motion synth -o OUT`` writes a synthetic video dataset instead (presets
pushed_static, pushed_changing, held_static, held_changing).

Examples:
  jaxcr motion synth --preset pushed_changing --seed 3 -o /tmp/push3
  jaxcr motion /tmp/push3 -o /tmp/push3_out
  jaxcr motion /tmp/push3 -o /tmp/out --model homography --lambda 20 --flow dis
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

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
    p.add_argument("dataset", help="dataset folder (jaxcr.motion/1), or 'synth' to generate one")
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


def _png(path: Path, a: np.ndarray) -> None:
    from jaxcr.io.images import write_png

    write_png(path, a)


def timing_line(timing: dict) -> str:
    """The report's median per-frame times (ms, one decimal; '-' without used frames)."""
    parts = []
    for k in ("flow", "segmentation", "likelihood"):
        v = timing.get(f"{k}_ms")
        parts.append(f"{k} -" if v is None else f"{k} {v:.1f} ms")
    return "Median per-frame time: " + ", ".join(parts) + "."


def run(args) -> int:
    if args.dataset == "synth":
        return _synth(args)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    from jaxcr.io.motion_dataset import load_motion_dataset
    from jaxcr.limits import check_number
    from jaxcr.motion import metrics as mt
    from jaxcr.motion.flow import FlowConfig
    from jaxcr.motion.pipeline import MODELS, MotionConfig, resolve_steps
    from jaxcr.motion.run import first_touch, run_baseline, run_motion
    from jaxcr.progress import progress

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
    ds = load_motion_dataset(args.dataset)
    # a grid step over the frame's shorter side leaves one superpixel / one flow vector
    short = min(ds.width, ds.height)
    from jaxcr.limits import check_count

    for flag, step in (
        ("--superpixel-step", args.superpixel_step),
        ("--flow-step", args.flow_step),
    ):
        check_count(step, flag, 0, short, "the frames' shorter side; 0 = auto")
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
    out = Path(args.out)
    from jaxcr.io import outdir

    # new, empty or an earlier motion run (whose results are replaced), never another command's
    # folder; locked until exit
    outdir.claim(out, "motion", recognise=lambda o: (o / "frames.jsonl").exists())
    # An earlier run's results must not sit beside this run's partial log if it stops early:
    # remove them now; summary.json and report.md (last) are written only when it completes.
    for stale in ("summary.json", "report.md", "baseline_pr.csv", "mask_baseline.png"):
        (out / stale).unlink(missing_ok=True)
    for pattern in ("prob_*.npy", "prob_*.png", "mask_*.png", "pr_*.csv"):
        for f in out.glob(pattern):
            f.unlink()
    t0 = time.time()
    log = open(out / "frames.jsonl", "w")
    bar = progress(total=len(ds), desc="motion", unit="frame")

    def on_step(rec):
        log.write(
            json.dumps(
                {k: (round(v, 3) if isinstance(v, float) else v) for k, v in vars(rec).items()}
            )
            + "\n"
        )
        log.flush()
        bar.update(1)

    try:
        res = run_motion(ds, cfg, on_step=on_step)
    except RuntimeError as err:
        raise InputError(str(err), file=args.dataset) from None
    finally:
        bar.close()
        log.close()
    # Frames the reader could not use (unreadable, corrupt, wrong size) are failed frames: the
    # run went on without them but exits 1 (README exit codes). Pairs the method itself does not
    # use (first frame, end-effector still or out of view, no valid flow) are not failures.
    failed = res.failed
    gt = ds.mask(res.eval_frame)
    ths = np.round(np.linspace(0.05, 1.0, 20), 3)
    summary = {
        "dataset": str(args.dataset),
        "eval_frame": res.eval_frame,
        "first_touch": first_touch(ds),
        "warnings": res.warnings,
        "models": {},
    }
    for m in models:
        pm = res.maps[m]
        norm = pm / max(float(pm.max()), 1e-12)
        np.save(out / f"prob_{m}.npy", pm)
        _png(out / f"prob_{m}.png", np.clip(np.round(norm * 255), 0, 255).astype(np.uint8))
        mask = norm >= args.threshold
        _png(out / f"mask_{m}.png", mask)
        info = {"max_probability": float(pm.max())}
        if gt is not None:
            import jax.numpy as jnp

            pr, re = mt.pr_curve(jnp.asarray(norm), jnp.asarray(gt), jnp.asarray(ths))
            pr, re = np.asarray(pr), np.asarray(re)
            np.savetxt(
                out / f"pr_{m}.csv",
                np.stack([ths, pr, re], 1),
                delimiter=",",
                header="threshold,precision,recall",
                comments="",
                fmt="%.5f",
            )
            k, tbest = mt.optimal_threshold(ths, pr, re)
            info.update(
                tanimoto=float(mt.tanimoto_distance(jnp.asarray(mask), jnp.asarray(gt))),
                l2=float(mt.l2_distance(jnp.asarray(mask), jnp.asarray(gt))),
                optimal_threshold=tbest,
                optimal_precision=float(pr[k]),
                optimal_recall=float(re[k]),
            )
        summary["models"][m] = info
    if not args.no_baseline:
        bth = float(args.baseline_threshold)
        bths = sorted({2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, bth})
        bl = run_baseline(ds, bths if gt is not None else [bth])
        if bl is None:
            summary["warnings"].append(
                "baseline skipped: no touch event at frame >= 2 with readable frames"
            )
        else:
            _png(out / "mask_baseline.png", bl[bth])
            summary["baseline"] = {"threshold": bth, "mask_pixels": int(bl[bth].sum())}
        if bl is not None and gt is not None:
            import jax.numpy as jnp

            rows = []
            for th, msk in bl.items():
                p_, r_ = mt.precision_recall(jnp.asarray(msk), jnp.asarray(gt))
                rows.append(
                    [
                        th,
                        float(p_),
                        float(r_),
                        float(mt.tanimoto_distance(jnp.asarray(msk), jnp.asarray(gt))),
                    ]
                )
            np.savetxt(
                out / "baseline_pr.csv",
                np.array(rows),
                delimiter=",",
                header="threshold,precision,recall,tanimoto",
                comments="",
                fmt="%.5f",
            )
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
        "threshold": args.threshold,
    }
    summary.update(
        settings=settings,
        frames=len(ds),
        used=len(used),
        skipped=len(skipped),
        failed={str(k): v for k, v in sorted(failed.items())},
        median_ms=timing,
        wall_s=time.time() - t0,
    )
    R.atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    lines = [
        f"# Motion-Likelihood: {args.dataset}",
        "",
        f"{len(ds)} frames, {len(used)} frame pairs used, {len(skipped)} skipped; evaluation frame {res.eval_frame} "
        f"(first touch {first_touch(ds)}).",
        "",
    ]
    lines.append(
        f"Settings: superpixel step {sp} px (SLIC on the frame shrunk {scale}x), "
        f"{cfg.flow.method.upper()} flow on a {flow_step}-px grid (window {cfg.flow.window} px, "
        f"{cfg.flow.levels} levels), lambda {cfg.lam:g} px^2, threshold {args.threshold:g} x the map "
        "maximum."
    )
    lines.append("")
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
                f"| {m} | {info['tanimoto']:.3f} | {info['l2']:.2e} | {info['optimal_threshold']:.2f}, "
                f"{info['optimal_precision']:.2f}, {info['optimal_recall']:.2f} |"
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
    lines += [
        "",
        timing_line(timing),
    ]
    R.atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    if failed:
        i, why = min(failed.items())
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        more += f"; all listed in {out / 'summary.json'}"
        print(f"jaxcr motion: {len(failed)} frame(s) failed: frame {i}: {why}{more}",
              file=sys.stderr)  # fmt: skip
    return 0 if used and not failed else 1
