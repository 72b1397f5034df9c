"""jaxcr: a JAX batch estimation engine for the vision of continuum robots."""

__version__ = "0.1.0"
