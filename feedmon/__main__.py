"""``python -m feedmon`` = the ``feedmon`` command."""

import sys

from .cli import main

sys.exit(main())
