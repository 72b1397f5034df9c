"""``jaxcr bench segment|fk|motion|registration|planning|compile``: run a benchmark and report it (console table + Markdown).

The measurements live in the package, :mod:`jaxcr.benchmarks` (``segment.py``:
``run_segment_benchmark``, ``fk.py``: ``run_fk_benchmark``, ``motion.py``:
``run_motion_benchmark``, ``registration.py``: ``run_registration_benchmark`` and
``run_planning_benchmark``, ``compile.py``: ``run_compile_benchmark``, first-process
compilation of segment/demo/stereo in child processes), so this command works from an
installed wheel; it finds them (see :data:`PROVIDERS`), passes the options they accept, and
prints and writes what they return.

A provider returns a dict. Recognised keys (all optional besides ``name``): ``name``,
``median_s``, ``spread_s`` (e.g. IQR), ``compile_s``, ``reference`` (what the reference is),
``reference_median_s``, ``ratio`` (reference / ours; computed if both medians are given),
``unit`` (what one timed call does, e.g. "frame"), ``rows`` (a list of dicts: one table row
each, e.g. per batch size; also printed on the console), ``console_columns`` (the
columns of ``rows`` printed on the console; the Markdown has all), ``failed`` (the number of
failed rows: the report is written and the command exits 1) and ``notes``. Every other scalar is listed as a key/value.
A provider given as a ``.py`` file path (e.g. a script of one's own) without such a function
but with ``main(argv)`` is run as a script
(``-o REPORT.md``, plus ``--batch/--repeats/--frames/--size/--seed`` when given); it prints
and writes its own report.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import importlib.util
import inspect
import json
import math
import os
import platform
import sys
from pathlib import Path

from jaxcr.cli._common import seed as _seed
from jaxcr.errors import InputError
from jaxcr.io import results as R

HELP = (
    "benchmark segmentation, kinematics, motion, registration, planning or first-process "
    "compilation (medians, compile time, ratio vs reference)"
)

#: where each benchmark function lives, searched in order (module, function); a module name
#: ending in .py is a file path (absolute, or relative to the current folder), never a path
#: inside the checkout: ``jaxcr bench`` must work from an installed wheel.
PROVIDERS = {
    "segment": [("jaxcr.benchmarks.segment", "run_segment_benchmark")],
    "fk": [("jaxcr.benchmarks.fk", "run_fk_benchmark")],
    "motion": [("jaxcr.benchmarks.motion", "run_motion_benchmark")],
    "registration": [("jaxcr.benchmarks.registration", "run_registration_benchmark")],
    "planning": [("jaxcr.benchmarks.registration", "run_planning_benchmark")],
    "compile": [("jaxcr.benchmarks.compile", "run_compile_benchmark")],
}


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("bench", help=HELP, description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=sorted(PROVIDERS), metavar="WHAT",
                   help="which benchmark: " + ", ".join(sorted(PROVIDERS)))  # fmt: skip
    p.add_argument(
        "-o",
        "--out",
        default=None,
        metavar="REPORT.md",
        help="Markdown report (default: bench_<what>.md in the current folder)",
    )
    p.add_argument("--repeats", type=int, default=None,
                   help="timed repetitions (compile: rounds of every part, default 1)")  # fmt: skip
    p.add_argument(
        "--frames", type=int, default=None,
        help="segment: frames per batch; registration: forward pairs per scene (default 4); "
        "compile: frames of the synthetic sets (default 2)",
    )  # fmt: skip
    p.add_argument("--size", default=None, metavar="WxH",
                   help="segment, motion, compile: image size (compile: default 640x480)")  # fmt: skip
    p.add_argument("--batch", type=int, default=None, help="fk: joint vectors per batch (<= 65536)")
    p.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    p.add_argument(
        "--previous",
        action="store_true",
        help="fk, motion: also time the previous implementation in the same run "
        "(fk: the pre-issue-18 CTR solvers, minutes of compilation)",
    )
    p.add_argument(
        "--only", default=None, metavar="PARTS",
        help="compile: comma-separated parts of segment,second,warmup,demo,stereo,bucket "
        "(default all: a first and a second segment process, warmup then segment, a first "
        "demo and a first stereo, each beside the same command with --no-compile-cache, and "
        "a segment at a new size of (a)'s shape bucket beside --shape-buckets off; minutes "
        "of CPU, ~11 first compilations per --repeats, the reference first in odd repeats)",
    )  # fmt: skip
    p.set_defaults(func=run)
    return p  # fmt: skip


def find_provider(what: str):
    """The benchmark function for ``what`` (first of :data:`PROVIDERS` that exists)."""
    for mod, fn in PROVIDERS[what]:
        if mod.endswith(".py"):
            path = Path(mod)
            if not path.exists():
                continue
            spec = importlib.util.spec_from_file_location(f"_jaxcr_bench_{path.stem}", path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        else:
            if importlib.util.find_spec(mod.rsplit(".", 1)[0]) is None:
                continue
            try:
                module = importlib.import_module(mod)
            except ModuleNotFoundError:
                continue
        if hasattr(module, fn):
            return getattr(module, fn), f"{mod}:{fn}"
        if mod.endswith(".py") and hasattr(module, "main"):
            # a script benchmark: main(argv) -> int, writing its own Markdown to -o
            return _ScriptProvider(module.main), f"{mod}:main"
    where = ", ".join(f"{m}:{f}" for m, f in PROVIDERS[what])
    raise InputError(f"no '{what}' benchmark in this build (looked for {where})", field="what")


class _ScriptProvider:
    """Wraps an experiment script's ``main(argv)``: passes ``--batch/--repeats/--seed`` (when
    given) and ``-o``; the script writes the Markdown report itself."""

    def __init__(self, main):
        self.main = main

    def __call__(self, args, out: Path) -> int:
        argv = ["-o", str(out)]
        for opt in ("batch", "repeats", "frames"):
            v = getattr(args, opt)
            if v is not None:
                argv += [f"--{opt}", str(v)]
        argv += ["--seed", str(args.seed)]
        if args.size is not None:
            argv += ["--size", args.size]
        return int(self.main(argv) or 0)


def _call(fn, args) -> dict:
    """Call ``fn`` with the CLI options it accepts (by parameter name)."""
    opts = {"repeats": args.repeats, "frames": args.frames, "batch": args.batch,
            "seed": args.seed, "previous": getattr(args, "previous", False) or None,
            "only": getattr(args, "only", None)}  # fmt: skip
    if args.size is not None:
        from jaxcr.synth.generate import parse_size

        opts["size"] = parse_size(args.size)
    params = inspect.signature(fn).parameters
    kw = {k: v for k, v in opts.items() if v is not None and k in params}
    out = fn(**kw)
    if not isinstance(out, dict):
        raise TypeError(f"benchmark returned {type(out).__name__}, expected a dict")
    return out


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        return f"{v:.4g}"
    return str(v)


def _fmt_s(v) -> str:
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "n/a"
    return f"{1e3 * v:.3f} ms" if v < 1.0 else f"{v:.3f} s"


#: other spellings of the recognised keys: key -> (recognised key, scale to seconds)
ALIASES = {
    "batch_ms_per_frame_median": ("median_s", 1e-3),
    "compile_s_batch": ("compile_s", 1.0),
    "reference_ms_per_frame_median": ("reference_median_s", 1e-3),
    "speedup_vs_reference": ("ratio", 1.0),
}


def normalise(result: dict) -> dict:
    """Map :data:`ALIASES` onto the recognised keys, fill ``ratio`` from the medians when
    missing, and flatten nested dicts (``warm_start.cold_steps_mean``)."""
    r = {}
    for k, v in result.items():
        if isinstance(v, dict) and k != "meta":
            r.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        else:
            r[k] = v
    for alias, (key, scale) in ALIASES.items():
        if r.get(key) is None and isinstance(r.get(alias), (int, float)):
            r[key] = r[alias] * scale
            if key == "median_s":
                r.setdefault("unit", "frame")
    if r.get("ratio") is None and r.get("median_s") and r.get("reference_median_s"):
        r["ratio"] = r["reference_median_s"] / r["median_s"]
    return r


def metadata() -> dict:
    from jaxcr.cli.segment import versions

    return {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": platform.machine(),
        "processor": platform.processor() or "unknown",
        "cpus": _cpu_count(),
        "command": " ".join(["jaxcr"] + sys.argv[1:]),
        **versions(),
    }


def _cpu_count() -> int | None:
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count()


def to_markdown(result: dict, meta: dict, provider: str) -> str:
    r = result
    unit = r.get("unit", "call")
    lines = [f"# Benchmark: {r.get('name', provider)}", ""]
    lines += ["| | value |", "|---|---|"]
    if r.get("median_s") is not None or not r.get("rows"):
        lines.append(f"| median per {unit} | {_fmt_s(r.get('median_s'))} |")
    if r.get("spread_s") is not None:
        lines.append(f"| spread | {_fmt_s(r.get('spread_s'))} |")
    if r.get("compile_s") is not None:
        lines.append(f"| compile (excluded above) | {_fmt_s(r.get('compile_s'))} |")
    if r.get("reference") is not None:
        lines.append(f"| reference | {r['reference']} |")
        lines.append(f"| reference median per {unit} | {_fmt_s(r.get('reference_median_s'))} |")
    if r.get("ratio") is not None:
        lines.append(f"| speed-up vs reference | {_fmt(float(r['ratio']))}x |")
    known = {"name", "median_s", "spread_s", "compile_s", "reference", "reference_median_s",
             "ratio", "unit", "rows", "notes", "console_columns"}  # fmt: skip
    for k, v in r.items():
        if k in known or k in ALIASES or k == "meta":
            continue
        if isinstance(v, (int, float, str, bool)):
            lines.append(f"| {k} | {_fmt(v)} |")
        elif isinstance(v, (list, tuple)) and all(isinstance(x, (int, float)) for x in v):
            lines.append(f"| {k} | {', '.join(_fmt(x) for x in v)} |")
    rows = r.get("rows") or []
    if rows:
        cols = list(dict.fromkeys(k for row in rows for k in row))
        lines += ["", "| " + " | ".join(cols) + " |", "|---" * len(cols) + "|"]
        for row in rows:
            lines.append("| " + " | ".join(_fmt(row.get(c, "")) for c in cols) + " |")
    if r.get("notes"):
        lines += ["", str(r["notes"])]
    lines += ["", "## Metadata", "", f"- provider: `{provider}`"]
    lines += [f"- {k}: `{v}`" for k, v in meta.items()]
    return "\n".join(lines) + "\n"


#: upper bound of --batch: keeps a typo (e.g. 10000000) from exhausting the shared machine's
#: memory (the CTR batch holds N = 97 frames per joint vector)
MAX_BATCH = 65536


def _check_counts(args) -> None:
    for opt in ("repeats", "frames", "batch"):
        v = getattr(args, opt)
        if v is not None and v < 1:
            raise InputError(f"--{opt} must be >= 1, got {v}", field=opt)
    if args.batch is not None and args.batch > MAX_BATCH:
        raise InputError(f"--batch must be <= {MAX_BATCH}, got {args.batch}", field="batch")
    from jaxcr.limits import MAX_REPEATS, check_count, check_frames

    if args.frames is not None:
        check_frames(args.frames, "frames")
    if args.repeats is not None:
        check_count(args.repeats, "repeats", 1, MAX_REPEATS)
    if args.size is not None:
        from jaxcr.synth.generate import parse_size

        parse_size(args.size)
    if getattr(args, "only", None) is not None:
        if args.what != "compile":
            raise InputError("--only applies to 'jaxcr bench compile' only", field="only")
        from jaxcr.benchmarks.compile import parse_only

        parse_only(args.only)


def run(args) -> int:
    _check_counts(args)
    fn, provider = find_provider(args.what)
    # the report's folder is made (or refused, exit 2) before minutes of benchmarking, and
    # scripts get an absolute path (bench_fk.py's makedirs(dirname("x.md")) failed on "")
    out = Path(args.out or f"bench_{args.what}.md").absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    if not os.access(out.parent, os.W_OK):
        raise InputError("cannot write the report here (folder not writable)", file=str(out))
    if isinstance(fn, _ScriptProvider):
        code = fn(args, out)
        print(f"report: {out} (written by {provider})")
        return code
    result = normalise(_call(fn, args))
    meta = metadata()
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"jaxcr bench {args.what}: {result.get('name', provider)}")
    t.add_column("")
    t.add_column("value", justify="right")
    unit = result.get("unit", "call")
    if result.get("median_s") is not None or not result.get("rows"):
        t.add_row(f"median per {unit}", _fmt_s(result.get("median_s")))
    for key, label in (("spread_s", "spread"), ("compile_s", "compile"),
                       ("reference_median_s", f"reference ({result.get('reference')})")):  # fmt: skip
        if result.get(key) is not None:
            t.add_row(label, _fmt_s(result[key]))
    if result.get("ratio") is not None:
        t.add_row("speed-up vs reference", f"{_fmt(float(result['ratio']))}x")
    console = Console()
    if t.row_count:
        console.print(t)
    if result.get("rows"):
        console.print(_rows_table(result["rows"], f"jaxcr bench {args.what}",
                                  result.get("console_columns")))  # fmt: skip
    R.atomic_write_text(out, to_markdown(result, meta, provider))
    R.atomic_write_text(out.with_suffix(".json"), json.dumps(
        R.to_jsonable({"result": result, "meta": meta, "provider": provider}), indent=2))  # fmt: skip
    print(f"report: {out}")
    for row in result.get("rows") or []:
        if row.get("error"):
            print(f"{row.get('row', '?')}: {row['error']}", file=sys.stderr)
    if result.get("failed"):
        print(f"jaxcr bench {args.what}: {result['failed']} row(s) failed (see the report)",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def _rows_table(rows: list[dict], title: str, columns: list[str] | None = None):
    """A rich table of a benchmark's ``rows``: ``columns`` (the result's ``console_columns``),
    else the columns of every row, in the order seen."""
    from rich.table import Table

    t = Table(title=title)
    cols = columns or list(dict.fromkeys(k for row in rows for k in row))
    for c in cols:
        t.add_column(c, overflow="fold")
    for row in rows:
        t.add_row(*(_fmt(row.get(c, "")) for c in cols))
    return t
