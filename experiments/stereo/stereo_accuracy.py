"""Accuracy of the stereo shape-sensing pipeline on synthetic stereo sets (issue 4).

Usage::

    python experiments/stereo/stereo_accuracy.py [--green DIR] [--blue DIR] [--out MD]

Generates the sets if the folders do not exist (``jaxcr.synth.stereo_ctr``: green set seed
1, 20 frames; blue set seed 2, 8 frames; 640x480), runs ``reconstruct_pair`` on every
frame with the default configuration (chroma key, number of segments from the diameter
profile), and compares with the ground truth (:mod:`jaxcr.stereo.evaluate`). Also runs the
report's 3-D-interpolation diameter and the report's distance-from-base ordering for
comparison. Writes Markdown (and a JSON of all per-frame numbers) beside the done-when
thresholds and the report's numbers.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxcr.cli.stereo import _read_rgb, load_stereo_dataset
from jaxcr.stereo.evaluate import evaluate_frame
from jaxcr.stereo.ordering import order_by_base_distance
from jaxcr.stereo.pipeline import StereoFailure, reconstruct_pair
from jaxcr.synth.stereo_ctr import generate_stereo_set

THRESH = {"rms": 0.5, "diam": 5.0, "bound": 2.0, "angle": 2.0, "curv": 10.0}


def _ordering_breaks(rc: np.ndarray) -> bool:
    """True when consecutive ordered pixels are not 8-neighbours (a jump)."""
    return bool(np.any(np.abs(np.diff(rc, axis=0)).max(axis=1) > 1))


def run_set(folder: Path) -> list[dict]:
    ds = load_stereo_dataset(folder)
    recs = []
    for fr in ds["frames"]:
        ims = [_read_rgb(ds["root"] / fr["images"][n]) for n in ds["names"]]
        truth = dict(np.load(ds["root"] / fr["truth"], allow_pickle=False))
        rec = {"id": fr["id"], "tags": fr.get("tags", []), "set": folder.name}
        try:
            r = reconstruct_pair(ims[0], ims[1], ds["cam1"], ds["cam2"], ds["config"], ds["plates"])
        except StereoFailure as err:
            rec.update(ok=False, reason=err.reason)
            recs.append(rec)
            continue
        ev = evaluate_frame(r, truth)
        # Report's diameter method, per true segment (median over the true section's span).
        s_true = np.interp(
            np.arange(len(r["s"])), np.arange(len(r["s"])), r["s"]
        )  # reconstructed arclength, base included
        sec = np.searchsorted(truth["boundary_s"], s_true)
        rep = [float(np.median(r["diameter_report"][sec == k])) if np.any(sec == k) else np.nan
               for k in range(len(truth["seg_diameter"]))]  # fmt: skip
        ours = [float(np.median(r["diameter"][sec == k])) if np.any(sec == k) else np.nan
                for k in range(len(truth["seg_diameter"]))]  # fmt: skip
        ev["report_diameter_err_pct"] = [
            100 * (a / b - 1) for a, b in zip(rep, truth["seg_diameter"], strict=True)
        ]
        ev["ours_diameter_by_true_segment_err_pct"] = [
            100 * (a / b - 1) for a, b in zip(ours, truth["seg_diameter"], strict=True)
        ]
        # Ordering: ours never jumps; the distance-from-base sort on the same skeletons.
        ev["ordering_breaks"] = any(_ordering_breaks(rc) for rc in r["skeleton_rc"])
        base_breaks = []
        for rc, seed in zip(r["skeleton_rc"], r["seed_rc"], strict=True):
            sk = np.zeros((ims[0].shape[0], ims[0].shape[1]), bool)
            sk[rc[:, 0], rc[:, 1]] = True
            base_breaks.append(_ordering_breaks(order_by_base_distance(sk, seed)))
        ev["base_distance_ordering_breaks"] = any(base_breaks)
        ev["marker_rms_px"] = r["marker_rms_px"]
        ev["seg_epipolar_conditioning"] = [sg["epipolar_conditioning"] for sg in r["segments"]]
        ev["seg_view_weight_min"] = [sg["view_weight_min"] for sg in r["segments"]]
        ev["chain_rms_px"] = r["segments"][0].get("chain_rms_px")
        if ev["segments_ok"] and "phi_xy_deg_independent" in r["segments"][0]:
            # The separate per-segment plane and arc fits to the triangulated points (the
            # method before the joint chain fit), for comparison.
            keys = ("phi_xy_deg", "phi_zx_deg", "phi_yz_deg")
            ev["plane_angle_err_deg_independent"] = [
                [abs(sg[k + "_independent"] - a) for k, a in zip(keys, at, strict=True)]
                for sg, at in zip(r["segments"], truth["seg_plane_angles"], strict=True)
            ]
            ev["curvature_err_pct_independent"] = [
                100.0 * (sg["curvature_1pm_independent"] / kt - 1.0)
                for sg, kt in zip(r["segments"], truth["seg_curvature"], strict=True)
            ]
        rec.update(ok=True, **ev)
        recs.append(rec)
        print(json.dumps(rec, default=float), flush=True)
    return recs


def _flat(recs, key):
    vals = []
    for r in recs:
        if r.get("ok") and r.get("segments_ok") and key in r:
            v = r[key]
            vals.extend(np.ravel(v).tolist())
    return np.abs(np.array(vals, float))


def summarise(recs: list[dict]) -> list[str]:
    ok = [r for r in recs if r.get("ok")]
    lines = []
    rms = np.array([r["backbone_rms_mm"] for r in ok])
    segok = [r for r in ok if r["segments_ok"]]
    rows = [
        ("frames reconstructed", f"{len(ok)}/{len(recs)}", "all", len(ok) == len(recs)),
        ("backbone RMS (mm), mean / max over frames", f"{rms.mean():.3f} / {rms.max():.3f}", f"<= {THRESH['rms']}", rms.max() <= THRESH["rms"]),
        ("segment count correct", f"{len(segok)}/{len(ok)}", "all", len(segok) == len(ok)),
    ]  # fmt: skip
    for name, key, th, _unit in [
        ("diameter error per segment (%)", "diameter_err_pct", THRESH["diam"], "%"),
        ("boundary error (mm, 3-D)", "boundary_err_mm", THRESH["bound"], "mm"),
        (
            "plane-angle error (deg, 3 angles x segment)",
            "plane_angle_err_deg",
            THRESH["angle"],
            "deg",
        ),
        ("curvature error per segment (%)", "curvature_err_pct", THRESH["curv"], "%"),
    ]:
        v = _flat(segok, key)
        if len(v):
            rows.append(
                (
                    name + ", median / 95th pct / max",
                    f"{np.median(v):.3f} / {np.percentile(v, 95):.3f} / {v.max():.3f}",
                    f"<= {th}",
                    v.max() <= th,
                )
            )
    for name, key in [
        ("plane-angle error, separate per-segment fits (deg)", "plane_angle_err_deg_independent"),
        ("curvature error, separate per-segment fits (%)", "curvature_err_pct_independent"),
    ]:
        v = _flat(segok, key)
        if len(v):
            rows.append(
                (
                    name + ", median / 95th pct / max",
                    f"{np.median(v):.3f} / {np.percentile(v, 95):.3f} / {v.max():.3f}",
                    "(before the joint chain fit)",
                    None,
                )
            )
    rep = _flat(ok, "report_diameter_err_pct")
    ours = _flat(ok, "ours_diameter_by_true_segment_err_pct")
    rows.append(
        (
            "report's 3-D interpolation diameter error (%), median / max",
            f"{np.nanmedian(rep):.2f} / {np.nanmax(rep):.2f}",
            "(report: up to 6.76 % at 2.4 mm)",
            None,
        )
    )
    rows.append(
        (
            "our diameter, same true-segment medians (%), median / max",
            f"{np.nanmedian(ours):.2f} / {np.nanmax(ours):.2f}",
            "<= 5",
            np.nanmax(ours) <= 5,
        )
    )
    ob = sum(r["ordering_breaks"] for r in ok)
    bb = sum(r["base_distance_ordering_breaks"] for r in ok)
    rows.append(
        (
            "ordering breaks (ours) / (report's distance-from-base sort)",
            f"{ob} / {bb} of {len(ok)}",
            "0 for ours",
            ob == 0,
        )
    )
    mr = np.array([r["marker_rms_px"] for r in ok])
    rows.append(
        (
            "ArUco marker reprojection RMS (px), median / max",
            f"{np.median(mr):.3f} / {mr.max():.3f}",
            "",
            None,
        )
    )
    lines.append("| quantity | measured | target | met |")
    lines.append("|---|---|---|---|")
    for name, val, tgt, met in rows:
        lines.append(
            f"| {name} | {val} | {tgt} | {'' if met is None else ('yes' if met else 'NO')} |"
        )
    return lines


CONF = (0.2, 0.2)  # epipolar conditioning, smaller view weight (see jaxcr.stereo.pipeline)


def confident_rows(recs: list[dict]) -> list[str]:
    """Per-segment errors restricted to segments the pipeline itself flags as well
    conditioned (no truth used for the selection)."""
    pa, cu, n_all, n_conf = [], [], 0, 0
    for r in recs:
        if not (r.get("ok") and r["segments_ok"]):
            continue
        for k, (e, w) in enumerate(
            zip(r["seg_epipolar_conditioning"], r["seg_view_weight_min"], strict=True)
        ):
            n_all += 1
            if e >= CONF[0] and w >= CONF[1]:
                n_conf += 1
                pa.extend(r["plane_angle_err_deg"][k])
                cu.append(abs(r["curvature_err_pct"][k]))
    pa, cu = np.array(pa), np.array(cu)
    return [
        f"Segments flagged well conditioned by the pipeline (epipolar_conditioning >= {CONF[0]}"
        f" and view_weight_min >= {CONF[1]}, computed without the truth): {n_conf} of {n_all}.",
        "",
        "| quantity (well-conditioned segments) | median | 95th pct | max | target |",
        "|---|---|---|---|---|",
        f"| plane-angle error (deg) | {np.median(pa):.3f} | {np.percentile(pa, 95):.3f} | {pa.max():.3f} | <= 2 |",
        f"| curvature error (%) | {np.median(cu):.3f} | {np.percentile(cu, 95):.3f} | {cu.max():.3f} | <= 10 |",
    ]


def outliers(recs: list[dict]) -> list[str]:
    lines = [
        "| set | frame | kind | segment | plane err (deg) | curvature err (%) | epipolar cond. | min view weight | coverage | tip err (mm) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in recs:
        if not (r.get("ok") and r["segments_ok"]):
            continue
        for k in range(r["n_segments"]):
            pe = max(r["plane_angle_err_deg"][k])
            ce = abs(r["curvature_err_pct"][k])
            if pe > THRESH["angle"] or ce > THRESH["curv"]:
                lines.append(
                    f"| {r['set']} | {r['id']} | {r['tags'][0]} | {k + 1} | {pe:.2f} | {ce:.1f} | "
                    f"{r['seg_epipolar_conditioning'][k]:.2f} | {r['seg_view_weight_min'][k]:.2f} | "
                    f"{r['coverage']:.3f} | {r['tip_error_mm']:.1f} |"
                )
    return lines


def per_tag(recs):
    lines = [
        "| tag | frames | backbone RMS mean (mm) | max diameter err (%) | max boundary err (mm) | max plane err (deg) | max curvature err (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    tags = sorted({t for r in recs for t in r["tags"]})
    for t in tags:
        rs = [r for r in recs if t in r["tags"] and r.get("ok")]
        so = [r for r in rs if r["segments_ok"]]

        def mx(key, so=so):
            v = _flat(so, key)
            return f"{v.max():.2f}" if len(v) else "-"

        rms = np.mean([r["backbone_rms_mm"] for r in rs]) if rs else float("nan")
        lines.append(
            f"| {t} | {len(rs)} | {rms:.3f} | {mx('diameter_err_pct')} | {mx('boundary_err_mm')} | {mx('plane_angle_err_deg')} | {mx('curvature_err_pct')} |"
        )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--green", default="/tmp/stereo_green")
    ap.add_argument("--blue", default="/tmp/stereo_blue")
    ap.add_argument("--out", default="experiments/results/stereo/stereo_accuracy.md")
    args = ap.parse_args()
    t0 = time.time()
    sets = [(Path(args.green), 1, 20, "green"), (Path(args.blue), 2, 8, "blue")]
    recs = []
    set_meta = []
    for folder, seed, n, bg in sets:
        if str(folder) == "none":
            continue
        if not (folder / "stereo.json").exists():
            generate_stereo_set(folder, n_frames=n, seed=seed, background=bg)
        recs += run_set(folder)
        js = json.loads((folder / "stereo.json").read_text())
        set_meta.append(
            (
                folder,
                {"n": len(js["frames"]), "seed": js["meta"]["seed"], "bg": js["background"]["key"]},
            )
        )
    commit = subprocess.run(
        ["git", "log", "-1", "--format=%h", "--", "jaxcr/stereo", "jaxcr/synth/stereo_ctr.py"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    md = [
        "# Stereo shape sensing: accuracy on synthetic stereo sets (issue 4)",
        "",
        f"Command: `python experiments/stereo/stereo_accuracy.py --green {args.green} --blue {args.blue}`  ",
        f"commit {commit}, Python {sys.version.split()[0]}, {platform.machine()}, {time.time() - t0:.0f} s wall.",
        "",
        "Sets: "
        + " and ".join(
            f"`generate_stereo_set({f.name}, n_frames={m['n']}, seed={m['seed']},"
            f" background='{m['bg']}')`"
            for f, m in set_meta
        )
        + " (default: green seed 1, 20 frames; blue seed 2, 8 frames), 640x480, two"
        " cameras about 90 deg"
        " apart, 25 deg down, ~235 mm away (0.29 mm/px at the robot), 2- and 3-tube robots"
        " (OD 2.4/1.8/1.2 mm), frame kinds cycle general / curled / towards_cam1 /"
        " towards_cam2. Default pipeline settings (chroma key 0.5-0.8, segment count chosen"
        " from the diameter profile, not given; curvatures and bending planes from the joint"
        " chain fit to both views, `jaxcr.stereo.chain_fit`; shadow cut at 20 deg).",
        "",
        "## Done-when thresholds",
        "",
        *summarise(recs),
        "",
        "## By frame kind",
        "",
        *per_tag(recs),
        "",
        "## Segments the pipeline flags as well conditioned",
        "",
        *confident_rows(recs),
        "",
        "## Segments outside the plane-angle or curvature threshold",
        "",
        *outliers(recs),
        "",
        "Coverage (reconstructed / true arclength) min "
        f"{min(r['coverage'] for r in recs if r.get('ok')):.3f}, tip error median "
        f"{np.median([r['tip_error_mm'] for r in recs if r.get('ok')]):.2f} mm, max "
        f"{max(r['tip_error_mm'] for r in recs if r.get('ok')):.2f} mm (the backbone RMS measures"
        " reconstructed points against the true curve; a truncated tip shows here).",
        "",
        "Source report's numbers for comparison: diameter error up to 6.76 % for a 2.4 mm tube;"
        " curvature and arc length were not identified there; its distance-from-base ordering"
        " failed on curled-back tips (its Fig. 7).",
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(md) + "\n")
    out.with_suffix(".json").write_text(json.dumps(recs, indent=1, default=float) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
