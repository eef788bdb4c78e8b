"""``python -m loopmodel.cli``: the command line (the same as ``python -m loopmodel``)."""

import sys

from loopmodel.cli import main

if __name__ == "__main__":
    sys.exit(main())
