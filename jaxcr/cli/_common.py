"""CLI subcommands: one module per command (see ``jaxcr.cli``)."""


def seed(text: str) -> int:
    """argparse type of ``--seed``: a non-negative integer (numpy's generators reject negative
    seeds, which was a traceback deep inside numpy)."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}") from None
    from jaxcr.limits import MAX_SEED

    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {value}")
    if value > MAX_SEED:
        raise argparse.ArgumentTypeError(
            f"expected a non-negative integer <= {MAX_SEED}, got {value}"
        )
    return value


def check_writable_folder(path: str, what: str) -> None:
    """Create folder ``path`` if needed and check a file can be written there, before any
    long work (an InputError naming it otherwise)."""
    import os
    import tempfile

    from jaxcr.errors import InputError

    if os.path.exists(path) and not os.path.isdir(path):
        raise InputError(f"{what} exists and is not a folder", file=path)
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        raise InputError(f"{what} is not writable ({err.strerror or err})", file=path) from None
