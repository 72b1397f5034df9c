"""Write ``tests/slow_tests.txt``: the tests to mark ``slow``, from a measured run.

A test is slow when it used at least ``--cpu`` seconds of CPU (its own process and the
subprocesses it waited for) in a run with ``JAXCR_TESTS_COMPILE_LOG=DIR`` (tests/conftest.py
writes one line per test). CPU seconds rather than wall seconds, so a run on a loaded machine
gives the same list. A module fixture's cost is charged to the module's first test; when that
test is marked slow, ``-m "not slow"`` charges it to the next one, so the list is made from a
full run and then merged with a ``-m "not slow"`` run's log until that run has no slow test:

    JAXCR_TESTS_COMPILE_LOG=/tmp/clog pytest -n 2
    python -m tests.helpers.slow_marks /tmp/clog
    JAXCR_TESTS_COMPILE_LOG=/tmp/clog2 pytest -n 2 -m "not slow"
    python -m tests.helpers.slow_marks /tmp/clog2 --merge

Tests listed in the file but gone from the suite are dropped; new tests are not slow until a
run measures them.
"""

from __future__ import annotations

import argparse
import glob
import os

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LIST = os.path.join(HERE, "slow_tests.txt")
HEADER = """\
# Tests marked `slow` by tests/conftest.py (one pytest node id per line), so that
# `pytest -m "not slow"` is a quick subset. Generated from measured CPU seconds by
# `python -m tests.helpers.slow_marks LOGDIR` (see that module): a test is listed when it used
# >= {cpu:g} s of CPU in a run (the last merge used 0.8 s). Edit by re-running it, not by hand.
"""


def read_log(folder: str) -> dict[str, float]:
    """node id -> CPU seconds (own + waited-for subprocesses) from a compile-log folder."""
    cpu: dict[str, float] = {}
    for path in glob.glob(os.path.join(folder, "*.tsv")):
        with open(path) as f:
            for line in f:
                parts = line.rstrip("\n").split("\t")
                if len(parts) < 9:  # a log written before the CPU columns existed
                    continue
                cpu[parts[0]] = cpu.get(parts[0], 0.0) + float(parts[7]) + float(parts[8])
    return cpu


def read_list(path: str = LIST) -> set[str]:
    if not os.path.exists(path):
        return set()
    with open(path) as f:
        return {s.strip() for s in f if s.strip() and not s.startswith("#")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logdir", help="folder written by JAXCR_TESTS_COMPILE_LOG")
    ap.add_argument("--cpu", type=float, default=1.0, help="CPU seconds from which a test is slow")
    ap.add_argument(
        "--summary",
        action="store_true",
        help="print CPU seconds by module (largest first) and write nothing",
    )
    ap.add_argument(
        "--merge",
        action="store_true",
        help="add to the current list instead of replacing it (for a -m 'not slow' run)",
    )
    args = ap.parse_args(argv)
    cpu = read_log(args.logdir)
    if not cpu:
        raise SystemExit(f"{args.logdir}: no compile-log lines with CPU columns")
    if args.summary:
        by_module: dict[str, float] = {}
        for t, s in cpu.items():
            by_module[t.split("::")[0]] = by_module.get(t.split("::")[0], 0.0) + s
        print(f"{len(cpu)} tests, {sum(cpu.values()):.0f} s of CPU")
        for m, s in sorted(by_module.items(), key=lambda kv: -kv[1]):
            print(f"{s:8.1f}  {m}")
        return 0
    slow = {t for t, s in cpu.items() if s >= args.cpu}
    if args.merge:
        slow |= read_list()
    with open(LIST, "w") as f:
        f.write(HEADER.format(cpu=args.cpu))
        f.writelines(t + "\n" for t in sorted(slow))
    kept = sum(s for t, s in cpu.items() if t not in slow)
    print(
        f"{len(slow)} slow tests written to {LIST}; the other {len(cpu) - len(slow & set(cpu))} "
        f"measured tests used {kept:.0f} s of CPU in this log"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
