"""Reproduce Watson et al. Table II on the four synthetic presets.

Generates ``orthogonal``, ``orthogonal_occluded``, ``endoscopic`` and ``endoscopic_occluded``
(``jaxcr synth`` presets, 20 frames at 640x480 by default, as in the paper) for one seed,
segments each with ``jaxcr segment`` defaults (colour-mask background subtraction, the
refinement core's default RefineConfig), evaluates them together (``jaxcr evaluate``) and
writes ``experiments/results/segmentation/table2_seed<k>.md`` with the measured table next to the
published one, plus the machine-readable ``table2_seed<k>.csv`` / ``_per_frame.csv``.

Everything runs in one process, so the refinement compiles once for all four presets (equal
image sizes and robot sampling).

    python experiments/segmentation/table2.py --seed 0 [--frames 20] [--size 640x480] [--work DIR]

With ``--cameras 2`` each preset's stereo rig is rendered and one delta-u is refined against
both views with the rig-level camera correction (``--camera-mode rig``: one shared correction
of the robot-to-rig transform, the cameras keep their calibrated relative pose, so disparity
measures depth); ``--camera-mode camera`` estimates an independent correction per camera
(written as ``table2_seed<k>_cams2_percamera.md``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import shutil
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PRESETS = ["orthogonal", "orthogonal_occluded", "endoscopic", "endoscopic_occluded"]
# Rig mode's residual per-camera regulariser (= the default g_cam, 0.3), chosen on seed 1 (10
# frames per preset, 2 cameras; seeds 0 and 3 held out): the generator draws an independent
# calibration error per camera, so the rig's relative pose is as wrong as its registration
# (~0.4 deg, ~1.4 mm). Mean tip-error ratio refined/nominal and adjusted IoU left/right,
# orthogonal | orth. occluded | endoscopic | endo. occluded: rigid rig (0) 0.98 0.84/0.84 |
# 1.14 0.55/0.34 | 0.89 0.63/0.77 | 0.69 0.64/0.56; g_cam_rel 3: 0.79 | 1.03 0.67/0.40 | 0.89
# | 0.67; 0.3: 0.72 0.91/0.94 | 0.77 0.85/0.81 | 0.88 0.70/0.83 | 0.69 0.73/0.71; per-camera
# mode: 0.77 0.91/0.94 | 0.82 0.88/0.84 | 0.87 0.73/0.83 | 0.61 0.77/0.73.
RIG_G_CAM_REL = 0.3


def _sub_args(module, argv):
    p = argparse.ArgumentParser(prog="jaxcr")
    module.add_parser(p.add_subparsers())
    return p.parse_args(argv)


def _per_camera_iou(rows: list[dict], presets: list[str]) -> list[str]:
    """Markdown lines: mean IoU (raw | adjusted) per camera and preset; the tip-error rows of
    the table above are per frame (one 3-D estimate explains all cameras; components in the
    first camera's frame)."""
    import numpy as np

    cams = list(dict.fromkeys(r["camera"] for r in rows))
    groups = list(dict.fromkeys(r["group"] for r in rows))
    out = [
        "## IoU per camera (optimised projection, raw | adjusted; unoptimised in brackets)",
        "",
        "| camera | " + " | ".join(groups) + " |",
        "|---|" + "---|" * len(groups),
    ]
    for cam in cams:
        cells = []
        for g in groups:
            sel = [r for r in rows if r["camera"] == cam and r["group"] == g and r["ok"]]

            def mean(key, sel=sel):
                v = np.array([r[key] for r in sel], float)
                v = v[np.isfinite(v)]
                return f"{v.mean():.3f}" if v.size else "-"

            cells.append(
                f"{mean('iou_refined')} \\| {mean('adj_iou_refined')} "
                f"({mean('iou_nominal')} \\| {mean('adj_iou_nominal')})"
            )
        out.append(f"| {cam} | " + " | ".join(cells) + " |")
    out.append("")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--work", default=None, help="data folder (default /tmp/jaxcr-table2)")
    ap.add_argument("--results", default=str(HERE.parent / "results" / "segmentation"))
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--presets", nargs="*", default=PRESETS)
    ap.add_argument("--keep", action="store_true", help="reuse generated datasets if present")
    ap.add_argument(
        "--cameras",
        type=int,
        default=1,
        help="cameras per frame (default 1, as in the paper); 2 renders each preset's stereo rig "
        "and refines one delta-u against both views (multi-camera refinement, beyond the paper)",
    )
    ap.add_argument(
        "--camera-mode",
        choices=["camera", "rig"],
        default=None,
        help="camera correction with several cameras (default: rig; see the module docstring)",
    )
    ap.add_argument(
        "--g-cam-rel",
        type=float,
        default=None,
        help="rig mode: regularise a residual correction of each further camera by this; 0 = "
        f"rigid rig (default {RIG_G_CAM_REL}, see RIG_G_CAM_REL)",
    )
    a = ap.parse_args(argv)
    mode = a.camera_mode or ("rig" if a.cameras > 1 else None)
    seg_extra = [] if mode is None else ["--camera-correction-mode", mode]
    g_rel = RIG_G_CAM_REL if a.g_cam_rel is None else a.g_cam_rel
    if mode == "rig" and g_rel > 0:
        seg_extra += ["--g-cam-rel", str(g_rel)]
    mode_sfx = "_percamera" if (a.cameras > 1 and mode == "camera") else ""
    if mode == "rig" and g_rel != RIG_G_CAM_REL:
        mode_sfx += f"_gcamrel{g_rel:g}"

    from jaxcr.cli import segment
    from jaxcr.io import report as rep
    from jaxcr.io import results as R
    from jaxcr.segmentation import evaluate
    from jaxcr.synth.generate import generate, parse_size

    size = parse_size(a.size)
    cams_sfx = "" if a.cameras == 1 else f"_cams{a.cameras}"
    work = Path(a.work or "/tmp/jaxcr-table2") / f"seed{a.seed}{cams_sfx}"
    work.mkdir(parents=True, exist_ok=True)
    outs, timings = [], {}
    for preset in a.presets:
        ds_dir, out_dir = work / preset, work / f"{preset}_segment{mode_sfx}"
        t0 = time.perf_counter()
        if not (a.keep and (ds_dir / "dataset.json").exists()):
            shutil.rmtree(ds_dir, ignore_errors=True)
            generate(preset, ds_dir, seed=a.seed, frames=a.frames, size=size, n_cameras=a.cameras)
        t1 = time.perf_counter()
        args = _sub_args(segment, ["segment", str(ds_dir), "-o", str(out_dir), "--overwrite",
                                   "--batch-size", str(a.batch_size), "--seed", str(a.seed),
                                   *seg_extra])  # fmt: skip
        code = segment.run(args)
        t2 = time.perf_counter()
        timings[preset] = {"synth_s": t1 - t0, "segment_s": t2 - t1, "exit": code}
        print(f"{preset}: synth {t1 - t0:.0f} s, segment {t2 - t1:.0f} s (exit {code})")
        outs.append(out_dir)

    rows, infos = evaluate.evaluate_outputs(outs)
    table = rep.build_table2(rows, columns=a.presets)
    res = Path(a.results)
    res.mkdir(parents=True, exist_ok=True)
    stem = f"table2_seed{a.seed}{cams_sfx}{mode_sfx}"
    summaries = {
        p: json.loads((o / "summary.json").read_text())
        for p, o in zip(a.presets, outs, strict=True)
    }
    v = infos[0].get("versions", {})
    lines = [
        f"# Watson et al. Table II on jaxcr synthetic presets (seed {a.seed}"
        + (f", {a.cameras} cameras per frame" if a.cameras > 1 else "")
        + ")",
        "",
        f"Generated {dt.datetime.now(dt.UTC).isoformat(timespec='seconds')} by "
        f"`python experiments/segmentation/table2.py --seed {a.seed} --frames {a.frames} --size {a.size}"
        + (f" --cameras {a.cameras}" if a.cameras > 1 else "")
        + (f" --camera-mode {a.camera_mode}" if a.camera_mode else "")
        + (f" --g-cam-rel {a.g_cam_rel:g}" if a.g_cam_rel is not None else "")
        + "`.",
        "",
        f"- jaxcr {v.get('jaxcr')} commit `{v.get('git_commit')}`, jax {v.get('jax')}, "
        f"Python {platform.python_version()}, {platform.machine()}, "
        f"{platform.processor() or 'cpu'}",
        "- uncommitted changes in the code that ran: "
        + (", ".join(f"`{f}`" for f in v.get("git_dirty") or []) or "none"),
        f"- {a.frames} frames per preset at {size[0]}x{size[1]}, background subtraction: "
        f"colour mask, refinement: `jaxcr.segmentation.refine.RefineConfig()` defaults "
        f"(`{json.dumps(R.to_jsonable(infos[0]['config']))}`)",
        "- IoU (eq. 8) against the *visible* robot pixels (as the paper's hand labels); "
        '"raw \\| adjusted": adjusted removes predicted pixels inside occluder masks '
        "(Sec. III-B). The paper reports the adjusted IoU only for the endoscopic sets; we "
        "show it wherever the dataset has occluder masks.",
        "- Std is the population std over frames; failed frames are excluded from means and "
        "counted in the last row.",
        "",
        "## Measured",
        "",
        rep.table2_markdown(table),
        "## Published (Watson et al. Table II; real images of a physical CTR, 20 per set)",
        "",
        *(_per_camera_iou(rows, a.presets) if a.cameras > 1 else []),
        rep.paper_table2_markdown(),
        "## Run statistics",
        "",
        "| preset | frames | failed | compile (s) | run (s) | synth (s) | segment wall (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in a.presets:
        s, t = summaries[p], timings[p]
        lines.append(
            f"| {p} | {s['frames']} | {s['failed']} | {s['compile_s']:.1f} | {s['run_s']:.1f} "
            f"| {t['synth_s']:.0f} | {t['segment_s']:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    R.atomic_write_text(res / f"{stem}.md", text)
    R.atomic_write_text(res / f"{stem}.csv", rep.table2_csv(table))
    R.atomic_write_text(res / f"{stem}_per_frame.csv", evaluate.per_frame_csv(rows))
    evaluate.iou_plot(rows, res / f"{stem}_iou.png")
    from rich.console import Console

    Console().print(rep.table2_rich(table, title=f"Table II, seed {a.seed}"))
    print(f"wrote {res / (stem + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
