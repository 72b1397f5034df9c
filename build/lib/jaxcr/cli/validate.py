"""``jaxcr validate DATASET``: check a ``jaxcr.dataset/1`` dataset before a batch run.

Checks dataset.json (format version, robot, cameras and calibration files), every frame
(id, joint vector length and finiteness, image and mask files: present, readable, sized as
the camera) and background images, and prints one line per problem, naming the file, the
frame id and the field.

Exit code 0 when the dataset is clean, 2 when any problem was found.
With ``-o report.json`` the problems are also written as JSON
(``{"format": "jaxcr.validate/1", "dataset", "ok", "n_frames", "n_bad_frames",
"warnings", "problems": [{"file", "frame", "field", "message"}]}``).
A dataset without frames is well-formed (exit 0) but the summary line says it is empty.
"""

from __future__ import annotations

import argparse
import json
import os

from jaxcr.io.dataset import check_dataset

FORMAT = "jaxcr.validate/1"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "validate",
        help="check a dataset (files, robot, cameras, frames) and list every problem",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("dataset", help="dataset folder or its dataset.json")
    p.add_argument("-o", "--out", default=None, help="also write the problems as JSON here")
    p.add_argument(
        "--fast",
        action="store_true",
        help="read only PNG headers (sizes) instead of decoding every image",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="print only the summary line")
    p.set_defaults(func=run)


def _progress_bar(enabled: bool):
    from jaxcr.progress import progress

    bar = progress(
        total=0, unit="frame", desc="validate", enabled=enabled, leave=False, mininterval=0.5
    )

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    return bar, update


def run(args) -> int:
    bar, update = _progress_bar(not args.quiet)
    try:
        check = check_dataset(args.dataset, decode_images=not args.fast, progress=update)
    finally:
        bar.close()
    problems = check.report_errors  # one line per broken camera, not per frame using it
    n_ok = check.n_frames - check.n_bad_frames
    if not args.quiet:
        for err in problems:
            print(err.format())
    status = "OK" if check.ok else f"{len(problems)} problem(s)"
    # "frames": [] is well-formed (the format and DatasetWriter allow it, e.g. a dataset being
    # assembled), so it is no problem and the exit code stays 0; but a batch run has nothing
    # to do (jaxcr segment refuses it), so the summary says so instead of a bare "OK".
    warnings = []
    if check.n_frames == 0 and not check.errors:
        warnings.append("the dataset has no frames: nothing to process")
        status += " but empty (no frames: nothing to process)"
    cams = ", ".join(check.cameras) or "-"
    print(
        f"{check.path}: {status}; robot {check.robot_kind or '?'}; cameras {cams}; "
        f"frames {check.n_frames} ({n_ok} OK, {check.n_bad_frames} with problems)"
    )
    if args.out:
        report = {
            "format": FORMAT,
            "dataset": str(check.path),
            "ok": check.ok,
            "n_frames": check.n_frames,
            "n_bad_frames": check.n_bad_frames,
            "warnings": warnings,
            "problems": [
                {"file": e.file, "frame": e.frame, "field": e.field, "message": e.message}
                for e in problems
            ],
        }
        out = os.fspath(args.out)
        parent = os.path.dirname(out)
        if parent:
            os.makedirs(parent, exist_ok=True)
        tmp = f"{out}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=1)
            fh.write("\n")
        os.replace(tmp, out)
    return 0 if check.ok else 2
