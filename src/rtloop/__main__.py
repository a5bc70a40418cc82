"""``python -m rtloop``: the same as the ``rtloop`` command."""

import sys

from rtloop.cli.main import main

sys.exit(main())
