"""M-L vs the frame-differencing + grabCut baseline on fresh pushed_changing seeds (issue 17
item 9). Writes experiments/results/motion/motion_fresh_seeds.md (+ .json).

    python experiments/motion/motion_fresh_seeds.py --seeds 300-339 --data /tmp/motion_fresh

The seeds were reserved before development (experiments/results/segmentation/fresh_seeds_reserved.md:
300-339; development used 20-35) and are run once, with the package defaults: M-L
translation model, lambda 5 px^2, threshold 0.85 x the map maximum, superpixel step 20 px,
LK grid 4 px (all chosen on the static videos of seeds 0-9, motion_report.md). The baseline
is scored at its validated threshold, 40 grey levels (chosen on the same static videos), and,
as an upper bound no user can reach, at its per-video best threshold over the grid (oracle,
chosen with the ground truth). Scored on the ground-truth mask of the evaluation frame (the
first touch).

Each video is generated if missing (320x240, 24 frames, experiments/motion/motion_generate.py's
generator), run, and its record appended to --log (JSON lines) as it completes, so a stopped
run resumes where it stopped; the report is written from the completed records and states
how many there are. Win: M-L's Tanimoto distance strictly below the baseline's. Confidence
intervals of the win rate: Wilson score and exact (Clopper-Pearson) binomial, 95 %.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import binomtest  # noqa: E402

from jaxcr.io.motion_dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion import metrics as mt  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig  # noqa: E402
from jaxcr.motion.run import run_baseline, run_motion  # noqa: E402
from jaxcr.synth.motion_scenes import generate_motion_video  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "motion"
BL_THS = [2, 3, 5, 8, 12, 16, 20, 30, 40, 60, 80]  # motion_experiments.py's grid
BL_VALIDATED = 40.0  # chosen on the static videos of seeds 0-9 (motion_report.md)
# the audit: 16 fresh pushed_changing videos
AUDIT = {"n": 16, "ml": 0.523, "baseline": 0.627, "wins": 8}


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion k / n."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return float(mid - half), float(mid + half)


def tanimoto(mask, gt) -> float:
    return float(mt.tanimoto_distance(jnp.asarray(mask), jnp.asarray(gt)))


def run_one(d: Path, seed: int, retire_fraction: float) -> dict:
    if not (d / "motion.json").exists():
        generate_motion_video(d, "pushed_changing", seed=seed, size=(320, 240), n_frames=24)
    ds = load_motion_dataset(d)
    t = time.time()
    res = run_motion(ds, MotionConfig(models=("translation",), retire_fraction=retire_fraction))
    ml_s = time.time() - t
    gt = ds.mask(res.eval_frame)
    m = res.maps["translation"]
    ml_mask = m / max(float(m.max()), 1e-12) >= MotionConfig().threshold
    bl = run_baseline(ds, BL_THS)
    bl_t = {th: tanimoto(b, gt) for th, b in bl.items()} if bl else {}
    return {
        "video": d.name,
        "seed": seed,
        "object": ds.scene.get("object"),
        "changes": "+".join(ds.scene.get("changes", [])) or "-",
        "eval_frame": res.eval_frame,
        "gt_px": int(gt.sum()),
        "ml_px": int(ml_mask.sum()),
        "ml_tanimoto": tanimoto(ml_mask, gt),
        "baseline_tanimoto": bl_t.get(BL_VALIDATED, 1.0),
        "baseline_px": int(bl[BL_VALIDATED].sum()) if bl else 0,
        "baseline_oracle_tanimoto": min(bl_t.values()) if bl_t else 1.0,
        "baseline_oracle_threshold": min(bl_t, key=bl_t.get) if bl_t else None,
        "ml_seconds": ml_s,
    }


def summarise(recs: list[dict]) -> dict:
    ml = np.array([r["ml_tanimoto"] for r in recs])
    bl = np.array([r["baseline_tanimoto"] for r in recs])
    orc = np.array([r["baseline_oracle_tanimoto"] for r in recs])
    n = len(recs)
    out = {"n": n}
    for name, b in (("baseline", bl), ("oracle", orc)):
        k = int(np.sum(ml < b))
        ci = binomtest(k, n).proportion_ci(0.95, method="exact") if n else None
        out[name] = {
            "wins": k,
            "ties": int(np.sum(ml == b)),
            "win_rate": k / n if n else float("nan"),
            "wilson95": wilson(k, n),
            "exact95": (float(ci.low), float(ci.high)) if ci else None,
            "mean_tanimoto": float(b.mean()),
        }
    diff = bl - ml
    out["ml_mean_tanimoto"] = float(ml.mean())
    out["ml_median_tanimoto"] = float(np.median(ml))
    out["ml_misses"] = int(np.sum(ml >= 0.999))
    out["baseline_misses"] = int(np.sum(bl >= 0.999))
    # paired bootstrap of the mean difference (baseline - M-L), 95 %
    rng = np.random.default_rng(0)
    boots = [diff[rng.integers(0, n, n)].mean() for _ in range(5000)] if n else [np.nan]
    out["mean_diff_baseline_minus_ml"] = float(diff.mean())
    out["mean_diff_bootstrap95"] = [
        float(np.percentile(boots, 2.5)),
        float(np.percentile(boots, 97.5)),
    ]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="300-339", help="first-last (inclusive)")
    ap.add_argument("--data", default="/tmp/motion_fresh", help="video folder (generated)")
    ap.add_argument("--log", default=None, help="JSON-lines records (default: DATA/records.jsonl)")
    ap.add_argument("--report-only", action="store_true", help="write the report from the log")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument(
        "--retire-fraction",
        type=float,
        default=MotionConfig().retire_fraction,
        help="MotionConfig.retire_fraction (0: the tracking before the fix; use another --log)",
    )
    a = ap.parse_args()
    s0, s1 = (int(v) for v in a.seeds.split("-"))
    data = Path(a.data)
    data.mkdir(parents=True, exist_ok=True)
    log = Path(a.log) if a.log else data / "records.jsonl"
    done = {}
    if log.exists():
        for line in log.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[r["seed"]] = r
    load0 = os.getloadavg()
    t0 = time.time()
    if not a.report_only:
        for seed in range(s0, s1 + 1):
            if seed in done:
                continue
            r = run_one(data / f"pushed_changing_{seed}", seed, a.retire_fraction)
            with open(log, "a") as fh:
                fh.write(json.dumps(r) + "\n")
            done[seed] = r
            print(
                f"{r['video']}: M-L {r['ml_tanimoto']:.3f} baseline {r['baseline_tanimoto']:.3f} "
                f"({time.time() - t0:.0f} s)",
                flush=True,
            )
    recs = [done[s] for s in range(s0, s1 + 1) if s in done]
    summ = summarise(recs)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    seeds_done = [r["seed"] for r in recs]
    cmd = "python experiments/motion/motion_fresh_seeds.py " + " ".join(sys.argv[1:])
    b, o = summ["baseline"], summ["oracle"]
    md = [
        "# Motion-Likelihood vs baseline on fresh pushed_changing seeds (issue 17 item 9)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}; command: "
        f"`{cmd}`; load average at start {load0[0]:.1f}.",
        "",
        f"Seeds {s0}-{s1} were reserved before development (fresh_seeds_reserved.md); "
        f"{len(recs)} of them completed: {min(seeds_done, default='-')}-"
        f"{max(seeds_done, default='-')}"
        + (
            ""
            if len(recs) == s1 - s0 + 1
            else " (the rest not run: out of time on the shared machine)"
        )
        + ". Development seeds (looked at): 20-35. pushed_changing, 320x240, 24 frames; "
        "M-L translation, package defaults (lambda 5 px^2, threshold 0.85 x max, superpixels "
        "20 px, LK grid 4 px, lost segments retired at half their area); baseline = frame "
        "differencing + grabCut (seeded) at its validated threshold 40 (chosen on the static "
        "videos of seeds 0-9, motion_report.md); 'oracle' = the baseline at its best threshold "
        "per video, chosen with the ground truth (an upper bound, not a method). Tanimoto "
        "distance (eq. 20) on the first touch frame, lower is better; win = M-L strictly lower.",
        "",
        "| | videos | M-L mean Tanimoto | baseline mean Tanimoto | M-L wins | win rate | Wilson 95 % | exact 95 % |",
        "|---|---|---|---|---|---|---|---|",
        f"| this run, baseline at 40 | {summ['n']} | {summ['ml_mean_tanimoto']:.3f} | "
        f"{b['mean_tanimoto']:.3f} | {b['wins']} | {b['win_rate']:.2f} | "
        f"{b['wilson95'][0]:.2f}-{b['wilson95'][1]:.2f} | {b['exact95'][0]:.2f}-{b['exact95'][1]:.2f} |",
        f"| this run, baseline oracle threshold | {summ['n']} | {summ['ml_mean_tanimoto']:.3f} | "
        f"{o['mean_tanimoto']:.3f} | {o['wins']} | {o['win_rate']:.2f} | "
        f"{o['wilson95'][0]:.2f}-{o['wilson95'][1]:.2f} | {o['exact95'][0]:.2f}-{o['exact95'][1]:.2f} |",
        f"| issue 17 audit (previous code, its seeds) | {AUDIT['n']} | {AUDIT['ml']:.3f} | "
        f"{AUDIT['baseline']:.3f} | {AUDIT['wins']} | {AUDIT['wins'] / AUDIT['n']:.2f} | | |",
        "| motion_report_unseen.md (previous code, seeds 10-19, baseline 40) | 10 | 0.330 | 0.719 | 9 | 0.90 | | |",
        "",
        f"Mean difference baseline(40) - M-L: {summ['mean_diff_baseline_minus_ml']:.3f} "
        f"(paired bootstrap 95 %: {summ['mean_diff_bootstrap95'][0]:.3f} to "
        f"{summ['mean_diff_bootstrap95'][1]:.3f}). M-L median {summ['ml_median_tanimoto']:.3f}. "
        f"Complete misses (distance 1): M-L {summ['ml_misses']}, baseline(40) "
        f"{summ['baseline_misses']}.",
        "",
        "## What was wrong (development seeds 20-35 only)",
        "",
        "Traced on the development videos' intermediate outputs (per-frame label maps against "
        "the ground-truth masks, per-segment window means). The main failure: the tracked "
        "superpixel ids of the object were lost during the touch window. On pushed_changing_27 "
        "an id that covered the object up to frame 12 (of 24; touch from 10) was overrun and "
        "re-appeared on the background from frame 13 on, and another left the object at "
        "frame 15; both kept collecting evidence there (p ~ 0.02 per frame), so the touch-window "
        "mean of segments that were on the object at the evaluation frame fell to 0.2-0.3 "
        "and they dropped under the 0.85 threshold (most of the object missed). Fix: an id whose "
        "area falls below half its previous area has been lost by the tracking and stops "
        "collecting evidence (MotionConfig.retire_fraction = 0.5, a fixed rule, not tuned: the "
        "only value tried). On the development seeds 20-35 (baseline at 40): mean Tanimoto "
        "0.379 -> 0.366, wins 12 -> 14 of 16 (reproduce: this script with `--seeds 20-35` and "
        "`--retire-fraction 0`, each with its own `--data`/`--log`). Not fixed, seen on the "
        "same video: object segments still on the object whose translation b_j disagrees "
        "with the end-effector (the stabilised LK flow on the object spreads by +-10 px under "
        "the camera shake), which no integration rule recovers. The touch-window split itself "
        "(before / touching at the first touch flag) looked right on the four videos inspected "
        "(24, 25, 27, 29): pre-touch means 0.91-0.93 for object and background alike, except "
        "two object segments the arm passed over before the touch (0.08, 0.71).",
        "",
        "| video | object | changes | gt px | M-L px | M-L | baseline (40) | baseline oracle (threshold) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in recs:
        md.append(
            f"| {r['video']} | {r['object']} | {r['changes']} | {r['gt_px']} | {r['ml_px']} | "
            f"{r['ml_tanimoto']:.3f} | {r['baseline_tanimoto']:.3f} | "
            f"{r['baseline_oracle_tanimoto']:.3f} ({r['baseline_oracle_threshold']}) |"
        )
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "motion_fresh_seeds.md").write_text("\n".join(md) + "\n")
    (out / "motion_fresh_seeds.json").write_text(
        json.dumps({"command": cmd, "commit": commit, "summary": summ, "videos": recs}, indent=1)
    )
    print("\n".join(md[:12]))


if __name__ == "__main__":
    main()
