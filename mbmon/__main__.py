"""``python -m mbmon`` runs the command line."""

import sys

from mbmon.cli import main

sys.exit(main())
