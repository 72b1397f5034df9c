"""``jaxcr manifold``: eigen-feature pose estimation of a single-segment robot from stereo
pairs (Reiter et al.).

    jaxcr manifold train DATASET -o MODEL.npz [--bins 120 --variance 0.9 --params angles]
    jaxcr manifold query MODEL.npz DATASET -o OUTDIR
    jaxcr manifold synth -o DIR --frames N --split train|test [--occluded --size 512x384]

``train`` clusters the first frame's colours (k-means in CIELAB a*b*), extracts the stereo
angular-histogram descriptors of every frame, keeps the PCA components for the variance
fraction, fits the thin-plate spline manifold and resamples it; the model file is
versioned (``jaxcr.manifold/2``). ``query`` estimates psi = (theta_L, delta) (or the tip
position) of every frame and, where the dataset has the truth, the errors; frames without
marker pixels in a view are reported as failed. Both exit with code 1 when some frames
failed (train still writes the model from the others and lists them on stderr and in the
model's metadata).

``query`` under ``--shard I/N`` / ``--executor ray`` (docs/scale-out.md): one record per frame
in ``OUT/results.jsonl`` (or ``OUT/shards/I-of-N/``), appended as chunks of ``--chunk`` frames
complete; a rerun with the same model and dataset skips recorded frames; ``estimates.csv``,
``estimates.jsonl`` and ``summary.json``/``.md`` are written from the records once every frame
has one (the same files as an unsharded local run).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from jaxcr.cli._common import seed as _seed
from jaxcr.errors import InputError

#: frames per task of ``manifold query`` (descriptors and one batched k-NN query per chunk)
QUERY_CHUNK = 64


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "manifold",
        help="eigen-feature manifold pose estimation (Reiter et al.): train, query, synth",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="manifold_command", metavar="ACTION")

    t = sub.add_parser("train", help="train a manifold model from a stereo dataset")
    t.add_argument("dataset", help="training dataset (folder or dataset.json)")
    t.add_argument("-o", "--out", required=True, help="model file to write (.npz)")
    t.add_argument("--bins", type=int, default=120, help="histogram bins per image (default 120)")
    t.add_argument(
        "--variance", type=float, default=0.90, help="PCA variance fraction (default 0.90)"
    )
    t.add_argument(
        "--smoothing", type=float, default=1e-4, help="thin-plate smoothing lambda (default 1e-4)"
    )
    t.add_argument(
        "--step",
        type=float,
        default=None,
        help="resampling step (rad or m; default 0.5 deg / 0.5 mm)",
    )
    t.add_argument(
        "--params", choices=["angles", "position"], default="angles", help="manifold parameters"
    )
    t.add_argument(
        "--neighbours",
        type=int,
        default=3,
        help="b nearest manifold points in the query (default 3)",
    )
    t.add_argument(
        "--centre",
        choices=["fixed", "region"],
        default="fixed",
        help="histogram centre: 'fixed' = one point per view, the mean training region "
        "centroid (robust to partial occlusion; default), 'region' = each frame's region "
        "centroid (the paper)",
    )
    t.add_argument("--clusters", type=int, default=5, help="k-means colour clusters (default 5)")
    t.add_argument(
        "--colour-frame",
        type=int,
        default=None,
        help="index of the frame clustered for colours (default: the first frame whose image "
        "can be read)",
    )
    g = t.add_mutually_exclusive_group()
    g.add_argument(
        "--marker-rgb", default="0.55,0.85,0.12", help="marker reference colour r,g,b in [0,1]"
    )
    g.add_argument(
        "--marker-index", type=int, default=None, help="marker cluster index instead of a colour"
    )
    t.add_argument("--cameras", default="left,right", help="the two views, left first")
    t.add_argument("--seed", type=_seed, default=0, help="seed of the colour clustering")
    t.set_defaults(func=run_train)

    q = sub.add_parser("query", help="estimate every frame of a dataset with a model")
    q.add_argument("model", help="model file from 'jaxcr manifold train'")
    q.add_argument("dataset", help="dataset to estimate (folder or dataset.json)")
    q.add_argument(
        "-o", "--out", required=True, help="output folder (estimates.csv/.jsonl, summary.json/.md)"
    )
    from jaxcr.scale.executor import add_executor_arguments
    from jaxcr.scale.shards import add_shard_argument

    add_shard_argument(q)
    add_executor_arguments(q, f"{QUERY_CHUNK} frames")
    q.set_defaults(func=run_query)

    s = sub.add_parser("synth", help="generate an IREP stereo dataset (jaxcr.synth.irep)")
    s.add_argument("-o", "--out", required=True, help="output dataset folder")
    s.add_argument("--frames", type=int, default=100, help="number of frames")
    s.add_argument("--split", choices=["train", "test"], default="train", help="random stream")
    s.add_argument("--size", default="1024x768", help="image size WIDTHxHEIGHT (default 1024x768)")
    s.add_argument("--occluded", action="store_true", help="add a laparoscopic instrument")
    s.add_argument("--seed", type=_seed, default=0)
    s.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    s.set_defaults(func=run_synth)
    # no ACTION is bad usage: one line and "see --help", as every other command (issue 17 item
    # 6; the audit, experiments/contract_audit.py, found the whole help on stdout, exit 2)
    p.set_defaults(func=lambda a: p.error("the following arguments are required: ACTION"))


def _load(path):
    from jaxcr.io.dataset import load_dataset

    return load_dataset(path)


def _params(ds, kind: str, frames) -> np.ndarray:
    if kind == "angles":
        if ds.robot_dict.get("kind") != "single_segment":
            raise InputError(
                "angle manifolds need a single_segment robot (q = theta_L, delta)",
                file=str(ds.root),
                field="robot.kind",
            )
        return np.array([f.q for f in frames], np.float64)
    out = []
    for f in frames:
        tip = f.truth.get("tip")
        if tip is None or np.shape(tip) != (3,):
            raise InputError(
                "position manifolds need truth.tip = [x, y, z] in every frame",
                file=str(ds.root),
                frame=f.id,
                field="truth.tip",
            )
        out.append(tip)
    return np.asarray(out, np.float64)


def _cameras(text: str) -> tuple[str, str]:
    cams = tuple(c.strip() for c in text.split(",") if c.strip())
    if len(cams) != 2:
        raise InputError(f"need exactly two cameras, got {text!r}", field="cameras")
    return cams  # type: ignore[return-value]


def _check_grid_early(ds, cfg) -> None:
    """The --step and --neighbours ceilings before any image is read: the grid over the box
    of every frame's parameters (a superset of the frames training keeps, so never laxer than
    the checks after training, which still run) bounds the manifold's points. A frame without
    parameters is left to the later checks' own errors."""
    from jaxcr.eigen.manifold import check_grid
    from jaxcr.eigen.model import DEFAULT_STEP

    try:
        P = _params(ds, cfg.params, ds.frames)
    except InputError:
        return
    if len(P):
        n_grid = check_grid(P, DEFAULT_STEP[cfg.params] if cfg.step is None else cfg.step)
        if cfg.b > n_grid:  # the resampled manifold keeps at most the grid's points
            raise InputError(
                f"must be at most the manifold's points (at most {int(n_grid)}: the --step "
                f"grid over the training parameters), got {cfg.b}",
                field="neighbours",
            )


def run_train(args) -> int:
    from jaxcr.eigen.colour import fit_colour_model
    from jaxcr.eigen.model import TrainConfig, train
    from jaxcr.eigen.pipeline import (
        check_cameras,
        dataset_contours,
        stereo_histograms,
        view_centres,
    )
    from jaxcr.io.eigen_model import save_model

    cams = _cameras(args.cameras)
    cfg = TrainConfig(
        n_bins=args.bins,
        variance=args.variance,
        smoothing=args.smoothing,
        step=args.step,
        b=args.neighbours,
        params=args.params,
        centre=args.centre,
        cameras=cams,
    )
    cfg.check()
    ds = _load(args.dataset)
    check_cameras(ds, cams)
    if not ds.frames:
        raise InputError("dataset has no usable frames", file=args.dataset)
    if args.colour_frame is not None and not 0 <= args.colour_frame < len(ds.frames):
        raise InputError(f"colour frame must be in 0..{len(ds.frames) - 1}", field="colour-frame")
    marker_rgb = None
    if args.marker_index is None:
        try:
            marker_rgb = tuple(float(x) for x in args.marker_rgb.split(","))
            assert len(marker_rgb) == 3 and all(0 <= v <= 1 for v in marker_rgb)  # not NaN
        except (ValueError, AssertionError):
            raise InputError(
                f"marker colour must be r,g,b in [0, 1], got {args.marker_rgb!r}",
                field="marker-rgb",
            ) from None
    _check_grid_early(ds, cfg)
    from jaxcr.cli._common import check_writable_folder

    # the model's folder before the descriptors (the audit, item 6: a read-only folder failed
    # only at the end, after every frame's contours)
    check_writable_folder(os.path.dirname(os.path.abspath(args.out)), "model folder")
    t0 = time.perf_counter()
    colour = fit_colour_model(
        _colour_image(ds, args.colour_frame, cams[0]),
        k=args.clusters,
        marker_rgb=marker_rgb,
        marker_index=args.marker_index,
        seed=args.seed,
    )
    sc = dataset_contours(ds, colour, cams, cfg.spacing)
    by_id = {f.id: f for f in ds.frames}
    P = _params(ds, cfg.params, [by_id[i] for i in sc.ids])
    ok = sc.ok
    if ok.sum() < 10:
        raise InputError(
            f"only {int(ok.sum())} frames have marker pixels in both views; check the colour model",
            file=args.dataset,
        )
    centres = view_centres(sc) if cfg.centre == "fixed" else None
    H, ok = stereo_histograms(sc, cfg.n_bins, cfg.normalise, centres)
    t1 = time.perf_counter()
    model = train(H[ok], P[ok], colour, cfg, view_centres=centres)
    n_points = int(model.manifold.psi.shape[0])
    if cfg.b > n_points:  # query would refuse the model: never write it
        raise InputError(
            f"must be at most the manifold's {n_points} points, got {cfg.b}", field="neighbours"
        )
    t2 = time.perf_counter()
    meta = {
        "dataset": str(Path(args.dataset).resolve()),
        "frames_used": int(ok.sum()),
        "frames_failed": [i for i, o in zip(sc.ids, ok, strict=True) if not o],
        "frames_bad": dict(ds.bad_frames),  # rejected by the dataset loader
        "frames_unreadable": dict(sc.unreadable),  # an image could not be read
        "descriptor_s": t1 - t0,
        "train_s": t2 - t1,
    }
    save_model(model, args.out, meta=meta)
    if ds.bad_frames:
        shown = "; ".join(list(ds.bad_frames.values())[:3])
        more = f" (and {len(ds.bad_frames) - 3} more)" if len(ds.bad_frames) > 3 else ""
        print(
            f"jaxcr manifold: warning: {len(ds.bad_frames)} bad frame(s) not used: {shown}{more}",
            file=sys.stderr,
        )
    if sc.unreadable:
        fid, why = next(iter(sc.unreadable.items()))
        more = f" (and {len(sc.unreadable) - 1} more)" if len(sc.unreadable) > 1 else ""
        print(
            f"jaxcr manifold: warning: {len(sc.unreadable)} frame(s) not used, an image could "
            f"not be read: {why}{more}; all listed in the model's metadata (frames_unreadable)",
            file=sys.stderr,
        )
    if meta["frames_failed"]:
        ids = meta["frames_failed"]
        shown = ", ".join(map(str, ids[:10])) + (
            f" and {len(ids) - 10} more" if len(ids) > 10 else ""
        )
        print(
            f"jaxcr manifold: warning: {len(ids)} frame(s) not used: too few marker pixels in a "
            f"view ({shown})",
            file=sys.stderr,
        )
    print(
        f"manifold: {int(ok.sum())}/{len(ok) + len(ds.bad_frames) + len(sc.unreadable)} frames, "
        f"{cfg.n_bins} bins, "
        f"{model.n_components} components "
        f"({cfg.variance:.0%} variance), {model.manifold.psi.shape[0]} manifold points; "
        f"descriptors {t1 - t0:.1f} s, training {t2 - t1:.2f} s -> {args.out}"
    )
    # the model is written, but frames of the training set failed (listed above and in the
    # model's metadata): exit 1, as every batch command with failed frames
    return 1 if ds.bad_frames or meta["frames_failed"] or sc.unreadable else 0


def _colour_image(ds, index: int | None, camera: str) -> np.ndarray:
    """The image clustered for the colour model: frame ``index`` (--colour-frame; bad input
    when it cannot be read), else the first frame whose ``camera`` image reads."""
    if index is not None:
        try:
            return ds.frames[index].load_image(camera)
        except InputError as err:
            raise InputError(f"the colour frame cannot be read ({err.format()})",
                             field="colour-frame") from None  # fmt: skip
    first = None
    for f in ds.frames:
        try:
            return f.load_image(camera)
        except InputError as err:
            first = first or err.format()
    raise InputError(f"no frame's image can be read ({first})", file=str(ds.root))


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


QUERY_FORMAT = "jaxcr.manifold-query-frame/1"
#: keys of a results.jsonl record that estimates.jsonl leaves out (bookkeeping and timings)
_INTERNAL = ("format", "stage", "descriptor_s", "query_s")


class QueryWorker:
    """Estimates chunks of a dataset's frames with a model: one record per frame (the worker of
    :func:`jaxcr.scale.executor.run_frames`; nothing is written but the records)."""

    def __init__(self, model_path: str, dataset: str):
        from jaxcr.eigen.pipeline import check_cameras
        from jaxcr.io.eigen_model import load_model

        self.model = load_model(model_path)
        self.ds = _load(dataset)
        check_cameras(self.ds, self.model.config.cameras)
        self.by_id = {f.id: f for f in self.ds.frames}
        # errors are reported for every frame or none: all loaded frames need the truth
        try:
            truth = _params(self.ds, self.model.config.params, self.ds.frames)
            self.truth = {f.id: t for f, t in zip(self.ds.frames, truth, strict=True)}
        except InputError:
            self.truth = None
        self.compile_s = self.run_s = 0.0

    @property
    def items(self) -> list[str]:
        """Every frame id of the job: the loaded frames in order, then the loader's bad ones."""
        return [f.id for f in self.ds.frames] + list(self.ds.bad_frames)

    def failed_record(self, fid: str, reason: str) -> dict:
        return {"format": QUERY_FORMAT, "id": fid, "ok": False, "error": reason,
                "stage": "worker"}  # fmt: skip

    def process(self, ids: list[str]) -> list[dict]:
        from jaxcr.eigen.model import PARAM_KINDS, estimate
        from jaxcr.eigen.pipeline import dataset_contours, stereo_histograms

        cfg = self.model.config
        t0 = time.perf_counter()
        frames = [self.by_id[i] for i in ids if i in self.by_id]
        recs: dict[str, dict] = {}
        for fid in ids:
            if fid in self.ds.bad_frames:
                recs[fid] = {"format": QUERY_FORMAT, "id": fid, "ok": False,
                             "error": self.ds.bad_frames[fid], "stage": "loader"}  # fmt: skip
        try:
            sc = dataset_contours(self.ds, self.model.colour, cfg.cameras, cfg.spacing,
                                  progress=False, frames=frames) if frames else None  # fmt: skip
        except InputError:  # no frame of this chunk could be read: each one's reason
            sc = None
            for f in frames:
                try:
                    for c in cfg.cameras:
                        f.load_image(c)
                    why = "image could not be read"
                except InputError as err:
                    why = err.format()
                recs[f.id] = {"format": QUERY_FORMAT, "id": f.id, "ok": False, "error": why,
                              "stage": "unreadable"}  # fmt: skip
        if sc is not None:
            for fid, msg in sc.unreadable.items():
                recs[fid] = {"format": QUERY_FORMAT, "id": fid, "ok": False, "error": msg,
                             "stage": "unreadable"}  # fmt: skip
            H, ok = stereo_histograms(sc, cfg.n_bins, cfg.normalise, self.model.view_centres)
            t1 = time.perf_counter()
            names = PARAM_KINDS[cfg.params]
            est = np.full((len(ok), len(names)), np.nan)
            if ok.any():
                est[ok] = estimate(self.model, H[ok])
            t2 = time.perf_counter()
            unit = "deg" if cfg.params == "angles" else "mm"
            scale = np.rad2deg(1.0) if cfg.params == "angles" else 1e3
            n_ok = max(int(ok.sum()), 1)
            for i, fid in enumerate(sc.ids):
                rec = {"format": QUERY_FORMAT, "id": fid, "ok": bool(ok[i])}
                if ok[i]:
                    rec.update({n: float(v) for n, v in zip(names, est[i], strict=True)})
                    if self.truth is not None:
                        e = np.abs(est[i] - self.truth[fid]) * scale
                        rec["errors_" + unit] = {n: float(v) for n, v in zip(names, e,
                                                                              strict=True)}  # fmt: skip
                    rec["query_s"] = (t2 - t1) / n_ok
                else:
                    npx = (int(sc.views[0].marker_pixels[i]), int(sc.views[1].marker_pixels[i]))
                    rec["error"] = f"too few marker pixels (left {npx[0]}, right {npx[1]})"
                rec["stage"] = "estimate"
                rec["descriptor_s"] = (t1 - t0) / len(sc.ids)
                recs[fid] = rec
        self.run_s += time.perf_counter() - t0
        return [recs[i] for i in ids]


def build_query_worker(model_path: str, dataset: str) -> QueryWorker:
    return QueryWorker(model_path, dataset)


def _write_query_outputs(args, worker: QueryWorker, records: dict[str, dict]) -> tuple:
    """estimates.csv/.jsonl and summary.json/.md from every frame's record: the frames with
    an estimate attempt in dataset order, then the loader's bad frames, then the unreadable
    ones (the order of an unsharded local run). Returns (summary, failed records)."""
    from jaxcr.eigen.model import PARAM_KINDS

    cfg = worker.model.config
    out = Path(args.out)
    names = PARAM_KINDS[cfg.params]
    unit = "deg" if cfg.params == "angles" else "mm"
    items = worker.items
    recs = [records[i] for i in items]
    order = {"estimate": 0, "loader": 1, "unreadable": 2, "worker": 2}
    recs.sort(key=lambda r: order.get(r.get("stage"), 2))  # stable: dataset order within
    truth = worker.truth is not None
    header = ["id", "ok", *names] + ([f"err_{n}_{unit}" for n in names] if truth else [])
    rows, lines, errs = [], [], []
    for r in recs:
        ok = bool(r["ok"])
        if r.get("stage") == "estimate":
            row = [r["id"], int(ok)] + [f"{r[n]:.6g}" if ok else "" for n in names]
            if truth:
                row += [f"{r['errors_' + unit][n]:.6g}" if ok else "" for n in names]
                if ok:
                    errs.append([r["errors_" + unit][n] for n in names])
            rows.append(",".join(str(x) for x in row))
        else:
            rows.append(",".join([r["id"], "0"] + [""] * (len(header) - 2)))
        lines.append(json.dumps({k: v for k, v in r.items() if k not in _INTERNAL}))
    _atomic_text(out / "estimates.csv", ",".join(header) + "\n" + "\n".join(rows) + "\n")
    _atomic_text(out / "estimates.jsonl", "\n".join(lines) + "\n")
    failed = [r for r in recs if not r["ok"]]
    est = [r for r in recs if r.get("stage") == "estimate"]
    n_ok = len(recs) - len(failed)
    summary = {
        "model": str(args.model),
        "dataset": str(args.dataset),
        "frames": len(recs),
        "failed": len(failed),
        "params": cfg.params,
        "descriptor_s_per_frame": sum(r.get("descriptor_s", 0.0) for r in est) / max(len(est), 1),
        "query_s_per_frame": sum(r.get("query_s", 0.0) for r in est) / max(n_ok, 1),
    }
    md = [f"# jaxcr manifold query: {worker.ds.name}", "",
          f"model `{args.model}`, {len(recs)} frames, {len(failed)} failed", ""]  # fmt: skip
    if errs:
        E = np.array(errs)
        med = {n: float(np.median(E[:, j])) for j, n in enumerate(names)}
        med["combined"] = float(np.median(E.ravel()))
        if cfg.params == "position":
            med["euclidean"] = float(np.median(np.linalg.norm(E, axis=1)))
        summary["median_error_" + unit] = med
        md += [f"| quantity | median error ({unit}) |", "|---|---|"]
        md += [f"| {k} | {v:.3f} |" for k, v in med.items()]
    _atomic_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    _atomic_text(out / "summary.md", "\n".join(md) + "\n")
    return summary, failed


def _fail_line(rec: dict) -> str:
    why = rec["error"]  # a loader message names the frame already
    return why if f"frame {rec['id']}:" in why else f"frame {rec['id']}: {why}"


def run_query(args) -> int:
    import shutil

    from jaxcr.scale.executor import WorkerSpec, executor_config
    from jaxcr.scale.job import Job, file_digest
    from jaxcr.scale.shards import SHARDS_DIR, claim_output, parse_shard

    shard = parse_shard(args.shard)  # bad flags: one line, before reading anything
    executor = executor_config(args)
    worker = QueryWorker(args.model, args.dataset)  # bad model or dataset: exit 2 here

    # new, empty or an earlier query's folder, never another command's; locked until exit
    claim_output(args.out, "manifold query", shard, marker="estimates.csv")
    out = Path(args.out)
    whole = ("estimates.csv", "estimates.jsonl", "summary.json", "summary.md")
    for name in whole:  # rewritten at the end: none is left over that looks like this run's
        (out / name).unlink(missing_ok=True)
    ds_root = Path(worker.ds.root).resolve()
    run_info = {
        "inputs": {"model": str(Path(args.model).resolve()),
                   "model_sha256": file_digest(args.model), "dataset": str(ds_root)},
        "options": {},
    }  # fmt: skip
    job = Job(out, "manifold query", run_info, "id", shard,
              start_over=lambda: shutil.rmtree(out / SHARDS_DIR, ignore_errors=True))  # fmt: skip
    spec = WorkerSpec(build_query_worker, (str(Path(args.model).resolve()), str(ds_root)))
    items = worker.items
    records, _ = job.run(items, spec, executor, chunk=QUERY_CHUNK, local_worker=worker,
                         progress="manifold query", unit="frame")  # fmt: skip
    mine = items if shard is None else shard.select(items)
    complete = all(i in records for i in items)
    failed = [records[i] for i in mine if not records[i]["ok"]]
    where = f" (shard {shard})" if shard is not None else ""
    if complete:
        summary, _ = _write_query_outputs(args, worker, records)
        unit = "deg" if worker.model.config.params == "angles" else "mm"
        n = summary["frames"]
        msg = f"manifold query: {n - summary['failed']}/{n} frames estimated"
        if "median_error_" + unit in summary:
            msg += ", median errors " + ", ".join(
                f"{k} {v:.3f} {unit}" for k, v in summary["median_error_" + unit].items()
            )
        print(msg + f"{where} -> {out}")
    else:
        print(f"manifold query{where}: {len(mine) - len(failed)}/{len(mine)} frames estimated "
              f"-> {job.log_dir}; estimates.csv is written when every frame has a record (the "
              "last shard to finish, or jaxcr manifold query without --shard)")  # fmt: skip
    if failed:
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        where_all = out / "estimates.jsonl" if complete else job.log_dir / "results.jsonl"
        print(f"jaxcr manifold: {len(failed)} frame(s) failed: {_fail_line(failed[0])}{more}; "
              f"all listed in {where_all}", file=sys.stderr)  # fmt: skip
    return 1 if failed else 0


def _is_irep_dataset(out) -> bool:
    try:
        meta = json.loads((Path(out) / "dataset.json").read_text(encoding="utf-8")).get("meta")
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(meta, dict) and meta.get("generator") == "jaxcr.synth.irep"


def run_synth(args) -> int:
    from jaxcr.synth.generate import parse_size
    from jaxcr.synth.irep import generate_irep

    size = parse_size(args.size, kind="manifold synth")
    from jaxcr.limits import check_frames

    check_frames(args.frames, "frames")
    from jaxcr.io import outdir

    # new, empty or a dataset this command wrote (never a user's dataset, even with --overwrite)
    outdir.claim(args.out, "manifold synth", recognise=_is_irep_dataset)
    if (Path(args.out) / "dataset.json").exists() and not args.overwrite:
        raise InputError("a dataset exists there (use --overwrite)", file=args.out)
    info = generate_irep(
        args.out,
        args.frames,
        args.split,
        args.seed,
        size,
        occluded=args.occluded,
        overwrite=args.overwrite,
    )
    print(
        f"manifold synth: {info['frames']} frames {size[0]}x{size[1]} in {info['total_s']:.1f} s -> {args.out}"
    )
    return 0
