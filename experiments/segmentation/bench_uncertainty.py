"""Cost of the per-frame tip covariance (issue 16 item 6) beside the refinement, at 640x480.

A 640x480 frame of the calibration experiment's arc (one camera, fx = 800 px), refined with
the default :class:`RefineConfig` (camera correction on) by ``refine_batch`` and then
``shape_uncertainty_batch`` on the same frames: compile time of each (first call) and the
median wall time per frame of ``--repeats`` warm calls, in the same process, with the ratio.

    python experiments/segmentation/bench_uncertainty.py [--frames 4] [--repeats 5]

Writes experiments/results/segmentation/bench_uncertainty.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

# the sibling script: `python experiments/segmentation/bench_uncertainty.py` puts this folder
# first on sys.path, so it imports without editing sys.path
import uncertainty_calibration as uc

from jaxcr.segmentation.background import no_mask
from jaxcr.segmentation.refine import RefineConfig, refine_batch
from jaxcr.segmentation.shape import perturbed_centreline
from jaxcr.segmentation.uncertainty import shape_uncertainty_batch

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "experiments" / "results" / "segmentation" / "bench_uncertainty"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    uc.W, uc.H, uc.FX = 640, 480, 800.0
    base = uc.base_arc()
    cam = uc.camera_at([0, 0, -0.3])
    truth = perturbed_centreline(base, jnp.asarray(uc.TRUE_INPLANE))
    imgs = np.stack([uc.render(truth, cam, s) for s in range(args.frames)])
    bg, im = jax.vmap(no_mask)(jnp.asarray(imgs))
    f = args.frames
    bases = jax.tree.map(lambda x: jnp.broadcast_to(x, (f,) + x.shape), base)
    cfg = RefineConfig()

    def refine():
        return jax.block_until_ready(refine_batch(bases, (cam,), (im,), (bg,), cfg))

    t0 = time.perf_counter()
    res = refine()
    first_ref = time.perf_counter() - t0

    def unc():
        return jax.block_until_ready(
            shape_uncertainty_batch(
                bases, (cam,), (im,), (bg,), cfg, res.coeffs, res.camera_correction
            )
        )

    t0 = time.perf_counter()
    unc()
    first_unc = time.perf_counter() - t0
    t_ref, t_unc = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        refine()
        t_ref.append((time.perf_counter() - t0) / f)
        t0 = time.perf_counter()
        unc()
        t_unc.append((time.perf_counter() - t0) / f)
    med_r, med_u = float(np.median(t_ref)), float(np.median(t_unc))
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    out = {
        "frames": f, "repeats": args.repeats, "size": [640, 480],
        "refine_s_per_frame": t_ref, "uncertainty_s_per_frame": t_unc,
        "refine_median_s": med_r, "uncertainty_median_s": med_u, "ratio": med_u / med_r,
        "refine_first_call_s": first_ref, "uncertainty_first_call_s": first_unc,
        "median_steps": float(np.median(np.asarray(res.num_steps))),
        "load": load, "commit": commit, "jax": jax.__version__, "machine": platform.machine(),
    }  # fmt: skip
    print(json.dumps(out, indent=1))
    lines = [
        "# Cost of the tip covariance beside the refinement (640x480)",
        "",
        f"Command: `python experiments/segmentation/bench_uncertainty.py --frames {f} "
        f"--repeats {args.repeats}` (commit {commit}, jax {jax.__version__}, "
        f"{platform.machine()}). **Machine load average {load} on 2 cores shared by 8 "
        "engineers**: absolute times are inflated and noisy; the ratio (same process, "
        "interleaved runs) is the figure to read.",
        "",
        "Scene: the arc of uncertainty_calibration.py at 640x480, fx = 800 px, one camera, "
        "default RefineConfig (levels (1, 0), camera correction on), "
        f"median {out['median_steps']:.0f} solver steps per frame.",
        "",
        "| | refinement | covariance (shape_uncertainty_batch) | ratio |",
        "|---|---|---|---|",
        f"| median s per frame (warm, {args.repeats} runs of {f} frames) | {med_r:.3f} | "
        f"{med_u:.3f} | {med_u / med_r:.2f} |",
        f"| first call incl. compilation, s | {first_ref:.1f} | {first_unc:.1f} | |",
        "",
        "Per run (s per frame): refinement "
        + ", ".join(f"{x:.3f}" for x in t_ref)
        + "; covariance "
        + ", ".join(f"{x:.3f}" for x in t_unc)
        + ".",
        "",
    ]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.with_suffix(".md").write_text("\n".join(lines))
    OUT.with_suffix(".json").write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
