"""``jaxcr fk ROBOT Q.csv -o OUT``: forward kinematics for many joint vectors in one compile.

ROBOT is a robot.json, a dataset.json, or a dataset folder (robot from its dataset.json).
Q.csv holds one joint vector per row, comma-separated; blank lines and lines starting with
``#`` are skipped; an optional first line of column names (no field numeric) is a header.
``nan`` entries are allowed: that row is reported as failed (ok = 0), not an error.

Outputs (format ``jaxcr.fk/1``), written atomically (temp file, then rename):

- ``OUT/centrelines.npz``: ``format``, ``kind``, ``q`` (B, m), ``s`` (B, N), ``p`` (B, N, 3),
  ``R`` (B, N, 3, 3), ``rho`` (B, N), ``ok`` (B,), ``residual`` (B,), ``energy`` (B,),
  ``num_steps`` (B,); robot frame, metres.
- ``OUT/tips.csv``: ``# format: jaxcr.fk/1`` then a header
  ``row,ok,x,y,z,rx,ry,rz,residual,energy`` (tip position in m, tip rotation vector in rad).

Bookkeeping (docs/scale-out.md, :mod:`jaxcr.scale.job`): each task of ``--chunk`` rows (one
compiled batch) writes ``OUT/parts/<first>-<last>.npz`` (the arrays above for its rows, plus
``rows``) and one record per row to ``OUT/results.jsonl`` (format ``jaxcr.fk-row/1``:
``row``, ``ok``, ``part``, ``reason`` when failed); ``centrelines.npz`` and ``tips.csv`` are
assembled from them once every row has a record. A rerun with the same robot, Q.csv and
``--points`` skips the rows already recorded (an interrupted run resumes); with other inputs
it starts over. ``--shard I/N`` computes the I-th of N contiguous row blocks (records in
``OUT/shards/I-of-N/``; the last shard to finish writes ``tips.csv``), ``--executor ray`` runs
the chunks on a Ray cluster; the outputs are the same.

Exit code 0 when every row succeeded, 1 when any row failed (the summary line gives each
failed row's reason), 2 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import math
import os
from pathlib import Path

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.jsonfile import read_text
from jaxcr.kinematics.batch import CHUNK, batch_bucket, batch_forward, failure_reasons

__all__ = ["CHUNK", "FORMAT", "batch_forward", "failure_reasons", "read_q_csv", "run"]

FORMAT = "jaxcr.fk/1"
ROW_FORMAT = "jaxcr.fk-row/1"
PARTS = "parts"
ARRAYS = ("s", "p", "R", "rho", "ok", "residual", "energy", "num_steps", "tip_rotvec")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fk",
        help="forward kinematics of a robot for rows of joint values",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("robot", help="robot.json, dataset.json or dataset folder")
    p.add_argument("q_csv", metavar="Q.csv", help="joint values, one row per configuration")
    p.add_argument("-o", "--out", required=True, help="output folder (created if missing)")
    p.add_argument(
        "--points",
        type=int,
        default=None,
        help="centreline samples N, 2..10000 (default: robot's)",
    )
    from jaxcr.scale.executor import add_executor_arguments
    from jaxcr.scale.shards import add_shard_argument

    add_shard_argument(p)
    add_executor_arguments(p, f"{CHUNK} rows, or all rows when fewer; a task is one compiled batch")
    p.set_defaults(func=run)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_q_csv(path: str, n_joints: int) -> np.ndarray:
    """Rows of ``n_joints`` floats from ``path`` (see module docstring). NaN allowed."""
    text = read_text(path, "a CSV file", "not a text CSV file", newline="")
    rows: list[list[float]] = []
    seen_data = False
    header_allowed = True
    for lineno, fields in enumerate(csv.reader(io.StringIO(text)), start=1):
        fields = [f.strip() for f in fields]
        if not fields or all(f == "" for f in fields) or fields[0].startswith("#"):
            continue
        try:
            values = [float(f) for f in fields]
        except ValueError:
            # A header is a first line of names only; a half-numeric first line is a typo.
            if header_allowed and not seen_data and not any(map(_is_number, fields)):
                header_allowed = False
                continue
            raise InputError(
                f"row {len(rows)} (line {lineno}): non-numeric value in {fields}",
                file=path,
                field="q",
            ) from None
        header_allowed = False
        seen_data = True
        if len(values) != n_joints:
            raise InputError(
                f"row {len(rows)} (line {lineno}): expected {n_joints} joint values, got {len(values)}",
                file=path,
                field="q",
            )
        rows.append(values)
    if not rows:
        raise InputError("no joint rows found", file=path)
    return np.asarray(rows, np.float64)


def _with_points(model, n_points: int):
    from jaxcr.kinematics.base import MAX_POINTS

    if not 2 <= n_points <= MAX_POINTS:
        raise InputError(f"--points must be in [2, {MAX_POINTS}], got {n_points}", field="--points")
    try:
        return dataclasses.replace(model, n_points=n_points)
    except (TypeError, ValueError) as err:
        raise InputError(
            f"cannot use {n_points} points for this robot ({err})", field="--points"
        ) from None


def _atomic_write_all(writers: dict[str, object]) -> None:
    """Write every file to a temp name first, then rename them all (tips.csv last), so an
    interrupted run never leaves a new file next to a stale one that looks complete."""
    tmps = {
        path: os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.tmp{os.getpid()}")
        for path in writers
    }
    try:
        for path, write in writers.items():
            write(tmps[path])
        for path in writers:
            os.replace(tmps[path], path)
    finally:
        for tmp in tmps.values():
            if os.path.exists(tmp):
                os.remove(tmp)


def _fmt(x: float) -> str:
    return "nan" if not math.isfinite(x) else f"{float(x):.9g}"


class FkWorker:
    """Forward kinematics of chunks of rows of Q.csv: writes ``OUT/parts/<first>-<last>.npz``
    and returns one record per row (the worker of :func:`jaxcr.scale.executor.run_frames`).
    Every chunk is padded to ``chunk`` rows: one compiled program, and each row's result the
    same as in an unchunked ``batch_forward`` with that chunk."""

    def __init__(self, robot: str, q_csv: str, points: int | None, out: str, chunk: int):
        from jaxcr.io.robot import load_robot

        model = load_robot(robot)
        self.model = _with_points(model, points) if points is not None else model
        self.q = read_q_csv(q_csv, self.model.n_joints)
        self.out, self.chunk = Path(out), chunk
        self.compile_s = self.run_s = 0.0

    def failed_record(self, row: str, reason: str) -> dict:
        return {"format": ROW_FORMAT, "row": int(row), "ok": False, "reason": reason}

    def process(self, ids: list[str]) -> list[dict]:
        import time

        from jaxcr.io.results import atomic_write_bytes

        t0 = time.perf_counter()
        rows = np.array([int(i) for i in ids])
        q = self.q[rows]
        pad = self.chunk - len(rows)
        qp = np.concatenate([q, np.repeat(q[-1:], pad, axis=0)]) if pad > 0 else q
        from jaxcr.io.exported import cached_call  # the stored traced program (K4)

        res = batch_forward(self.model, qp, chunk=self.chunk, progress=False, jit_call=cached_call)
        res = {k: v[: len(rows)] for k, v in res.items()}
        reasons = failure_reasons(self.model, q, res)
        part = f"{PARTS}/{rows[0]:08d}-{rows[-1]:08d}.npz"
        buf = io.BytesIO()
        np.savez(buf, rows=rows, **{k: res[k] for k in ARRAYS})
        atomic_write_bytes(self.out / part, buf.getvalue())
        recs = []
        for j, i in enumerate(rows):
            rec = {"format": ROW_FORMAT, "row": int(i), "ok": bool(res["ok"][j]), "part": part}
            if not rec["ok"]:
                rec["reason"] = reasons.get(j, "kinematics reported failure")
            recs.append(rec)
        self.run_s += time.perf_counter() - t0
        return recs


def build_fk_worker(robot: str, q_csv: str, points: int | None, out: str,
                    chunk: int) -> FkWorker:  # fmt: skip
    return FkWorker(robot, q_csv, points, out, chunk)


def assemble(out: Path, q: np.ndarray, records: dict[str, dict], n_points: int) -> dict:
    """The whole-job arrays (as :func:`batch_forward` returns them) from the rows' parts; a
    row without a part (its worker was lost) is NaN with ok False."""
    B = q.shape[0]
    arrays: dict[str, np.ndarray] = {}
    by_part: dict[str, list[int]] = {}
    for i in range(B):
        part = records[str(i)].get("part")
        if part:
            by_part.setdefault(part, []).append(i)
    for part, rows in by_part.items():
        with np.load(out / part, allow_pickle=False) as z:
            where = {int(r): j for j, r in enumerate(z["rows"])}
            for k in ARRAYS:
                v = z[k]
                if k not in arrays:
                    fill = False if k == "ok" else (0 if v.dtype.kind in "iu" else np.nan)
                    arrays[k] = np.full((B, *v.shape[1:]), fill, v.dtype)
                arrays[k][rows] = v[[where[i] for i in rows]]
    if not arrays:  # no row has a part: every worker was lost
        N = n_points
        shapes = {"s": (N,), "p": (N, 3), "R": (N, 3, 3), "rho": (N,), "tip_rotvec": (3,)}
        for k in ARRAYS:
            dt = bool if k == "ok" else (np.int32 if k == "num_steps" else np.float32)
            fill = False if k == "ok" else (0 if k == "num_steps" else np.nan)
            arrays[k] = np.full((B, *shapes.get(k, ())), fill, dt)
    arrays["ok"] = np.array([bool(records[str(i)]["ok"]) for i in range(B)])
    return arrays


def _write_outputs(args, model, q, out: dict) -> None:
    npz_path = os.path.join(args.out, "centrelines.npz")
    csv_path = os.path.join(args.out, "tips.csv")

    def write_npz(tmp):
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                format=np.array(FORMAT),
                kind=np.array(model.kind),
                q=q,
                **{k: v for k, v in out.items() if k != "tip_rotvec"},
            )

    def write_csv(tmp):
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(f"# format: {FORMAT}\n")
            w = csv.writer(fh)
            w.writerow(["row", "ok", "x", "y", "z", "rx", "ry", "rz", "residual", "energy"])
            for i in range(q.shape[0]):
                tip = out["p"][i, -1]
                rv = out["tip_rotvec"][i]
                w.writerow(
                    [i, int(out["ok"][i]), *map(_fmt, tip), *map(_fmt, rv)]
                    + [_fmt(out["residual"][i]), _fmt(out["energy"][i])]
                )

    _atomic_write_all({npz_path: write_npz, csv_path: write_csv})


def _remove_outputs(out: str) -> None:
    # stale whole-job outputs go first: a crash below then leaves nothing that looks complete
    for name in ("tips.csv", "centrelines.npz"):
        path = os.path.join(out, name)
        if os.path.exists(path):
            os.remove(path)


def run(args) -> int:
    import shutil

    from jaxcr.scale.executor import WorkerSpec, executor_config
    from jaxcr.scale.job import Job, file_digest
    from jaxcr.scale.shards import claim_output, parse_shard

    shard = parse_shard(args.shard)  # bad flags: one line, before reading anything
    executor = executor_config(args)
    worker = FkWorker(args.robot, args.q_csv, args.points, args.out, 1)  # validates the inputs
    model, q = worker.model, worker.q
    B = q.shape[0]
    chunk = batch_bucket(B, executor.chunk or CHUNK)  # one program per power-of-two bucket
    worker.chunk = chunk

    # new, empty or an earlier fk output; an unwritable OUT fails now, not after the compile
    claim_output(args.out, "fk", shard, marker="tips.csv")
    out = Path(args.out)
    _remove_outputs(args.out)
    run_info = {
        "inputs": {"robot": str(Path(args.robot).resolve()), "q": str(Path(args.q_csv).resolve()),
                   "q_sha256": file_digest(args.q_csv), "rows": B},
        "options": {"points": args.points, "n_points": int(model.n_points)},
    }  # fmt: skip
    job = Job(out, "fk", run_info, "row", shard,
              start_over=lambda: shutil.rmtree(out / PARTS, ignore_errors=True))  # fmt: skip
    spec = WorkerSpec(build_fk_worker, (str(Path(args.robot).resolve()),
                                        str(Path(args.q_csv).resolve()), args.points,
                                        str(out.resolve()), chunk))  # fmt: skip
    items = [str(i) for i in range(B)]
    mine = items if shard is None else shard.select(items)
    records, _ = job.run(items, spec, executor, chunk=chunk, local_worker=worker,
                         progress="fk" if len(mine) > chunk else None, unit="row")  # fmt: skip
    complete = all(i in records for i in items)
    if complete:
        _write_outputs(args, model, q, assemble(out, q, records, int(model.n_points)))
    failed = [int(i) for i in mine if not records[i]["ok"]]
    n = len(mine)
    where = f"shard {shard}: " if shard is not None else ""
    wrote = (f"wrote {args.out}" if complete else
             f"wrote {job.log_dir}; tips.csv is written when every row has a record "
             "(the last shard to finish, or jaxcr fk without --shard)")  # fmt: skip
    if failed:
        by_reason: dict[str, list[int]] = {}
        for i in failed:
            by_reason.setdefault(records[str(i)]["reason"], []).append(i)
        parts = []
        for why, rows in by_reason.items():
            shown = ", ".join(str(i) for i in rows[:10]) + (" ..." if len(rows) > 10 else "")
            parts.append(f"row{'s' if len(rows) > 1 else ''} {shown}: {why}")
        print(
            f"jaxcr fk: {where}{n - len(failed)}/{n} rows ok, {len(failed)} failed "
            f"({'; '.join(parts)}; ok = 0 in tips.csv); {wrote}"
        )
        return 1
    print(f"jaxcr fk: {where}{n}/{n} rows ok; {wrote}")
    return 0
