"""`python -m roslab` is the `roslab` command."""

import sys

from roslab.cli import main

sys.exit(main())
