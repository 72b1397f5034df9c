"""Output folders of every ``jaxcr`` command: who may write into OUT, and who is writing now.

One rule for every command that writes a folder (``segment``, ``synth``, ``stereo``,
``motion``, ``model-object``, ``manifold query``, ...):

- **OUT must be new, empty, or an earlier run of the same command.** A folder holding a
  user's files, a dataset, or another command's output is refused (exit 2), so no user file
  and no other run's ``summary.json`` / ``report.md`` is ever replaced. A folder is "an
  earlier run of command C" when its owner file ``OUT/.jaxcr-out.json`` names C (written when
  a command first claims OUT), or, for folders written before that file existed, when the
  command recognises its own files (e.g. segment's ``run.json``).
- **One writer at a time.** While a command runs it holds the lock file ``OUT/.jaxcr.lock``.
  A second run into the same OUT is refused (exit 2) with one line naming the holder; this
  includes ``--overwrite``, which therefore cannot wipe a run while another process holds it.
- **Stale locks.** A lock whose process is gone (same host, and the pid no longer runs, or
  now belongs to a process started at another time) is stale, and so is an unreadable
  (empty, cut) lock older than :data:`UNREADABLE_STALE_S`: the next run reports it (a
  warning on the ``jaxcr`` logger, printed on stderr) and takes it over. A lock from another host cannot be checked and is never taken
  over; the refusal says so and which file to delete.
- **Leftovers.** Once the lock is held, temporary files left by a killed run (``.NAME.*.tmp``
  from :func:`jaxcr.io.results.atomic_write_bytes`, and ``NAME.tmp``) are removed: no other
  process can be writing them.

Lock file format (``jaxcr.lock/1``, JSON, created atomically with ``O_CREAT | O_EXCL``, so
exactly one process wins a race)::

    {"format": "jaxcr.lock/1", "command": "segment", "pid": 12345, "host": "node7",
     "pid_start": 8812345, "started": "2026-12-01T21:00:00+00:00", "argv": ["jaxcr", ...]}

``pid_start`` is the process start time in clock ticks since boot (field 22 of
``/proc/<pid>/stat``; ``null`` where there is no ``/proc``); with ``host`` and ``pid`` it
identifies the holder even when the pid is reused. Another executor (a Ray or shard worker)
can hold an OUT the same way: create the file with ``O_EXCL`` and this content (its own pid,
host and start time), and delete it when done.

Shards (``--shard I/N``, :mod:`jaxcr.scale.shards`): shard I holds
``OUT/shards/I-of-N/.jaxcr.lock`` (same format) instead of ``OUT/.jaxcr.lock``; :func:`claim`
refuses while any shard's lock is live, and a shard refuses while ``OUT/.jaxcr.lock`` is. A Ray
run's driver holds ``OUT/.jaxcr.lock`` for its workers, which write frame files only.

Interruption: :func:`release_all` deletes the locks this process holds; the CLI calls it on
exit, also after Ctrl-C (:mod:`jaxcr.cli`).
"""

from __future__ import annotations

import atexit
import datetime as _dt
import json
import logging
import os
import re
import socket
import sys
import time
from pathlib import Path

from jaxcr.errors import InputError

# warnings go to the "jaxcr" logger: the CLI prints them on stderr (jaxcr.cli.main), and a
# library user without logging configured sees them on stderr too (logging.lastResort)
_log = logging.getLogger(__name__)

LOCK_FILE = ".jaxcr.lock"
OWNER_FILE = ".jaxcr-out.json"
LOCK_FORMAT = "jaxcr.lock/1"
OWNER_FORMAT = "jaxcr.out/1"
#: entries of OUT that do not make it "not empty" (our own bookkeeping)
BOOKKEEPING = (LOCK_FILE, OWNER_FILE)

_HELD: list[Path] = []  # lock files held by this process, in order of acquisition
atexit.register(lambda: release_all())  # library callers outside the CLI: released at exit


# --------------------------------------------------------------------------- process identity


def _pid_start(pid: int) -> int | None:
    """Start time of process ``pid`` in clock ticks since boot, or None (no /proc, or no such
    process)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may hold spaces: split after it
    try:
        return int(data[data.rindex(b")") + 2 :].split()[19])
    except (ValueError, IndexError):
        return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        return True
    except OSError:
        return False
    return True


def lock_info(command: str) -> dict:
    """The lock content for this process (format ``jaxcr.lock/1``)."""
    return {
        "format": LOCK_FORMAT,
        "command": command,
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "pid_start": _pid_start(os.getpid()),
        "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "argv": list(sys.argv),
    }


def read_lock(path: str | os.PathLike) -> dict | None:
    """The lock file's content, ``{}`` when it is unreadable or not a lock (e.g. cut by a
    full disk), None when it does not exist."""
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read().decode("utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def is_stale(info: dict) -> bool:
    """True when the holder named by ``info`` is certainly gone: same host and its pid does not
    run, or runs a process started at another time (pid reused). An unreadable lock, or one
    from another host, is not known to be stale."""
    pid, host = info.get("pid"), info.get("host")
    if not isinstance(pid, int) or isinstance(pid, bool) or host != socket.gethostname():
        return False
    if not _pid_alive(pid):
        return True
    start = info.get("pid_start")
    now = _pid_start(pid)
    return isinstance(start, int) and now is not None and now != start


#: an unreadable lock older than this (seconds) was abandoned between its creation and its
#: content being written (a holder writes it at once): it is stale
UNREADABLE_STALE_S = 10.0


def _abandoned(path: Path, info: dict) -> bool:
    if info:
        return False
    try:
        return time.time() - path.stat().st_mtime > UNREADABLE_STALE_S
    except OSError:
        return False


def describe(info: dict) -> str:
    """``jaxcr segment (pid 12345 on node7, started 2026-...)`` for a lock's content."""
    if not info:
        return "an unknown process (unreadable lock file)"
    cmd = info.get("command") or "?"
    return (
        f"jaxcr {cmd} (pid {info.get('pid', '?')} on {info.get('host', '?')}, "
        f"started {info.get('started', '?')})"
    )


# --------------------------------------------------------------------------- locking


def acquire(out: str | os.PathLike, command: str) -> Path:
    """Create ``OUT/.jaxcr.lock`` for this process (OUT must exist). A live holder raises
    :class:`InputError` naming it; a stale lock is reported on stderr and taken over."""
    path = Path(out) / LOCK_FILE
    data = (json.dumps(lock_info(command)) + "\n").encode("utf-8")
    for _ in range(5):  # a few rounds: a racing process may take a stale lock over first
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            info = read_lock(path)
            if info is None:
                continue  # released meanwhile
            if path in _HELD and info.get("pid") == os.getpid():
                return path  # re-entrant: this process holds it already (library callers)
            if not (is_stale(info) or _abandoned(path, info)):
                raise InputError(
                    f"output folder is in use by {describe(info)}; wait for it to finish, or "
                    f"if it is gone delete {path}",
                    file=str(out),
                ) from None
            # Move the stale lock aside under a unique name: of two processes taking it over,
            # only one rename succeeds; the other finds the new lock on its next round.
            aside = path.with_name(f"{LOCK_FILE}.stale.{os.getpid()}")
            try:
                os.rename(path, aside)
            except FileNotFoundError:
                continue
            os.unlink(aside)
            _log.warning(
                "jaxcr %s: %s: taking over a stale lock of %s, which is no longer running",
                command, out, describe(info),
            )  # fmt: skip
            continue
        try:
            os.write(fd, data)
            os.fsync(fd)
        except OSError as err:  # e.g. a full disk: no half-written lock is left behind
            os.close(fd)
            os.unlink(path)
            raise OSError(err.errno, err.strerror or os.strerror(err.errno), str(path)) from None
        os.close(fd)
        _HELD.append(path)
        return path
    raise InputError("could not take the output folder's lock (contended)", file=str(path))


def release(path: str | os.PathLike) -> None:
    """Delete a lock this process holds (no-op for one it does not hold)."""
    path = Path(path)
    if path not in _HELD:
        return
    _HELD.remove(path)
    info = read_lock(path)
    if info and info.get("pid") == os.getpid():
        try:
            os.unlink(path)
        except OSError:
            pass


def held() -> list[Path]:
    """The lock files this process holds, oldest first."""
    return list(_HELD)


def release_all(since: int = 0) -> None:
    """Release the locks acquired after the first ``since`` (all by default). Safe to call from
    a signal handler (only unlinks files)."""
    for path in list(_HELD[since:]):
        release(path)


# --------------------------------------------------------------------------- claiming OUT


def owner(out: str | os.PathLike) -> str | None:
    """The command named by ``OUT/.jaxcr-out.json``, or None."""
    try:
        with open(Path(out) / OWNER_FILE, "rb") as f:
            info = json.loads(f.read().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return info.get("command") if isinstance(info, dict) else None


def _user_entries(out: Path) -> list[str]:
    return sorted(e.name for e in os.scandir(out) if e.name not in BOOKKEEPING)


def _what(out: Path, entries: list[str]) -> str:
    if "dataset.json" in entries:
        return "a dataset"
    if "stereo.json" in entries:
        return "a stereo dataset"
    if "run.json" in entries or "results.jsonl" in entries:
        return "a jaxcr run's output"
    return "other files (" + ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "") + ")"


#: the hidden temporary names of the writers that add the pid (``.NAME.tmp1234``, e.g.
#: jaxcr.io.dataset's ``.dataset.json.tmp1234`` and ``.000.npy.tmp1234.npy``)
_PID_TMP = re.compile(r"^\..+\.tmp\d+(\.[A-Za-z0-9]+)?$")


def clean_leftovers(out: str | os.PathLike) -> list[Path]:
    """Delete the temporary files a killed run left anywhere under OUT (``.NAME.*.tmp``,
    ``NAME.tmp`` and ``.NAME.tmpPID[.EXT]``; the caller holds the lock, so no process is
    writing them). Returns them."""
    removed = []
    for root, _dirs, files in os.walk(out):
        for name in files:
            if (name.endswith(".tmp") or name.startswith(f"{LOCK_FILE}.stale.")
                    or _PID_TMP.match(name)):  # fmt: skip
                p = Path(root) / name
                try:
                    p.unlink()
                    removed.append(p)
                except OSError:
                    pass
    return removed


def claim(out: str | os.PathLike, command: str, recognise=None) -> Path:
    """Take OUT for ``command``: create it if missing, take its lock, and check that it is new,
    empty, or an earlier run of ``command``; then delete a killed run's temporary files.

    Args:
        out: the output folder.
        command: the command's name as the user types it (``"segment"``, ``"manifold query"``).
        recognise: optional ``f(out) -> bool``, True when OUT holds this command's output
            written before owner files existed (e.g. segment's ``run.json``).

    Returns the lock file; the lock is released by :func:`release` / :func:`release_all`
    (the CLI does that on exit). Raises :class:`InputError` (exit 2) when OUT is not a folder,
    belongs to something else, or another process holds it.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", file=str(out))
    out.mkdir(parents=True, exist_ok=True)
    lock = acquire(out, command)
    try:
        from jaxcr.scale.shards import refuse_if_shards_run

        refuse_if_shards_run(out)  # after taking our lock: of two racing runs one sees the other
        prev = owner(out)
        if prev is None:
            entries = _user_entries(out)
            if entries and not (recognise is not None and recognise(out)):
                raise InputError(
                    f"output folder is not empty and holds {_what(out, entries)}, not written by "
                    f"jaxcr {command}; choose a new or empty folder",
                    file=str(out),
                )
            from jaxcr.io.results import atomic_write_json

            atomic_write_json(
                out / OWNER_FILE,
                {
                    "format": OWNER_FORMAT,
                    "command": command,
                    "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                },
            )
        elif prev != command:
            raise InputError(
                f"output folder holds the output of jaxcr {prev}, not written by jaxcr {command}; "
                "choose a new or empty folder",
                file=str(out),
            )
        clean_leftovers(out)
    except BaseException:
        release(lock)
        raise
    return lock
