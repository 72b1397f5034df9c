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
