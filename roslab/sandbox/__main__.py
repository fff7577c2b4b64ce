"""`python -m roslab.sandbox up|status|down|...` (the same as `roslab sandbox ...`)."""

import sys

from .cli import main

sys.exit(main(["sandbox", *sys.argv[1:]]))
