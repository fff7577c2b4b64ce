"""The classroom roster: loaded, checked in full before any host is touched, turned into an inventory.

    problems.py   Problem, Report, RosterError: every problem names file:line, team, host, field
    loading.py    strict, bounded YAML reading (duplicate keys, lines, alias bombs, encodings)
    reader.py     the roster's structure: levels, teams, hosts; values checked where they are set
    checks.py     value checks from roslab.settings, and checks across hosts and settings
    model.py      Classroom, Team, Host
    inventory.py  pyinfra groups and host data; which roster file to use

`load_roster(path)` collects every problem and raises one RosterError listing them all.
"""

from __future__ import annotations

from pathlib import Path

from roslab.class_lock import check_class_lock as _check_class_lock
from roslab.network.settings import validate_roster as _validate_network
from roslab.profiles.packages import check_classroom as _check_ros_packages
from roslab.roster.checks import Validator, assign_domain_ids, check_classroom
from roslab.roster.inventory import add_host_lists, default_roster_path, group_names, inventory_groups
from roslab.roster.model import ROLES, Classroom, Host, Team
from roslab.checked.problems import Problem, Report, RosterError, display_path, team_wide
from roslab.roster.reader import RosterReader
from roslab.sources.groups import check_underlay_builders as _check_underlay_builders

# Checks across the classroom that live with their concern, each `(classroom, report)`.
VALIDATORS: list[Validator] = [_validate_network, _check_ros_packages, _check_underlay_builders,
                               _check_class_lock]


def load_roster(path: Path | str, validators: list[Validator] | None = None,
                command_line: list | None = None) -> Classroom:
    """Load and check a roster; raise RosterError listing every problem.

    `command_line`: pyinfra's --data/--user/--port/--key values
    (`roslab.roster.overrides.command_line_data`), checked as the level that wins.
    """
    reader = RosterReader(Path(path), command_line)
    classroom = reader.read()
    if classroom is not None:
        reader.check_command_line(classroom)
        assign_domain_ids(classroom)
        check_classroom(classroom, reader.report)
        add_host_lists(classroom)
        for validator in VALIDATORS if validators is None else validators:
            validator(classroom, reader.report)
        reader.blame_command_line()
    # A team's or the classroom's value is read for each host: its problem is said once per team.
    team_hosts = {team.name: {host.name for host in team.hosts} for team in classroom.teams} if classroom else {}
    errors = team_wide(reader.report.errors, team_hosts)
    if errors or classroom is None:  # no classroom: the reader said why
        raise RosterError(errors)
    classroom.warnings = team_wide(reader.report.warnings, team_hosts)
    return classroom


__all__ = [
    "ROLES", "Classroom", "Host", "Problem", "Report", "RosterError", "Team", "Validator",
    "default_roster_path", "display_path", "group_names", "inventory_groups", "load_roster",
]
