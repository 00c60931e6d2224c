"""``python -m mccnn_cl`` runs the command line (:mod:`mccnn_cl.cli`)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
