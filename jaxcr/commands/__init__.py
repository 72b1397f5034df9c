"""CLI subcommands: one module per command (see ``jaxcr.cli``)."""
