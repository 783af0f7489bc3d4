"""``python -m mapfree.cli`` = the ``mapfree`` command (as ``python -m mapfree``)."""

import sys

from . import main

sys.exit(main())
