"""`jaxcr evaluate` on records with the tip uncertainty (format jaxcr.segment/2,
docs/uncertainty.md): the sigma columns of per_frame.csv (an unbounded sigma, JSON null, as
"inf") and the "Tip uncertainty" table of table2.md, whose coverage column is checked against
a count made here from the same numbers. No refinement runs: the output folder is written by
hand from the dataset's own truth."""

import csv
import json

import numpy as np

from jaxcr.io import results as R
from tests.helpers.datasets import make_dataset


def _write_run(root, out):
    from jaxcr.io.dataset import load_dataset

    ds = load_dataset(root)
    out.mkdir()
    R.atomic_write_json(out / "run.json", {
        "format": R.RUN_FORMAT, "dataset": str(root), "dataset_name": ds.name,
        "cameras": ["main"],
    })  # fmt: skip
    cam = ds.cameras["main"]
    depth_axis = np.asarray(cam.R, np.float64)[2]
    lines, depth_err = [], {}
    # frame i: the refined centreline is the truth moved 2 mm along the optical axis; the
    # predicted depth sigmas 3 mm (within 1 sigma), 1.5 mm (within 2) and unbounded (null)
    sigmas = [3.0, 1.5, None]
    for i, f in enumerate(ds.frames):
        truth = np.asarray(f.load_truth("centreline"), np.float64)[:, :3]
        refined = truth + 2e-3 * depth_axis
        files = {"masks": {}, "nominal": {}, "background": {}}
        mask = f.load_mask("main")
        for kind in files:
            rel = f"{kind}/main/{f.id}.png"
            R.atomic_write_png(out / rel, mask)
            files[kind]["main"] = rel
        for key, arr in (("centreline", refined), ("centreline_nominal", truth)):
            rel = f"{key}/{f.id}.npy"
            R.atomic_write_npy(out / rel, arr)
            files[key] = rel
        depth_err[f.id] = 2.0
        s = sigmas[i]
        cams = {"main": {"sigma_depth_mm": s, "sigma_image_mm": 0.1, "sigma_image_px": 0.5,
                         "depth_ratio": None if s is None else s / 0.1,
                         "depth_ambiguous": True, "noise_std": 0.05}}  # fmt: skip
        rec = {"format": R.RESULTS_FORMAT, "frame": f.id, "ok": True, "reason": None,
               "tags": list(f.tags), "cameras": ["main"], "num_steps": 3, "time_s": 0.1,
               "files": files,
               "uncertainty": {"model": "laplace-gauss-newton/1", "depth_factor": 3.0,
                               "depth_ambiguous": True, "cameras": cams}}  # fmt: skip
        lines.append(json.dumps(rec))
    (out / "results.jsonl").write_text("\n".join(lines) + "\n")
    (out / "DONE").write_text("now\n")


def test_evaluate_reports_tip_uncertainty(tmp_path):
    from jaxcr.cli import main

    root = make_dataset(tmp_path / "d", n_frames=3)
    out = tmp_path / "run"
    _write_run(root, out)
    assert main(["evaluate", str(out), "--no-plot"]) == 0
    rows = list(csv.DictReader((out / "per_frame.csv").open()))
    assert [r["sigma_depth_mm"] for r in rows] == ["3.0", "1.5", "inf"]
    assert all(r["sigma_image_px"] == "0.5" and r["depth_ambiguous"] == "True" for r in rows)
    # the refined tip is 2 mm off along the optical axis in every frame (evaluate's own
    # tip_depth_refined_mm must say so, to float32 rounding of 0.1 m-scale points)
    assert all(abs(float(r["tip_depth_refined_mm"]) - 2.0) < 1e-3 for r in rows)
    md = (out / "table2.md").read_text()
    assert "Tip uncertainty" in md
    row = next(line for line in md.splitlines() if line.startswith("| test | main |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # a 2 mm depth error is within 1 sigma for sigma 3 mm and the unbounded one, within 2
    # sigma for all three (2 <= 2 x 1.5)
    assert cells[2] == "3"  # frames
    assert cells[6] == "3"  # depth-ambiguous
    assert cells[7] == "67% / 100% of 3"
