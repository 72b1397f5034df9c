"""User-facing input errors: one line naming the file, frame and field."""

from __future__ import annotations


class InputError(Exception):
    """Bad user input. The CLI prints ``str(err)`` as one line and exits with code 2.

    Parameters
    ----------
    message : str
        what is wrong, in plain words.
    file : str or None
        the offending file (path as the user gave it), if any.
    frame : str, int or None
        frame id within a dataset, if any.
    field : str or None
        the field name (e.g. ``"q"``, ``"cameras.left.K"``), if any.

    Examples
    --------
    >>> from jaxcr import InputError
    >>> err = InputError("must be finite", file="run/dataset.json", frame="000003", field="q")
    >>> err.field
    'q'
    >>> len(str(err).splitlines())  # one line, for the CLI
    1
    """

    def __init__(
        self,
        message: str,
        file: str | None = None,
        frame: str | int | None = None,
        field: str | None = None,
    ):
        self.message = message
        self.file = None if file is None else str(file)
        self.frame = frame
        self.field = field
        super().__init__(self.format())

    def format(self) -> str:
        parts = []
        if self.file is not None:
            parts.append(self.file)
        if self.frame is not None:
            parts.append(f"frame {self.frame}")
        if self.field is not None:
            parts.append(f"field '{self.field}'")
        prefix = ": ".join(parts)
        return f"{prefix}: {self.message}" if prefix else self.message


class InputErrors(InputError):
    """Several input problems found at once (e.g. by the dataset validator).

    The one-line message is the first problem and, when there are more, their exact count and
    ``where`` (e.g. "run jaxcr validate DATASET") they are all listed.
    """

    def __init__(self, errors: list[InputError], where: str | None = None):
        self.errors = list(errors)
        first = self.errors[0].format() if self.errors else "no errors"
        n = len(self.errors) - 1
        more = ""
        if n > 0:
            more = f" (and {n} more problem{'s' if n > 1 else ''}"
            more += f"; {where})" if where else ")"
        super().__init__(first + more)
