"""``python -m mbmon`` runs the command line (a Ctrl-C at any instant exits 130 quietly)."""

import sys

try:
    from mbmon.cli import main
except KeyboardInterrupt:  # before main() could take over
    sys.exit(130)

sys.exit(main())
