"""M-L experiments on the synthetic video set (paper Figs. 6, 7 and 10).

  python experiments/motion_generate.py --out /tmp/motion_data
  python experiments/motion_experiments.py --data /tmp/motion_data --cache /tmp/motion_runs

For every video: M-L with both motion models (one run, shared flow and segmentation), the
frame-differencing + grabCut baseline over its threshold, and M-L + GraphCuts at the chosen
M-L threshold. Scored on the ground-truth mask of the evaluation frame (pushed set: the first
touch frame, as in the paper; held set: the middle of the carried motion).

Outputs: experiments/results/motion_report.md, motion_per_video.csv, motion_pr.png (Fig. 6),
motion_distances.png (Fig. 7), motion_3d_pr.png (Fig. 10). Runs on one core.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxcr.motion import metrics as mt  # noqa: E402
from jaxcr.motion.baseline import ml_graphcut  # noqa: E402
from jaxcr.motion.dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig  # noqa: E402
from jaxcr.motion.run import run_baseline, run_motion  # noqa: E402

ML_THS = np.round(np.linspace(0.05, 1.0, 20), 3)
BL_THS = [2, 3, 5, 8, 12, 16, 20, 30, 40, 60, 80]
OUT = Path(__file__).parent / "results"


def run_video(d: Path, cfg: MotionConfig, cache: Path) -> dict:
    f = cache / f"{d.name}.npz"
    if f.exists():
        z = np.load(f, allow_pickle=True)
        return {k: z[k] for k in z.files}
    ds = load_motion_dataset(d)
    t = time.time()
    res = run_motion(ds, cfg)
    ml_s = time.time() - t
    gt = ds.mask(res.eval_frame)
    rec = {
        "gt": gt,
        "map_translation": res.maps["translation"],
        "map_homography": res.maps["homography"],
        "ml_s": ml_s,
        "eval_frame": res.eval_frame,
        "scene": json.dumps(ds.scene),
        "timing": np.array(
            [[r.flow_ms, r.segmentation_ms, r.likelihood_ms] for r in res.records if r.used]
        ),
    }
    if ds.scene.get("set") == "pushed":
        bl = run_baseline(ds, BL_THS)
        rec["baseline"] = np.stack([bl[float(t)] for t in BL_THS])
        frames = {i: rgb for i, rgb, _ in ds.frames() if i == res.eval_frame}
        rec["eval_rgb"] = np.clip(np.round(frames[res.eval_frame] * 255), 0, 255).astype(np.uint8)
    np.savez_compressed(f, **rec)
    return rec


def norm(m):
    return m / max(float(m.max()), 1e-12)


def pr_of(score, gt, ths):
    p, r = mt.pr_curve(
        jnp.asarray(score), jnp.asarray(gt), jnp.asarray(np.asarray(ths, np.float32))
    )
    return np.asarray(p), np.asarray(r)


def dist(mask, gt):
    return float(mt.tanimoto_distance(jnp.asarray(mask), jnp.asarray(gt))), float(
        mt.l2_distance(jnp.asarray(mask), jnp.asarray(gt))
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/tmp/motion_data")
    ap.add_argument("--cache", default="/tmp/motion_runs")
    ap.add_argument("--lam", type=float, default=15.0)
    ap.add_argument("--superpixel-step", type=int, default=20)
    a = ap.parse_args()
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    cfg = MotionConfig(lam=a.lam, superpixel_step=a.superpixel_step)
    vids = sorted(p for p in Path(a.data).iterdir() if (p / "motion.json").exists())
    runs = {}
    for d in vids:
        t = time.time()
        runs[d.name] = run_video(d, cfg, cache)
        print(f"{d.name}: {time.time() - t:.1f} s", flush=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    OUT.mkdir(exist_ok=True)
    pushed = {k: v for k, v in runs.items() if k.startswith("pushed")}
    held = {k: v for k, v in runs.items() if k.startswith("held")}
    # ---- Fig. 6: P-R over the threshold (mean precision and recall over videos) --------------
    curves = {}
    for bg in ("static", "changing"):
        vs = [v for k, v in pushed.items() if bg in k]
        for m in ("translation", "homography"):
            prs = np.array([pr_of(norm(v[f"map_{m}"]), v["gt"], ML_THS) for v in vs])
            curves[(bg, f"M-L {m}")] = (ML_THS, prs[:, 0].mean(0), prs[:, 1].mean(0))
        bl = []
        for v in vs:
            rows = [
                mt.precision_recall(jnp.asarray(b), jnp.asarray(v["gt"])) for b in v["baseline"]
            ]
            bl.append([[float(p), float(r)] for p, r in rows])
        bl = np.array(bl)
        curves[(bg, "baseline")] = (np.array(BL_THS), bl[:, :, 0].mean(0), bl[:, :, 1].mean(0))
    # optimal thresholds over all pushed videos (paper: closest to (1, 1) for all objects)
    allv = list(pushed.values())
    prs = np.array([pr_of(norm(v["map_translation"]), v["gt"], ML_THS) for v in allv])
    k_ml, th_ml = mt.optimal_threshold(ML_THS, prs[:, 0].mean(0), prs[:, 1].mean(0))
    blp = np.array(
        [
            [
                [float(x) for x in mt.precision_recall(jnp.asarray(b), jnp.asarray(v["gt"]))]
                for b in v["baseline"]
            ]
            for v in allv
        ]
    )
    k_bl, th_bl = mt.optimal_threshold(BL_THS, blp[:, :, 0].mean(0), blp[:, :, 1].mean(0))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, bg in zip(axes, ("static", "changing"), strict=True):
        for (b, name), (_ths, p, r) in curves.items():
            if b == bg:
                ax.plot(r, p, "o-", ms=3, label=name)
        ax.set(
            xlabel="recall",
            ylabel="precision",
            title=f"{bg} backgrounds",
            xlim=(0, 1.02),
            ylim=(0, 1.02),
        )
        ax.legend(fontsize=8)
    fig.suptitle("P-R over the threshold (cf. M-L Fig. 6)")
    fig.tight_layout()
    fig.savefig(OUT / "motion_pr.png", dpi=110)
    # ---- per-video distances at the chosen thresholds (Fig. 7) ------------------------------
    rows = []
    for k, v in pushed.items():
        sc = json.loads(str(v["scene"]))
        ml_mask = norm(v["map_translation"]) >= th_ml
        ml75 = norm(v["map_translation"]) >= 0.75
        gc = ml_graphcut(v["eval_rgb"], ml_mask)
        row = {
            "video": k,
            "object": sc["object"],
            "background": sc["background"],
            "changes": "+".join(sc["changes"]) or "-",
        }
        for name, msk in (
            ("ml", ml_mask),
            ("ml75", ml75),
            ("ml_gc", gc),
            ("baseline", v["baseline"][k_bl]),
        ):
            row[f"{name}_tanimoto"], row[f"{name}_l2"] = dist(msk, v["gt"])
        row["ml_s"] = float(v["ml_s"])
        rows.append(row)
    import csv

    with open(OUT / "motion_per_video.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    def stat(sel, key):
        x = np.array([r[key] for r in rows if sel(r)])
        return x.mean(), x.std(), len(x)

    methods = [
        ("ml", "M-L"),
        ("ml_gc", "M-L + GraphCuts"),
        ("baseline", "baseline (diff + grabCut)"),
    ]
    groups = [
        (f"object {o}", lambda r, o=o: r["object"] == o)
        for o in ("book", "mug", "spirit_level", "bottle", "rabbit")
    ]
    groups += [
        ("static background", lambda r: r["background"] == "static"),
        ("changing background", lambda r: r["background"] == "changing"),
    ]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, metric in zip(axes, ("l2", "tanimoto"), strict=True):
        xs = np.arange(len(groups))
        for j, (key, name) in enumerate(methods):
            mv = [stat(sel, f"{key}_{metric}") for _, sel in groups]
            ax.bar(
                xs + (j - 1) * 0.27,
                [m[0] for m in mv],
                0.27,
                yerr=[m[1] for m in mv],
                label=name,
                capsize=2,
            )
        ax.set_xticks(
            xs,
            [g[0].replace("object ", "").replace(" background", "\nbg") for g in groups],
            fontsize=8,
        )
        ax.set_title(
            f"{'L2 (eq. 19)' if metric == 'l2' else 'Tanimoto (eq. 20)'} distance, mean +- std (lower is better)"
        )
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "motion_distances.png", dpi=110)
    # ---- Fig. 10: translation vs homography on the held (3-D) set ---------------------------
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    held_rows = []
    for ax, obj in zip(axes, ("book", "spirit_level"), strict=True):
        vs = [(k, v) for k, v in held.items() if json.loads(str(v["scene"]))["object"] == obj]
        for m in ("translation", "homography"):
            if not vs:
                continue
            prs = np.array([pr_of(norm(v[f"map_{m}"]), v["gt"], ML_THS) for _, v in vs])
            ax.plot(prs[:, 1].mean(0), prs[:, 0].mean(0), "o-", ms=3, label=m)
        ax.set(
            xlabel="recall", ylabel="precision", title=f"held {obj}", xlim=(0, 1.02), ylim=(0, 1.02)
        )
        ax.legend()
    fig.suptitle("3-D motion set: translation vs homography (cf. M-L Fig. 10)")
    fig.tight_layout()
    fig.savefig(OUT / "motion_3d_pr.png", dpi=110)
    for k, v in held.items():
        sc = json.loads(str(v["scene"]))
        r = {"video": k, "object": sc["object"], "background": sc["background"]}
        for m in ("translation", "homography"):
            p, rc = pr_of(norm(v[f"map_{m}"]), v["gt"], ML_THS)
            r[f"{m}_tanimoto_075"] = dist(norm(v[f"map_{m}"]) >= 0.75, v["gt"])[0]
            r[f"{m}_best_tanimoto"] = min(
                dist(norm(v[f"map_{m}"]) >= t, v["gt"])[0] for t in ML_THS
            )
            r[f"{m}_ap"] = float(np.sum(np.diff(np.concatenate([[0.0], rc[::-1]])) * p[::-1]))
        held_rows.append(r)
    # ---- report -------------------------------------------------------------------------------
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).parent,
    ).stdout.strip()
    tim = np.concatenate([v["timing"] for v in runs.values() if len(v["timing"])])
    L = [
        "# Motion-Likelihood experiments (synthetic videos)",
        "",
        f"commit {commit}, jax {jax.__version__}, {platform.processor() or platform.machine()}, one core; "
        f"lambda = {a.lam} px^2, superpixel step {a.superpixel_step} px, LK grid step {cfg.flow.step} px, "
        f"{len(pushed)} pushed videos ({sum('static' in k for k in pushed)} static, {sum('changing' in k for k in pushed)} changing), "
        f"{len(held)} held (3-D) videos, 320x240, 24 frames each.",
        "",
        "Reproduce: `python experiments/motion_generate.py --out /tmp/motion_data && python experiments/motion_experiments.py`.",
        "",
        "## Thresholds (P-R point closest to (1, 1), all pushed videos; Fig. 6: motion_pr.png)",
        "",
        f"- M-L (translation): {th_ml:.2f} x the map maximum (the paper found 0.75)",
        f"- baseline: difference > {th_bl:g} grey levels (the paper found 5)",
        "",
        "## Distances per object and background (Fig. 7: motion_distances.png)",
        "",
        "| group | n | M-L Tanimoto | M-L+GC Tanimoto | baseline Tanimoto | M-L L2 | M-L+GC L2 | baseline L2 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g, sel in groups:
        cells = []
        n = stat(sel, "ml_tanimoto")[2]
        for metric in ("tanimoto", "l2"):
            for key, _ in methods:
                mu, sd, _ = stat(sel, f"{key}_{metric}")
                cells.append(
                    f"{mu:.3f} +- {sd:.3f}" if metric == "tanimoto" else f"{mu:.2e} +- {sd:.1e}"
                )
        L.append(f"| {g} | {n} | " + " | ".join(cells) + " |")
    L += [
        "",
        "M-L at the paper's fixed 0.75 threshold: mean Tanimoto "
        f"{stat(lambda r: r['background'] == 'static', 'ml75_tanimoto')[0]:.3f} (static), "
        f"{stat(lambda r: r['background'] == 'changing', 'ml75_tanimoto')[0]:.3f} (changing).",
        "",
        "## Kolmogorov-Smirnov comparison with the baseline (Tanimoto and L2; one-sided: ours smaller)",
        "",
        "| background | method | metric | KS D | p-value | P(random video of ours beats theirs) | videos won |",
        "|---|---|---|---|---|---|---|",
    ]
    ks_out = {}
    for bg in ("static", "changing"):
        for key, name in methods[:2]:
            for metric in ("tanimoto", "l2"):
                ours = [r[f"{key}_{metric}"] for r in rows if r["background"] == bg]
                theirs = [r[f"baseline_{metric}"] for r in rows if r["background"] == bg]
                ks = mt.ks_compare(ours, theirs)
                ks_out[(bg, key, metric)] = ks
                L.append(
                    f"| {bg} | {name} | {metric} | {ks['ks_statistic']:.2f} | {ks['ks_pvalue']:.3g} | "
                    f"{ks['p_random_win']:.2f} | {ks['fraction_won']:.2f} |"
                )
    L += [
        "",
        "## Translation vs homography on the 3-D (held) set (Fig. 10: motion_3d_pr.png)",
        "",
        "| video | object | background | translation AP | homography AP | translation Tanimoto @0.75 | homography Tanimoto @0.75 | translation best Tanimoto | homography best Tanimoto |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in held_rows:
        L.append(
            f"| {r['video']} | {r['object']} | {r['background']} | {r['translation_ap']:.3f} | {r['homography_ap']:.3f} | "
            f"{r['translation_tanimoto_075']:.3f} | {r['homography_tanimoto_075']:.3f} | {r['translation_best_tanimoto']:.3f} | {r['homography_best_tanimoto']:.3f} |"
        )
    if held_rows:
        for key in ("ap", "tanimoto_075", "best_tanimoto"):
            t_ = np.mean([r[f"translation_{key}"] for r in held_rows])
            h_ = np.mean([r[f"homography_{key}"] for r in held_rows])
            L.append(
                f"| **mean** | | | {key}: translation {t_:.3f} | homography {h_:.3f} | | | | |"
            )
    ch = [r for r in rows if r["background"] == "changing"]
    win = np.mean([r["ml_tanimoto"] < r["baseline_tanimoto"] for r in ch]) if ch else float("nan")
    L += [
        "",
        "## Done-when checks",
        "",
        f"- changing backgrounds: mean Tanimoto M-L {stat(lambda r: r['background'] == 'changing', 'ml_tanimoto')[0]:.3f} vs baseline "
        f"{stat(lambda r: r['background'] == 'changing', 'baseline_tanimoto')[0]:.3f}; M-L better on {win * 100:.0f}% of the changing videos.",
        f"- timing of the experiment runs (320x240, median per frame): flow {np.median(tim[:, 0]):.1f} ms, segmentation "
        f"{np.median(tim[:, 1]):.1f} ms, likelihood (both models) {np.median(tim[:, 2]):.1f} ms (shared machine, see motion_bench.md for 640x480).",
    ]
    (OUT / "motion_report.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
