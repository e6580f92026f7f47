"""``python -m mbmon`` runs the command line (a Ctrl-C at any instant exits 130 quietly)."""

import sys

try:
    from mbmon.cli import main

    status = main()
except KeyboardInterrupt:  # before main() could take over, or as it hands back
    status = 130

sys.exit(status)
