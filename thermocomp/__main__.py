"""``python -m thermocomp``: the same as the ``thermocomp`` command."""

import sys

from .cli import main

sys.exit(main())
