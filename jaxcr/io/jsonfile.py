"""Reading a JSON file with one-line errors (the shared reader of jaxcr's JSON formats)."""

from __future__ import annotations

import json
import os
from typing import Any

from jaxcr.errors import InputError


def read_json(path: str | os.PathLike) -> Any:
    """The parsed content of the JSON file ``path``.

    A UTF-8 byte-order mark is skipped. A missing file, a directory, undecodable bytes,
    invalid or pathologically nested JSON and other read errors raise
    :class:`jaxcr.errors.InputError` naming the file (one line, never a traceback).
    """
    file = str(path)
    try:
        with open(path, encoding="utf-8-sig") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise InputError("file not found", file=file) from None
    except IsADirectoryError:
        raise InputError("is a directory, expected a JSON file", file=file) from None
    except UnicodeDecodeError:
        raise InputError("not valid JSON (not UTF-8 text)", file=file) from None
    except json.JSONDecodeError as err:
        raise InputError(f"not valid JSON ({err.msg}, line {err.lineno})", file=file) from None
    except RecursionError:
        raise InputError("not valid JSON (nested too deeply)", file=file) from None
    except OSError as err:
        raise InputError(f"cannot read ({err.strerror})", file=file) from None
