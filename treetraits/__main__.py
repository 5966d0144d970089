"""`python -m treetraits` runs the command line."""

import sys

from treetraits.cli import main

# Guarded: `treetraits eval` starts worker processes that import this module again.
if __name__ == "__main__":
    sys.exit(main())
