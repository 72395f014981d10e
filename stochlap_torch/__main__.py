"""``python -m stochlap_torch``: the ``stochlap`` command line tool."""

import sys

from .cli import main

sys.exit(main())
