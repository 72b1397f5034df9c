"""Reading a JSON (or any text) file with one-line errors (the shared reader of jaxcr's JSON
formats, and of the text formats such as fk's joint CSV)."""

from __future__ import annotations

import json
import os
from typing import Any

from jaxcr.errors import InputError


def read_text(
    path: str | os.PathLike,
    expected: str = "a text file",
    not_text: str = "not UTF-8 text",
    encoding: str = "utf-8",
    newline: str | None = None,
) -> str:
    """The whole text of ``path``; a missing file, a directory (``"is a directory,
    expected <expected>"``), undecodable bytes (``not_text``) and other read errors raise
    :class:`jaxcr.errors.InputError` naming the file (one line, never a traceback)."""
    file = str(path)
    try:
        with open(path, encoding=encoding, newline=newline) as fh:
            return fh.read()
    except FileNotFoundError:
        raise InputError("file not found", file=file) from None
    except IsADirectoryError:
        raise InputError(f"is a directory, expected {expected}", file=file) from None
    except UnicodeDecodeError:
        raise InputError(not_text, file=file) from None
    except OSError as err:
        raise InputError(f"cannot read ({err.strerror})", file=file) from None


def read_json(path: str | os.PathLike) -> Any:
    """The parsed content of the JSON file ``path``.

    A UTF-8 byte-order mark is skipped. A missing file, a directory, undecodable bytes,
    invalid or pathologically nested JSON and other read errors raise
    :class:`jaxcr.errors.InputError` naming the file (one line, never a traceback).
    """
    file = str(path)
    text = read_text(path, "a JSON file", "not valid JSON (not UTF-8 text)", "utf-8-sig")
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InputError(f"not valid JSON ({err.msg}, line {err.lineno})", file=file) from None
    except RecursionError:
        raise InputError("not valid JSON (nested too deeply)", file=file) from None
