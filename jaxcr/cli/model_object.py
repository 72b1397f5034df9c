"""``jaxcr model-object SCENE -o OUT``: progressive object modelling with a continuum arm.

SCENE is a ``jaxcr.rgbd_scene/1`` folder (docs/rgbd-scene-format.md). The arm plans
collision-free arcs around the target (Algorithm 1), captures RGB-D frames from the
simulated tip camera, registers them forward (SIFT/ASIFT + RANSAC/Kabsch + weighted ICP),
closes the loop and refines all poses (Algorithm 2). OUT receives:

  plan.png          the arm motion from above (obstacles, arcs, arm shapes, camera views)
  model.ply         the merged model after global optimisation (frame O = last view)
  model_before.ply  the model from forward pairwise registration only
  fig13.png         the paper's Fig. 13 statistics before/after global optimisation
  poses.json        every view's estimated camera pose before/after global optimisation
                    and its true pose (when the scene has one) as 4x4 matrices, frame O
                    = the last ring view's camera (format jaxcr.model_poses/1,
                    docs/rgbd-scene-format.md)
  poses.csv         per view (ring or not): rotation/translation errors before/after
  report.md, report.json

Exit codes: 0 model built with a closed loop, 1 registration failed or no loop closed
(partial models are still written), 2 bad input.

``jaxcr model-object synth --task 1 -o SCENE`` writes a synthetic scene (tasks 1, 2).

Examples:
  jaxcr model-object synth --task 1 -o /tmp/task1
  jaxcr model-object /tmp/task1 -o /tmp/task1_out
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxcr.cli._common import seed as _seed
from jaxcr.io import results as R


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "model-object",
        help="build a 3-D object model with a continuum arm's tip RGB-D camera, or 'synth'",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("scene", help="scene folder (jaxcr.rgbd_scene/1), or 'synth' to generate one")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--asift", action="store_true", help="affine-simulated SIFT keypoints")
    p.add_argument(
        "--association",
        choices=["projective", "nearest"],
        default="projective",
        help="ICP data association: projection into the target depth image (default) or "
        "brute-force nearest neighbours on the voxel clouds",
    )
    p.add_argument(
        "--global-opt",
        choices=["pose_graph", "alg2"],
        default="pose_graph",
        help="global optimisation: weighted pose graph over the ring edges plus extra "
        "registrations of views two apart (default), or the paper's Algorithm 2 alone "
        "(Algorithm 2 is reported either way)",
    )
    p.add_argument(
        "--edge-weights",
        choices=["calibrated", "information", "points"],
        default="calibrated",
        help="pose-graph edge weights: each registration's information (the inverse of its "
        "sandwich covariance from its own residuals) rescaled by a covariance model fitted to "
        "the graph's own loops (default), that information as stated, or the same point "
        "information on every edge (Algorithm 2's objective)",
    )
    p.add_argument("--seed", type=_seed, default=0, help="seed of the sensor noise / sampling")
    p.add_argument(
        "--capture-frames",
        type=_capture_frames,
        default=None,
        metavar="N",
        help="depth frames averaged per capture while the arm is still (each with its own "
        "sensor noise; a pixel is the mean of its valid frames, kept when valid in at least "
        "half); default: the scene's capture_frames, else 1 (the paper's single frame)",
    )
    g = p.add_argument_group("synth (with SCENE = synth)")
    g.add_argument("--task", choices=["1", "2"], default="1")
    g.add_argument("--size", default="320x240", help="WIDTHxHEIGHT")
    p.set_defaults(func=run)


def _capture_frames(text: str) -> int:
    """argparse type of ``--capture-frames``: an integer in [1, limits.MAX_CAPTURE_FRAMES]."""
    from jaxcr.limits import MAX_CAPTURE_FRAMES

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 1 <= value <= MAX_CAPTURE_FRAMES:
        raise argparse.ArgumentTypeError(f"must be between 1 and {MAX_CAPTURE_FRAMES}, got {value}")
    return value


def _parse_size(text: str) -> tuple[int, int]:
    from jaxcr.limits import parse_size

    # the floor (32x24) is the scene generator's (rgbd_tasks.generate_task), checked here too
    # so that a refused size never creates OUT (the audit's `--size 8x8` left an owned folder)
    return parse_size(text, "size", "model-object", min_size=(32, 24))


def run(args) -> int:
    if args.scene == "synth":
        from jaxcr.io import outdir
        from jaxcr.synth.rgbd_tasks import generate_task

        size = _parse_size(args.size)
        outdir.claim(args.out, "model-object synth")  # new, empty or an earlier scene; locked
        out = generate_task(args.out, args.task, args.seed, size)
        print(f"wrote task {args.task} scene to {out}")
        return 0
    from jaxcr.registration.pairwise import RegistrationFailed
    from jaxcr.registration.pipeline import PipelineConfig, build_model
    from jaxcr.synth.rgbd_tasks import RgbdSimulator

    sim = RgbdSimulator(args.scene, seed=args.seed, capture_frames=args.capture_frames)
    out = Path(args.out)
    from jaxcr.io import outdir

    # new, empty or an earlier model-object run, never another command's folder; locked
    outdir.claim(out, "model-object", recognise=lambda o: (o / "report.json").exists())
    # an earlier run's model and report must not outlive a rerun that fails or is stopped
    for stale in ("report.md", "report.json", "model.ply", "model_before.ply", "poses.csv", "poses.json",
                  "fig13.png", "plan.png", *(p.name for p in out.glob("partial_*.ply"))):  # fmt: skip
        (out / stale).unlink(missing_ok=True)
    cfg = PipelineConfig(
        asift=args.asift,
        association=args.association,
        global_method=args.global_opt,
        edge_weights=args.edge_weights,
    )
    from jaxcr.progress import progress as progress_bar

    # No total: a route ends at loop closure or when the planner stops, known only then;
    # cfg.max_steps per route is a bound, shown beside the count of views done.
    routes = [str(r["name"]) for r in sim.cfg["runs"]]
    bar = progress_bar(
        desc="model-object",
        unit="view",
        every=5,  # plain lines (redirected stderr): one per 5 views, and at least one a minute
        bar_format="{desc}: {n} views [{elapsed}]{postfix}",
    )

    def progress(log, cap):
        k = routes.index(log.name) + 1 if log.name in routes else 0
        bar.set_postfix_str(
            f"route {log.name} ({k}/{len(routes)}): view {len(log.captures)} registered "
            f"(at most {cfg.max_steps} per route)",
            refresh=False,  # drawn by update, with the new count
        )
        bar.update(1)

    t0 = time.perf_counter()
    try:
        result = build_model(sim, cfg, progress=progress, seed=args.seed)
    except RegistrationFailed as e:
        bar.close()
        print(f"jaxcr model-object: registration failed: {e}")
        R.atomic_write_text(out / "report.md", f"# model-object\n\nregistration failed: {e}\n")
        return 1
    # the callback is per view: the loop closure and global optimisation that follow the last
    # view are reported once they are done
    bar.set_postfix_str("registration done; evaluating")
    bar.refresh()
    bar.close()
    wall = time.perf_counter() - t0
    from jaxcr.registration.evaluation import evaluate_result

    ev = evaluate_result(sim, result, seed=args.seed)
    ev["wall_seconds"] = wall
    ev["capture_frames"] = sim.capture_frames
    write_outputs(out, sim, result, ev)
    print((out / "report.md").read_text())
    return 0 if result.global_result is not None else 1


def write_outputs(out: Path, sim, result, ev: dict) -> None:
    from jaxcr.io.ply import write_ply
    from jaxcr.registration.evaluation import model_cloud
    from jaxcr.registration.pipeline import chain, partial_model

    plot_plan(out / "plan.png", sim, result)
    g = result.global_result
    if g is not None:
        for name, poses in (("model.ply", g.poses), ("model_before.ply", g.initial)):
            c = model_cloud(result, poses, voxel=0.002)
            write_ply(out / name, c.points, c.colours, c.normals)
        plot_fig13(out / "fig13.png", ev)
        write_poses(out, sim, result, ev)
    else:
        for r in result.runs:  # partial models from forward registration only
            c = partial_model(r.captures, chain(r.pairs[: len(r.captures) - 1]), 0.002)
            write_ply(out / f"partial_{r.name}.ply", c.points, c.colours, c.normals)
    clean = json.loads(json.dumps(ev, default=_jsonable))
    # each file appears complete or not at all (temporary name, fsync, rename); report.md last
    R.atomic_write_text(out / "report.json", json.dumps(clean, indent=1))
    R.atomic_write_text(out / "report.md", report_markdown(sim, ev))


POSES_FORMAT = "jaxcr.model_poses/1"


def write_poses(out: Path, sim, result, ev: dict) -> None:
    """poses.json (every view's T_O,i before/after and true, 4x4) and poses.csv (errors per
    view, ring views and those left out of it); both atomic. See docs/rgbd-scene-format.md."""
    from jaxcr.registration.pipeline import _capture

    before, after = ev["views"]["before"], ev["views"]["after"]
    anchor = _capture(result.runs, result.ring[-1]).T_true

    def mat(T):
        return None if T is None else np.asarray(T, np.float64).round(9).tolist()

    def num(x, scale=1.0):
        return None if x is None or not np.isfinite(x) else float(scale * x)

    views = []
    for b, a in zip(before, after, strict=True):
        views.append(
            {
                "run": a["run"],
                "index": a["index"],
                "ring_position": a["ring_position"],
                "T_O_cam": mat(a["T"]),
                "T_O_cam_before": mat(b["T"]),
                "T_O_cam_true": mat(a["T_true"]),
                "rot_err_deg": num(a["rot_deg"]),
                "trans_err_mm": num(a["trans_m"], 1000.0),
                "rot_err_before_deg": num(b["rot_deg"]),
                "trans_err_before_mm": num(b["trans_m"], 1000.0),
            }
        )
    doc = {
        "format": POSES_FORMAT,
        "frame": "O = the camera frame (OpenCV: x right, y down, z forward; metres) of the "
        "last ring view; T_O_cam maps a point from view i's camera frame to frame O",
        "T_world_O_true": mat(anchor),
        "views": views,
    }
    last = result.ring[-1]
    doc["anchor"] = {"run": result.runs[last[0]].name, "index": last[1]}  # the view of frame O
    R.atomic_write_text(out / "poses.json", json.dumps(doc, indent=1))

    def f(x, fmt):
        return "" if x is None else format(x, fmt)

    rows = ["run,index,ring_position,rot_before_deg,trans_before_mm,rot_after_deg,trans_after_mm"]
    for v in views:
        rows.append(
            f"{v['run']},{v['index']},{f(v['ring_position'], 'd')},"
            f"{f(v['rot_err_before_deg'], '.5f')},{f(v['trans_err_before_mm'], '.4f')},"
            f"{f(v['rot_err_deg'], '.5f')},{f(v['trans_err_mm'], '.4f')}"
        )
    R.atomic_write_text(out / "poses.csv", "\n".join(rows) + "\n")


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return None  # raw per-point arrays stay out of the JSON
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(type(x))


def report_markdown(sim, ev: dict) -> str:
    lines = [f"# model-object: task {sim.cfg.get('task', '?')}", ""]
    n_frames = ev.get("capture_frames", 1)
    if n_frames != 1:  # never mixed silently with the paper's single-frame captures
        lines += [f"Depth frames averaged per capture: {n_frames} (the paper: 1).", ""]
    lines += [
        "| run | images | Delta-s (cm) | T_mp (ms) | T_mp per step, median / max (ms) "
        "| status | mean pair time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in ev["runs"]:
        pt = np.mean(r["pair_seconds"][1:]) if len(r["pair_seconds"]) > 1 else float("nan")
        steps = r.get("planning_step_ms") or []
        per = f"{np.median(steps):.1f} / {max(steps):.1f}" if steps else ""
        lines.append(
            f"| {r['name']} | {r['images']} | {100 * r['delta_s_m']:.0f} | "
            f"{r['planning_ms']:.0f} | {per} | {r['status']} | {pt:.2f} |"
        )
    lines.append("")
    for n in ev["notes"]:
        lines.append(f"- note: {n}")
    if "after" in ev:
        a2 = ev.get("alg2")
        final = "pose graph" if a2 is not None else "Alg. 2"
        lines += [
            "",
            "| | before (chained) | "
            + ("Alg. 2 | " if a2 is not None else "")
            + f"after ({final}) | true poses (reference) |",
            "|---|---|---|---|" + ("---|" if a2 is not None else ""),
        ]
        b, a = ev["before"], ev["after"]
        t = ev.get("truth", {})

        def pose_row(name, key, scale, fmt):
            mid = (scale * a2["pose"][key],) if a2 is not None else ()
            return (name, scale * b["pose"][key], *mid, scale * a["pose"][key], None, fmt)

        rows = [
            pose_row("max rotation error (deg)", "max_rot_deg", 1.0, "{:.3f}"),
            pose_row("max translation error (mm)", "max_trans_m", 1000.0, "{:.2f}"),
            pose_row("mean rotation error (deg)", "mean_rot_deg", 1.0, "{:.3f}"),
            pose_row("mean translation error (mm)", "mean_trans_m", 1000.0, "{:.2f}"),
        ]
        for name, key, fmt in (
            ("mean dist. to K=100 NN (mm), whole model", "knn_mean_mm", "{:.3f}"),
            ("mean #neighbours within 3 mm, whole model", "neigh3mm_mean", "{:.2f}"),
            ("mean dist. to K=100 NN (mm), loop seam overlap", "seam_knn_mean_mm", "{:.3f}"),
            (
                "mean #neighbours within 3 mm, loop seam overlap",
                "seam_neigh3mm_mean",
                "{:.2f}",
            ),
            ("model-to-truth mean (mm)", "surface_mean_mm", "{:.2f}"),
            ("model-to-truth 95th pct (mm)", "surface_p95_mm", "{:.2f}"),
        ):
            if key in b:
                mid = (a2[key],) if a2 is not None else ()
                rows.append((name, b[key], *mid, a[key], t.get(key), fmt))
        for name, *vals, z, fmt in rows:
            ref = "" if z is None else fmt.format(z)
            lines.append(f"| {name} | " + " | ".join(fmt.format(v) for v in vals) + f" | {ref} |")
        o = ev.get("outside_ring") or {}
        if o.get("views"):
            lines += [
                "",
                f"{o['views']} view(s) outside the ring (captured before the loop's closing "
                "view; pose-graph nodes with registrations to several ring views, or chained "
                "from the nearest ring view without a pose graph): worst "
                f"{o['max_rot_deg']:.3f} deg / {1000 * o['max_trans_m']:.2f} mm after global "
                "optimisation (poses.csv, poses.json).",
            ]
        gl = ev["global"]
        if gl.get("method") == "pose_graph":
            lines += [
                "",
                f"Algorithm 2: {gl['views']} views, {gl['alg2_refinements']} Align calls, "
                f"queue emptied {gl['alg2_converged']}, {gl['alg2_seconds']:.2f} s. Pose graph: "
                f"{gl['views']} ring edges + {gl['extra_edges']} extra registrations "
                f"({gl['extra_seconds']:.1f} s), {gl['refinements']} Gauss-Newton steps, "
                f"converged {gl['converged']}, {gl['seconds']:.2f} s (incl. compilation).",
            ]
        else:
            lines += [
                "",
                f"Global optimisation (Algorithm 2): {gl['views']} views, "
                f"{gl['refinements']} Align calls, converged {gl['converged']}, "
                f"{gl['seconds']:.2f} s.",
            ]
    if "wall_seconds" in ev:
        lines.append(f"Total wall time {ev['wall_seconds']:.1f} s.")
    return "\n".join(lines) + "\n"


def _save_figure(fig, path: Path, dpi: int) -> None:
    """PNG written atomically (rendered in memory, then temporary name + rename)."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    R.atomic_write_bytes(path, buf.getvalue())


def plot_plan(path: Path, sim, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    ob = sim.obstacles
    ax.scatter(ob[:, 0], ob[:, 1], s=1, c="0.75", label="obstacles (unknown)")
    colours = plt.cm.tab10.colors
    for k, r in enumerate(result.runs):
        if r.obstacles is not None and len(r.obstacles):
            ax.scatter(r.obstacles[:, 0], r.obstacles[:, 1], s=1, c="0.35")
        for c in r.captures:
            ax.plot(c.centreline[:, 0], c.centreline[:, 1], c=colours[k], lw=0.6, alpha=0.5)
            p, z = c.T_nominal[:3, 3], c.T_nominal[:3, 2]
            ax.arrow(p[0], p[1], 0.04 * z[0], 0.04 * z[1], width=0.002, color=colours[k])
        for j, a in enumerate(r.arcs):
            s = np.linspace(0, a.length, 50)
            from jaxcr.registration.arm import arc_points_np

            xy = arc_points_np(np.asarray(a.start), np.array([a.kappa]), s[None, :])[0]
            ax.plot(xy[:, 0], xy[:, 1], "--", c=colours[(k + j + 2) % 10], lw=1.5)
        ax.plot([], [], c=colours[k], label=f"run {r.name} ({len(r.captures)} views, {r.status})")
    th = np.linspace(0, 2 * np.pi, 200)
    o = sim.cfg["object"]
    if o["kind"] == "cylinder":
        ax.fill(o["radius"] * np.cos(th), o["radius"] * np.sin(th), c="tab:red", alpha=0.6)
    else:
        hx, hy = o["half"][:2]
        sq = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]) @ sim.R_obj[:2, :2].T
        ax.fill(sq[:, 0], sq[:, 1], c="tab:red", alpha=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("arm motion from above (dashed: planned arcs)")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    _save_figure(fig, path, dpi=120)


def plot_fig13(path: Path, ev: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(9, 3.5))
    for tag, c in (
        ("before", "tab:orange"),
        ("alg2", "tab:green"),
        ("after", "tab:blue"),
        ("truth", "0.5"),
    ):
        if tag not in ev:
            continue
        knn = 1000 * ev[tag]["_knn"]
        cnt = ev[tag]["_cnt"]
        label = {
            "truth": "true poses",
            "alg2": "Algorithm 2",
            "before": "before global opt.",
            "after": "after global opt.",
        }[tag]
        axs[0].hist(knn, bins=60, histtype="step", color=c, label=label)
        axs[1].hist(
            cnt, bins=np.arange(0, cnt.max() + 2) - 0.5, histtype="step", color=c, label=tag
        )
    axs[0].set_xlabel("mean distance to K = 100 nearest neighbours (mm)")
    axs[1].set_xlabel("number of neighbours within 3 mm")
    for a in axs:
        a.set_ylabel("points")
        a.legend(fontsize=8)
    fig.tight_layout()
    _save_figure(fig, path, dpi=110)
