"""pyinfra inventory from the classroom roster.

    pyinfra inventories/lab.py deploy.py [--limit team1 | --limit robot | --limit jazzy]

Reads $ROSLAB_ROSTER, else (in the current folder) classroom.yaml or
inventories/classroom.yaml if present, else the example inventories/lab.yaml: the roster
`roslab check` and every roslab command use (roslab.roster.default_roster_path). An invalid
roster stops here, before pyinfra connects to any host; so does a bad `--data key=value`
(or --user/--port/--key): pyinfra applies those on top of the host data, so they are
checked here like the roster's values, and so is each --limit pattern: one that selects no
host (a typo, or `--limit a,b`: repeat the option instead) stops the run, exit 2.
Groups: `main`, `robot`, one per team (`-` in a team name becomes `_`), one per distro.
"""

from roslab.packaged import checked_classroom as _checked_classroom
from roslab.packaged import checked_groups as _checked_groups
from roslab.reach import refuse_unmatched_limit as _refuse_unmatched_limit
from roslab.roster import default_roster_path as _default_roster_path

# Names without a leading underscore would become pyinfra groups.
_classroom = _checked_classroom(_default_roster_path())  # found as every roslab command finds it
_groups = _checked_groups(_classroom)  # a refused network move: its line, exit 2, no traceback
_refuse_unmatched_limit(_groups)  # a --limit that selects no host stops here, naming it
globals().update(_groups)
