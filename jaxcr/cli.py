"""The ``jaxcr`` command line. Each subcommand lives in ``jaxcr/commands/<name>.py`` and
exposes ``add_parser(subparsers)`` (registering its arguments and ``set_defaults(func=run)``)
and ``run(args) -> int``.

Exit codes: 0 success, 1 a run that failed (e.g. some frames failed), 2 bad usage or input
(including an output that cannot be written, e.g. a read-only folder), 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import re
import sys

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxcr",
        description="jaxcr: JAX batch estimation for the vision of continuum robots.",
    )
    from jaxcr import __version__

    parser.add_argument("--version", action="version", version=f"jaxcr {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        modname = f"jaxcr.commands.{name}"
        if importlib.util.find_spec(modname) is None:
            continue
        importlib.import_module(modname).add_parser(sub)
    _plain_help(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        from jaxcr.progress import mode as progress_mode

        progress_mode()  # a bad JAXCR_PROGRESS is bad input before any work (exit 2)
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
    except KeyboardInterrupt:
        print(f"jaxcr {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
