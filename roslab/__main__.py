"""`python -m roslab` is the `roslab` command."""

import sys

from roslab.cli.main import main

sys.exit(main())
