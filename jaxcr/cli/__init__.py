"""The ``jaxcr`` command line. Each subcommand lives in ``jaxcr/cli/<name>.py`` and
exposes ``add_parser(subparsers)`` (registering its arguments and ``set_defaults(func=run)``)
and ``run(args) -> int``.

Exit codes: 0 success, 1 a run that failed (e.g. some frames failed), 2 bad usage or input
(including an output that cannot be written, e.g. a read-only folder), 130 interrupted
(SIGINT, Ctrl-C), 143 terminated (SIGTERM, e.g. ``kill``, a job scheduler or a container
stop).

Interruption (Ctrl-C, SIGINT): the handler installed by :func:`main` releases the output
folder's lock (:mod:`jaxcr.io.outdir`), prints one line and ends the process at once with
:func:`os._exit` (exit 130). It does not raise ``KeyboardInterrupt``: raised at an arbitrary
bytecode it can land in a garbage-collector callback (JAX's ``_xla_gc_callback``), where Python
prints and swallows it and the run goes on, and unwinding lets the interpreter finalise while
XLA's and OpenCV's native threads still run, which crashed with SIGSEGV (exit 139). Ending at
once is as safe as ``kill -9``, which every command survives: outputs are written atomically
(temporary name + rename) and per-item logs line by line, so ``--resume`` (or a rerun)
continues; the temporary files a killed run leaves are deleted when OUT is next claimed.

Termination (SIGTERM) is handled the same way, with the line ``jaxcr CMD: terminated`` and
exit 143 (128 + 15, what a shell reports for a process SIGTERM ended): the lock is released,
so the next run neither waits for nor reports a stale lock, and resumes like after Ctrl-C.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import os
import re
import signal
import sys
import threading
import warnings

from jaxcr.errors import InputError

# Order shown in --help.
COMMANDS = [
    "demo",
    "synth",
    "validate",
    "fk",
    "fit",
    "segment",
    "evaluate",
    "bench",
    "calibrate",
    "stereo",
    "manifold",
    "motion",
    "model_object",
    "warmup",
]


# reST markup of the module docstrings that become --help texts: roles (:func:`~a.b` shows as
# b), inline literals (``x``, possibly across a line break), interpreted text (`x`), strong
# emphasis (**x**) and the literal-block marker "::" ending a paragraph line
_REST = (
    (re.compile(r":[a-z]+(?::[a-z]+)?:`~[^`]*?([^`.]+)`"), r"\1"),
    (re.compile(r":[a-z]+(?::[a-z]+)?:`([^`]+)`"), r"\1"),
    (re.compile(r"``(.+?)``", re.S), r"\1"),
    (re.compile(r"`([^`]+)`_?"), r"\1"),
    (re.compile(r"\*\*(.+?)\*\*", re.S), r"\1"),
    (re.compile(r" ?::$", re.M), ":"),
)


def plain_text(text: str | None) -> str | None:
    """``text`` (a docstring-derived help text) with its reST markup removed, for --help."""
    if not text:
        return text
    for pattern, repl in _REST:
        text = pattern.sub(repl, text)
    return text


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Apply :func:`plain_text` to the description, epilog and argument helps of ``parser`` and
    of every subcommand parser below it."""
    parser.description = plain_text(parser.description)
    parser.epilog = plain_text(parser.epilog)
    for action in parser._actions:
        action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = plain_text(choice.help)
            for sub in dict.fromkeys(action.choices.values()):  # aliases share a parser
                _plain_help(sub)


class _Parser(argparse.ArgumentParser):
    """Bad usage is one line on stderr, ``PROG: error: MESSAGE (see PROG --help)``, exit 2,
    instead of argparse's multi-line usage block (subcommand parsers inherit the class)."""

    def error(self, message: str):
        line = " ".join(str(message).split())
        self.exit(2, f"{self.prog}: error: {line} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxcr",
        description="jaxcr: JAX batch estimation for the vision of continuum robots.",
    )
    from jaxcr import __version__

    parser.add_argument("--version", action="version", version=f"jaxcr {__version__}")
    parser.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="do not use the persistent compilation cache (default: on, in $JAXCR_CACHE_DIR "
        "or ~/.cache/jaxcr/jax; JAXCR_COMPILE_CACHE=0 also turns it off)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        modname = f"jaxcr.cli.{name}"
        if importlib.util.find_spec(modname) is None:
            continue
        importlib.import_module(modname).add_parser(sub)
    for sp in dict.fromkeys(sub.choices.values()):  # also accepted after the command's name
        sp.add_argument(
            "--no-compile-cache",
            action="store_true",
            default=argparse.SUPPRESS,  # unset here: the global flag's value stands
            help="do not use the persistent compilation cache (as jaxcr --no-compile-cache)",
        )
    _plain_help(parser)
    return parser


#: exit code and message per handled signal (see the module docstring)
_SIGNALS = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated")}


def _on_signal(state: dict):
    """The SIGINT/SIGTERM handler of :func:`main`; ``state`` holds the command name (known once
    the arguments are parsed) and the number of locks held before this run."""

    def handler(signum, frame):
        from jaxcr.io import outdir

        outdir.release_all(state["lock_base"])
        code, what = _SIGNALS.get(signum, (130, "interrupted"))
        name = f"jaxcr {state['command']}" if state["command"] else "jaxcr"
        # os.write, not print: the handler may run in the middle of a write to sys.stderr
        msg = f"\n{name}: {what}\n" if _tty(2) else f"{name}: {what}\n"
        try:
            os.write(2, msg.encode())
        except OSError:
            pass
        os._exit(code)  # see the module docstring: no unwinding, no interpreter finalisation

    return handler


def _tty(fd: int) -> bool:
    try:
        return os.isatty(fd)
    except OSError:
        return False


def _quiet_warnings(state: dict) -> None:
    """Warnings are not part of the one-line contract: numpy's RuntimeWarnings (overflow, an
    empty mean) and library deprecations are not shown, unless the user asked for them with
    ``python -W`` or ``PYTHONWARNINGS``; the others (e.g. synth's "true-robot kinematics did
    not converge") are one line each, ``jaxcr CMD: warning: MESSAGE``."""
    if sys.warnoptions:
        return
    for category in (RuntimeWarning, DeprecationWarning, PendingDeprecationWarning, FutureWarning):
        warnings.simplefilter("ignore", category)

    def one_line(message, category, filename, lineno, file=None, line=None):
        name = f"jaxcr {state['command']}" if state["command"] else "jaxcr"
        text = " ".join(str(message).split())
        print(f"{name}: warning: {text}", file=sys.stderr if file is None else file)

    warnings.showwarning = one_line  # restored by the caller's catch_warnings


class _StderrLines(logging.Handler):
    """The library's warnings (the ``jaxcr`` logger: a stale lock taken over, an unwritable
    compile cache) as plain lines on stderr: the library logs, the CLI prints. ``sys.stderr``
    is looked up per line, so a redirected stderr (pytest's capsys) receives them."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            print(self.format(record), file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001  (logging's contract: a handler never raises)
            self.handleError(record)


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    from jaxcr.io import outdir

    library_log = logging.getLogger("jaxcr")
    printer = _StderrLines(logging.WARNING)
    library_log.addHandler(printer)

    # installed first: importing the commands (JAX, OpenCV) takes seconds, and a Ctrl-C then
    # must end the process too
    state = {"command": None, "lock_base": len(outdir.held())}
    old_handlers = {}
    if threading.current_thread() is threading.main_thread():
        handler = _on_signal(state)
        old_handlers = {sig: signal.signal(sig, handler) for sig in _SIGNALS}
    try:
        with warnings.catch_warnings():
            _quiet_warnings(state)
            parser = build_parser()
            args = parser.parse_args(argv)
            if not getattr(args, "func", None):  # bare `jaxcr`: one line, as all bad usage
                parser.error("the following arguments are required: COMMAND")
            state["command"] = args.command
            return _run(args)
    finally:
        library_log.removeHandler(printer)
        outdir.release_all(state["lock_base"])
        for sig, old in old_handlers.items():
            signal.signal(sig, old)


def _run(args) -> int:
    try:
        from jaxcr.progress import mode as progress_mode

        progress_mode()  # a bad JAXCR_PROGRESS is bad input before any work (exit 2)
        from jaxcr.io.compile_cache import enable_compile_cache

        # before any compilation; a bad JAXCR_COMPILE_CACHE is bad input (exit 2), an
        # unwritable cache folder one warning
        enable_compile_cache(path=False if args.no_compile_cache else None)
        code = args.func(args)
    except InputError as err:
        print(f"jaxcr {args.command}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        # e.g. a read-only or full output folder, a file where a folder is expected: one line
        # naming the file (outputs are written atomically, so nothing partial looks complete)
        where = err.filename if err.filename is not None else "file system"
        print(f"jaxcr {args.command}: error: {where}: {err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # raised by code (tests), or SIGINT outside the main thread
        print(f"jaxcr {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
