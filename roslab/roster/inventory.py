"""From a valid classroom to pyinfra's inventory: groups of (host name, host data)."""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from roslab.ssh import identity
from roslab.network.state import address_during_change, addresses_path, last_known_addresses, pending_changes
from roslab.roster.checks import host_ip
from roslab.roster.model import ROLES, Classroom
from roslab.checked.problems import Problem, RosterError, display_path

DEFAULT_ROSTER = Path("inventories/lab.yaml")
CLASSROOM_ROSTER = Path("inventories/classroom.yaml")
FOLDER_ROSTER = Path("classroom.yaml")  # a classroom folder (`roslab init DIR`)


def default_roster_path(base: Path | None = None) -> Path:
    """The roster every roslab command and inventories/lab.py use when none is named:
    $ROSLAB_ROSTER, else in the current folder (`base`) a classroom folder's classroom.yaml,
    a clone's inventories/classroom.yaml, else the example inventories/lab.yaml."""
    if os.environ.get("ROSLAB_ROSTER"):
        return Path(os.environ["ROSLAB_ROSTER"])
    base = Path.cwd() if base is None else base
    for candidate in (FOLDER_ROSTER, CLASSROOM_ROSTER):
        if (base / candidate).exists():
            return base / candidate
    return base / DEFAULT_ROSTER


def add_host_lists(classroom: Classroom) -> None:
    """Each host's view of the classroom: every host (for /etc/hosts) and its own team."""
    ips = {host.name: host_ip(host) for host in classroom.hosts}  # each host's once, not once per list
    everyone = [{"name": host.name, "address": ips[host.name]} for host in classroom.hosts]
    for team in classroom.teams:
        members = [{"name": host.name, "address": ips[host.name], "role": host.role}
                   for host in team.hosts]
        for host in team.hosts:
            host.set_data(roslab_classroom_hosts=everyone, roslab_team_hosts=members)


def group_names(classroom: Classroom) -> dict[str, list[str]]:
    """The roster's pyinfra groups, by host name: `main`, `robot`, one per team (its name with
    `-` as `_`), one per expected distro. `inventory_groups` gives the hosts their connection
    data; every `--limit` selects by these groups (roslab.reach.limit_selection)."""
    groups: dict[str, list[str]] = {role: [] for role in ROLES}
    for team in classroom.teams:
        groups[team.group] = []
        for host in team.hosts:
            groups[team.group].append(host.name)
            groups[host.role].append(host.name)
            if host.distro:
                groups.setdefault(host.distro, []).append(host.name)
    return groups


def inventory_groups(classroom: Classroom) -> dict[str, list[tuple[str, dict]]]:
    """pyinfra inventory groups (`group_names`) of (host name, host data).

    A host the network deploy has moved is reached at its last confirmed address
    (recorded beside the roster), not at the roster's now stale `address`. A host whose change
    a killed run left pending is reached where it answers, its last address or the new one
    (roslab.network.state.address_during_change), so one re-run confirms or makes the change.

    Hosts connect with strict host key checking against the classroom's known_hosts
    (`roslab.ssh.identity`) unless the roster sets `ssh_known_hosts_file` or
    `ssh_strict_host_key_checking`; a known host's key is listed there under every
    address it will be reached at in this run (`known_addresses`), and a refusal is
    explained by one line naming the roslab command to run.
    """
    try:
        moved = last_known_addresses(classroom.path)
    except (OSError, ValueError, yaml.YAMLError) as error:
        state_file = display_path(addresses_path(classroom.path))
        reason = getattr(error, "strerror", None) or (
            str(error).split(": ", 1)[-1] if isinstance(error, ValueError) and str(error) else
            "not a mapping of host name to address")
        raise RosterError([Problem(state_file, f"cannot read where moved hosts are: {reason}; "
                                   "fix or delete the file")]) from None
    pending = pending_changes(classroom.path)
    classroom_known_hosts = str(identity.known_hosts_path(classroom.path))
    checked: dict[str, tuple[list[str], int]] = {}
    entries: dict[str, tuple[str, dict]] = {}
    for host in classroom.hosts:
        data = {
            "ssh_known_hosts_file": classroom_known_hosts,
            "ssh_strict_host_key_checking": "yes",
            **host.data,
            "ssh_hostname": moved.get(host.name) or host.address,
        }
        if host.name in pending:  # a killed run's change: the host may answer at its new address
            data["ssh_hostname"] = address_during_change(data["ssh_hostname"], pending[host.name],
                                                         data.get("ssh_port") or 22)
        if data["ssh_known_hosts_file"] == classroom_known_hosts:
            reached = known_addresses(host, moved.get(host.name))
            reached += [data["ssh_hostname"]] if data["ssh_hostname"] not in reached else []
            checked[host.name] = (reached, data.get("ssh_port") or 22)
        entries[host.name] = (host.name, data)
    own_files: dict[str, list] = {}  # each roster-named known_hosts file read once
    unknown_moves = [problem for host in classroom.hosts
                     for problem in _move_without_key(classroom, host, entries[host.name][1], own_files)]
    if unknown_moves:
        raise RosterError(unknown_moves)
    groups = {group: [entries[name] for name in names] for group, names in group_names(classroom).items()}
    if checked:
        explain_refusals(classroom, checked)
        try:
            identity.sync_addresses(classroom.path, checked)
        except (OSError, identity.IdentityError) as error:
            shown = display_path(identity.known_hosts_path(classroom.path))
            raise RosterError([Problem(shown, f"cannot update the classroom's known hosts: "
                                       f"{getattr(error, 'strerror', None) or error}")]) from None
    return groups


def _move_without_key(classroom: Classroom, host, data: dict, own_files: dict[str, list]) -> list[Problem]:
    """A network change to an address the roster's own known_hosts file (ssh_known_hosts_file)
    has no key for: pyinfra would refuse the host there, and the change would roll back on every
    run. roslab adds a moved host's addresses only to the classroom's own file, so say it now."""
    own = data.get("ssh_known_hosts_file")
    new = (data.get("network_address") or "").split("/")[0]
    if (own in (None, str(identity.known_hosts_path(classroom.path)), os.devnull) or not new
            or not data.get("network_enabled", True) or new == data["ssh_hostname"]
            or data.get("ssh_strict_host_key_checking") not in (None, "yes")):
        return []
    port = data.get("ssh_port") or 22
    try:
        if own not in own_files:
            own_files[own] = identity.read_known_hosts(classroom.path, Path(own))
        entries = own_files[own]
    except identity.IdentityError:
        return []  # an unreadable file is pyinfra's to report, naming it
    if identity.knows_address(entries, new, port) or not identity.knows_address(entries, data["ssh_hostname"], port):
        return []  # known there already; or unknown where it is now: refused with the trust hint
    return [Problem(display_path(classroom.path), f"its network change moves it to {new}, and "
                    f"{display_path(own)} (ssh_known_hosts_file) holds its key for {data['ssh_hostname']} but "
                    f"none for {new}: pyinfra would refuse the host there and the change would roll back; run "
                    f"`roslab trust --limit {host.name}` (it records the key at every address the host is "
                    "reached at), or leave ssh_known_hosts_file unset (roslab then records it)",
                    line=host.lines.get("network_address") or host.line, team=host.team, host=host.name,
                    field="network_address")]


def known_addresses(host, moved_to: str | None) -> list[str]:
    """Every address this host may be reached at in a run: the roster's, the last confirmed
    one, and the static address the network deploy moves it to (and reconnects at)."""
    addresses = [host.address, moved_to]
    network_address = host.settings.network_address
    if network_address and host.settings.network_enabled:
        addresses.append(network_address.split("/")[0])
    return [address for address in dict.fromkeys(addresses) if address]


def explain_refusals(classroom: Classroom, checked: dict[str, tuple[list[str], int]]) -> None:
    """Teach the log filter on pyinfra's logger which host each address is (see identity)."""
    known_hosts = identity.known_hosts_path(classroom.path)
    identity.explainer().add_classroom(
        display_path(classroom.path), display_path(known_hosts), checked, known_hosts_file=str(known_hosts))
