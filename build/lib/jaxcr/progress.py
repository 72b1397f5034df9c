"""Progress reporting of long loops, one policy for every ``jaxcr`` command.

Policy (:func:`mode`):

- stderr is a terminal: a tqdm bar on stderr (``"bar"``);
- stderr is redirected (a log file, a pipe): no bar and no carriage returns, but a few plain
  lines on stderr, one per ~10 % of a known total (or every ``every`` items when the total is
  not known) and at least one a minute, each with the elapsed time, so a log shows the run is
  alive (``"lines"``);
- the environment variable ``JAXCR_PROGRESS`` overrides the terminal test: ``1`` forces bars,
  ``0`` forces plain lines, ``auto`` (or unset) is the default above. Any other value is an
  :class:`~jaxcr.errors.InputError` (the CLI checks it before running a command).

A command's ``--quiet`` (``enabled=False``) silences both. Library loops that draw progress
(synthetic data generators, contour extraction) use :func:`progress` as well, so they follow
the same policy when a command calls them.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TextIO

from jaxcr.errors import InputError

ENV = "JAXCR_PROGRESS"
_ON = ("1", "on", "true", "yes")
_OFF = ("0", "off", "false", "no")
_AUTO = ("", "auto")
#: longest quiet gap (seconds) between two plain lines while items keep completing
MAX_SILENCE_S = 60.0


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def mode(stream: TextIO | None = None, env: str | None = None) -> str:
    """``"bar"`` or ``"lines"``: how progress is shown on ``stream`` (default ``sys.stderr``).

    ``env`` is the override's value (default: the ``JAXCR_PROGRESS`` environment variable).
    Raises :class:`~jaxcr.errors.InputError` for a value other than 0/1/auto (and the
    synonyms on/off, true/false, yes/no).
    """
    value = os.environ.get(ENV, "") if env is None else env
    v = value.strip().lower()
    if v in _ON:
        return "bar"
    if v in _OFF:
        return "lines"
    if v in _AUTO:
        return "bar" if _isatty(sys.stderr if stream is None else stream) else "lines"
    raise InputError(f"environment variable {ENV}: expected 0, 1 or auto, got {value!r}")


def _plural(unit: str) -> str:
    if not unit or unit.endswith("s"):
        return unit
    return unit + ("es" if unit.endswith(("ch", "sh", "x")) else "s")


def _elapsed(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s"


class PlainProgress:
    """The ``"lines"`` mode: the subset of tqdm's interface the commands use (``update``,
    ``set_postfix_str``, ``set_description``, ``refresh``, ``close``, ``n``, ``total``,
    iteration, context manager), printing whole lines (no carriage returns) instead of
    redrawing a bar.

    With a known ``total``, a line is printed when ``n`` enters a new tenth of it; without,
    every ``every`` items; and in both cases when ``MAX_SILENCE_S`` seconds have passed since
    the last line. ``close`` prints the final count if it was not the last line printed.
    ``silent=True`` prints nothing (a command's ``--quiet``).
    """

    def __init__(
        self,
        iterable: Iterable | None = None,
        *,
        total: int | None = None,
        desc: str = "",
        unit: str = "item",
        every: int = 10,
        file: TextIO | None = None,
        silent: bool = False,
        clock=time.monotonic,
    ):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.iterable = iterable
        self.total = total
        self.desc = desc
        self.unit = unit
        self.every = max(1, int(every))
        self.file = file
        self.silent = silent
        self.postfix = ""
        self.n = 0
        self._clock = clock
        self._t0 = clock()
        self._last_t = self._t0
        self._last_n = 0
        self._last_postfix = ""
        self._closed = False

    # tqdm-compatible surface -------------------------------------------------------------

    def __iter__(self) -> Iterator:
        if self.iterable is None:
            raise TypeError("PlainProgress made without an iterable")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = str(s)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = desc or ""

    def refresh(self) -> None:
        """Print the current line now (e.g. after a new stage in ``set_postfix_str``), unless
        it is the same count and postfix as the last line printed."""
        if (self.n, self.postfix) != (self._last_n, self._last_postfix):
            self._emit()

    def update(self, n: int = 1) -> None:
        if n <= 0:
            return
        self.n += n
        if self._due():
            self._emit()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.n != self._last_n:
            self._emit()

    # ------------------------------------------------------------------------------------

    def _due(self) -> bool:
        if self._clock() - self._last_t >= MAX_SILENCE_S:
            return True
        if self.total:
            tenth = lambda k: math.floor(10 * min(k, self.total) / self.total)  # noqa: E731
            return tenth(self.n) > tenth(self._last_n)
        return self.n // self.every > self._last_n // self.every

    def line(self) -> str:
        """The current progress line, e.g. ``segment: 30/100 frames (30 %), 12.3 s``."""
        now = self._clock()
        head = f"{self.desc}: " if self.desc else ""
        if self.total:
            count = f"{self.n}/{self.total} {_plural(self.unit)} ({100 * self.n // self.total} %)"
        else:
            count = f"{self.n} {self.unit if self.n == 1 else _plural(self.unit)}"
        tail = f"; {self.postfix}" if self.postfix else ""
        return f"{head}{count}, {_elapsed(now - self._t0)}{tail}"

    def _emit(self) -> None:
        self._last_n, self._last_postfix = self.n, self.postfix
        self._last_t = self._clock()
        if self.silent:
            return
        f = sys.stderr if self.file is None else self.file
        print(self.line(), file=f, flush=True)


def progress(
    iterable: Iterable | None = None,
    *,
    total: int | None = None,
    desc: str = "",
    unit: str = "item",
    enabled: bool = True,
    every: int = 10,
    leave: bool = True,
    **bar_kwargs: Any,
):
    """A progress reporter following the module's policy: a tqdm bar on stderr (mode
    ``"bar"``), else a :class:`PlainProgress` (lines on stderr; silent when not ``enabled``).

    Use it as tqdm: iterate over it, or call ``update``/``set_postfix_str``/``close``.
    ``every`` is the line interval for an unknown ``total`` (plain lines only); ``leave`` and
    ``bar_kwargs`` (e.g. ``bar_format``, ``mininterval``) go to tqdm only.
    """
    if enabled and mode() == "bar":
        from tqdm import tqdm

        return tqdm(
            iterable,
            total=total,
            desc=desc,
            unit=unit,
            leave=leave,
            file=sys.stderr,
            disable=False,
            dynamic_ncols=True,
            **bar_kwargs,
        )
    return PlainProgress(
        iterable, total=total, desc=desc, unit=unit, every=every, silent=not enabled
    )
