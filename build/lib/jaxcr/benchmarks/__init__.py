"""Benchmarks that ship with the package, so ``jaxcr bench`` runs from an installed wheel.

Each module has one ``run_*_benchmark(...) -> dict`` (keys read by :mod:`jaxcr.cli.bench`);
the experiments/ scripts of the same name are thin wrappers that write the committed reports.
See README.md in this folder.
"""
