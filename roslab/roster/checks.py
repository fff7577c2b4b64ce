"""Checks of a roster: each value against its setting's schema, then the classroom as a whole.

Value checks run where a key is set (classroom, team or host) and come from
`roslab.settings`; the classroom checks below need several hosts or several settings
at once (duplicate addresses, one domain per team, a distro with packages for the
release, mirror mode's URL and key). Every check reports through `report.error` and
never raises: one bad value must not hide the others, nor stop the whole classroom.
"""

from __future__ import annotations

import difflib
import ipaddress
from collections.abc import Callable
from pathlib import Path

from roslab.ros import discovery
from roslab.ros import distro as distros
from roslab.ros import snapshots
from roslab import boards, host_rules, openpgp, settings
from roslab.host_settings import HostSettings
from roslab.roster.model import ROLES, Classroom, Host
from roslab.checked.problems import Report

# Group names pyinfra or roslab already use; a team may not take them.
RESERVED_GROUPS = {"all", *ROLES, *distros.DISTRO_RELEASES}

# Checks that run on a loaded classroom, each `(classroom, report)`.
Validator = Callable[[Classroom, Report], None]


def unknown_key_message(key: str, level: str) -> str:
    known = settings.SETTINGS.get(key)
    if known is not None:
        where = " or ".join(f"a {other}" for other in known.levels)
        return f"{key!r} can only be set on {where}, not on a {level}"
    message = f"unknown key {key!r}"
    close = difflib.get_close_matches(key, list(settings.SETTINGS), n=1)
    if close:
        levels = settings.SETTINGS[close[0]].levels
        where = "" if level in levels else f", set on {' or '.join(f'a {other}' for other in levels)}"
        message += f" (did you mean {close[0]!r}{where}?)"
    return message


# --- the classroom as a whole ---------------------------------------------------------


def check_classroom(classroom: Classroom, report: Report) -> None:
    check_groups(classroom, report)
    check_domain_ids(classroom, report)
    check_discovery(classroom, report)
    check_unique(classroom, report, None, lambda host: host.name.lower())
    check_unique(classroom, report, "address", _address_key)
    check_unique(classroom, report, "network_address", _network_ip_key)
    check_apt_cache_host(classroom, report)
    seen: set = set()
    resolved: dict = {}  # each distinct folder value resolved on disk once, not once per host
    for host in classroom.hosts:
        check_host(host, report)
        check_controller_folders(host, report, seen, resolved)


def check_host(host: Host, report: Report) -> None:
    """Settings of one host that only make sense together (roslab.host_rules: the rules a
    hand-made inventory's hosts meet too, then the roster's own)."""
    where = {"team": host.team, "host": host.name}
    # host_rules judges a hand-made inventory's mapping too, before any typed settings exist
    for key, problem in host_rules.across_problems(host.data, given=host.lines):
        report.error(problem, field=key, line=host.lines.get(key), **where)
    typed = host.settings
    codename = distros.UBUNTU_CODENAMES.get(str(host.ubuntu_release))
    override = typed.ros_distro
    if codename and override in distros.DISTRO_RELEASES:
        try:
            distros.check_distro(str(override), codename)
        except distros.DistroError as exc:
            report.error(str(exc), field="ros_distro", line=host.lines.get("ros_distro"), **where)
    board_problem = codename and boards.release_problem(typed.board, distros.BY_CODENAME[codename].release)
    if board_problem:
        report.error(board_problem, field="board",
                     line=host.lines.get("board") or host.lines.get("ubuntu_release"), **where)
    mode = typed.ros_apt_source_mode
    if typed.ros_apt_source_enabled and mode in SOURCE_MODE_SETTINGS:
        for key in SOURCE_MODE_SETTINGS[mode]:
            if not getattr(typed, key):
                report.error(f"ros_apt_source_mode is '{mode}', so {key} must be set",
                             field=key, line=host.lines.get("ros_apt_source_mode"), **where)
        if mode == "snapshot":
            check_snapshot(host, report)
    elif typed.ros_apt_source_enabled and codename:
        if codename not in (typed.ros_apt_source_sha256 or {}):
            version = typed.ros_apt_source_version
            report.error(
                f"roslab knows no sha256 of ros2-apt-source {version} for Ubuntu {host.ubuntu_release} "
                f"({codename}), which this host runs: set ros_apt_source_sha256: {{{codename}: <sha256 of "
                f"ros2-apt-source_{version}.{codename}_all.deb>}} from its release page, "
                "or use ros_apt_source_mode: mirror",
                field="ros_apt_source_sha256",
                line=host.lines.get("ros_apt_source_sha256") or host.lines.get("ubuntu_release"), **where)
    if typed.login_user == "root" or (not typed.login_user and typed.ssh_user == "root"):
        field = "login_user" if typed.login_user else "ssh_user"
        report.error("the ROS environment belongs to a student account, not root: set login_user",
                     field=field, line=host.lines.get(field), **where)
    elif typed.ssh_user == "root" and typed.ssh_hardening_enabled and typed.ssh_permit_root_login == "no":
        report.error("roslab logs in as root, and ssh hardening (PermitRootLogin no) would lock it out: "
                     "log in as the lab user, or set ssh_permit_root_login: prohibit-password",
                     field="ssh_user", line=host.lines.get("ssh_user"), **where)


# The settings a ROS source mode cannot do without (package mode has its defaults).
SOURCE_MODE_SETTINGS = {"mirror": ("ros_apt_mirror_url", "ros_apt_mirror_key_file"),
                        "snapshot": ("ros_apt_snapshot", "ros_apt_snapshot_key_file")}


def check_snapshot(host: Host, report: Report) -> None:
    """Snapshot mode: an LTS distro (snapshots.ros.org keeps no other), and from
    snapshots.ros.org its own key (the fingerprint the ROS docs publish)."""
    where = {"team": host.team, "host": host.name}
    typed = host.settings
    line = host.lines.get("ros_apt_source_mode")
    if host.distro in distros.BY_NAME and not distros.record(host.distro).lts:
        report.error(f"ros_apt_source_mode is 'snapshot', but ROS {host.distro} is not an LTS distro: "
                     "snapshots.ros.org keeps LTS distros only (use package or mirror mode for this host)",
                     field="ros_apt_source_mode", line=line or host.lines.get("ros_distro"), **where)
    if typed.ros_apt_snapshot_key_file:
        path = Path(typed.ros_apt_snapshot_key_file)
        try:
            problem = snapshots.key_problem(typed.ros_apt_snapshot_url, openpgp.dearmored(path.read_bytes()))
        except (OSError, ValueError) as error:
            problem = f"cannot be read: {error}"
        if problem:
            report.error(f"{typed.ros_apt_snapshot_key_file} {problem}", field="ros_apt_snapshot_key_file",
                         line=host.lines.get("ros_apt_snapshot_key_file"), **where)


# The controller's folders that roslab writes into and copies from, each with a purpose of its
# own: a cache inside another (or two caches in one folder) would have one's healing (a damaged
# mirror moved aside) touch the other's files; a cache inside the nodes folder would be copied
# to every Pi with the students' packages.
CACHE_SETTINGS = ("ros_apt_source_cache_dir", "rosdep_cache_dir", "sources_cache_dir", "python_wheelhouse_dir",
                  "class_lock_debs_dir")


def check_controller_folders(host: Host, report: Report, seen: set, resolved: dict | None = None) -> None:
    """The host's cache folders are apart from each other and from workspace_nodes_dir; each
    clash is reported once (`seen`), at the first host that has it. `resolved` keeps each
    value's real path for the next host (the same few folders on every host of a class)."""
    import os

    resolved = {} if resolved is None else resolved

    def real(value):
        value = str(value)
        if value not in resolved:
            resolved[value] = os.path.realpath(os.path.expanduser(value))
        return resolved[value]

    def inside(inner, outer):
        return inner == outer or inner.startswith(outer.rstrip("/") + "/")

    where = {"team": host.team, "host": host.name}
    typed = host.settings
    folders = [(key, real(getattr(typed, key))) for key in CACHE_SETTINGS if getattr(typed, key)]
    nodes = typed.workspace_nodes_dir
    layout = ("layout", tuple(folders), nodes)
    if layout in seen:
        return  # the same folders as a host before: each of their clashes was reported there
    seen.add(layout)
    for index, (key, folder) in enumerate(folders):
        for other, other_folder in folders[:index]:
            if (inside(folder, other_folder) or inside(other_folder, folder)) and \
                    (key, folder, other, other_folder) not in seen:
                seen.add((key, folder, other, other_folder))
                report.error(f"{key} ({folder}) and {other} ({other_folder}) share a folder: each cache needs "
                             "one of its own", field=key, line=host.lines.get(key) or host.lines.get(other), **where)
        if nodes and (inside(folder, real(nodes)) or inside(real(nodes), folder)) and (key, folder, nodes) not in seen:
            seen.add((key, folder, nodes))
            report.error(f"{key} ({folder}) and workspace_nodes_dir ({real(nodes)}) overlap: the nodes folder is "
                         "copied to every Pi, a cache is not", field=key,
                         line=host.lines.get(key) or host.lines.get("workspace_nodes_dir"), **where)


def check_apt_cache_host(classroom: Classroom, report: Report) -> None:
    """apt_cache_host (a classroom setting) names a host of this roster."""
    names = {host.name for host in classroom.hosts}
    for host in classroom.hosts[:1]:  # the same classroom value on every host: report it once
        cache_host = host.settings.apt_cache_host
        if cache_host and cache_host not in names:
            close = difflib.get_close_matches(cache_host, sorted(names), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            report.error(f"{cache_host!r} is not a host of this roster{hint}", field="apt_cache_host",
                         line=host.lines.get("apt_cache_host"))


def check_groups(classroom: Classroom, report: Report) -> None:
    groups: dict[str, str] = {}
    for team in classroom.teams:
        if team.group in RESERVED_GROUPS:
            report.error(
                f"the team's group {team.group!r} is already a pyinfra group "
                f"(reserved: {', '.join(sorted(RESERVED_GROUPS))}); rename the team",
                team=team.name, line=team.line)
        elif team.group in groups:
            report.error(
                f"the team's group {team.group!r} is also team {groups[team.group]!r}'s "
                "('-' becomes '_'); rename one of them", team=team.name, line=team.line)
        groups[team.group] = team.name
    group_names = set(groups) | RESERVED_GROUPS
    for host in classroom.hosts:
        if host.name in group_names:
            report.error(
                f"{host.name!r} is also a group name, so --limit {host.name} would be "
                "ambiguous; rename the host", team=host.team, host=host.name, line=host.line)


def assign_domain_ids(classroom: Classroom) -> None:
    """Give each team the roster left without a ros_domain_id a free one from its name
    (roslab.ros.discovery.assign_domain_ids), in the team and in each of its hosts' data."""
    assigned = discovery.assign_domain_ids(
        {team.name: team.ros_domain_id if team.domain_set else None for team in classroom.teams})
    for team in classroom.teams:
        if team.name not in assigned:
            continue
        team.ros_domain_id = assigned[team.name]
        team.domain_assigned = True
        for host in team.hosts:
            host.set_data(ros_domain_id=team.ros_domain_id)
            host.domain_assigned = True


def check_domain_ids(classroom: Classroom, report: Report) -> None:
    owners: dict[int, str] = {}
    for team in classroom.teams:
        line = team.domain_line or team.line
        if team.ros_domain_id is None:
            if not team.domain_set:
                report.error("no free ROS_DOMAIN_ID is left for this team (roslab gives out 1 to 101): "
                             "set its ros_domain_id (215 to 232 also work on Linux)",
                             team=team.name, field="ros_domain_id", line=line)
            continue
        if team.ros_domain_id in owners:
            report.error(
                f"ROS_DOMAIN_ID {team.ros_domain_id} is already team "
                f"{owners[team.ros_domain_id]!r}'s; teams on one domain see and disturb "
                "each other's topics", team=team.name, field="ros_domain_id", line=line)
        else:
            owners[team.ros_domain_id] = team.name


def check_discovery(classroom: Classroom, report: Report) -> None:
    """Middleware and discovery mode: the combinations that cannot work, refused before connecting."""
    for team in classroom.teams:
        main = next((host for host in team.hosts if host.role == "main"), None)
        for host in team.hosts:
            typed = host.settings
            where = {"team": host.team, "host": host.name}
            mode, middleware = typed.ros_discovery_mode, typed.ros_middleware
            mode_line = host.lines.get("ros_discovery_mode") or host.line
            if mode == "discovery_server" and middleware != discovery.FASTDDS:
                report.error(f"a discovery server is Fast DDS's: ros_middleware {middleware} has none "
                             "(use ros_discovery_mode static, or ros_middleware rmw_fastrtps_cpp)",
                             field="ros_discovery_mode", line=mode_line, **where)
            needs_main = mode == "discovery_server" or (middleware == discovery.ZENOH and mode != "localhost")
            what = "the discovery server" if mode == "discovery_server" else "the Zenoh router"
            if needs_main and main is None:
                report.error(f"{what} runs on the team's main host, and this team has none: "
                             "give it a host with role: main", field="ros_discovery_mode", line=mode_line, **where)
            elif needs_main and main is not None and main is not host and main.settings.ros_discovery_mode == "localhost":
                report.error(f"{what} runs on the team's main host, and {main.name!r} keeps its discovery on "
                             "itself (ros_discovery_mode localhost): this host would find nobody",
                             field="ros_discovery_mode",
                             line=main.lines.get("ros_discovery_mode") or main.line, **where)
            dds_only = _dds_only_package(typed) if middleware == discovery.ZENOH else None
            if dds_only:
                report.error(f"{dds_only} speaks DDS only, so its robot would be invisible under "
                             "rmw_zenoh_cpp: use rmw_fastrtps_cpp for this class",
                             field="ros_middleware", line=host.lines.get("ros_middleware") or host.line, **where)


def _dds_only_package(typed: HostSettings) -> str | None:
    """What the host runs or installs that speaks DDS only (a profile's `dds_only_packages`), in
    words: from its launch, its extra packages or its profile's packages; else None."""
    from roslab.profiles.library import dds_only_packages

    profile = typed.roslab_profile
    names = [*(profile.ros_packages if profile else ()), *(profile.packages if profile else ()),
             *typed.ros_extra_packages, (typed.nodes_launch or "").split(" ")[0]]
    for package, what in dds_only_packages().items():
        if any(package in str(name).replace("-", "_") for name in names):
            return what
    return None


def check_unique(classroom: Classroom, report: Report, field_name: str | None, key_of) -> None:
    """Report hosts sharing a name (field_name None) or a field's value: one pass, a dict."""
    seen: dict = {}
    for host in classroom.hosts:
        key = key_of(host)
        if key is None:
            continue
        other = seen.setdefault(key, host)
        if other is host:
            continue
        what = "the host name" if field_name is None else str(key)
        report.error(
            f"{what} is already used by host {other.name!r} of team {other.team!r}",
            team=host.team, host=host.name, field=field_name,
            line=host.lines.get(field_name) if field_name else host.line)


def _address_key(host: Host):
    """An address by value (::ffff:10.0.0.1 is 10.0.0.1), a host name by its lower-case text."""
    try:
        ip = ipaddress.ip_address(host.address)
        return getattr(ip, "ipv4_mapped", None) or ip
    except ValueError:
        return host.address.lower().rstrip(".")


def _network_ip_key(host: Host):
    value = host.settings.network_address
    try:
        return ipaddress.ip_interface(value).ip if value else None
    except ValueError:
        return None


def host_ip(host: Host) -> str | None:
    """The address other hosts reach this host at, for /etc/hosts: an IP or None."""
    ip = _network_ip_key(host)
    if ip is not None:
        return str(ip)
    try:
        return str(ipaddress.ip_address(host.address))
    except ValueError:
        return None


__all__ = ["Validator", "check_classroom", "host_ip", "unknown_key_message"]
