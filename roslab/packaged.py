"""What roslab ships besides its Python code: the classroom deploy and the demo nodes.

In a checkout they are the repository's `deploy.py` and `nodes/`; in an installed roslab
(a wheel, `pip install`/`pipx install`) they are package data, `roslab/data/deploy.py` and
`roslab/data/nodes/` (in a checkout those are links to the same files, so both read one
source). A classroom folder made by `roslab init` holds only the teacher's files and two
small pyinfra entry files that run these (`classroom_inventory`, `run_deploy`).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import CodeType

DATA = Path(__file__).resolve().parent / "data"
FOLDER_ROSTER = "classroom.yaml"


def nodes_dir() -> Path:
    """The demo ROS 2 packages (the default `workspace_nodes_dir`)."""
    return (DATA / "nodes").resolve()


def deploy_file() -> Path:
    """The classroom deploy (the checkout's deploy.py, or the installed copy)."""
    return (DATA / "deploy.py").resolve()


_compiled: dict[str, CodeType] = {}


def run_deploy() -> None:
    """Run roslab's classroom deploy for the current host (a folder's deploy.py calls this;
    pyinfra runs that file once per host)."""
    path = deploy_file()
    code = _compiled.get(str(path))
    if code is None:
        code = _compiled[str(path)] = compile(path.read_text(encoding="utf-8"), str(path), "exec")
    exec(code, {"__name__": "roslab_deploy", "__file__": str(path)})  # noqa: S102 - roslab's own file


def checked_groups(classroom) -> dict:
    """pyinfra's groups for `classroom` (roslab.roster.inventory_groups); a problem found only
    here (a network move to an address whose key the roster's known_hosts file lacks, an
    unreadable record of moved hosts) stops the run as a roster error does: its lines, exit 2,
    no traceback, before pyinfra connects."""
    from roslab.roster import RosterError, inventory_groups

    try:
        return inventory_groups(classroom)
    except RosterError as error:
        print(f"roslab: the roster has errors, no host was touched:\n{error}", file=sys.stderr)
        sys.exit(2)


def classroom_inventory(folder_file: str) -> dict:
    """pyinfra's groups for a classroom folder's inventory.py: the roster $ROSLAB_ROSTER names,
    else classroom.yaml beside that file; an invalid roster stops here, before pyinfra
    connects (as inventories/lab.py)."""
    from roslab.reach import refuse_unmatched_limit

    path = Path(os.environ.get("ROSLAB_ROSTER") or Path(folder_file).resolve().parent / FOLDER_ROSTER)
    groups = checked_groups(checked_classroom(path))
    refuse_unmatched_limit(groups)  # a --limit that selects no host stops here, naming it
    return groups


def checked_classroom(path: Path):
    """The roster at `path`, checked for a pyinfra run, for any inventory file (the checkout's
    inventories/lab.py, a classroom folder's inventory.py).

    pyinfra puts --data, --user, --port and --key values on top of the host data after the
    inventory file: they are checked here like the roster's own (roslab.roster.overrides).
    An invalid roster or override stops the run here, before pyinfra connects to any host.
    """
    from roslab import pyinfra_planning, remote_files
    from roslab.ssh import keepalive as ssh_keepalive
    from roslab.ssh import sudo
    from roslab.reporting import summary
    from roslab.roster import RosterError, load_roster, overrides

    try:
        classroom = load_roster(path, command_line=overrides.command_line_data(sys.argv))
    except RosterError as error:
        print(f"roslab: the roster has errors, no host was touched:\n{error}", file=sys.stderr)
        sys.exit(2)
    for warning in classroom.warnings:
        print(f"roslab: warning: {warning}", file=sys.stderr)
    summary.install()  # before pyinfra connects: a run where no host answers is summarised too
    sudo.install()  # before pyinfra's first command: no sudo password on a host's command line
    remote_files.install()  # every upload: never through a link, never via SFTP or a temp file
    ssh_keepalive.install()  # a host that goes silent mid-step is lost in seconds, not waited for forever
    pyinfra_planning.install()  # before pyinfra builds its hosts: its connectors read once, not four times
    return classroom
