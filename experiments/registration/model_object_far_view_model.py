"""Issue 17 item 10, tried and rejected: the first capture (0.59 m) registered to the fused
ring model instead of to single ring views.

Development seeds only. On the models recorded by ``model_object_outside_both.py --record
DIR`` (the pipeline before ``outside_far_mode="both"``), the first capture's pose from the
pose graph (``base``) is refined by registering it to the ring views merged in their
optimised poses (or, ``*_true``, their true poses: the far frame's own share of the error):

- ``fused``: the ring views' sample pixels (denoised positions) seen by the far camera
  (normals facing it, depth within 1 cm of its depth image) as the projective-ICP source,
  the far view's depth image as the target (point-to-plane, no keypoints, no colour);
- ``render``: the ring views' full-resolution points rendered into a virtual camera at the
  far view's pose (z-buffer; per pixel the mean of the points within 4 mm of the nearest:
  the near views' depth noise averaged) as the target, the far view's raw sample as the
  source (geometry only);
- ``render_chroma``: the same with the chromaticity term (source pixel colours read from
  the far image, no depth-noise parallax: the virtual camera sits at the far camera).

The first capture is a view outside the ring (pose-graph node) or the ring's first view;
for the latter the model leaves that view out.

    python experiments/registration/model_object_far_view_model.py --record /tmp/obj27/rec \
        --cases 1:0 1:1 1:2 1:3 1:4 1:5 1:6 1:7 1:8 1:9 --jsonl /tmp/obj27/fv.jsonl
    python experiments/registration/model_object_far_view_model.py --jsonl /tmp/obj27/fv.jsonl \
        --report-only

Writes experiments/results/registration/model_object_far_view_model.md (+ .json).
"""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from model_object_far_edge_factorial import _commit  # noqa: E402
from model_object_outside_both import case_args, read_records, recorded, truth  # noqa: E402

from jaxcr.registration.clouds import Cloud, pad_cloud  # noqa: E402
from jaxcr.registration.icp import DEFAULT_ICP, CloudArrays, no_keypoints  # noqa: E402
from jaxcr.registration.metrics import pose_error  # noqa: E402
from jaxcr.registration.pairwise import geometric_sample  # noqa: E402
from jaxcr.registration.pipeline import _capture  # noqa: E402
from jaxcr.registration.projective import depth_image, projective_icp_jit  # noqa: E402

OUT = Path(__file__).parent.parent / "results" / "registration"
VARIANTS = ("fused", "render", "render_chroma")


def _in_camera(P_cam, P_view, pts, nrm):
    T = np.linalg.inv(P_cam) @ P_view
    return pts @ T[:3, :3].T + T[:3, 3], nrm @ T[:3, :3].T


def _pixels(K, p, shape):
    h, w = shape
    z = np.where(p[:, 2] > 1e-3, p[:, 2], 1.0)
    iu = np.rint(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(int)
    iv = np.rint(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(int)
    ok = (p[:, 2] > 1e-3) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    return np.clip(iu, 0, w - 1), np.clip(iv, 0, h - 1), ok


def fused(res, K, poses, P0, frame, members, size=16384, seed=0):
    """``fused`` (module docstring): the far camera's pose in frame O."""
    dep = np.asarray(frame.image.points)[..., 2]
    msk = np.asarray(frame.image.mask)
    parts = []
    for j in members:
        fr = _capture(res.runs, res.ring[j]).frame
        m = np.asarray(fr.sample.mask)
        p = np.asarray(fr.sample_plane, np.float64)[m]
        n = np.asarray(fr.sample.normals, np.float64)[m]
        pf, nf = _in_camera(P0, poses[j], p, n)
        iu, iv, ok = _pixels(K, pf, msk.shape)
        facing = np.sum(nf * -pf, 1) / np.linalg.norm(pf, axis=1) > 0.2
        ok &= facing & msk[iv, iu] & (np.abs(dep[iv, iu] - pf[:, 2]) < 0.01)
        T = poses[j]
        parts.append(
            (
                p[ok] @ T[:3, :3].T + T[:3, 3],
                np.asarray(fr.sample.colours)[m][ok],
                n[ok] @ T[:3, :3].T,
            )
        )
    cloud = Cloud(*(np.concatenate([x[k] for x in parts]) for k in range(3)))
    src = CloudArrays(
        *(jnp.asarray(a) for a in pad_cloud(cloud, size, np.random.default_rng(seed)))
    )
    out = projective_icp_jit(
        src,
        frame.image,
        jnp.asarray(np.linalg.inv(P0), jnp.float32),
        DEFAULT_ICP,
        no_keypoints(),
        window=0,
    )
    return np.linalg.inv(np.asarray(out.T, np.float64))


def rendered(res, K, poses, P0, members, shape, band=0.004):
    """The ring views ``members`` rendered into a camera at ``P0`` (module docstring)."""
    h, w = shape
    pts, cols, nrms = [], [], []
    for j in members:
        img = _capture(res.runs, res.ring[j]).frame.image
        ok = np.asarray(img.mask)
        p, n = _in_camera(
            P0, poses[j], np.asarray(img.points, np.float64)[ok], np.asarray(img.normals)[ok]
        )
        pts.append(p)
        nrms.append(n)
        cols.append(np.asarray(img.colours, np.float64)[ok])
    p, c, n = (np.concatenate(x) for x in (pts, cols, nrms))
    iu, iv, ok = _pixels(K, p, shape)
    ok &= np.sum(n * -p, 1) > 0
    p, c, n, flat = p[ok], c[ok], n[ok], (iv * w + iu)[ok]
    zmin = np.full(h * w, np.inf)
    np.minimum.at(zmin, flat, p[:, 2])
    sel = p[:, 2] < zmin[flat] + band
    p, c, n, flat = p[sel], c[sel], n[sel], flat[sel]
    cnt = np.bincount(flat, minlength=h * w).astype(float)

    def mean(a):
        s = np.stack([np.bincount(flat, a[:, k], minlength=h * w) for k in range(3)], -1)
        return (s / np.maximum(cnt, 1)[:, None]).reshape(h, w, 3).astype(np.float32)

    N = mean(n)
    N /= np.maximum(np.linalg.norm(N, axis=-1, keepdims=True), 1e-12)
    return depth_image(mean(p), mean(c), N, (cnt > 0).reshape(h, w), K)


def render_register(res, K, poses, P0, frame, members, chroma: bool):
    tgt = rendered(res, K, poses, P0, members, np.asarray(frame.image.mask).shape)
    kw = {}
    if chroma:
        kw = dict(
            src_image=frame.image, photometric="chromaticity", photo_points=frame.sample_plane
        )
    out = projective_icp_jit(
        geometric_sample(frame, "raw"),
        tgt,
        jnp.eye(4, dtype=jnp.float32),
        DEFAULT_ICP,
        no_keypoints(),
        window=0,
        **kw,
    )
    return P0 @ np.asarray(out.T, np.float64)


def analyse(task: str, seed: int, res, K) -> list[dict]:
    m = len(res.ring)
    nodes = res.ring + res.outside
    true = truth(res, nodes)
    est = list(res.global_result.poses) + list(res.outside_poses)
    rows = []
    for n, key in enumerate(nodes):
        if key[1] != 0:
            continue
        frame = _capture(res.runs, key).frame
        members = [j for j in range(m) if j != n]
        d = np.asarray(frame.depth)
        row = {
            "task": task,
            "seed": seed,
            "view": list(key),
            "outside": n >= m,
            "depth_m": float(np.median(d[d > 0])),
        }

        def err(P, n=n):
            return 1000 * pose_error(P, true[n])[1]

        row["base"] = err(est[n])
        for label, poses in (("", list(res.global_result.poses)), ("_true", true[:m])):
            row["fused" + label] = err(fused(res, K, poses, est[n], frame, members, seed=seed))
            for v, chroma in (("render", False), ("render_chroma", True)):
                row[v + label] = err(render_register(res, K, poses, est[n], frame, members, chroma))
        rows.append(row)
    return rows


def report(recs, out: Path, cmd: str) -> None:
    commit = _commit()
    md = [
        "# The first capture registered to the fused ring model (issue 17 item 10; rejected)",
        "",
        f"commit {commit} (script), development seeds only; command: `{cmd}`. Position error "
        "(mm) of the first capture against the truth, frame O.",
        "",
        "| first capture | n | base | "
        + " | ".join(f"{v} / {v} (true ring)" for v in VARIANTS)
        + " |",
        "|---|---|---|" + "---|" * len(VARIANTS),
    ]
    groups = [
        (f"task {t}, {'outside the ring' if o else 'ring view'}", t, o)
        for t in sorted({r["task"] for r in recs})
        for o in (True, False)
    ]
    for lab, t, o in groups:
        rows = [r for r in recs if r["task"] == t and r["outside"] == o]
        if not rows:
            continue

        def s(k, rows=rows):
            v = np.array([r[k] for r in rows])
            return f"{v.mean():.2f} (max {v.max():.2f})"

        md.append(
            f"| {lab} | {len(rows)} | {s('base')} | "
            + " | ".join(f"{s(v)} / {s(v + '_true')}" for v in VARIANTS)
            + " |"
        )
    md += ["", "Per view (mm): task, seed, view, base, " + ", ".join(VARIANTS) + ":", ""]
    for r in sorted(recs, key=lambda r: (r["task"], r["seed"], r["view"])):
        md.append(
            f"- {r['task']} {r['seed']} {tuple(r['view'])}{' outside' if r['outside'] else ''}: "
            f"{r['base']:.2f}, " + ", ".join(f"{r[v]:.2f}" for v in VARIANTS)
        )
    out.mkdir(parents=True, exist_ok=True)
    (out / "model_object_far_view_model.md").write_text("\n".join(md) + "\n")
    (out / "model_object_far_view_model.json").write_text(
        json.dumps({"command": cmd, "commit": commit, "records": recs}, indent=1)
    )
    print("\n".join(md))


def main() -> None:
    a = case_args(OUT)
    jl = Path(a.jsonl)
    if not a.report_only:
        for case in a.cases:
            task, seed = case.split(":")
            res, K = recorded(task, int(seed), Path(a.record))
            rows = analyse(task, int(seed), copy.copy(res), K)
            with open(jl, "a") as fh:
                fh.write("".join(json.dumps(r) + "\n" for r in rows))
            print(f"{case}: {len(rows)} first captures", flush=True)
        return
    recs = read_records(jl)
    cmd = (
        "python experiments/registration/model_object_far_view_model.py --record REC --cases "
        "1:0 ... 1:9 --jsonl J (two processes), then --jsonl J --report-only"
    )
    report(recs, Path(a.out), cmd)


if __name__ == "__main__":
    main()
