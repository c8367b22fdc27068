"""``python -m telefringe``: the command-line tool, as ``telefringe``."""

import sys

from telefringe.cli import main

sys.exit(main())
