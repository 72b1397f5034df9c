"""Label leakage of the tracked superpixels (M-L step 1) against the ground-truth masks.

  python experiments/motion/motion_label_leakage.py --data /tmp/motion_data [--out FILE.md]
      [--variants before,now]

M-L paints each segment's integrated probability onto the evaluation frame's label map, so a
segment id must cover the same physical surface in every frame whose flow it integrates. This
script runs :class:`jaxcr.motion.pipeline.MotionTracker` over every video, keeps the label map
of every frame and compares it with the ground-truth object masks. With r the evaluation frame
(pushed set: the first touch frame) and O the *object ids* (segments with at least half of their
area on the object at r):

* leak(t): fraction of the area carrying an object id at frame t that is background in the
  ground truth (object segments spilling onto the table),
* capture(t): fraction of the ground-truth object area at frame t that carries a non-object id
  (background segments captured by the pushed object),
* flip: area-weighted fraction of segments whose majority (object / background) at frame t
  differs from that at r, averaged over the touching frames.

Per video the mean over the frames before the touch, the last frame, and the per-frame curve
after the touch are reported, with the Tanimoto distance of the M-L translation map at the
fixed thresholds 0.75 and 0.85 of the maximum and its AP, so label quality and the final
scores can be read side by side. Runs on one core.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxcr.io.motion_dataset import load_motion_dataset  # noqa: E402
from jaxcr.motion.pipeline import MotionConfig, MotionTracker  # noqa: E402
from jaxcr.motion.propagate import warp_labels  # noqa: E402
from jaxcr.motion.run import end_effector_pixels, first_touch  # noqa: E402


def leakage_curves(
    labels: list[np.ndarray], masks: list[np.ndarray], ref: int, n_segments: int
) -> dict[str, np.ndarray]:
    """leak(t), capture(t) and flip(t) (see the module docstring) for label maps ``labels``
    and boolean ground-truth masks ``masks`` of the same frames, reference frame ``ref``."""

    def obj_fraction(lbl, m):
        area = np.bincount(lbl.ravel(), minlength=n_segments).astype(float)
        on = np.bincount(lbl.ravel(), weights=m.ravel().astype(float), minlength=n_segments)
        return on / np.maximum(area, 1.0), area

    f_ref, a_ref = obj_fraction(labels[ref], masks[ref])
    obj_ids = (f_ref >= 0.5) & (a_ref > 0)
    leak, capture, flip = [], [], []
    for lbl, m in zip(labels, masks, strict=True):
        is_obj = obj_ids[lbl]
        leak.append(float((is_obj & ~m).sum()) / max(float(is_obj.sum()), 1.0))
        capture.append(float((~is_obj & m).sum()) / max(float(m.sum()), 1.0))
        f, a = obj_fraction(lbl, m)
        present = (a > 0) & (a_ref > 0)
        changed = present & ((f >= 0.5) != obj_ids)
        flip.append(float(a[changed].sum()) / max(float(a[present].sum()), 1.0))
    return {"leak": np.array(leak), "capture": np.array(capture), "flip": np.array(flip)}


def track_video(d: Path, cfg: MotionConfig) -> dict:
    """Run M-L on one video, keeping every frame's label map; returns labels, masks, the
    translation map on the evaluation frame and the median segmentation time (ms)."""
    ds = load_motion_dataset(d)
    uv, vis = end_effector_pixels(ds)
    tracker, labels, seg_ms = None, [], []
    for i, rgb, _ in ds.frames():
        if tracker is None:
            tracker = MotionTracker(cfg, rgb)
        else:
            rec = tracker.step(i, rgb, uv[i - 1], uv[i], bool(ds.touch[i]), vis[i - 1], vis[i])
            seg_ms.append(rec.segmentation_ms)
        labels.append(np.asarray(tracker.labels))
    ev = ds.eval_frame if ds.eval_frame is not None else first_touch(ds)
    sp = tracker.segment_probability("translation")
    sph = tracker.segment_probability("homography")
    return {
        "labels": labels,
        "masks": [ds.mask(i) for i in range(len(ds))],
        "eval": ev,
        "touch": first_touch(ds),
        "n_segments": tracker.n_segments,
        "map": sp[labels[ev]],
        "map_h": sph[labels[ev]],
        "scene": ds.scene,
        "seg_ms": float(np.median(seg_ms[2:])),
    }


def tanimoto(a: np.ndarray, b: np.ndarray) -> float:
    return 1.0 - float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def average_precision(score: np.ndarray, gt: np.ndarray) -> float:
    """Area under the P-R curve over thresholds 0.05..1.0 of the map maximum (as
    motion_experiments.ap_of)."""
    s = score / max(float(score.max()), 1e-12)
    ps, rs = [], []
    for th in np.round(np.linspace(0.05, 1.0, 20), 3):
        m = s >= th
        tp = float((m & gt).sum())
        ps.append(tp / max(float(m.sum()), 1.0) if m.any() else 1.0)
        rs.append(tp / max(float(gt.sum()), 1.0))
    ps, rs = np.array(ps), np.array(rs)
    return float(np.sum(np.diff(np.concatenate([[0.0], rs[::-1]])) * ps[::-1]))


def summarise(rec: dict) -> dict:
    c = leakage_curves(rec["labels"], rec["masks"], rec["eval"], rec["n_segments"])
    t0 = rec["touch"]
    gt = rec["masks"][rec["eval"]]
    s = rec["map"] / max(float(rec["map"].max()), 1e-12)
    return {
        "leak_pre": float(c["leak"][:t0].mean()),
        "leak_last": float(c["leak"][-1]),
        "leak_touch_mean": float(c["leak"][t0:].mean()),
        "capture_touch_mean": float(c["capture"][t0:].mean()),
        "capture_last": float(c["capture"][-1]),
        "flip_touch_mean": float(c["flip"][t0:].mean()),
        "leak_curve": c["leak"][t0:],
        "capture_curve": c["capture"][t0:],
        "tan75": tanimoto(s >= 0.75, gt),
        "tan85": tanimoto(s >= 0.85, gt),
        "ap": average_precision(rec["map"], gt),
        "ap_h": average_precision(rec["map_h"], gt),
        "seg_ms": rec["seg_ms"],
    }


KEYS = [
    "leak_pre",
    "leak_touch_mean",
    "leak_last",
    "capture_touch_mean",
    "capture_last",
    "flip_touch_mean",
    "tan75",
    "tan85",
    "ap",
    "ap_h",
    "seg_ms",
]
GROUPS = ("pushed_static", "pushed_changing", "held_static", "held_changing")


@jax.jit
def scatter_order_splat(labels, flow):
    """The splat before the layering fix (commit ef2091b), for the "before" variants: the
    scatter's write order decides collisions, holes take the first labelled neighbour 1, 2,
    2, 3 px right/left/down/up, then the backward lookup."""
    h, w = labels.shape
    yy, xx = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    dx = jnp.round(xx + flow[..., 0]).astype(jnp.int32)
    dy = jnp.round(yy + flow[..., 1]).astype(jnp.int32)
    inside = (dx >= 0) & (dx < w) & (dy >= 0) & (dy < h)
    flat = jnp.where(inside, dy * w + dx, h * w)
    out = (
        jnp.full((h + 1) * w, -1, jnp.int32)
        .at[flat.reshape(-1)]
        .set(labels.astype(jnp.int32).reshape(-1), mode="promise_in_bounds")
    )
    out = out[: h * w].reshape(h, w)
    for d in (1, 2, 2, 3):
        padded = jnp.pad(out, d, mode="edge")
        for oy, ox in ((0, d), (0, -d), (d, 0), (-d, 0)):
            nb = padded[d + oy : d + oy + h, d + ox : d + ox + w]
            out = jnp.where((out < 0) & (nb >= 0), nb, out)
    return jnp.where(out >= 0, out, warp_labels(labels, flow))


VARIANTS = {
    # name: (scatter-order splat, grid-step candidates)
    "before": (True, True),
    "reach_only": (True, False),
    "now": (False, False),
}


def run_variant(vids: list[Path], variant: str) -> dict:
    """Per-video summaries with the tracking of ``variant`` (:data:`VARIANTS`): "now" is the
    package; "before" the splat and refinement before the leakage fix (scatter-order splat,
    candidates at the grid step); "reach_only" the local candidates with the old splat."""
    import jaxcr.motion.superpixels as sp

    old_splat, old_reach = VARIANTS[variant]
    original = sp.track_reach, sp.splat_labels
    if old_reach:
        sp.track_reach = lambda step: step  # read when segment_track is traced
    if old_splat:
        sp.splat_labels = scatter_order_splat
    sp.segment_track.clear_cache()
    try:
        rows = {}
        for d in vids:
            t = time.time()
            rows[d.name] = summarise(track_video(d, MotionConfig()))
            r = rows[d.name]
            print(
                f"[{variant}] {d.name}: leak touch {r['leak_touch_mean']:.3f} last "
                f"{r['leak_last']:.3f} | capture touch {r['capture_touch_mean']:.3f} | tan85 "
                f"{r['tan85']:.3f} AP {r['ap']:.3f} ({time.time() - t:.1f} s)",
                flush=True,
            )
        return rows
    finally:
        sp.track_reach, sp.splat_labels = original
        sp.segment_track.clear_cache()


def table(rows: dict) -> list[str]:
    L = ["| group | n | " + " | ".join(KEYS) + " |", "|---|---|" + "---|" * len(KEYS)]
    for g in GROUPS:
        ks = [k for k in rows if k.startswith(g)]
        if ks:
            L.append(
                f"| {g} | {len(ks)} | "
                + " | ".join(f"{np.mean([rows[k][key] for k in ks]):.3f}" for key in KEYS)
                + " |"
            )
    return L


def bench(data: str, repeats: int = 5) -> list[str]:
    """Time (ms) of one tracking step at 640x480 (superpixels at working scale 2, i.e. a
    320x240 working frame, step 20 working px, 2 refinement iterations: the defaults at that
    size) for each variant, interleaved frame by frame so that the machine's load hits all
    variants alike, on the frames and LK flows of one pushed video (its 320x240 frames stand
    in for the working frames). Median, IQR and minimum over ``repeats`` passes."""
    import functools

    import jaxcr.motion.superpixels as sp
    from jaxcr.colour import rgb_to_lab
    from jaxcr.motion import flow as fm
    from jaxcr.motion.propagate import splat_labels

    d = sorted(p for p in Path(data).iterdir() if p.name.startswith("pushed_changing"))[0]
    frames = [f for _, f, _ in load_motion_dataset(d).frames()][:12]
    h, w = frames[0].shape[:2]
    k = int(np.prod(sp.grid_shape(h, w, 20)))
    flows = []
    for a, b in zip(frames[:-1], frames[1:], strict=True):
        pts, fl, va = fm.grid_flow(fm.to_gray_u8(a), fm.to_gray_u8(b))
        flows.append(jnp.asarray(fm.dense_from_grid(fl, va, h, w, 4, 1)))
    rgbs = [jnp.asarray(f) for f in frames]
    lbl0, _ = sp.segment_first(rgbs[0], k, 20, 10.0, 6, 2, 2 * h, 2 * w)

    def track(splat, reach, lbl, fl, rgb):  # segment_track with the variant's parts
        new = sp.slic(rgb_to_lab(rgb), splat(lbl, fl), k, 20, 10.0, 2, reach)
        return new, sp.upsample_labels(new, 2 * h, 2 * w, 2)

    fns = {
        name: jax.jit(
            functools.partial(
                track,
                scatter_order_splat if old_splat else splat_labels,
                20 if old_reach else sp.track_reach(20),
            )
        )
        for name, (old_splat, old_reach) in VARIANTS.items()
    }
    fns["package segment_track"] = functools.partial(
        sp.segment_track,
        n_segments=k,
        step=20,
        compactness=10.0,
        n_iter=2,
        scale=2,
        height=2 * h,
        width=2 * w,
    )
    times = {name: [] for name in fns}
    for rep in range(repeats + 1):
        lbls = dict.fromkeys(fns, lbl0)
        for fl, rgb in zip(flows, rgbs[1:], strict=True):
            for name, f in fns.items():
                t = time.perf_counter()
                lbls[name], full = f(lbls[name], fl, rgb)
                full.block_until_ready()
                if rep:  # the first pass compiles
                    times[name].append(1e3 * (time.perf_counter() - t))
    out = []
    for name, ts in times.items():
        q = np.percentile(ts, [25, 50, 75])
        out.append(
            f"| {name} | {q[1]:.1f} | {q[0]:.1f}-{q[2]:.1f} | {np.min(ts):.1f} | {len(ts)} |"
        )
        print(out[-1], flush=True)
    return [
        f"Tracking step (splat + 2 refinement iterations + upsampling) at 640x480 (working "
        f"320x240), variants interleaved, load {os.getloadavg()[0]:.1f}; "
        "`python experiments/motion/motion_label_leakage.py --bench-only`:",
        "",
        "| variant | median ms | IQR ms | min ms | steps |",
        "|---|---|---|---|---|",
        *out,
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/tmp/motion_data")
    ap.add_argument("--out", default="", help="Markdown report (default: print only)")
    ap.add_argument("--only", default="", help="substring filter on the video names")
    ap.add_argument(
        "--variants", default="before,reach_only,now", help="comma-separated keys of VARIANTS"
    )
    ap.add_argument("--bench-only", action="store_true", help="only time the tracking step")
    a = ap.parse_args()
    if a.bench_only:
        print("\n".join(bench(a.data)))
        return
    vids = sorted(
        p for p in Path(a.data).iterdir() if (p / "motion.json").exists() and a.only in p.name
    )
    results = {v: run_variant(vids, v) for v in a.variants.split(",")}
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    L = [
        "# Label leakage of the tracked superpixels (M-L step 1)",
        "",
        f"commit {commit} (+ working tree), {len(vids)} videos of `{a.data}`, one core, "
        f"load {os.getloadavg()[0]:.1f}. Reproduce: `python experiments/motion/motion_label_leakage.py "
        f"--data {a.data} --out experiments/results/motion/motion_label_leakage.md` (~6 min).",
        "",
        "Definitions (module docstring of experiments/motion/motion_label_leakage.py): r = evaluation "
        "frame (pushed: first touch), object ids = segments >= 50 % on the object at r. "
        "leak = fraction of the object ids' area on the background; capture = fraction of the "
        "object's area under non-object ids; flip = area fraction of segments whose majority "
        "side changed since r. *_pre: mean over the frames before the touch, *_touch_mean: "
        "over the touching frames, *_last: the last frame. tan75/tan85: Tanimoto distance of "
        "the M-L translation map thresholded at 0.75/0.85 of its maximum; ap: area under its "
        "P-R curve (lambda 5 px^2, the package default); ap_h: the same for the homography map; seg_ms: median segmentation time per frame (320x240).",
        "",
        "Variants: *before* = the tracking before the fix (splat collisions decided by the "
        "scatter's write order, holes filled right/left/down/up first; refinement candidates "
        "at the grid step, 20 px); *reach_only* = the old splat with the refinement "
        "candidates 3 px apart (jaxcr.motion.superpixels.track_reach); *now* = the package "
        "(plus the layered splat of jaxcr.motion.propagate).",
    ]
    for v, rows in results.items():
        L += ["", f"## {v}", ""] + table(rows)
    L += ["", "## Speed", ""] + bench(a.data)
    last = list(results)[-1]
    L += [
        "",
        f"## Per video ({last}), leak after the touch per frame",
        "",
        "| video | " + " | ".join(KEYS) + " | leak per frame from the touch |",
        "|---|" + "---|" * (len(KEYS) + 1),
    ]
    for k, r in results[last].items():
        curve = " ".join(f"{x:.2f}" for x in r["leak_curve"])
        L.append(f"| {k} | " + " | ".join(f"{r[key]:.3f}" for key in KEYS) + f" | {curve} |")
    if len(results) > 1:
        first = list(results)[0]
        L += [
            "",
            f"## Per video ({first}), leak after the touch per frame",
            "",
            "| video | leak_touch_mean | capture_touch_mean | tan85 | ap | leak per frame |",
            "|---|---|---|---|---|---|",
        ]
        for k, r in results[first].items():
            curve = " ".join(f"{x:.2f}" for x in r["leak_curve"])
            L.append(
                f"| {k} | {r['leak_touch_mean']:.3f} | {r['capture_touch_mean']:.3f} | "
                f"{r['tan85']:.3f} | {r['ap']:.3f} | {curve} |"
            )
    print("\n".join(L))
    if a.out:
        Path(a.out).write_text("\n".join(L) + "\n")


if __name__ == "__main__":
    main()
