"""``python -m memlog`` = the ``memlog`` command."""

import sys

from memlog.cli.app import main

sys.exit(main())
