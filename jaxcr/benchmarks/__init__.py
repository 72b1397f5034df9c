"""Benchmarks that ship with the package, so ``jaxcr bench`` runs from an installed wheel.

Each module has one ``run_*_benchmark(...) -> dict`` (keys read by :mod:`jaxcr.cli.bench`);
the experiments/ scripts of the same name are thin wrappers that write the committed reports.
See README.md in this folder.
"""


def parse_seeds(text: str) -> list[int]:
    """Seeds from a command-line list: ``"0-9"``, ``"3,5"`` or ``"0-3,7,10-12"`` (ranges
    inclusive), in the order given. Shared by the experiments/ scripts' ``--seeds``."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.strip().partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out
