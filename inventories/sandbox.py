"""pyinfra inventory for the running sandbox classroom (see docs/sandbox.md).

    roslab sandbox up
    pyinfra inventories/sandbox.py deploy.py

Targets the instance named by $ROSLAB_SANDBOX (default: roslab), through the
roster `roslab sandbox up` wrote, loaded exactly as inventories/lab.py loads a
real classroom's roster.
"""

import os as _os
import sys as _sys
from pathlib import Path as _Path

from roslab import pyinfra_planning as _pyinfra_planning
from roslab import remote_files as _remote_files
from roslab.ssh import keepalive as _ssh_keepalive
from roslab.ssh import sudo as _sudo
from roslab.reporting import summary as _summary
from roslab.reach import refuse_unmatched_limit as _refuse_unmatched_limit
from roslab.roster import RosterError as _RosterError
from roslab.roster import inventory_groups as _inventory_groups
from roslab.roster import load_roster as _load_roster

# Names without a leading underscore would become pyinfra groups.
_name = _os.environ.get("ROSLAB_SANDBOX") or "roslab"
_roster_path = _Path("/run/roslab/sandbox") / _name / "roster.yaml"
if not _roster_path.exists():
    print(f"roslab: no sandbox {_name!r} is running: run `roslab sandbox up`", file=_sys.stderr)
    _sys.exit(2)
try:
    _classroom = _load_roster(_roster_path)
except _RosterError as _error:
    print(f"roslab: the sandbox roster {_roster_path} has errors:\n{_error}", file=_sys.stderr)
    _sys.exit(2)

_summary.install()  # before pyinfra connects: a run where no host answers is summarised too
_sudo.install()  # before pyinfra's first command: no sudo password on a host's command line
_remote_files.install()  # every upload: never through a link, never via SFTP or a temp file
_ssh_keepalive.install()  # a host that goes silent mid-step is lost in seconds, not waited for forever
_pyinfra_planning.install()  # before pyinfra builds its hosts: its connectors read once, not four times
_groups = _inventory_groups(_classroom)
_refuse_unmatched_limit(_groups)  # a --limit that selects no host stops here, naming it
globals().update(_groups)
