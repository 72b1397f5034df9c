"""Split the image-plane (lateral) tip error of segment outputs into its part along the true
tip tangent and across it, in the first camera's frame, nominal and refined (mm, means over
frames), plus the |length difference| refined vs true (delta-u changes curvature only, so a
length error stays as error along the tangent).

    python experiments/segmentation/tip_lateral_split.py DATASET OUT [DATASET OUT ...]

OUT is a ``jaxcr segment`` output folder (centrelines/ and centrelines_nominal/).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def split(ds: Path, out: Path) -> dict[str, float]:
    d = json.loads((ds / "dataset.json").read_text())
    cam = next(iter(d["cameras"].values()))
    R = np.asarray(cam["T_cam_robot"])[:3, :3]
    acc: dict[str, list[float]] = {}
    for r in (out / "results.jsonl").read_text().splitlines():
        rec = json.loads(r)
        if not rec.get("ok"):
            continue
        fid = rec["frame"]
        tr = np.load(ds / "truth" / f"{fid}.npy", allow_pickle=False)[:, :3]
        t = tr[-1] - tr[-2]
        tc = R @ (t / np.linalg.norm(t))
        for tag, sub in (("nominal", "centrelines_nominal"), ("refined", "centrelines")):
            p = np.load(out / sub / f"{fid}.npy", allow_pickle=False)[:, :3]
            dd = R @ (p[-1] - tr[-1])
            along = (dd @ tc) * tc
            acc.setdefault(f"lateral_{tag}", []).append(np.linalg.norm(dd[:2]))
            acc.setdefault(f"along_{tag}", []).append(np.linalg.norm(along[:2]))
            acc.setdefault(f"across_{tag}", []).append(np.linalg.norm((dd - along)[:2]))
        length = [np.linalg.norm(np.diff(x, axis=0), axis=1).sum() for x in (p, tr)]
        acc.setdefault("dlen_refined", []).append(abs(length[0] - length[1]))
    return {k: 1e3 * float(np.mean(v)) for k, v in acc.items()}


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) % 2 or not args:
        print(__doc__)
        return 2
    print("| dataset | lateral nom -> ref | along tangent nom -> ref | across nom -> ref "
          "| abs length diff |\n|---|---|---|---|---|")  # fmt: skip
    for ds, out in zip(args[::2], args[1::2], strict=True):
        m = split(Path(ds), Path(out))
        print(
            f"| {ds} | {m['lateral_nominal']:.2f} -> {m['lateral_refined']:.2f} "
            f"| {m['along_nominal']:.2f} -> {m['along_refined']:.2f} "
            f"| {m['across_nominal']:.2f} -> {m['across_refined']:.2f} | {m['dlen_refined']:.2f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
