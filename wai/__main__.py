"""``python -m wai``: the ``wai`` command, for environments whose scripts folder is not on PATH."""

import sys

from wai.cli import main

sys.exit(main())
