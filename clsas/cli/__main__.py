"""``python -m clsas.cli``."""

import sys

from . import main

sys.exit(main())
