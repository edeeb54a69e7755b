"""``python -m memlog`` = the ``memlog`` command."""

import sys

from memlog.cli import main

sys.exit(main())
