"""Accuracy of the speed settings: experiments/motion/motion_experiments.py with one MotionConfig
change, so a faster setting is only adopted if the mean Tanimoto distances do not drop.

  python experiments/motion/motion_speed_accuracy.py VARIANT [--data /tmp/motion_data]

VARIANT is one of the keys of VARIANTS ("default" runs the experiments unchanged). The
experiment module is loaded from this folder and run with ``--no-ablation``; its MotionConfig
gets the variant's extra fields and its report goes to /tmp/motion_speed/VARIANT (cache in
/tmp/motion_speed/VARIANT/cache), not to experiments/results. After the run the mean Tanimoto
distance of M-L (translation) is printed per video group at fixed thresholds 0.85 and 0.90 of
the map maximum, so that variants can be compared without the static-set threshold selection
(which moves in 0.05 steps) getting in the way. Results:
experiments/results/motion/motion_speed_accuracy.md.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np

from jaxcr.motion.flow import FlowConfig
from jaxcr.motion.pipeline import MotionConfig

VARIANTS = {
    "default": {},
    "superpixels_half": {"superpixel_scale": 2},  # SLIC on 160x120 for the 320x240 videos
    "lk_window9": {"flow": FlowConfig(step=4, window=9, levels=3)},
    "lk_grid8_window9_levels2": {"flow": FlowConfig(step=8, window=9, levels=2)},
    "dis": {"flow": FlowConfig(step=4, method="dis")},
}


def tanimoto(a: np.ndarray, b: np.ndarray) -> float:
    return 1.0 - float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def summary(cache: Path, lam: str) -> list[str]:
    """Mean +- std Tanimoto distance of the translation map per group at fixed thresholds,
    for the runs with the chosen lambda."""
    lines = []
    files = sorted(cache.glob(f"*__v2_lam{lam}_*_st1.npz"))
    for th in (0.85, 0.90):
        for group in ("pushed_static", "pushed_changing", "held"):
            t = []
            for f in files:
                if not f.name.startswith(group):
                    continue
                z = np.load(f, allow_pickle=True)
                m = z["map_translation"] / max(float(z["map_translation"].max()), 1e-12)
                t.append(tanimoto(m >= th, z["gt"].astype(bool)))
            if t:
                lines.append(
                    f"threshold {th:.2f} {group}: {np.mean(t):.3f} +- {np.std(t):.3f} ({len(t)})"
                )
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("variant", choices=sorted(VARIANTS))
    ap.add_argument("--data", default="/tmp/motion_data")
    a = ap.parse_args()
    out = Path("/tmp/motion_speed") / a.variant
    cache = out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    spec = importlib.util.spec_from_file_location(
        "motion_experiments", Path(__file__).parent / "motion_experiments.py"
    )
    mx = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mx)
    mx.MotionConfig = functools.partial(MotionConfig, **VARIANTS[a.variant])
    mx.OUT = out
    sys.argv = ["motion_experiments.py", "--data", a.data, "--cache", str(cache), "--no-ablation"]
    mx.main()
    report = (out / "motion_report.md").read_text()
    lam = re.search(r"chosen: lambda = ([0-9.e+-]+) px", report).group(1)
    print(f"\nreport: {out / 'motion_report.md'} (lambda {lam})")
    print("\n".join(summary(cache, lam)))


if __name__ == "__main__":
    main()
