"""Why multi-camera refinement does not halve the tip error on the synthetic presets.

Two diagnostics on ``experiments/segmentation/table2.py`` work folders (``<work>/seed<k>_cams<n>``):

* ``--oracle``: segments each preset again with the *true* cameras (``meta.true_cameras`` of
  the dataset, written by the generator) and no camera correction: the tip error left when
  calibration is exact (a bound for any camera-correction scheme, not a method).
* the tip error of every segment output found (``<preset>_segment*``, plus the oracle's) is
  split into the part along the true tip tangent and the distance of the estimated tip from
  the true centreline (off the curve), and the length difference between the refined and
  the true centreline is reported. delta-u changes curvature only, so the robot's length
  (set by the nominal joint values; the generator adds tube translation offsets) cannot change:
  a length error stays as tip error along the tangent whatever the images show.

    python experiments/segmentation/multicam_tip_floor.py /tmp/jaxcr-table2/seed1_cams2 [--oracle]

Prints one Markdown table per output folder kind (mm, means over frames).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
import table2  # noqa: E402


def _point_to_polyline(p: np.ndarray, poly: np.ndarray) -> float:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-18), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def decompose(out: Path, ds: Path) -> dict[str, float]:
    """Mean (mm) over the ok frames of ``out``: tip error, its component along the true tip
    tangent, the tip's distance from the true centreline, nominal and refined; |length
    difference| refined vs true."""
    acc: dict[str, list[float]] = {}
    for line in (out / "results.jsonl").read_text().splitlines():
        r = json.loads(line)
        if not r.get("ok"):
            continue
        f = r["frame"]
        truth = np.load(ds / "truth" / f"{f}.npy", allow_pickle=False)[:, :3]
        tang = truth[-1] - truth[-2]
        tang /= np.linalg.norm(tang)
        for tag, sub in (("nominal", "centrelines_nominal"), ("refined", "centrelines")):
            p = np.load(out / sub / f"{f}.npy", allow_pickle=False)
            d = p[-1] - truth[-1]
            acc.setdefault(f"tip_{tag}", []).append(np.linalg.norm(d))
            acc.setdefault(f"along_{tag}", []).append(abs(float(d @ tang)))
            acc.setdefault(f"off_{tag}", []).append(_point_to_polyline(p[-1], truth))
            acc.setdefault(f"dlen_{tag}", []).append(abs(_length(p) - _length(truth)))
    return {k: 1e3 * float(np.mean(v)) for k, v in acc.items()}


def oracle(work: Path, presets: list[str]) -> Path:
    """Segment copies of the datasets whose cameras are the true ones; returns the folder."""
    from jaxcr.cli import segment

    dst = work.parent / f"{work.name}_truecams"
    dst.mkdir(exist_ok=True)
    for preset in presets:
        src, d = work / preset, dst / preset
        d.mkdir(exist_ok=True)
        for sub in os.listdir(src):
            if sub != "dataset.json" and not (d / sub).exists():
                os.symlink(src / sub, d / sub)
        meta = json.loads((src / "dataset.json").read_text())
        for name, T in meta["meta"]["true_cameras"].items():
            meta["cameras"][name]["T_cam_robot"] = T
        (d / "dataset.json").write_text(json.dumps(meta))
        argv = ["segment", str(d), "-o", str(dst / f"{preset}_segment"), "--overwrite",
                "--no-camera-correction", "--no-overlays", "--quiet"]  # fmt: skip
        segment.run(table2._sub_args(segment, argv))
    return dst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", help="a table2.py work folder, e.g. /tmp/jaxcr-table2/seed1_cams2")
    ap.add_argument("--oracle", action="store_true", help="also segment with the true cameras")
    ap.add_argument("--presets", nargs="*", default=table2.PRESETS)
    a = ap.parse_args(argv)
    work = Path(a.work)
    roots = [work] + ([oracle(work, a.presets)] if a.oracle else [])
    print(
        "| output | preset | tip nom -> ref | along tangent nom -> ref | off the true curve "
        "nom -> ref | abs length diff, refined |\n|---|---|---|---|---|---|"
    )
    for root in roots:
        for preset in a.presets:
            for out in sorted(root.glob(f"{preset}_segment*")):
                suffix = out.name[len(f"{preset}_segment") :]
                if suffix and not suffix.startswith("_"):
                    continue
                m = decompose(out, work / preset)
                label = ("true cameras, no correction" if root != work else "table2") + suffix
                print(
                    f"| {label} | {preset} | {m['tip_nominal']:.2f} -> "
                    f"{m['tip_refined']:.2f} | {m['along_nominal']:.2f} -> {m['along_refined']:.2f} "
                    f"| {m['off_nominal']:.2f} -> {m['off_refined']:.2f} | {m['dlen_refined']:.2f} |"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
