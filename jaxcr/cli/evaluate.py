"""``jaxcr evaluate OUT [OUT ...] [-o REPORT_DIR]``: Watson et al. Table II for segment runs.

What is measured and how: :mod:`jaxcr.segmentation.evaluate` (the library this command
calls; its module docstring lists every column).

Writes ``table2.md``, ``table2.csv`` (long format), ``per_frame.csv`` and ``iou.png`` into
OUT (one run) or REPORT_DIR; a REPORT_DIR other than an OUT must be new, empty or an earlier
evaluate report, and is locked while the command runs (:mod:`jaxcr.io.outdir`)
(the evaluation itself is :mod:`jaxcr.segmentation.evaluate`; this module parses arguments,
prints and sets the exit code).
A ``jaxcr stereo`` OUT (``--shard`` runs, docs/scale-out.md) is merged in place instead: the
records of every shard, ``segments.csv``/``.md`` over all recorded frames and ``merge.json``
(:func:`jaxcr.cli.stereo.merge_outputs`), the failed and the missing frames named.
A ``jaxcr fk`` or ``jaxcr manifold query`` OUT: the rows/frames no shard recorded are named
(exit 1); when all are, the command writes its whole-job files (``tips.csv``, ``estimates.csv``).
Exit code 1 when the report counts failed frames (failed in the segment run, or outputs
missing/damaged/mis-sized); they are listed in ``per_frame.csv`` with the reason.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from jaxcr.errors import InputError
from jaxcr.io import report as rep
from jaxcr.io import results as R
from jaxcr.segmentation.evaluate import (  # noqa: F401  (re-exported for older callers)
    PER_FRAME_FIELDS,
    evaluate_outputs,
    frame_rows,
    iou_plot,
    per_frame_csv,
    write_report,
)

HELP = "evaluate segment outputs against ground truth (Watson et al. Table II)"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "evaluate", help=HELP, description=__doc__.split("\n\n")[0].replace("``", "")
    )
    p.add_argument("outs", nargs="+", metavar="OUT",
                   help="output folder(s) of jaxcr segment, or of jaxcr stereo (merged in "
                   "place: shards' records, segments.csv/.md over all frames, merge.json, the "
                   "missing frames named)")  # fmt: skip
    p.add_argument(
        "-o", "--out", default=None, metavar="REPORT_DIR",
        help="report folder (default: OUT for one run, ./jaxcr-report for several)",
    )  # fmt: skip
    p.add_argument("--no-plot", action="store_true", help="do not write iou.png")
    p.add_argument("--title", default=None, help="title of the Markdown report")
    from jaxcr.scale.executor import add_executor_arguments
    from jaxcr.segmentation.evaluate import EVALUATE_CHUNK

    # segment outputs only: their frames' masks are read and scored as tasks (a long run on a
    # shared filesystem); stereo, fk and manifold query outputs are merged from their records
    add_executor_arguments(p, f"{EVALUATE_CHUNK} frames; segment outputs only")
    p.set_defaults(func=run)
    return p


def _same_folder(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _run_stereo(outs: list[Path]) -> int:
    """Merge stereo outputs (shards and unsharded runs) in place: tables over every recorded
    frame, the failed and the missing frames named (:func:`jaxcr.cli.stereo.merge_outputs`)."""
    from jaxcr.cli.stereo import merge_outputs
    from jaxcr.io import outdir

    code = 0
    for o in outs:
        try:  # tables only while no run writes OUT (a live run or shard: report alone)
            lock = outdir.claim(o, "stereo")
        except InputError as err:
            lock = None
            print(f"jaxcr evaluate: warning: {o}: not writing the merged tables ({err})",
                  file=sys.stderr)  # fmt: skip
        try:
            info = merge_outputs(o, write=lock is not None)
        finally:
            if lock is not None:
                outdir.release(lock)
        n_fail, miss = len(info["failed"]), info["missing"]
        print(f"jaxcr evaluate: {o}: {info['ok']}/{info['frames']} frames reconstructed, "
              f"{n_fail} failed, {len(miss)} missing"
              + (f"; tables in {o / 'segments.csv'}, summary in {o / 'merge.json'}"
                 if lock is not None else ""))  # fmt: skip
        if info["failed"]:
            first = next(iter(info["failed"].values()))
            more = f" (and {n_fail - 1} more)" if n_fail > 1 else ""
            print(f"jaxcr evaluate: {o}: failed: {first}{more}", file=sys.stderr)
        if miss:
            shown = ", ".join(miss[:10]) + (f" (and {len(miss) - 10} more)" if len(miss) > 10
                                            else "")  # fmt: skip
            shards = info["unfinished_shards"]
            also = f"; shard(s) {', '.join(shards[:8])} not finished" if shards else ""
            print(f"jaxcr evaluate: {o}: {len(miss)} of {info['frames']} frame(s) missing (no "
                  f"record in results.jsonl or its shards): {shown}{also}; continue with jaxcr "
                  "stereo (the missing --shard, or without --shard: it skips recorded frames)",
                  file=sys.stderr)  # fmt: skip
        if info["failed"] or miss:
            code = 1
    return code


def _run_jobs(outs: list[Path]) -> int:
    """``fk`` / ``manifold query`` outputs (:mod:`jaxcr.scale.job`): name the items (rows,
    frames) no run or shard has recorded and the shards without ``DONE``; when every item is
    recorded, write the whole-job files (``tips.csv`` ..., by the command itself: it resumes,
    computes nothing, and assembles them)."""
    import json

    from jaxcr.cli import main
    from jaxcr.io import outdir
    from jaxcr.scale import job as J
    from jaxcr.scale import shards as S

    code = 0
    for o in outs:
        command = outdir.owner(o)
        runs = [f for f in [o / "run.json"] + [d / "run.json" for _, d in S.shard_dirs(o)]
                if f.exists()]  # fmt: skip
        if not runs:
            raise InputError(f"no run.json: not a jaxcr {command} output", file=str(o))
        try:
            info = json.loads(runs[0].read_text(encoding="utf-8"))
            inputs, options = info["inputs"], info["options"]
        except (UnicodeDecodeError, ValueError, KeyError, TypeError):
            raise InputError(f"not a {J.RUN_FORMAT} file", file=str(runs[0])) from None
        key = "row" if command == "fk" else "id"
        recorded = set()
        for f in S.results_files(o, J.RESULTS):
            recorded |= {str(r[key]) for r in J.read_keyed(f, key)}
        if command == "fk":
            items = [str(i) for i in range(int(inputs["rows"]))]
            argv = ["fk", inputs["robot"], inputs["q"], "-o", str(o)]
            if options.get("points") is not None:
                argv += ["--points", str(options["points"])]
        else:
            from jaxcr.cli.manifold import QueryWorker

            items = QueryWorker(inputs["model"], inputs["dataset"]).items
            argv = ["manifold", "query", inputs["model"], inputs["dataset"], "-o", str(o)]
        missing = [i for i in items if i not in recorded]
        if missing:
            dirs = S.shard_dirs(o)
            done = {(s.count, s.index) for s, d in dirs if (d / J.DONE).exists()}
            unfinished = ", ".join(str(S.Shard(i, n)) for n in sorted({s.count for s, _ in dirs})
                                   for i in range(n) if (n, i) not in done)  # fmt: skip
            shown = ", ".join(missing[:10]) + (f" (and {len(missing) - 10} more)"
                                               if len(missing) > 10 else "")  # fmt: skip
            print(f"jaxcr evaluate: {o}: {len(missing)} of {len(items)} {key}(s) missing (no "
                  f"record in results.jsonl or its shards): {shown}"
                  + (f"; shard(s) {unfinished} not finished" if unfinished else "")
                  + f"; continue with jaxcr {command} (the missing --shard, or without --shard:"
                  " it skips recorded items)", file=sys.stderr)  # fmt: skip
            code = 1
            continue
        # every item recorded: the command assembles the whole-job files (exit 1: failed items)
        code = max(code, main(argv))
    return code


def run(args) -> int:
    outs = [Path(o) for o in args.outs]
    for o in outs:
        if not o.exists():
            raise InputError("output folder not found", file=str(o))
    from jaxcr.cli.stereo import is_stereo_output
    from jaxcr.io import outdir
    from jaxcr.scale.executor import executor_config

    executor = executor_config(args)
    jobs = [outdir.owner(o) in ("fk", "manifold query") for o in outs]
    stereo = [is_stereo_output(o) for o in outs]
    if executor.kind != "local" and (any(jobs) or any(stereo)):
        # those merges read only their records (no images): nothing to distribute
        raise InputError("--executor ray evaluates segment outputs; stereo, fk and manifold "
                         "query outputs are merged from their records in this process",
                         field="executor")  # fmt: skip
    if any(jobs):
        if not all(jobs) or args.out:
            raise InputError("fk and manifold query outputs are merged in place, one kind at "
                             "a time: no -o, no other outputs", field="outs")  # fmt: skip
        return _run_jobs(outs)

    if any(stereo):
        if not all(stereo):
            raise InputError("cannot evaluate stereo and segment outputs together",
                             file=str(outs[stereo.index(False)]))  # fmt: skip
        if args.out:
            raise InputError("stereo outputs are merged in place: no -o", field="out")
        return _run_stereo(outs)
    report_dir = Path(args.out) if args.out else (outs[0] if len(outs) == 1 else
                                                  Path("jaxcr-report"))  # fmt: skip
    if not any(_same_folder(report_dir, o) for o in outs):
        # a report folder of its own (-o, or ./jaxcr-report): new, empty or an earlier
        # evaluate report, never a user's or another command's folder; locked until exit.
        # (The default for one run is that run's own folder, which segment owns.)
        from jaxcr.io import outdir

        outdir.claim(report_dir, "evaluate", recognise=lambda o: (o / "table2.md").exists())
    rows, infos = evaluate_outputs(outs, executor=executor)
    if not rows:
        raise InputError("no results to evaluate (empty results.jsonl)", file=str(outs[0]))
    from jaxcr.scale import shards as S

    incomplete = [o for o in outs if not (R.output_is_complete(o) or S.sharded_complete(o))]
    table = write_report(rows, infos, report_dir, args.title, plot=not args.no_plot,
                         incomplete=incomplete)  # fmt: skip
    for o, info in zip(outs, infos, strict=True):
        eval_failed = info.get("evaluate_failed") or {}
        if eval_failed:
            fid, why = next(iter(eval_failed.items()))
            more = f" (and {len(eval_failed) - 1} more)" if len(eval_failed) > 1 else ""
            print(f"jaxcr evaluate: warning: {o}: {len(eval_failed)} frame(s) counted as failed: "
                  f"frame {fid}: {why}{more}", file=sys.stderr)  # fmt: skip
    missing = {
        str(o): info.get("evaluate_missing") or [] for o, info in zip(outs, infos, strict=True)
    }
    for o in incomplete:
        unfinished = S.missing_shards(o)
        if unfinished:
            names = ", ".join(str(x) for x in unfinished[:8])
            more = f" (and {len(unfinished) - 8} more)" if len(unfinished) > 8 else ""
            print(f"jaxcr evaluate: warning: {o} is incomplete: shard(s) {names}{more} not "
                  "finished (no DONE marker)", file=sys.stderr)  # fmt: skip
        else:
            print(f"jaxcr evaluate: warning: {o} is incomplete (no DONE marker)", file=sys.stderr)
    from rich.console import Console

    Console().print(rep.table2_rich(table))
    print(f"report: {report_dir / 'table2.md'}")
    # exit 1 when the report counts failed frames (failed in the segment run, or whose outputs
    # could not be evaluated): the numbers are over fewer frames than the run was given
    # records of frames a dataset does not have are failed records of unknown frames, not
    # dataset frames: counted apart (a 4-frame dataset is never "1 of 5")
    unknown = {(str(o), f) for o, info in zip(outs, infos, strict=True)
               for f in info.get("evaluate_unknown") or []}  # fmt: skip
    frames = {(r["out"], r["frame"]): r for r in rows if (r["out"], r["frame"]) not in unknown}
    failed = [r for r in frames.values() if not r["ok"]]
    code = 0
    for o, info in zip(outs, infos, strict=True):
        ids = missing[str(o)]
        if ids:
            done = "no DONE marker" if o in incomplete else "DONE marker present"
            shown = ", ".join(ids[:10]) + (f" (and {len(ids) - 10} more)" if len(ids) > 10 else "")
            print(f"jaxcr evaluate: {o}: {len(ids)} of {info['evaluate_expected']} frame(s) "
                  f"missing (no record in results.jsonl or its shards; {done}): {shown}; "
                  "continue the run with jaxcr segment --resume (or the missing --shard)",
                  file=sys.stderr)  # fmt: skip
            code = 1
    if failed or unknown:
        n_eval = sum(1 for r in failed if str(r.get("reason") or "").startswith("evaluate: "))
        ids = sorted(f for _, f in unknown)
        extra = (f"; {len(unknown)} failed record(s) of frame(s) the dataset does not have "
                 f"({', '.join(ids[:5])}{' ...' if len(ids) > 5 else ''}), not counted as "
                 "dataset frames" if unknown else "")  # fmt: skip
        print(f"jaxcr evaluate: {len(failed)} of {len(frames)} frame(s) failed ("
              f"{len(failed) - n_eval} in the segment run, {n_eval} in evaluation){extra}; "
              f"reasons in {report_dir / 'per_frame.csv'} (rows with ok False)",
              file=sys.stderr)  # fmt: skip
        return 1
    return code
