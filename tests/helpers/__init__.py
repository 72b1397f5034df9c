"""Shared test helpers (scenes, datasets, references), imported as
``tests.helpers.<module>`` from every test folder; fixtures in ``helpers/data/``."""
