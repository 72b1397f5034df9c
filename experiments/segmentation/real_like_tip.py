"""Tip pixel error of the plate foreground (:mod:`jaxcr.segmentation.foreground`) on the ``real_like``
preset (issue 16 item 2), with the old segmentations as baselines in the same run.

Per seed one frame of :func:`jaxcr.synth.real_like.render_real_like_frame` (two views:
dark green-tinted outer tube and grey inner tubes over creased, shadowed green cloth, a
white circle-grid board with black tape crossed by the tube in view 1, drifted plates,
webcam noise, lens distortion, entry pixel with model error). Methods per view:

* ``trace`` -- :func:`jaxcr.segmentation.foreground.plate_foreground` (aligned plate, cues, hysteresis,
  tracing with gap bridging; a view where the tube is k >= 2 times ``tube_width_px`` wide is
  traced reduced k times, the tip refined at full resolution) from the entry pixel and the
  projected base axis (both with model error); tip = its ``tip``;
* ``trace_stereo`` -- the same two traces, each tip moved to its silhouette's end minus the
  end face's foreshortening computed from the tube's 3-D direction, which the two calibrated
  views give (:func:`jaxcr.stereo.tip_geometry.end_face_lengths`; the view's own estimate
  where the two end directions leave the axis undetermined;
  :func:`jaxcr.stereo.pipeline.traced_stereo_tips`, what ``jaxcr stereo --segmentation
  trace`` records: where the two tips are over 5 px from each other's epipolar lines, the
  branch a view took at a crossing is chosen again by both views,
  :mod:`jaxcr.stereo.branch_choice` (candidates: each view's trace and its re-traces from
  its junctions; where no pair of those explains itself, also its tube searched again along
  the other view's trace, :mod:`jaxcr.stereo.guided_retrace`), ranked by how much of the two whole backbones fails
  to triangulate consistently, :mod:`jaxcr.stereo.backbone_consistency`; a view whose
  tube hooks back over its own silhouette gets its tip where the way back ends
  (``fold_back_tip``), else a view's trace whose end the other view does not explain is
  cut back (``open_end_tails``; where the path to cut passes no junction, gap or hop,
  the other view's end is re-decided on its mask by the kept tip's epipolar line instead,
  ``rebranched``), else the tips are re-searched
  along the tubes, :mod:`jaxcr.stereo.tip_consistency`). The epipolar distance of each
  method's two tips is recorded per frame (a frame over 5 px is flagged);
* ``trace_r1`` -- the first round's foreground (commit cf4b1bb, from git);
* ``plate`` -- the stereo pipeline's old plate mode: ``plate_alpha > 0.5`` (unaligned plate,
  lo/hi 0.06/0.15), 3x3 closing, the component at the entry;
* ``gmm`` -- ``--background gmm``: :func:`jaxcr.segmentation.background.fit_background_model` on the
  plate (one component, min_std 0.03) and :func:`~jaxcr.segmentation.background.background_model_mask`;
  the component at the entry;
* ``colour`` -- ``--background colour``: :func:`jaxcr.segmentation.background.colour_mask` (defaults);
  the component at the entry.

For the baselines the tip is the component pixel farthest from the entry along the
component (geodesic, ``skimage.graph.MCP_Geometric``), i.e. the end of the skeleton ordered
from the base as the stereo pipeline does. Success: tip within 5 px of the truth.

    python experiments/segmentation/real_like_tip.py --seeds 1000-1023 --size 640x360 \
        --out experiments/results/segmentation/real_like_tip

``--methods`` picks the methods (default ``trace,trace_stereo``; the baselines cost a minute
a frame at 1280x720); ``--merge A.json B.json`` writes one report from runs of seed subsets
run in parallel processes.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import platform
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from skimage.graph import MCP_Geometric

from jaxcr.benchmarks import parse_seeds
from jaxcr.segmentation import background as bgm
from jaxcr.segmentation.foreground import PlateForegroundConfig, plate_foreground
from jaxcr.stereo.base_locate import flood_component
from jaxcr.stereo.chroma import plate_alpha
from jaxcr.stereo.epipolar_tolerance import REAL_LIKE_CALIBRATION
from jaxcr.stereo.pipeline import traced_stereo_tips
from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import epipolar_distances, fundamental_from_poses
from jaxcr.synth.real_like import render_real_like_frame

METHODS = ("trace", "trace_stereo", "trace_r1", "plate", "gmm", "colour")
DEFAULT_METHODS = ("trace", "trace_stereo")
EPIPOLAR_FLAG_PX = 5.0  # a frame whose two tips are farther from each other's epilines is flagged
# The first round's foreground (results/segmentation/real_like_tip_round1.md), loaded from
# git history so that it runs in the same process on the same frames.
ROUND1_COMMIT = "cf4b1bb"


def _round1_module(commit: str):
    """jaxcr/segmentation/foreground.py as of ``commit``, imported from ``git show``."""
    import types

    src = subprocess.run(
        ["git", "show", f"{commit}:jaxcr/segmentation/foreground.py"],
        capture_output=True, text=True, check=True, cwd=Path(__file__).parent,
    ).stdout  # fmt: skip
    mod = types.ModuleType("foreground_round1")
    mod.__dict__["__name__"] = "foreground_round1"
    sys.modules["foreground_round1"] = mod  # dataclasses look their module up
    exec(compile(src, f"{commit}:foreground.py", "exec"), mod.__dict__)
    return mod


def geodesic_tip(mask: np.ndarray, entry_uv: np.ndarray) -> np.ndarray:
    """(u, v) of the pixel of the entry's component farthest from the entry along it."""
    comp = flood_component(mask, (entry_uv[1], entry_uv[0]))
    if not comp.any():
        return np.array([np.nan, np.nan])
    rr, cc = np.nonzero(comp)
    k = int(np.argmin((rr - entry_uv[1]) ** 2 + (cc - entry_uv[0]) ** 2))
    cost = np.where(comp, 1.0, np.inf)
    mcp = MCP_Geometric(cost)
    dist, _ = mcp.find_costs([(rr[k], cc[k])])
    dist = np.where(np.isfinite(dist), dist, -1)
    r, c = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return np.array([c, r], float)


def _close(m: np.ndarray) -> np.ndarray:
    return cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0


def run_view(view, cfg: PlateForegroundConfig, r1, methods) -> dict:
    img = view.image.astype(np.float32) / 255.0
    plate = view.plate.astype(np.float32) / 255.0
    out = {}
    t = time.perf_counter()
    tr = plate_foreground(view.image, view.plate, view.entry_px, view.entry_dir_px, cfg=cfg)
    out["trace"] = {"tip": tr.tip.tolist(), "time_s": time.perf_counter() - t,
                    "gaps": len(tr.gaps), "shift": tr.shift.tolist(), "cap_px": tr.cap_px,
                    "scale": tr.scale, "measured_width_px": tr.measured_width_px,
                    "end_dir": tr.end_dir.tolist(),
                    "end_half_width_px": tr.end_half_width_px}  # fmt: skip
    out["_trace_obj"] = tr  # for the two-view step (not written)
    if "trace_r1" in methods:
        t = time.perf_counter()
        tr1 = r1.plate_foreground(view.image, view.plate, view.entry_px, view.entry_dir_px,
                                  cfg=r1.PlateForegroundConfig())  # fmt: skip
        out["trace_r1"] = {"tip": tr1.tip.tolist(), "time_s": time.perf_counter() - t,
                           "gaps": len(tr1.gaps)}  # fmt: skip
    if "plate" in methods:
        a = np.asarray(plate_alpha(img, plate))
        out["plate"] = {"tip": geodesic_tip(_close(a > 0.5), view.entry_px).tolist()}
    if "gmm" in methods:
        model = bgm.fit_background_model(plate[None], n_components=1)
        bg, _ = bgm.background_model_mask(model, img)
        out["gmm"] = {"tip": geodesic_tip(_close(~np.asarray(bg)), view.entry_px).tolist()}
    if "colour" in methods:
        bg, _ = bgm.colour_mask(img)
        out["colour"] = {"tip": geodesic_tip(_close(~np.asarray(bg)), view.entry_px).tolist()}
    out["truth_tip"] = view.tip_px.tolist()
    out["drift_px"] = view.drift_px.tolist()
    out["entry_error_px"] = float(np.linalg.norm(view.entry_px - view.entry_true_px))
    return out


def stereo_step(fr, views: list[dict]) -> dict:
    """``trace_stereo``: each view's tip from ``trace`` with the end face's foreshortening
    taken from the tube's 3-D direction, both cameras known
    (:func:`jaxcr.stereo.pipeline.traced_stereo_tips`, which ``jaxcr stereo --segmentation
    trace`` records as ``tip_px``) instead of the end's shape in one view; and the epipolar
    distance (px, undistorted) of both methods' tip pairs."""
    # The rig's calibration (with the preset's calibration error), not the rendering cameras;
    # the preset states that error (REAL_LIKE_CALIBRATION, docs/decisions.md S37).
    calibrated = all(getattr(v, "calib_camera", None) is not None for v in fr.views)
    cams = [v.calib_camera if calibrated else v.camera for v in fr.views]
    objs = [v.pop("_trace_obj") for v in views]
    tips, source, recheck, chosen = traced_stereo_tips(
        cams, objs, calibration=REAL_LIKE_CALIBRATION if calibrated else None
    )
    for k, v in enumerate(views):
        v["trace_stereo"] = {
            "tip": [float(x) for x in tips[k]], "fallback": source != "trace_stereo",
            "recheck": None if recheck is None else recheck.action,
            "moved": recheck is not None and recheck.view == k,
            "branch": getattr(chosen[k], "curl_of", chosen[k]) is not objs[k],
        }  # fmt: skip
    F = fundamental_from_poses(cams[0].K, cams[0].T_cam_robot, cams[1].K, cams[1].T_cam_robot)
    epi = {}
    for m in ("trace", "trace_stereo"):
        t1, t2 = (np.asarray(v[m]["tip"]) for v in views)
        if m == "trace_stereo" and recheck is not None:
            epi["trace_stereo_before_recheck"] = recheck.epipolar_before_px
        if np.all(np.isfinite(t1)) and np.all(np.isfinite(t2)):
            epi[m] = max(epipolar_distances(F, undistort_pixels(cams[0], t1)[0],
                                            undistort_pixels(cams[1], t2)[0]))  # fmt: skip
        else:
            epi[m] = float("inf")
    return epi


def _frame(seed: int, size: tuple, cache: str | None):
    """The rendered frame of ``seed`` (from the ``cache`` folder when it holds it)."""
    if cache is None:
        return render_real_like_frame(seed, size)
    path = Path(cache) / f"real_like_{size[0]}x{size[1]}_{seed}.pkl"
    if path.exists():
        with open(path, "rb") as f:
            return pickle.load(f)
    fr = render_real_like_frame(seed, size)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(fr, f)
    os.replace(tmp, path)
    return fr


def _atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _errors(view: dict, methods) -> None:
    for m in methods:
        tip = np.asarray(view[m]["tip"])
        view[m]["err_px"] = (
            float(np.linalg.norm(tip - np.asarray(view["truth_tip"])))
            if np.all(np.isfinite(tip)) else float("inf")
        )  # fmt: skip


def summarise(rows: list[dict], methods) -> dict:
    s = {}
    for m in methods:
        errs = np.array([v[m]["err_px"] for r in rows for v in r["views"]])
        frames_ok = [all(v[m]["err_px"] <= 5.0 for v in r["views"]) for r in rows]
        fin = errs[np.isfinite(errs)]
        s[m] = {
            "views": len(errs),
            "views_within_5px": float(np.mean(errs <= 5.0)) if len(errs) else float("nan"),
            "frames_within_5px_both_views": float(np.mean(frames_ok)) if rows else float("nan"),
            "median_px": float(np.median(errs)) if len(errs) else float("nan"),
            "p90_px": float(np.percentile(fin, 90)) if len(fin) else float("nan"),
            "max_px": float(np.max(errs)) if len(errs) else float("nan"),
        }
        if m in ("trace", "trace_stereo") and rows and "epipolar_px" in rows[0]:
            flagged = [r["epipolar_px"][m] > EPIPOLAR_FLAG_PX for r in rows]
            s[m]["frames_flagged_epipolar"] = int(np.sum(flagged))
            s[m]["flagged_frames_failing"] = int(
                sum(f and not ok for f, ok in zip(flagged, frames_ok, strict=True))
            )
            s[m]["unflagged_frames_failing"] = int(
                sum((not f) and not ok for f, ok in zip(flagged, frames_ok, strict=True))
            )
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0-9", help="seeds, e.g. 0-9 or 1000-1023,2000")
    ap.add_argument("--size", default="1280x720", help="WxH (default 1280x720)")
    ap.add_argument("--out", default="experiments/results/segmentation/real_like_tip",
                    help="output path without extension (.md and .json are written)")  # fmt: skip
    ap.add_argument("--role", default="fresh", help="'dev' or 'fresh' (recorded)")
    ap.add_argument(
        "--cache",
        default=None,
        help="folder for rendered frames (pickles, scratch): a frame found there is "
        "loaded instead of rendered (rendering is independent of the methods)",
    )
    ap.add_argument(
        "--render-only",
        action="store_true",
        help="render the frames into --cache and stop (no method is run)",
    )
    ap.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated, of {', '.join(METHODS)} (default "
        f"{','.join(DEFAULT_METHODS)}; trace_stereo needs trace)",
    )
    ap.add_argument(
        "--merge",
        nargs="+",
        default=None,
        metavar="JSON",
        help="write the report from these runs' JSON files (same size and config; e.g. the "
        "halves of a seed range run in two processes) instead of running",
    )
    args = ap.parse_args(argv)
    methods = tuple(m for m in METHODS if m in args.methods.split(","))
    if "trace_stereo" in methods and "trace" not in methods:
        ap.error("trace_stereo needs trace")
    size = tuple(int(x) for x in args.size.lower().split("x"))
    cfg = PlateForegroundConfig()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    jpath = out.with_suffix(".json")
    rows = []
    if jpath.exists():  # resumable: keep the seeds already done with the same settings
        prev = json.loads(jpath.read_text())
        if prev.get("size") == list(size) and prev.get("config") == cfg.__dict__:
            rows = prev["rows"]
    merged_from = []
    if args.merge:
        rows = []
        for f in args.merge:
            prev = json.loads(Path(f).read_text())
            if prev.get("size") != list(size) or prev.get("config") != cfg.__dict__:
                raise SystemExit(f"{f}: another size or configuration")
            rows += prev["rows"]
            merged_from.append(f"`{prev['command']}` (commit {prev['commit']})")
    done = {r["seed"] for r in rows}
    r1 = None if args.render_only or "trace_r1" not in methods else _round1_module(ROUND1_COMMIT)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=Path(__file__).parent).stdout.strip()  # fmt: skip
    cmd = "python experiments/segmentation/real_like_tip.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    load = os.getloadavg()
    for seed in [] if args.merge else parse_seeds(args.seeds):
        if seed in done:
            continue
        t0 = time.perf_counter()
        fr = _frame(seed, size, args.cache)
        t_render = time.perf_counter() - t0
        if args.render_only:
            print(f"seed {seed}: rendered", flush=True)
            continue
        t1 = time.perf_counter()
        views = [run_view(v, cfg, r1, methods) for v in fr.views]
        row = {"seed": seed, "views": views, "render_s": t_render,
               "methods_s": time.perf_counter() - t1, "load": os.getloadavg()[0]}  # fmt: skip
        if "trace_stereo" in methods:
            row["epipolar_px"] = stereo_step(fr, views)
        for v in views:
            v.pop("_trace_obj", None)
        for v in views:
            _errors(v, methods)
        rows.append(row)
        errs = " ".join(f"{m}={[round(v[m]['err_px'], 1) for v in views]}" for m in methods)
        print(f"seed {seed}: {errs}", flush=True)
        meta = {
            "format": "jaxcr.experiment.real_like_tip/2", "command": cmd, "commit": commit,
            "role": args.role, "size": list(size), "config": cfg.__dict__,
            "methods": list(methods), "load_at_start": list(load),
            "python": platform.python_version(), "machine": platform.machine(),
            "summary": summarise(rows, methods), "rows": rows,
        }  # fmt: skip
        _atomic(jpath, json.dumps(meta, indent=1) + "\n")
    if args.render_only:
        return 0
    summ = summarise(rows, methods)
    seeds = sorted(r["seed"] for r in rows)
    if args.merge:
        meta = {
            "format": "jaxcr.experiment.real_like_tip/2", "command": cmd, "commit": commit,
            "merged_from": merged_from, "role": args.role, "size": list(size),
            "config": cfg.__dict__, "methods": list(methods),
            "python": platform.python_version(), "machine": platform.machine(),
            "summary": summ, "rows": sorted(rows, key=lambda r: r["seed"]),
        }  # fmt: skip
        _atomic(jpath, json.dumps(meta, indent=1) + "\n")
    loads = [r["load"] for r in rows if "load" in r]
    per = [r["methods_s"] / len(r["views"]) for r in rows if "methods_s" in r]
    md = [
        "# Tip pixel error on the real_like preset (issue 16 item 2)",
        "",
        f"Command: `{cmd}` (commit {commit})"
        + ("; rows from " + "; ".join(merged_from) if merged_from else "")
        + ".",
        "",
        f"Seeds ({args.role}): {', '.join(map(str, seeds))} ({len(seeds)} frames x 2 views), "
        f"image size {size[0]}x{size[1]}.",
        "",
        "Target: tip within 5 px per view in >= 95 % of frames.",
        "",
        "Methods: `trace` this commit's plate foreground (defaults, one view at a time); "
        "`trace_stereo` the same, with the end face's foreshortening from the tube's 3-D "
        "direction seen by both calibrated cameras (jaxcr.stereo.tip_geometry); where the "
        "two tips are over 5 px from each other's epipolar lines, the branch a view took at "
        "a crossing chosen again by both views (jaxcr.stereo.branch_choice, ranked by the "
        "length of the two whole backbones that does not triangulate consistently, "
        "jaxcr.stereo.backbone_consistency; each view's candidates its trace and its "
        "re-traces from its junctions, and, since round 14, where no pair of those explains "
        "itself, also its tube searched again along the other view's trace, "
        "jaxcr.stereo.guided_retrace), a view whose tube hooks back over its own "
        "silhouette given the tip where the way back ends (folded, fold_back_tip), else a "
        "trace's end that the other view does not explain cut back (trimmed, placed by an "
        "open-ended match; before a hop of the path across background behind the cut, "
        "the tube's end is before the hop, foreground.end_before_hop; where the path to "
        "cut passes no junction, gap or hop, the other view's end re-decided instead: the "
        "end of the branch of its mask on the kept tip's epipolar line, rebranched), else "
        "the tips "
        "re-searched along the traced tubes (since round 15, fold, trim and re-search only "
        "where the tips are further apart than 3 standard deviations of right tips' "
        "epipolar distance under the preset's stated calibration error, at least 5 px, "
        "jaxcr.stereo.epipolar_tolerance), and, since round 19, last, a view's tip "
        "replaced by the end of a gently bent end fitted to its cue map where that is 10 px "
        "away and the pair then agrees (refitted, jaxcr.stereo.curl_choice, S47; the curled "
        "end of S46 off since S48) "
        "(jaxcr.stereo.tip_consistency; jaxcr.stereo.pipeline."
        "traced_stereo_tips, what `jaxcr stereo --segmentation trace` records), with the "
        "rig's calibration (`calib_camera`, with the preset's calibration error); `trace_r1` "
        f"the first round's (commit {ROUND1_COMMIT}); `plate`, `gmm`, `colour` the older "
        "segmentations (module docstring). Run here: " + ", ".join(methods) + ".",
        "",
        "| method | views | views within 5 px | frames with both views within 5 px | median px "
        "| p90 px | max px | frames flagged (epipolar > 5 px): failing / all; unflagged failing |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        r = summ[m]
        flag = (f"{r['flagged_frames_failing']} / {r['frames_flagged_epipolar']}; "
                f"{r['unflagged_frames_failing']}" if "frames_flagged_epipolar" in r else "")  # fmt: skip
        md.append(
            f"| {m} | {r['views']} | {100 * r['views_within_5px']:.0f} % | "
            f"{100 * r['frames_within_5px_both_views']:.0f} % | {r['median_px']:.1f} | "
            f"{r['p90_px']:.1f} | {r['max_px']:.1f} | {flag} |"
        )
    if per:
        md += ["", f"Time of the methods: median {np.median(per):.0f} s per view (wall, "
               f"single process) at a machine load of {np.median(loads):.1f} (1-min average, "
               "2 cores shared with other jobs; not a benchmark)."]  # fmt: skip
    md += [
        "",
        "Real-rig numbers from the issue for comparison (not this preset): old plate mode "
        "354 / 158 px off; `--background gmm` 175-410 px on 3 of 5 frames; a simple "
        "reference method 1-2 px.",
        "",
        "Per seed (px, view 1 / view 2):",
        "",
        "| seed | "
        + " | ".join(methods)
        + " | epipolar px (trace / stereo) | trace scale | plate drift px | trace gaps "
        "| re-search |",
        "|---|" + "---|" * (len(methods) + 5),
    ]
    for r in sorted(rows, key=lambda r: r["seed"]):
        v = r["views"]
        cells = [f"{v[0][m]['err_px']:.1f} / {v[1][m]['err_px']:.1f}" for m in methods]
        epi = r.get("epipolar_px", {})
        epi_s = " / ".join(f"{epi[m]:.1f}" for m in ("trace", "trace_stereo") if m in epi)
        scale = " / ".join(str(x["trace"].get("scale", 1)) for x in v)
        drift = " / ".join(f"{np.linalg.norm(x['drift_px']):.1f}" for x in v)
        gaps = " / ".join(str(x["trace"]["gaps"]) for x in v)
        ts = v[0].get("trace_stereo", {})
        moved = [str(i + 1) for i, x in enumerate(v) if x.get("trace_stereo", {}).get("moved")]
        rs = f"{ts.get('recheck')}" + (f" (view {moved[0]})" if moved else "")
        branch = [str(i + 1) for i, x in enumerate(v) if x.get("trace_stereo", {}).get("branch")]
        rs += f"; branch (view {', '.join(branch)})" if branch else ""
        md.append(f"| {r['seed']} | " + " | ".join(cells)
                  + f" | {epi_s} | {scale} | {drift} | {gaps} | {rs} |")  # fmt: skip
    _atomic(out.with_suffix(".md"), "\n".join(md) + "\n")
    print(json.dumps(summ, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
