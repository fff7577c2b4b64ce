"""From a valid classroom to pyinfra's inventory: groups of (host name, host data)."""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from roslab.network.state import addresses_path, last_known_addresses
from roslab.roster.checks import host_ip
from roslab.roster.model import ROLES, Classroom
from roslab.roster.problems import Problem, RosterError, display_path

DEFAULT_ROSTER = Path("inventories/lab.yaml")
CLASSROOM_ROSTER = Path("inventories/classroom.yaml")


def default_roster_path(base: Path | None = None) -> Path:
    """The roster to use: $ROSLAB_ROSTER, else a real classroom.yaml, else the example."""
    if os.environ.get("ROSLAB_ROSTER"):
        return Path(os.environ["ROSLAB_ROSTER"])
    base = Path.cwd() if base is None else base
    if (base / CLASSROOM_ROSTER).exists():
        return base / CLASSROOM_ROSTER
    return base / DEFAULT_ROSTER


def add_host_lists(classroom: Classroom) -> None:
    """Each host's view of the classroom: every host (for /etc/hosts) and its own team."""
    everyone = [{"name": host.name, "address": host_ip(host)} for host in classroom.hosts]
    for team in classroom.teams:
        members = [{"name": host.name, "address": host_ip(host), "role": host.role}
                   for host in team.hosts]
        for host in team.hosts:
            host.data["roslab_classroom_hosts"] = everyone
            host.data["roslab_team_hosts"] = members


def inventory_groups(classroom: Classroom) -> dict[str, list[tuple[str, dict]]]:
    """pyinfra inventory groups: `main`, `robot`, one per team, one per expected distro.

    A host the network deploy has moved is reached at its last confirmed address
    (recorded beside the roster), not at the roster's now stale `address`.
    """
    try:
        moved = last_known_addresses(classroom.path)
    except (OSError, ValueError, yaml.YAMLError) as error:
        state_file = display_path(addresses_path(classroom.path))
        reason = getattr(error, "strerror", None) or "not a mapping of host name to address"
        raise RosterError([Problem(state_file, f"cannot read where moved hosts are: {reason}; "
                                   "fix or delete the file")]) from None
    groups: dict[str, list[tuple[str, dict]]] = {role: [] for role in ROLES}
    for team in classroom.teams:
        groups[team.group] = []
        for host in team.hosts:
            entry = (host.name, {**host.data, "ssh_hostname": moved.get(host.name) or host.address})
            groups[team.group].append(entry)
            groups[host.role].append(entry)
            if host.distro:
                groups.setdefault(host.distro, []).append(entry)
    return groups
