"""``python -m hammer_ros.cli``: the same as the ``hammer-ros`` console script."""

import sys

from . import main

sys.exit(main())
