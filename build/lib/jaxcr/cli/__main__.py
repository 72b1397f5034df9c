"""``python -m jaxcr.cli`` (same as ``python -m jaxcr``)."""

import sys

from jaxcr.cli import main

sys.exit(main())
