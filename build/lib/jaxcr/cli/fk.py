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

import numpy as np

from jaxcr.errors import InputError
from jaxcr.io.jsonfile import read_text
from jaxcr.kinematics.batch import CHUNK, batch_forward, failure_reasons

__all__ = ["CHUNK", "FORMAT", "batch_forward", "failure_reasons", "read_q_csv", "run"]

FORMAT = "jaxcr.fk/1"


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
    p.add_argument(
        "--chunk", type=int, default=CHUNK, help="rows per compiled batch (default %(default)s)"
    )
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


def run(args) -> int:
    from jaxcr.io.robot import load_robot

    model = load_robot(args.robot)
    if args.points is not None:
        model = _with_points(model, args.points)
    if args.chunk < 1:
        raise InputError(f"--chunk must be >= 1, got {args.chunk}", field="--chunk")
    q = read_q_csv(args.q_csv, model.n_joints)
    from jaxcr.io import outdir

    # new, empty or an earlier fk output; an unwritable OUT fails now, not after the compile
    outdir.claim(args.out, "fk", recognise=lambda o: (o / "tips.csv").exists())
    out = batch_forward(model, q, chunk=args.chunk)

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

    # Remove stale outputs of an earlier run first: a crash below then leaves nothing that
    # looks complete.
    for path in (csv_path, npz_path):
        if os.path.exists(path):
            os.remove(path)
    _atomic_write_all({npz_path: write_npz, csv_path: write_csv})

    failed = np.flatnonzero(~out["ok"])
    B = q.shape[0]
    if failed.size:
        by_reason: dict[str, list[int]] = {}
        for i, why in failure_reasons(model, q, out).items():
            by_reason.setdefault(why, []).append(i)
        parts = []
        for why, rows in by_reason.items():
            shown = ", ".join(str(i) for i in rows[:10]) + (" ..." if len(rows) > 10 else "")
            parts.append(f"row{'s' if len(rows) > 1 else ''} {shown}: {why}")
        print(
            f"jaxcr fk: {B - failed.size}/{B} rows ok, {failed.size} failed ({'; '.join(parts)}; "
            f"ok = 0 in tips.csv); wrote {args.out}"
        )
        return 1
    print(f"jaxcr fk: {B}/{B} rows ok; wrote {args.out}")
    return 0
