"""Cheaper LK settings for M-L against the validated setting, on the development videos only
(issue 18, row "motion likelihood, 640x480"). Writes experiments/results/motion/motion_speed_r2.md
(+ .json).

    python experiments/motion/motion_speed_r2.py --data /tmp/motion/dev640 --seeds 20-27 --size 640x480
    python experiments/motion/motion_speed_r2.py --data /tmp/seeds/mdev --seeds 20-35 --size 320x240

Videos: ``pushed_changing`` development seeds (fresh_seeds_reserved.md: motion development
20-35; the fresh seeds 300-339 were used once and are not touched here), generated with
``jaxcr.synth.motion_scenes.generate_motion_video`` if missing (24 frames). Each variant
changes one :class:`~jaxcr.motion.flow.FlowConfig` field of the package defaults; both
motion models run (lambda 5, threshold 0.85, as validated). Per video and model: the
Tanimoto distance of the mask at 0.85 x the map maximum (eq. 20, lower is better) and the
average precision of the probability map over the pixels (exact, ties grouped) against the
ground-truth mask of the evaluation frame; per frame pair the flow time and the wall time
of the default (overlapped) path. Records are appended to ``--log`` as they complete (a
stopped run resumes). The accuracy tolerance is stated before the run: a variant is "equal"
when its mean paired change is within 0.02 for Tanimoto and for AP in both models, and the
paired bootstrap 95 % interval of the change contains 0 (the per-video spread over seeds is
0.2, motion_speed_accuracy.md: 0.02 is a tenth of it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

from jaxcr.io.motion_dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig  # noqa: E402
from jaxcr.motion.run import run_motion  # noqa: E402
from jaxcr.synth.motion_scenes import generate_motion_video  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "motion"
VARIANTS = {
    "validated": {},
    "iters10": {"iters": 10},
    "levels2": {"levels": 2},
    "iters10_levels2": {"iters": 10, "levels": 2},
}
EQUAL_TOL = 0.02


def average_precision(prob: np.ndarray, gt: np.ndarray) -> float:
    """Area under the precision-recall curve of ranking the pixels by ``prob`` (the
    step-wise sum of precision x recall increments, one step per distinct value)."""
    p = prob.ravel().astype(np.float64)
    y = gt.ravel().astype(bool)
    if not y.any():
        return float("nan")
    order = np.argsort(-p, kind="stable")
    p, y = p[order], y[order]
    last = np.r_[np.flatnonzero(np.diff(p)), len(p) - 1]  # end of each group of ties
    tp = np.cumsum(y)[last]
    prec = tp / (last + 1)
    rec = tp / y.sum()
    return float(np.sum(np.diff(np.r_[0.0, rec]) * prec))


def tanimoto(mask: np.ndarray, gt: np.ndarray) -> float:
    inter = np.logical_and(mask, gt).sum()
    union = np.logical_or(mask, gt).sum()
    return 0.0 if union == 0 else float(1.0 - inter / union)


def run_one(d: Path, variant: str) -> dict:
    base = MotionConfig()
    cfg = replace(base, flow=replace(base.flow, **VARIANTS[variant]))
    ds = load_motion_dataset(d)
    stamps: list[tuple[bool, float]] = []
    t0 = time.time()
    res = run_motion(ds, cfg, on_step=lambda r: stamps.append((r.used, time.perf_counter())))
    wall_s = time.time() - t0
    gt = ds.mask(res.eval_frame)
    rec = {"video": d.name, "variant": variant, "wall_s": wall_s, "models": {}}
    for m in cfg.models:
        pm = res.maps[m]
        norm = pm / max(float(pm.max()), 1e-12)
        rec["models"][m] = {
            "tanimoto": tanimoto(norm >= cfg.threshold, gt),
            "ap": average_precision(pm, gt),
        }
    used = [r for r in res.records if r.used]
    rec["flow_ms"] = float(np.median([r.flow_ms for r in used]))
    rec["jax_ms"] = float(np.median([r.segmentation_ms + r.likelihood_ms for r in used]))
    rec["frame_wall_ms"] = float(
        np.median(
            [1e3 * (b - a) for (_, a), (u, b) in zip(stamps[:-1], stamps[1:], strict=True) if u]
        )
    )
    return rec


def bootstrap_ci(d: np.ndarray, n: int = 10000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), (n, len(d)))].mean(1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def summarise(recs: list[dict]) -> dict:
    by = {}
    for r in recs:
        by.setdefault(r["variant"], {})[r["video"]] = r
    ref = by.get("validated", {})
    out = {}
    for v, vids in by.items():
        common = sorted(set(vids) & set(ref))
        row = {"videos": len(vids), "paired": len(common)}
        for m in ("translation", "homography"):
            for k in ("tanimoto", "ap"):
                a = np.array([vids[x]["models"][m][k] for x in common])
                b = np.array([ref[x]["models"][m][k] for x in common])
                row[f"{m}_{k}"] = float(a.mean()) if len(a) else None
                row[f"{m}_{k}_std"] = float(a.std(ddof=1)) if len(a) > 1 else None
                if v != "validated" and len(a) > 1:
                    d = a - b
                    row[f"{m}_{k}_change"] = float(d.mean())
                    row[f"{m}_{k}_ci"] = bootstrap_ci(d)
        for k in ("flow_ms", "jax_ms", "frame_wall_ms"):
            row[k] = float(np.median([vids[x][k] for x in common])) if common else None
        if v != "validated" and common:
            ok = True
            for m in ("translation", "homography"):
                for k in ("tanimoto", "ap"):
                    ch, (lo, hi) = row[f"{m}_{k}_change"], row[f"{m}_{k}_ci"]
                    worse = ch if k == "tanimoto" else -ch
                    ok &= worse <= EQUAL_TOL and lo <= 0 <= hi
            row["equal"] = bool(ok)
        out[v] = row
    return out


def report(recs, summary, args, load) -> str:
    lines = [
        "# M-L speed, round 2: cheaper LK on the development videos",
        "",
        f"Command: `python experiments/motion/motion_speed_r2.py --data {args.data} --seeds "
        f"{args.seeds} --size {args.size}`; {platform.machine()}, load average at start "
        f"{load[0]:.1f} (a shared 2-core machine: times are inflated by the load, compare within "
        "the table).",
        "",
        f"{'Fresh (reserved)' if args.fresh else 'Development'} seeds only ({args.seeds}, pushed_changing, {args.size}, 24 frames); both "
        "models, package defaults otherwise. Equal = mean paired change within "
        f"{EQUAL_TOL} (Tanimoto not higher, AP not lower by more) and the bootstrap 95 % interval "
        "of the change contains 0, for both models.",
        "",
        "| variant | videos | Tanimoto transl. | Tanimoto homog. | AP transl. | AP homog. | "
        "change (T-t, T-h, AP-t, AP-h) | equal | flow ms | JAX ms | wall ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for v, r in summary.items():
        ch = (
            ", ".join(
                f"{r[f'{m}_{k}_change']:+.3f} [{r[f'{m}_{k}_ci'][0]:+.3f}, {r[f'{m}_{k}_ci'][1]:+.3f}]"
                for m, k in (
                    ("translation", "tanimoto"),
                    ("homography", "tanimoto"),
                    ("translation", "ap"),
                    ("homography", "ap"),
                )
            )  # fmt: skip
            if v != "validated" and r.get("translation_tanimoto_change") is not None
            else "-"
        )
        lines.append(
            f"| {v} {VARIANTS[v] or '(iters 20, levels 3)'} | {r['paired']} | "
            f"{r['translation_tanimoto']:.3f} +- {r['translation_tanimoto_std']:.3f} | "
            f"{r['homography_tanimoto']:.3f} +- {r['homography_tanimoto_std']:.3f} | "
            f"{r['translation_ap']:.3f} | {r['homography_ap']:.3f} | {ch} | "
            f"{r.get('equal', '-')} | {r['flow_ms']:.1f} | {r['jax_ms']:.1f} | "
            f"{r['frame_wall_ms']:.1f} |"
        )
    lines += ["", "Per video (Tanimoto translation / homography, AP translation / homography):", ""]
    vids = sorted({r["video"] for r in recs})
    lines.append("| video | " + " | ".join(summary) + " |")
    lines.append("|---|" + "---|" * len(summary))
    idx = {(r["video"], r["variant"]): r for r in recs}
    for x in vids:
        cells = []
        for v in summary:
            r = idx.get((x, v))
            cells.append("-" if r is None else "{:.3f}/{:.3f}, {:.3f}/{:.3f}".format(
                r["models"]["translation"]["tanimoto"], r["models"]["homography"]["tanimoto"],
                r["models"]["translation"]["ap"], r["models"]["homography"]["ap"]))  # fmt: skip
        lines.append(f"| {x} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="video folder (pushed_changing_<seed>)")
    ap.add_argument("--seeds", default="20-27", help="first-last, development seeds only")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--log", default=None, help="JSON lines (default: DATA/speed_r2.jsonl)")
    ap.add_argument("--out", default=None, help="report .md (default: print only)")
    ap.add_argument("--fresh", action="store_true",
                    help="the seeds reserved for this check, 340-355 (fresh_seeds_reserved.md), "
                    "run once with the variants fixed before the run")  # fmt: skip
    args = ap.parse_args()
    lo, hi = (int(v) for v in args.seeds.split("-"))
    allowed = (340, 355) if args.fresh else (20, 35)
    if lo < allowed[0] or hi > allowed[1]:
        raise SystemExit(f"seeds must be within {allowed[0]}-{allowed[1]} "
                         "(fresh_seeds_reserved.md)")  # fmt: skip
    w, h = (int(v) for v in args.size.split("x"))
    data = Path(args.data)
    log = Path(args.log or data / "speed_r2.jsonl")
    recs = [json.loads(x) for x in log.read_text().splitlines()] if log.exists() else []
    have = {(r["video"], r["variant"]) for r in recs}
    load = os.getloadavg()
    variants = args.variants.split(",")
    for seed in range(lo, hi + 1):
        d = data / f"pushed_changing_{seed}"
        if not (d / "motion.json").exists():
            generate_motion_video(d, "pushed_changing", seed=seed, size=(w, h), n_frames=24)
        for v in variants:
            if (d.name, v) in have:
                continue
            rec = run_one(d, v)
            recs.append(rec)
            with open(log, "a") as f:
                f.write(json.dumps(rec) + "\n")
            print(d.name, v, {m: round(x["tanimoto"], 3) for m, x in rec["models"].items()},
                  f"flow {rec['flow_ms']:.1f} ms", flush=True)  # fmt: skip
    summary = summarise(recs)
    text = report(recs, summary, args, load)
    print(text)
    if args.out:
        Path(args.out).write_text(text)
        Path(args.out).with_suffix(".json").write_text(
            json.dumps({"summary": summary, "records": recs}, indent=1)
        )


if __name__ == "__main__":
    main()
