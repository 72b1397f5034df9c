import sys

from jaxcr.cli import main

sys.exit(main())
