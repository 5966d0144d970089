"""`python -m treetraits` runs the command line."""

import sys

from treetraits.cli import main

sys.exit(main())
