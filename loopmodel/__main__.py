"""``python -m loopmodel``: the command line."""

import sys

from loopmodel.cli import main

if __name__ == "__main__":
    sys.exit(main())
