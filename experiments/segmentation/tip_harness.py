"""What the issue-16 tip harnesses that evaluate variants on stored traces share
(``real_like_tip_guided.py``, ``_end.py``, ``_wrongcurve.py``, ``_bothcross.py``): their
command line (``--seeds``, ``--store``, ``--out``, ``--summary``; development seeds only) and
their resumable loop over the stored seeds (``real_like_tip_spline.py trace`` writes the
store: one ``SEED.pkl`` per frame). Not a script of its own."""

from __future__ import annotations

import argparse
import json
import os
import pickle
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from jaxcr.benchmarks import parse_seeds

FORBIDDEN_FROM = 5010  # the lead's fresh seeds (fresh_seeds_reserved.md; from 5010 after stop 40): never run by a harness


def harness_parser(doc: str, default_out: str) -> argparse.ArgumentParser:
    """The harnesses' common options; a harness adds its own before parsing."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--seeds", help="development seeds, e.g. 4000-4100,4117")
    ap.add_argument("--store", type=Path, help="folder of stored traces (SEED.pkl)")
    ap.add_argument("--out", type=Path, default=Path(default_out),
                    help="rows are written to OUT.json (resumed if it exists)")  # fmt: skip
    ap.add_argument("--summary", type=Path, help="print the tables of a rows file and stop")
    return ap


def dev_seeds(ap: argparse.ArgumentParser, args) -> list[int]:
    """``--seeds`` parsed, after checking that ``--store`` is given and that no seed is one
    of the reserved fresh seeds (``ap.error`` otherwise)."""
    if args.seeds is None or args.store is None:
        ap.error("--seeds and --store are required (or --summary ROWS.json)")
    seeds = parse_seeds(args.seeds)
    if any(s >= FORBIDDEN_FROM for s in seeds):
        ap.error(f"seeds from {FORBIDDEN_FROM} are reserved for the fresh run")
    return seeds


def resumed_rows(out: Path) -> list[dict]:
    """The rows an earlier run wrote to ``out``.json (empty if none)."""
    jpath = out.with_suffix(".json")
    return json.loads(jpath.read_text())["rows"] if jpath.exists() else []


def stored_records(seeds, store: Path, rows: list[dict]) -> Iterator[tuple[int, dict]]:
    """(seed, stored record) for each seed not in ``rows`` whose ``SEED.pkl`` is in
    ``store``, in the order given."""
    done = {r["seed"] for r in rows}
    for seed in seeds:
        path = store / f"{seed}.pkl"
        if seed in done or not path.exists():
            continue
        with open(path, "rb") as f:
            yield seed, pickle.load(f)


def merged_rows(path) -> list[dict]:
    """The rows of the rows files ``path`` lists (comma separated), one per seed (a later
    file's row replaces an earlier one's), in seed order."""
    rows = []
    for p in str(path).split(","):
        rows += json.loads(Path(p).read_text())["rows"]
    return sorted({r["seed"]: r for r in rows}.values(), key=lambda r: r["seed"])


def write_rows(out: Path, rows: list[dict]) -> None:
    """``rows`` to ``out``.json, replaced whole (a run stopped part way leaves the last
    complete file, which :func:`resumed_rows` resumes from)."""
    jpath = out.with_suffix(".json")
    tmp = jpath.with_suffix(".tmp")
    tmp.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    os.replace(tmp, jpath)


def variant_table(sel: list[dict], title: str, names) -> None:
    """Print, for the rows ``sel``, each variant's frames with both views within 5 px and
    views within 5 px (``row[name]["err_px"]``, one per view)."""
    print(f"\n{title} ({len(sel)} frames)\n")
    print("| variant | frames with both views within 5 px | views within 5 px |\n|---|---|---|")
    for n in names:
        ok = sum(max(r[n]["err_px"]) <= 5 for r in sel)
        v = sum(x <= 5 for r in sel for x in r[n]["err_px"])
        print(f"| {n} | {ok} of {len(sel)} | {v} of {2 * len(sel)} |")


def tip_errors(tips, truth) -> list[float]:
    """Each view's tip error (px) against the truth."""
    return [float(np.linalg.norm(np.asarray(t) - g)) for t, g in zip(tips, truth, strict=True)]


def along_across(d, tip, truth) -> list[float]:
    """The truth minus the tip (px), along the unit end direction ``d`` and across it (NaNs
    where ``d`` is not a direction)."""
    d = np.asarray(d, np.float64)
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        return [float("nan"), float("nan")]
    d = d / np.linalg.norm(d)
    r = np.asarray(truth, np.float64) - np.asarray(tip, np.float64)
    return [float(r @ d), float(d[0] * r[1] - d[1] * r[0])]


@contextmanager
def stored_alternatives(rec: dict, key=id):
    """Within the block, :func:`jaxcr.stereo.pipeline.trace_alternatives` returns the stored
    record's alternatives of each of its traces (``key(trace)`` identifies a trace; a placed
    copy of a trace shares its ``retrace``) instead of computing them again: they are
    deterministic, and the stored ones are what the store's rows were made from."""
    from jaxcr.stereo import pipeline

    alts = {key(t): list(a) for t, a in zip(rec["traces"], rec["alts"], strict=True)}
    saved = pipeline.trace_alternatives
    pipeline.trace_alternatives = lambda t: alts[key(t)]
    try:
        yield
    finally:
        pipeline.trace_alternatives = saved


def harness_main(
    doc: str, default_out: str, evaluate: Callable, summary: Callable, *, cache: bool = False
) -> int:
    """A harness's command line with the common options only: ``--summary ROWS.json`` prints
    ``summary(ROWS.json)``; otherwise ``evaluate(seeds, store, out)`` on development seeds.
    ``cache``: also a required ``--cache`` (the rendered frames, real_like_tip.py --cache),
    passed as ``evaluate(seeds, store, cache, out)``."""
    ap = harness_parser(doc, default_out)
    if cache:
        ap.add_argument("--cache", type=Path, help="the rendered frames (real_like_tip.py --cache)")
    args = ap.parse_args()
    if args.summary is not None:
        summary(args.summary)
        return 0
    seeds = dev_seeds(ap, args)
    if not cache:
        evaluate(seeds, args.store, args.out)
    elif args.cache is None:
        ap.error("--cache is required")
    else:
        evaluate(seeds, args.store, args.cache, args.out)
    return 0
