"""Issue 17 item 10: which frame's depth noise carries the far view's registration error.

The first capture of Task 1 lies outside the ring, ~0.6 m from the object (ring views
0.2-0.47 m); its pose after the pose graph was the only fresh-seed miss (1-3 mm), and its
far -> near registrations are 1-2 mm off when started at the true pose
(model_object_scale_match_edges.md). Every one of its edges shares the one far frame, so
if that frame's noise draw carries the error, the edges are correlated and no pose-graph
weighting averages it out.

Here each development scene is seen by a far camera (``--far`` m from the object's axis)
and a near camera per ``--pairs`` entry (distance m : azimuth offset deg; 0.25 m high,
looking at the object's middle, as in model_object_scale_match_edges.py) and registered far
-> near by :func:`jaxcr.registration.pipeline.register_views` (pipeline defaults, raw
source points for a far source) from the true pose, with the depth noise of each frame
switched on or off (a 2 x 2 factorial on one noise draw; 'clean' = sigma_z 0, the 0.5 mm
depth quantisation, holes and colour noise as generated), plus ``--draws`` further
independent noise draws of both frames (bias vs spread). Errors against the true relative
pose, in the near camera's frame (x right, y down, z forward).

    python experiments/registration/model_object_far_edge_factorial.py --seeds 0-9 --tasks 1

Link mode (``--links``): one far view per noise draw registered to several near views (the
outside node's links), the far camera's position error from each link, from their equal-
weight mean and from their ICP-information-weighted mean (exact near poses), per
``--variants`` (``label=field:value,...`` PipelineConfig overrides, ``icp.field`` for
IcpConfig):

    python experiments/registration/model_object_far_edge_factorial.py --seeds 0-9 --tasks 1 \
        --links 0.37:25 0.37:-25 0.30:40 0.47:-12 --draws 2 --variants base=

Writes experiments/results/registration/<--name>.md (+ .json).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import os
import platform
import subprocess
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from jaxcr.registration.metrics import pose_error  # noqa: E402
from jaxcr.registration.pairwise import RegistrationFailed  # noqa: E402
from jaxcr.registration.pipeline import (  # noqa: E402
    PipelineConfig,
    capture_frame,
    register_views,
)
from jaxcr.synth.rgbd_tasks import RgbdSimulator, generate_task  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "registration"


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World <- camera pose (OpenCV frame: z forward, y down), world z up."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def camera(dist: float, azimuth: float, target: np.ndarray) -> np.ndarray:
    return look_at(np.array([dist * np.cos(azimuth), dist * np.sin(azimuth), 0.25]), target)


def render(sim: RgbdSimulator, T: np.ndarray, clean: bool, key) -> tuple:
    noise = dict(sim.cfg["depth_noise"])
    if clean:
        sim.cfg["depth_noise"] = dict(noise, sigma0=0.0, sigma2=0.0)
    sim.rng = np.random.default_rng(key)
    try:
        return sim.capture(T)
    finally:
        sim.cfg["depth_noise"] = noise


def _scene(task, seed, scratch):
    """The task's simulator, its intrinsics and the point the cameras look at (the object's
    mid-height on the turntable axis)."""
    scene = generate_task(scratch / f"task{task}_seed{seed}", task, seed)
    sim = RgbdSimulator(scene, seed=seed)
    obj = sim.cfg["object"]
    height = 2 * obj["half"][2] if obj["kind"] == "box" else obj["height"]
    return sim, sim.K, np.array([0.0, 0.0, 0.5 * height])


def run_scene(task, seed, scratch, far, pairs, draws) -> list[dict]:
    sim, K, target = _scene(task, seed, scratch)
    rng = np.random.default_rng([seed, int(task), 17])
    cfg = PipelineConfig()
    gate = (cfg.closure_gate_deg, cfg.closure_gate_m)
    out = []
    for k, (near, offset_deg) in enumerate(pairs):
        az = rng.uniform(0, 2 * np.pi)
        Tf = camera(far, az, target)
        Tn = camera(near, az + np.deg2rad(offset_deg), target)
        T_true = np.linalg.inv(Tn) @ Tf  # near <- far
        conds = [
            ("far noisy, near noisy", 0, False, False),
            ("far clean, near noisy", 0, True, False),
            ("far noisy, near clean", 0, False, True),
            ("far clean, near clean", 0, True, True),
        ]
        conds += [(f"draw {d}", d, False, False) for d in range(1, draws + 1)]
        rec = {"task": task, "seed": seed, "pair": k, "near_m": near, "offset_deg": offset_deg}
        for name, d, fclean, nclean in conds:
            key_f, key_n = [seed, int(task), k, d, 0], [seed, int(task), k, d, 1]
            ff = capture_frame(*render(sim, Tf, fclean, key_f), K, cfg, seed + k, "far")
            fn = capture_frame(*render(sim, Tn, nclean, key_n), K, cfg, seed + k, "near")
            try:
                p = register_views(cfg, ff, fn, K, T_true, seed + k, gate)
            except RegistrationFailed as err:
                rec[name] = {"failed": str(err)}
                continue
            r, t = pose_error(p.T, T_true)
            dt = 1000 * (np.asarray(p.T)[:3, 3] - T_true[:3, 3])
            rv = np.degrees(
                Rotation.from_matrix(np.asarray(p.T)[:3, :3] @ T_true[:3, :3].T).as_rotvec()
            )
            rec[name] = {"mm": 1000 * t, "deg": r, "dt_mm": dt.tolist(), "rot_deg": rv.tolist()}
        out.append(rec)
    return out


def parse_variant(text: str) -> tuple[str, dict]:
    """``label=field:value,...`` (PipelineConfig fields, ``icp.field`` for IcpConfig; values
    Python literals) -> (label, overrides)."""
    label, _, rest = text.partition("=")
    over = {}
    for item in filter(None, rest.split(",")):
        key, _, val = item.partition(":")
        try:
            over[key] = ast.literal_eval(val)
        except (ValueError, SyntaxError):
            over[key] = val
    return label, over


def configured(over: dict) -> PipelineConfig:
    base = PipelineConfig()
    icp = {k[4:]: v for k, v in over.items() if k.startswith("icp.")}
    cfg = dataclasses.replace(base, **{k: v for k, v in over.items() if not k.startswith("icp.")})
    return dataclasses.replace(cfg, icp=dataclasses.replace(cfg.icp, **icp)) if icp else cfg


def world_information(Tn: np.ndarray, info) -> np.ndarray | None:
    """A registration's information (left perturbation (v, w) of T_{near <- far} in the near
    frame) as the information of the left perturbation of T_{world <- far} in the world
    frame: Omega_w = Ad^-T Omega Ad^-1, Ad = [[R, [t]x R], [0, R]] of T_{world <- near}."""
    if info is None:
        return None
    R, t = Tn[:3, :3], Tn[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ad = np.block([[R, tx @ R], [np.zeros((3, 3)), R]])
    Ai = np.linalg.inv(Ad)
    return Ai.T @ np.asarray(info, np.float64) @ Ai


def weighted_position_error(errs, infos, Tf) -> float | None:
    """Camera position error (mm) of the information-weighted mean of the links' world
    perturbations (each link's (v, w) from the truth: w its rotation vector, v = dt - w x c
    with c the true camera centre), i.e. a pose graph with the ICP information as weights
    and exact near poses."""
    if not errs or any(i is None for i in infos):
        return None
    c = Tf[:3, 3]
    xs = []
    for dt_mm, rv_deg in errs:
        w = np.radians(rv_deg)
        xs.append(np.concatenate([dt_mm / 1000 - np.cross(w, c), w]))
    N = sum(infos)
    x = np.linalg.solve(N, sum(I @ v for I, v in zip(infos, xs, strict=True)))
    return float(1000 * np.linalg.norm(x[:3] + np.cross(x[3:], c)))


def run_links(task, seed, scratch, far, links, draws, variants) -> list[dict]:
    """One far view (per noise draw) registered to ``links`` near views (distance m :
    azimuth offset deg), each near view its own noise draw: the far camera's world pose from
    each link and from their mean (equal weights, as a pose graph with alike edges would),
    against the truth. Per variant (PipelineConfig overrides)."""
    sim, K, target = _scene(task, seed, scratch)
    rng = np.random.default_rng([seed, int(task), 19])
    out = []
    az = rng.uniform(0, 2 * np.pi)
    Tf = camera(far, az, target)
    Tns = [camera(d, az + np.deg2rad(o), target) for d, o in links]
    for d in range(draws):
        raw_f = render(sim, Tf, False, [seed, int(task), 99, d, 0])
        raw_n = [render(sim, T, False, [seed, int(task), 99, d, 1 + k]) for k, T in enumerate(Tns)]
        rec = {"task": task, "seed": seed, "draw": d}
        for vname, over in variants.items():
            cfg = configured(over)
            gate = (cfg.closure_gate_deg, cfg.closure_gate_m)
            ff = capture_frame(*raw_f, K, cfg, seed, "far")
            errs, infos = [], []
            for k, (Tn, rn) in enumerate(zip(Tns, raw_n, strict=True)):
                fn = capture_frame(*rn, K, cfg, seed + 1 + k, f"near{k}")
                T_true = np.linalg.inv(Tn) @ Tf
                try:
                    p = register_views(cfg, ff, fn, K, T_true, seed + k, gate)
                except RegistrationFailed:
                    continue
                Tw = Tn @ np.asarray(p.T, np.float64)  # world <- far, estimated
                infos.append(world_information(Tn, p.information))
                errs.append(
                    (
                        1000 * (Tw[:3, 3] - Tf[:3, 3]),
                        np.degrees(Rotation.from_matrix(Tw[:3, :3] @ Tf[:3, :3].T).as_rotvec()),
                    )
                )
            dts = np.array([e[0] for e in errs])
            rec[vname] = {
                "links_mm": np.linalg.norm(dts, axis=1).tolist(),
                "dt_mm": dts.tolist(),
                "rot_deg": [e[1].tolist() for e in errs],
                "mean_mm": float(np.linalg.norm(dts.mean(0))),
                "info_mm": weighted_position_error(errs, infos, Tf),
            }
        out.append(rec)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="0-9", help="first-last (development seeds only)")
    ap.add_argument("--tasks", nargs="+", default=["1"])
    ap.add_argument("--far", type=float, default=0.6)
    ap.add_argument("--pairs", nargs="+", default=["0.37:25", "0.47:12"])
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument(
        "--links",
        nargs="*",
        default=None,
        help="link mode: near views (m:deg) each registered from one far view",
    )
    ap.add_argument("--variants", nargs="+", default=["base="])
    ap.add_argument("--scratch", default="/tmp/model_object_far_edge_factorial")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="model_object_far_edge_factorial")
    a = ap.parse_args()
    s0, s1 = (int(v) for v in a.seeds.split("-"))
    pairs = [tuple(float(x) for x in p.split(":")) for p in a.pairs]
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    recs = []
    if a.links:
        links = [tuple(float(x) for x in p.split(":")) for p in a.links]
        variants = dict(map(parse_variant, a.variants))
        for task in a.tasks:
            for seed in range(s0, s1 + 1):
                recs += run_links(task, seed, Path(a.scratch), a.far, links, a.draws, variants)
                print(f"task {task} seed {seed} done", flush=True)
        write_links(a, recs, variants, load0, t0, c0)
        return
    for task in a.tasks:
        for seed in range(s0, s1 + 1):
            recs += run_scene(task, seed, Path(a.scratch), a.far, pairs, a.draws)
            print(f"task {task} seed {seed} done", flush=True)
    commit = _commit()
    cmd = (
        f"python experiments/registration/model_object_far_edge_factorial.py --seeds {a.seeds} "
        f"--tasks {' '.join(a.tasks)} --far {a.far} --pairs {' '.join(a.pairs)} "
        f"--draws {a.draws} --name {a.name}"
    )
    names = [n for n in recs[0] if isinstance(recs[0][n], dict)]
    md = [
        "# Far -> near registrations from the true pose: depth-noise factorial (issue 17 item 10)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}; `{cmd}`; "
        f"load average at start {load0:.1f}; {time.perf_counter() - t0:.0f} s wall, "
        f"{time.process_time() - c0:.0f} s CPU. Development seeds only. Cells: mm, "
        "(dx, dy, dz) mm and rotation vector (deg) of the error in the near camera frame.",
        "",
        "| task | seed | pair | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for r in recs:
        cells = []
        for n in names:
            v = r[n]
            if "failed" in v:
                cells.append("failed")
            else:
                cells.append(
                    f"{v['mm']:.2f} ({', '.join(f'{x:+.1f}' for x in v['dt_mm'])}) "
                    f"[{', '.join(f'{x:+.2f}' for x in v['rot_deg'])}]"
                )
        md.append(
            f"| {r['task']} | {r['seed']} | {r['near_m']}:{r['offset_deg']:.0f} | "
            + " | ".join(cells)
            + " |"
        )
    md += [
        "",
        "| condition | n | mean mm | RMS mm | max mm | mean deg |",
        "|---|---|---|---|---|---|",
    ]
    for n in names:
        ok = [r[n] for r in recs if "failed" not in r[n]]
        mm = np.array([v["mm"] for v in ok])
        dg = np.array([v["deg"] for v in ok])
        md.append(
            f"| {n} | {len(ok)} | {mm.mean():.2f} | {np.sqrt((mm**2).mean()):.2f} | "
            f"{mm.max():.2f} | {dg.mean():.3f} |"
        )
    _write(a, md, recs)


def write_links(a, recs, variants, load0, t0, c0) -> None:
    commit = _commit()
    cmd = (
        f"python experiments/registration/model_object_far_edge_factorial.py --seeds {a.seeds} "
        f"--tasks {' '.join(a.tasks)} --far {a.far} --links {' '.join(a.links)} "
        f"--draws {a.draws} --variants {' '.join(a.variants)} --name {a.name}"
    )
    names = list(variants)
    md = [
        "# One far view registered to several near views (issue 17 item 10)",
        "",
        f"commit {commit}, {platform.machine()}, python {platform.python_version()}; `{cmd}`; "
        f"load average at start {load0:.1f}; {time.perf_counter() - t0:.0f} s wall, "
        f"{time.process_time() - c0:.0f} s CPU. Development seeds only. Far camera position "
        "error (mm) from each link, and of the links' mean; 'corr': mean cosine between the "
        "links' error vectors.",
        "",
        "| task | seed | draw | "
        + " | ".join(f"{n} links mm | {n} mean mm | {n} corr" for n in names)
        + " |",
        "|---|---|---|" + "---|---|---|" * len(names),
    ]
    for r in recs:
        cells = []
        for n in names:
            v = r[n]
            dts = np.array(v["dt_mm"])
            u = dts / np.maximum(np.linalg.norm(dts, axis=1, keepdims=True), 1e-9)
            c = u @ u.T
            k = len(u)
            corr = (c.sum() - k) / max(k * (k - 1), 1)
            cells += [
                " ".join(f"{x:.2f}" for x in v["links_mm"]),
                f"{v['mean_mm']:.2f}",
                f"{corr:+.2f}",
            ]
        md.append(f"| {r['task']} | {r['seed']} | {r['draw']} | " + " | ".join(cells) + " |")
    md += [
        "",
        "| variant | n | mean link mm | RMS link mm | links' mean: mean mm | max mm | information-weighted: mean mm | max mm |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n in names:
        lk = np.concatenate([r[n]["links_mm"] for r in recs])
        mm = np.array([r[n]["mean_mm"] for r in recs])
        wi = np.array([r[n].get("info_mm") or np.nan for r in recs])
        md.append(
            f"| {n} | {len(recs)} | {lk.mean():.2f} | {np.sqrt((lk**2).mean()):.2f} | "
            f"{mm.mean():.2f} | {mm.max():.2f} | {np.nanmean(wi):.2f} | {np.nanmax(wi):.2f} |"
        )
    _write(a, md, recs)


def _commit() -> str:
    """The checkout's short commit (empty outside a git checkout)."""
    return subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()


def _write(a, md: list[str], recs) -> None:
    """``<out>/<name>.md`` (the report's lines) and ``<out>/<name>.json`` (the records)."""
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.md").write_text("\n".join(md) + "\n")
    (out / f"{a.name}.json").write_text(json.dumps(recs, indent=1) + "\n")


if __name__ == "__main__":
    main()
