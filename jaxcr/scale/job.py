"""The bookkeeping of a record-per-item job (``jaxcr fk``, ``jaxcr manifold query``) under
``--shard`` and ``--executor``: which items are done, which run, and where their records go.

``segment`` and ``stereo`` have their own (older) bookkeeping; the commands that used to write
their outputs in one go at the end use this one. Layout of OUT (docs/scale-out.md):

- ``run.json`` (``jaxcr.job-run/1``: ``command``, ``inputs`` -- paths and content digests --,
  ``options``): the job. An unsharded run whose ``run.json`` differs starts over (the command
  used to replace its outputs on every run); a shard refuses a job that differs from OUT's or
  another shard's (shards of one job must agree).
- ``results.jsonl`` (unsharded) or ``shards/I-of-N/results.jsonl``: one record per item,
  appended by the driver alone as items complete (:func:`jaxcr.scale.executor.run_frames`);
  the item's files (if any) are written by the worker before its record (atomic rename).
- ``DONE`` (in the same folder) once every item of the run (or shard) has a record.

Resume: a rerun with the same ``run.json`` skips every item recorded by OUT or any shard (a
failed item is a result, as in ``stereo``; delete the folder to re-run it). The command writes
its whole-job outputs (``tips.csv``, ``estimates.csv`` ...) from the merged records once every
item has one: an unsharded run always, a shard when it finds the others done (the last shard
to finish; two finishing at once write identical files by atomic rename).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import shutil
from pathlib import Path

from jaxcr.errors import InputError

RUN_FORMAT = "jaxcr.job-run/1"
RESULTS = "results.jsonl"
DONE = "DONE"


def file_digest(path: str | Path) -> str:
    """sha256 of a file's bytes (the job's identity: the same path with other content is
    another job)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_keyed(path: str | Path, key: str) -> list[dict]:
    """The records of a ``results.jsonl`` keyed by ``key``: one per item, the last winning
    (in its first position); a line cut by a killed run (no newline) is ignored."""
    path = Path(path)
    if not path.exists():
        return []
    merged: dict[str, dict] = {}
    data = path.read_bytes()
    for lineno, line in enumerate(data.split(b"\n")[:-1], start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as err:
            raise InputError(f"line {lineno}: malformed JSON ({err.msg})", file=str(path)) from None
        if not isinstance(rec, dict) or key not in rec:
            raise InputError(f"line {lineno}: not a record (no {key!r})", file=str(path))
        merged[str(rec[key])] = rec
    return list(merged.values())


class Job:
    """One run of a record-per-item command into OUT (the lock is already held: the caller
    ran :func:`jaxcr.io.outdir.claim` or :func:`jaxcr.scale.shards.claim_shard`)."""

    def __init__(self, out, command: str, run_info: dict, key: str, shard=None,
                 start_over=None):  # fmt: skip
        """``start_over()``: removes the command's own files of an earlier, different job
        (called for an unsharded run whose ``run.json`` differs)."""
        from jaxcr.scale.shards import shard_dir

        self.out, self.command, self.key, self.shard = Path(out), command, key, shard
        self._start_over = start_over
        self.log_dir = self.out if shard is None else shard_dir(self.out, shard)
        self.info = {"format": RUN_FORMAT, "command": command, **run_info}
        self._check_run()

    # ------------------------------------------------------------------ run.json

    def _check_run(self) -> None:
        from jaxcr.io.results import atomic_write_json, to_jsonable
        from jaxcr.scale.shards import SHARDS_DIR, shard_dirs

        mine = self.log_dir / "run.json"
        want = to_jsonable(self.info)
        others = [self.out / "run.json"] + [d / "run.json" for _, d in shard_dirs(self.out)]
        differ = [p for p in others if p.exists() and _read(p) != want]
        if differ and self.shard is None:
            # an unsharded run of another job: start over (no shard runs: OUT is locked)
            for name in (RESULTS, DONE, "run.json"):
                (self.out / name).unlink(missing_ok=True)
            shutil.rmtree(self.out / SHARDS_DIR, ignore_errors=True)
            if self._start_over is not None:
                self._start_over()
        elif differ:
            p = differ[0]
            raise InputError(
                f"OUT holds a {self.command} job with other inputs or options ({p}); shards of "
                "one job must have the same inputs and options: choose a new -o",
                file=str(self.out),
            )
        self.log_dir.mkdir(parents=True, exist_ok=True)
        if not mine.exists():
            atomic_write_json(mine, {**self.info, "created": _now()})

    # ------------------------------------------------------------------ records

    def records(self) -> dict[str, dict]:
        """Every item's record in OUT and its shards (this run's own file last: it wins)."""
        from jaxcr.scale.shards import results_files

        merged: dict[str, dict] = {}
        files = [f for f in results_files(self.out, RESULTS) if f != self.log_dir / RESULTS]
        for f in [*files, self.log_dir / RESULTS]:
            for rec in read_keyed(f, self.key):
                merged[str(rec[self.key])] = rec
        return merged

    def run(self, items: list[str], spec, executor, *, chunk: int, local_worker=None,
            progress: str | None = None, unit: str = "item",
            quiet: bool = False) -> tuple[dict[str, dict], list[dict]]:  # fmt: skip
        """Process this run's items (``items``: the whole job's, in order; a shard takes its
        block) that have no record yet. Returns (every item's record so far, this run's new
        records)."""
        from jaxcr.io.results import ResultsLog, atomic_write_text
        from jaxcr.scale.executor import run_frames

        mine = items if self.shard is None else self.shard.select(items)
        done = self.records()
        todo = [i for i in mine if i not in done]
        bar = None
        if progress and todo and not quiet:
            from jaxcr.progress import progress as progress_bar

            bar = progress_bar(total=len(todo), desc=progress, unit=unit)
        with ResultsLog(self.log_dir / RESULTS) as log:
            stats = run_frames(spec, todo, log, executor, chunk=chunk, key=self.key,
                               local_worker=local_worker,
                               on_chunk=None if bar is None else bar.update)  # fmt: skip
        if bar is not None:
            bar.close()
        if executor.kind != "local" and self.shard is None:
            from jaxcr.io.outdir import clean_leftovers

            clean_leftovers(self.out)  # a SIGKILLed worker's temporary files (OUT is locked)
        for rec in stats.records:
            done[str(rec[self.key])] = rec
        self.stats = stats
        if all(i in done for i in mine):
            atomic_write_text(self.log_dir / DONE, _now() + "\n")
        return done, stats.records


def _read(path: Path):
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if isinstance(d, dict):
        d.pop("created", None)
    return d


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
