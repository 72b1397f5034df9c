"""Where the time of one pairwise RGB-D registration goes (issue 18, row "pairwise RGB-D
registration": 0.22-0.36 s/pair, target <= 0.1 s/pair at equal pose error). Writes
experiments/results/registration/bench_pairwise_profile.md (+ .json).

    python experiments/registration/bench_pairwise_profile.py --pairs 8 --repeats 3

Frames: a Task 1 scene (development seed 5), rendered by the scene's simulator (noisy depth)
from cameras on a circle around the target at the scene's view radius, 25 deg apart (the
forward registrations' baseline), looking at the target. Each forward pair is registered by
``PipelineConfig().register`` (the pipeline's defaults: SIFT + RANSAC/Kabsch seed, projective
ICP with the chromaticity term, ICP information) and, separately, stage by stage with
timers (``block_until_ready`` on the jitted stages): keypoint features of the pair's new
(target) frame (OpenCV SIFT + smoothed depth; the source's come from the per-frame cache, as
in a run's forward chain), matching + lifting, RANSAC/Kabsch, projective ICP, ICP information. Compilation (the first pair)
is reported apart; medians and the spread (min-max) over pairs x repeats after it. The
machine is shared (load average recorded): read the stage shares, not the absolute times.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxcr.benchmarks.registration import look_at
from jaxcr.registration.keypoints import matched_features
from jaxcr.registration.metrics import pose_error
from jaxcr.registration.pairwise import _keypoint_arrays, frame_features, geometric_sample
from jaxcr.registration.pipeline import PipelineConfig, capture_frame
from jaxcr.registration.projective import projective_icp_jit, projective_information_jit
from jaxcr.registration.ransac import estimate_transform
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task

OUT = Path(__file__).parent.parent / "results" / "registration"


def frames(scratch: Path, n: int, step_deg: float, seed: int):
    scene = generate_task(scratch / f"task1_seed{seed}", "1", seed)
    sim = RgbdSimulator(scene, seed=seed)
    cfg = PipelineConfig()
    zt = float(sim.cfg.get("tilt_target_z", 0.0))
    r = float(sim.cfg["view_radius"])
    target = np.array([0.0, 0.0, zt])
    out = []
    for k in range(n):
        a = np.deg2rad(step_deg * k)
        T = look_at(np.array([r * np.cos(a), r * np.sin(a), zt + 0.1]), target)
        rgb, depth = sim.capture(T)
        f = capture_frame(rgb, depth, sim.K, cfg, seed + k, str(k))
        out.append((f, T))
    return sim.K, out


def stages(cfg: PipelineConfig, fa, fb, K, prior, seed: int) -> dict:
    """Seconds per stage of ``cfg.register(fa, fb, ...)``, run stage by stage."""
    t = {}
    # as in a run's chain of forward registrations: the source's keypoint features were
    # computed when it was the previous pair's target (pairwise.frame_features), the
    # target's are computed here, once for every pair it takes part in
    frame_features(fa, asift=cfg.asift, crop_margin=cfg.keypoint_crop)
    fb.features.clear()
    t0 = time.perf_counter()
    fb_features = frame_features(fb, asift=cfg.asift, crop_margin=cfg.keypoint_crop)
    t["keypoints: SIFT + smoothed depth of the new frame"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ka, kb = matched_features(
        frame_features(fa, asift=cfg.asift, crop_margin=cfg.keypoint_crop), fb_features, K
    )
    t["keypoints: match + lift"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    T_kp, _ = estimate_transform(ka, kb, seed=seed) if len(ka) else (None, 0)
    t["ransac"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    import jax.numpy as jnp

    T0 = jnp.asarray(T_kp if T_kp is not None else prior, jnp.float32)
    kp = _keypoint_arrays(ka, kb, T_kp, upper=cfg.icp.sigma_keypoint)
    kw = dict(
        window=0, src_image=fa.image, photometric=cfg.photometric, photo_points=fa.sample_plane
    )
    src = geometric_sample(fa, cfg.geometric_points)
    t["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = projective_icp_jit(src, fb.image, T0, cfg.icp, kp, **kw)
    res.T.block_until_ready()
    t["icp"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    info, _ = projective_information_jit(res.T, src, fb.image, cfg.icp, kp, **kw)
    info.block_until_ready()
    t["information"] = time.perf_counter() - t0
    return t


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--step-deg", type=float, default=25.0)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--scratch", default="/tmp/bench_pairwise")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="bench_pairwise_profile", help="output file stem")
    a = ap.parse_args()
    load0 = os.getloadavg()
    K, fr = frames(Path(a.scratch), a.pairs + 1, a.step_deg, a.seed)
    cfg = PipelineConfig()
    # compilation: the first pair, once per stage set and once through register
    t0 = time.perf_counter()
    comp_stages = stages(cfg, fr[0][0], fr[1][0], K, np.linalg.inv(fr[1][1]) @ fr[0][1], 0)
    t0 = time.perf_counter()
    cfg.register(fr[0][0], fr[1][0], K, np.linalg.inv(fr[1][1]) @ fr[0][1], 0)
    first_total = time.perf_counter() - t0
    rows = {k: [] for k in comp_stages}
    total, rot, tra = [], [], []
    for rep in range(a.repeats):
        for k in range(a.pairs):
            (fa, Ta), (fb, Tb) = fr[k], fr[k + 1]
            truth = np.linalg.inv(Tb) @ Ta
            for name, v in stages(cfg, fa, fb, K, truth, k).items():
                rows[name].append(v)
            fb.features.clear()  # the target's features computed in the timed call
            t0 = time.perf_counter()
            p = cfg.register(fa, fb, K, truth, k)
            total.append(time.perf_counter() - t0)
            if rep == 0:
                r, t = pose_error(p.T, truth)
                rot.append(r)
                tra.append(1000 * t)
    load1 = os.getloadavg()
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    med = {k: float(np.median(v)) for k, v in rows.items()}
    s = sum(med.values())
    cmd = "python experiments/registration/bench_pairwise_profile.py " + " ".join(sys.argv[1:])
    md = [
        "# Pairwise RGB-D registration: time per stage (issue 18)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs shared with other jobs; load average {load0[0]:.1f} at start, "
        f"{load1[0]:.1f} at end. Command: `{cmd}`.",
        "",
        f"{a.pairs} forward pairs ({a.step_deg:g} deg apart, Task 1 scene seed {a.seed}, "
        f"{fr[0][0].rgb.shape[1]}x{fr[0][0].rgb.shape[0]}, sample {cfg.sample_size} px) x "
        f"{a.repeats} repeats; medians after compilation, [min-max].",
        "",
        "| stage | median ms | min-max ms | share of the stage sum |",
        "|---|---|---|---|",
    ]
    for k, v in rows.items():
        md.append(
            f"| {k} | {1000 * med[k]:.1f} | {1000 * min(v):.1f}-{1000 * max(v):.1f} | "
            f"{100 * med[k] / s:.0f} % |"
        )
    md += [
        f"| **register (whole, PipelineConfig().register)** | {1000 * np.median(total):.1f} | "
        f"{1000 * min(total):.1f}-{1000 * max(total):.1f} | |",
        "",
        f"First pair (compilation included): stages {json.dumps({k: round(v, 2) for k, v in comp_stages.items()})} s, "
        f"register {first_total:.2f} s.",
        f"Pose error of the registrations against the truth: rotation median "
        f"{np.median(rot):.3f} deg (max {max(rot):.3f}), translation median "
        f"{np.median(tra):.2f} mm (max {max(tra):.2f}).",
    ]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(
        json.dumps(
            {
                "command": cmd,
                "commit": commit,
                "load_start": load0,
                "load_end": load1,
                "stages_s": rows,
                "register_s": total,
                "compile_stages_s": comp_stages,
                "compile_register_s": first_total,
                "rot_deg": rot,
                "trans_mm": tra,
            },
            indent=1,
        )
    )
    print("\n".join(md))


if __name__ == "__main__":
    main()
