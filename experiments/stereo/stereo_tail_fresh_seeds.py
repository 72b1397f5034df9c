"""The single-view tail in the stored stereo backbone, on fresh seeds (issue 17 item 11).

Usage::

    python experiments/stereo/stereo_tail_fresh_seeds.py [--seeds 304-313] [--frames 1] \
        [--work /tmp/stereo_tail] [--out experiments/results/stereo/stereo_tail_fresh_seeds.md]

Where a tip is foreshortened or curled in one view, the stereo matching stops before the
tip; the other view still sees the rest. Since this change the pipeline appends that
single-view tail to the stored backbone (``result["single_view"]`` flags it; the joint
chain fit, constrained across the tube by the view that sees it and in depth by the
continuing arc, gives its points; ``StereoConfig.single_view_tail``). One reconstruction per
frame; "stereo only" is the same result cut at the last stereo sample (the stored backbone
before this change), "with tail" the stored backbone.

Sets: ``generate_stereo_set(seed=S, n_frames=F, kinds=("curled", "towards_cam1",
"towards_cam2"))``, 640x480, default pipeline (markers base, chroma key). Settings (the
tail's 0.5 mm spacing, the chain fit's 50 mm reach past the last stereo sample, attaching
the chain's tail at the last stereo point, ending it where its projection in the view that
sees it reaches that view's tip pixel) were fixed on development seeds 1 (4 frames) and
301-303 (seed 302's curled frame: without the tip-pixel end the tail ran 44 mm where 22 mm
were missing); the seeds reported here (default 304-313) were not looked at before this
run.

Metrics against the truth (``jaxcr.stereo.evaluate``): backbone RMS / max (each stored
point to the dense true backbone), coverage (stored arclength / true), tip error (last
stored point to the true tip), RMS over the last 10 mm of the true backbone (true samples
there to the nearest stored point: what a cut backbone misses counts).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from jaxcr.cli.stereo import _read_rgb, load_stereo_dataset
from jaxcr.stereo.pipeline import StereoFailure, reconstruct_pair
from jaxcr.synth.stereo_ctr import generate_stereo_set

KINDS = ("curled", "towards_cam1", "towards_cam2")


def metrics(p: np.ndarray, s_end: float, truth: dict) -> dict:
    tp, ts = np.asarray(truth["p"]), np.asarray(truth["s"])
    d, _ = cKDTree(tp).query(p)
    near_tip = tp[ts >= ts[-1] - 0.01]
    d_tip, _ = cKDTree(p).query(near_tip)
    return {
        "rms_mm": 1e3 * float(np.sqrt(np.mean(d**2))),
        "max_mm": 1e3 * float(d.max()),
        "coverage": float(s_end / ts[-1]),
        "tip_mm": 1e3 * float(np.linalg.norm(p[-1] - tp[-1])),
        "last10_rms_mm": 1e3 * float(np.sqrt(np.mean(d_tip**2))),
    }


def run_seed(folder: Path) -> list[dict]:
    ds = load_stereo_dataset(folder)
    out = []
    for fr in ds["frames"]:
        ims = [_read_rgb(ds["root"] / fr["images"][n]) for n in ds["names"]]
        truth = dict(np.load(ds["root"] / fr["truth"], allow_pickle=False))
        rec = {"set": folder.name, "id": fr["id"], "kind": fr["tags"][0]}
        try:
            r = reconstruct_pair(ims[0], ims[1], ds["cam1"], ds["cam2"], ds["config"], ds["plates"])
        except StereoFailure as err:
            rec.update(ok=False, reason=err.reason)
            out.append(rec)
            continue
        sv = r["single_view"]
        rec.update(
            ok=True,
            tail_mm=1e3 * float(r["s"][-1] - r["s_stereo_end"]),
            stereo=metrics(r["p"][~sv], r["s_stereo_end"], truth),
            tail=metrics(r["p"], float(r["s"][-1]), truth),
        )
        out.append(rec)
        print(json.dumps(rec), flush=True)
    return out


def _stats(recs, key, metric):
    v = np.array([r[key][metric] for r in recs])
    return f"{np.mean(v):.3f} / {np.median(v):.3f} / {np.max(v):.3f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="304-313")
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--work", default="/tmp/stereo_tail")
    ap.add_argument("--out", default="experiments/results/stereo/stereo_tail_fresh_seeds.md")
    args = ap.parse_args()
    a, b = (int(x) for x in args.seeds.split("-"))
    seeds = list(range(a, b + 1))
    recs = []
    for seed in seeds:
        folder = Path(args.work) / f"seed{seed}"
        if not (folder / "stereo.json").exists():
            generate_stereo_set(folder, args.frames, seed=seed, kinds=KINDS)
        recs += run_seed(folder)
    ok = [r for r in recs if r["ok"]]
    per_seed = ", ".join(f"{sd}: {sum(r['set'] == f'seed{sd}' for r in recs)}" for sd in seeds)
    with_tail = [r for r in ok if r["tail_mm"] > 0]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    cmd = "python experiments/stereo/stereo_tail_fresh_seeds.py " + " ".join(sys.argv[1:])
    md = [
        "# Single-view tail in the stored stereo backbone: fresh seeds",
        "",
        f"Command: `{cmd}` (commit {commit}, {platform.machine()}, Python "
        f"{platform.python_version()}).",
        "",
        f"Seeds {seeds[0]}-{seeds[-1]} ({len(seeds)} seeds, never looked at while developing; "
        f"development: seeds 1 and 301-303), frames per seed: {per_seed} (kinds cycle {', '.join(KINDS)}; "
        "a set generated earlier with more frames is used whole), 640x480. "
        f"{len(ok)}/{len(recs)} frames reconstructed; {len(with_tail)} have a single-view "
        "tail. Values mean / median / max over frames (mm, coverage a fraction).",
        "",
        "| frames | backbone | RMS mm | max mm | coverage | tip error mm | last-10-mm RMS mm |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, group in (("all", ok), ("with a tail", with_tail)):
        if not group:
            continue
        for key, label in (("stereo", "stereo only (before)"), ("tail", "with tail (now)")):
            md.append(
                f"| {name} ({len(group)}) | {label} | "
                + " | ".join(
                    _stats(group, key, m)
                    for m in ("rms_mm", "max_mm", "coverage", "tip_mm", "last10_rms_mm")
                )
                + " |"
            )
    md += [
        "",
        "Previous note (issue 17 item 11): a curled frame at a fresh seed reached 0.67 mm RMS, "
        "2 mm near the tip, with the backbone cut at 75 of 91 mm.",
        "",
        "Per frame (tail length mm; tip error stereo-only -> with tail):",
        "",
    ]
    for r in recs:
        if r["ok"]:
            md.append(
                f"- {r['set']}/{r['id']} {r['kind']}: tail {r['tail_mm']:.1f} mm, tip "
                f"{r['stereo']['tip_mm']:.2f} -> {r['tail']['tip_mm']:.2f} mm, coverage "
                f"{r['stereo']['coverage']:.3f} -> {r['tail']['coverage']:.3f}, RMS "
                f"{r['stereo']['rms_mm']:.3f} -> {r['tail']['rms_mm']:.3f} mm"
            )
        else:
            md.append(f"- {r['set']}/{r['id']} {r['kind']}: failed ({r['reason']})")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(md) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"seeds": seeds, "records": recs}, indent=1))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
