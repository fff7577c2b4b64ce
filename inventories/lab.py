"""pyinfra inventory from the classroom roster.

    pyinfra inventories/lab.py deploy.py [--limit team1 | --limit robot | --limit jazzy]

Reads $ROSLAB_ROSTER, else (in the current folder) classroom.yaml or
inventories/classroom.yaml if present, else the example inventories/lab.yaml: the roster
`roslab check` and every roslab command use (roslab.roster.default_roster_path). An invalid
roster stops here, before pyinfra connects to any host; so does a bad `--data key=value`
(or --user/--port/--key): pyinfra applies those on top of the host data, so they are
checked here like the roster's values.
Groups: `main`, `robot`, one per team (`-` in a team name becomes `_`), one per distro.
"""

import sys as _sys

from roslab import remote_files as _remote_files
from roslab import sudo as _sudo
from roslab import summary as _summary
from roslab.roster import RosterError as _RosterError
from roslab.roster import default_roster_path as _default_roster_path
from roslab.roster import inventory_groups as _inventory_groups
from roslab.roster import load_roster as _load_roster
from roslab.roster import overrides as _overrides

# Names without a leading underscore would become pyinfra groups.
_roster_path = _default_roster_path()  # found as every roslab command finds it
# pyinfra puts --data, --user, --port and --key values on top of the host data after this
# file: they are checked here like the roster's own (roslab.roster.overrides).
_command_line = _overrides.command_line_data(_sys.argv)
try:
    _classroom = _load_roster(_roster_path, command_line=_command_line)
except _RosterError as _error:
    print(f"roslab: the roster has errors, no host was touched:\n{_error}", file=_sys.stderr)
    _sys.exit(2)

for _warning in _classroom.warnings:
    print(f"roslab: warning: {_warning}", file=_sys.stderr)

_summary.install()  # before pyinfra connects: a run where no host answers is summarised too
_sudo.install()  # before pyinfra's first command: no sudo password on a host's command line
_remote_files.install()  # every upload: never through a link, never via SFTP or a temp file
globals().update(_inventory_groups(_classroom))
