"""``--shard i/n``: deterministic frame shards of one job, written into one output folder.

For Slurm array jobs (or any set of processes that do not talk to each other): process ``i``
of ``n`` takes the i-th of n contiguous, near-equal blocks of the command's frame list (the
order of the dataset; contiguous so that ``--warm-start`` sequences stay together inside a
shard), and writes

- its frames' files straight into OUT, as an unsharded run would (different shards never
  write the same frame, so they never write the same file);
- its bookkeeping into ``OUT/shards/<i>-of-<n>/``: ``run.json``, ``results.jsonl``,
  ``summary.json`` and ``DONE``, and its lock ``.jaxcr.lock`` (format ``jaxcr.lock/1``,
  :mod:`jaxcr.io.outdir`). Only one process appends to each results file, so no two processes
  ever append to one file (appends are not atomic across hosts on NFS).

Locks (docs/scale-out.md): a shard holds ``OUT/shards/<i>-of-<n>/.jaxcr.lock``; an unsharded
run holds ``OUT/.jaxcr.lock``. A shard refuses to start while a live unsharded run holds OUT,
while the same shard runs elsewhere, or while a shard of another split (a different n) runs;
an unsharded run refuses while any shard runs. Each side takes its own lock *before* looking
for the other's, so of two racing processes at least one sees the other.

Merging: :func:`read_all_records` reads ``OUT/results.jsonl`` and every shard's
``results.jsonl`` (a later record of a frame wins, as in :func:`jaxcr.io.results.read_results`);
``jaxcr evaluate OUT`` evaluates the merged records and names the frames that are missing.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from jaxcr.errors import InputError

SHARDS_DIR = "shards"
_SHARD_RE = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")
_DIR_RE = re.compile(r"^(\d+)-of-(\d+)$")
#: at most this many shards (a Slurm array larger than this is not a frame split)
MAX_SHARDS = 100_000


@dataclass(frozen=True)
class Shard:
    """Shard ``index`` (0-based) of ``count``."""

    index: int
    count: int

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def dirname(self) -> str:
        return f"{self.index}-of-{self.count}"

    def select(self, items: list) -> list:
        """This shard's contiguous block of ``items``: items ``[start, stop)`` with
        ``start = floor(index * len / count)``; blocks differ in size by at most one, cover
        every item exactly once, and depend only on the list and (index, count)."""
        n = len(items)
        start = self.index * n // self.count
        stop = (self.index + 1) * n // self.count
        return list(items[start:stop])


def parse_shard(text: str | None) -> Shard | None:
    """``"i/n"`` (0 <= i < n) as a :class:`Shard`; None for None. Bad text is an
    :class:`InputError` (exit 2)."""
    if text is None:
        return None
    m = _SHARD_RE.match(str(text))
    if not m:
        raise InputError(f"--shard {text!r}: expected I/N, e.g. 0/4 (shard I of N, 0-based)",
                         field="shard")  # fmt: skip
    i, n = int(m.group(1)), int(m.group(2))
    if not 1 <= n <= MAX_SHARDS or not 0 <= i < n:
        raise InputError(
            f"--shard {text}: need 0 <= I < N and 1 <= N <= {MAX_SHARDS} "
            "(e.g. I = $SLURM_ARRAY_TASK_ID, N = the array size)",
            field="shard",
        )
    return Shard(i, n)


def add_shard_argument(parser) -> None:
    """``--shard I/N`` on a command's parser."""
    parser.add_argument(
        "--shard",
        default=None,
        metavar="I/N",
        help="process only the I-th of N contiguous frame blocks (0-based, e.g. "
        "$SLURM_ARRAY_TASK_ID/N) into the same OUT; its records go to OUT/shards/I-of-N/, "
        "jaxcr evaluate OUT merges the shards (default: all frames)",
    )


def shard_dir(out: str | os.PathLike, shard: Shard) -> Path:
    return Path(out) / SHARDS_DIR / shard.dirname


def shard_dirs(out: str | os.PathLike) -> list[tuple[Shard, Path]]:
    """The shard folders present in OUT, ordered by (count, index)."""
    root = Path(out) / SHARDS_DIR
    found = []
    try:
        entries = list(os.scandir(root))
    except OSError:
        return []
    for e in entries:
        m = _DIR_RE.match(e.name)
        if m and e.is_dir():
            i, n = int(m.group(1)), int(m.group(2))
            if 0 <= i < n:
                found.append((Shard(i, n), Path(e.path)))
    return sorted(found, key=lambda t: (t[0].count, t[0].index))


# --------------------------------------------------------------------------- locks


def _live_holder(lock: Path) -> dict | None:
    """The content of ``lock`` when a live (or unverifiable) process holds it, else None."""
    from jaxcr.io import outdir

    info = outdir.read_lock(lock)
    if info is None or outdir.is_stale(info) or outdir._abandoned(lock, info):
        return None
    return info


def live_shards(out: str | os.PathLike) -> list[tuple[Shard, dict]]:
    """Shards of OUT whose lock is held by a live (or unverifiable) process."""
    from jaxcr.io.outdir import LOCK_FILE

    live = []
    for shard, d in shard_dirs(out):
        info = _live_holder(d / LOCK_FILE)
        if info is not None:
            live.append((shard, info))
    return live


def refuse_if_shards_run(out: str | os.PathLike) -> None:
    """For an unsharded run that holds ``OUT/.jaxcr.lock``: raise :class:`InputError` naming a
    shard that still runs."""
    from jaxcr.io import outdir

    live = live_shards(out)
    if live:
        shard, info = live[0]
        more = f" (and {len(live) - 1} more shard(s))" if len(live) > 1 else ""
        raise InputError(
            f"output folder is in use by shard {shard} of {outdir.describe(info)}{more}; wait "
            f"for the shards to finish, or if they are gone delete "
            f"{shard_dir(out, shard) / outdir.LOCK_FILE}",
            file=str(out),
        )


def claim_output(out: str | os.PathLike, command: str, shard: Shard | None, marker: str) -> Path:
    """Take OUT for ``command``, whole or one shard of it: :func:`jaxcr.io.outdir.claim` when
    ``shard`` is None, else :func:`claim_shard`. OUT counts as an earlier run of ``command`` when
    it holds ``marker`` (a file every run of the command writes) or a shards folder. Returns the
    lock (released by :func:`jaxcr.io.outdir.release`, or at exit)."""
    from jaxcr.io import outdir

    def recognise(o):
        return (Path(o) / marker).exists() or (Path(o) / SHARDS_DIR).is_dir()

    if shard is None:
        return outdir.claim(out, command, recognise=recognise)
    return claim_shard(out, command, shard, recognise=recognise)


def claim_shard(out: str | os.PathLike, command: str, shard: Shard, recognise=None) -> Path:
    """Take shard ``shard`` of OUT for ``command`` (see the module docstring): create OUT and
    the shard folder, take the shard's lock, and check that no unsharded run, no other process
    of this shard and no shard of another split runs, and that OUT is new, empty, or this
    command's output. Returns the shard's lock (released by :func:`jaxcr.io.outdir.release`)."""
    from jaxcr.io import outdir

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", file=str(out))
    whole = out / outdir.LOCK_FILE

    def refuse_whole():
        info = _live_holder(whole)
        if info is not None:
            raise InputError(
                f"output folder is in use by {outdir.describe(info)} (an unsharded run); wait "
                f"for it to finish, or if it is gone delete {whole}",
                file=str(out),
            )

    refuse_whole()  # before creating anything
    d = shard_dir(out, shard)
    d.mkdir(parents=True, exist_ok=True)
    lock = outdir.acquire(d, command)
    try:
        refuse_whole()  # again, now that our lock exists: one of two racing runs sees the other
        others = [(s, i) for s, i in live_shards(out) if s.count != shard.count]
        if others:
            s, info = others[0]
            raise InputError(
                f"output folder is in use by shard {s} of another split ({outdir.describe(info)});"
                f" shards of one job must share N (here {shard.count})",
                file=str(out),
            )
        _check_owner(out, command, recognise)
        outdir.clean_leftovers(d)  # our own temporary files only: other shards write in OUT
    except BaseException:
        outdir.release(lock)
        raise
    return lock


def _check_owner(out: Path, command: str, recognise) -> None:
    """OUT must be new, empty (apart from shards/ and bookkeeping) or ``command``'s output."""
    import datetime as _dt

    from jaxcr.io import outdir
    from jaxcr.io.results import atomic_write_json

    prev = outdir.owner(out)
    if prev is None:
        entries = [e for e in outdir._user_entries(out) if e != SHARDS_DIR]
        if entries and not (recognise is not None and recognise(out)):
            raise InputError(
                f"output folder is not empty and holds {outdir._what(out, entries)}, not "
                f"written by jaxcr {command}; choose a new or empty folder",
                file=str(out),
            )
        atomic_write_json(out / outdir.OWNER_FILE, {
            "format": outdir.OWNER_FORMAT, "command": command,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        })  # fmt: skip
    elif prev != command:
        raise InputError(
            f"output folder holds the output of jaxcr {prev}, not written by jaxcr {command}; "
            "choose a new or empty folder",
            file=str(out),
        )


# --------------------------------------------------------------------------- merging


def results_files(out: str | os.PathLike, name: str = "results.jsonl") -> list[Path]:
    """OUT's own results file and every shard's, in merge order (OUT first, then shards by
    (N, I)); only files that exist."""
    out = Path(out)
    files = [out / name] + [d / name for _, d in shard_dirs(out)]
    return [f for f in files if f.exists()]


def read_all_records(out: str | os.PathLike, reader=None, key: str = "frame",
                     name: str = "results.jsonl") -> list[dict]:  # fmt: skip
    """The merged records of OUT and all its shards: one per frame, the later file's record
    winning (a re-run supersedes), in first-seen order. ``reader(path) -> list[dict]``
    defaults to :func:`jaxcr.io.results.read_results`."""
    from jaxcr.io.results import read_results

    reader = reader or read_results
    merged: dict[str, dict] = {}
    for f in results_files(out, name):
        for rec in reader(f):
            merged[str(rec[key])] = rec
    return list(merged.values())


@dataclass(frozen=True)
class ShardStatus:
    """One shard folder of OUT: its shard, whether it finished (``DONE``), and its frame
    count in ``results.jsonl``."""

    shard: Shard
    done: bool
    records: int


def shard_status(out: str | os.PathLike, name: str = "results.jsonl") -> list[ShardStatus]:
    from jaxcr.io.results import read_results

    return [
        ShardStatus(s, (d / "DONE").exists(), len(read_results(d / name)))
        for s, d in shard_dirs(out)
    ]


def sharded_complete(out: str | os.PathLike) -> bool:
    """True when OUT was written by shards and every shard 0..N-1 of one N has ``DONE``."""
    by_n: dict[int, set[int]] = {}
    for st in shard_status(out):
        if st.done:
            by_n.setdefault(st.shard.count, set()).add(st.shard.index)
    return any(len(ix) == n for n, ix in by_n.items())


def missing_shards(out: str | os.PathLike) -> list[Shard]:
    """Shards of the split(s) present in OUT that have not finished (no folder or no DONE)."""
    status = shard_status(out)
    done = {(st.shard.count, st.shard.index) for st in status if st.done}
    counts = sorted({st.shard.count for st in status})
    return [Shard(i, n) for n in counts for i in range(n) if (n, i) not in done]
