"""One host's values, checked by the same rules wherever they come from: a roster, pyinfra's
`--data`, or a hand-made inventory (no roster).

    value_problems(data, context)   each key's format: the schema's check (roslab.settings)
    across_problems(data)           values of one host that must fit together: the folders roslab
                                    manages apart from each other, no port taken twice
    hand_made_problems(data)        both, for a hand-made inventory's host data (but the place of
                                    controller-side files: relative to a roster's folder)

The roster loader runs `value_problems` where each key is set (roslab.roster.reader) and
`across_problems` on each resolved host (roslab.roster.checks.check_host), naming file:line;
roslab.host_settings runs `hand_made_problems` on a host without a roster before any deploy
reads it, naming host and key. One list of rules, so the two ways in cannot drift apart.
Each problem is `(key, message)`; a message quotes at most the offending value.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from roslab import formats, settings

# Folders in the login user's home that roslab manages, each with a purpose of its own: the
# underlay's switch replaces its `install` (a workspace there would lose the students' build).
HOME_FOLDERS = ("workspace_dir", "sources_underlay_dir")
# Ports one host listens on or is reached at, by the setting that names them.
PORT_SETTINGS = ("ssh_port", "ros_zenoh_router_port", "ros_discovery_server_port")


def value_problems(data: Mapping, context: formats.Context | None = None,
                   controller_paths: bool = True) -> list[tuple[str, str]]:
    """Each schema setting `data` holds, against its check (null only where the schema allows it);
    `controller_paths` False: not the files and folders on the controller, whose place (the
    roster's folder) a hand-made inventory does not have."""
    problems = []
    for key, value in data.items():
        setting = settings.SETTINGS.get(key)
        if setting is None or setting.concern == "roster" or (
                not controller_paths and getattr(setting.check, "controller_path", False)):
            continue  # the roster's own keys (role, address...); files named relative to a roster
        problem = settings.check_value(setting, value, context)
        if problem:
            problems.append((key, problem))
    return problems


def _inside(inner: str, outer: str) -> bool:
    inner, outer = inner.rstrip("/"), outer.rstrip("/")
    return inner == outer or inner.startswith(outer + "/")


def folder_problems(data: Mapping, given=None) -> list[tuple[str, str]]:
    """The home folders roslab manages neither are nor hold one another; the problem is the key
    of the pair that was `given`, else the later one."""
    folders = [(key, data[key]) for key in HOME_FOLDERS if isinstance(data.get(key), str)
               and formats.home_path(data[key]) is None]
    problems = []
    for index, (key, folder) in enumerate(folders):
        for other, other_folder in folders[:index]:
            if _inside(folder, other_folder) or _inside(other_folder, folder):
                how = "is" if folder.rstrip("/") == other_folder.rstrip("/") else "overlaps"
                blamed, other, value, other_value = _blamed(key, other, given, folder, other_folder)
                problems.append((blamed, f"{value!r} {how} {other} ({other_value!r}): each folder roslab manages "
                                         "needs one of its own (the underlay's switch replaces its install folder)"))
    return problems


def _blamed(key: str, other: str, given, *values) -> tuple:
    """(key, other, its value, other's value), swapped when only `other` was given by hand."""
    if given is not None and key not in given and other in given:
        return (other, key, *reversed(values)) if values else (other, key, None, None)
    return (key, other, *values) if values else (key, other, None, None)


def port_problems(data: Mapping, given=None) -> list[tuple[str, str]]:
    """No two of the host's ports are one: the Zenoh router or discovery server on the SSH port
    would not start, or would take SSH's place. The problem is the key of the pair that was
    `given` (set in the roster or on the command line), else the later one."""
    ports = [(key, data.get(key) if key != "ssh_port" else data.get(key) or 22) for key in PORT_SETTINGS]
    ports = [(key, port) for key, port in ports if isinstance(port, int) and not isinstance(port, bool)]
    if data.get("apt_cache_enabled") and data.get("apt_cache_host") and \
            data.get("apt_cache_host") == data.get("roslab_hostname"):
        ports.append(("apt_cache_port", data.get("apt_cache_port")))
    problems: list[tuple[str, str]] = []
    seen: dict[int | None, str] = {}
    for key, port in ports:
        if port in seen:
            blamed, other, _, _ = _blamed(key, seen[port], given)
            problems.append((blamed, f"port {port} is also this host's {other}: give each its own port"))
        seen.setdefault(port, key)
    return problems


def across_problems(data: Mapping, given=None) -> list[tuple[str, str]]:
    """`given`: the keys set by hand (not defaults), to blame the one a person wrote."""
    return [*folder_problems(data, given), *port_problems(data, given)]


def hand_made_problems(data: Mapping, merged: Mapping | None = None) -> list[tuple[str, str]]:
    """A hand-made inventory host's data against every rule a roster's values meet, but the place
    of controller-side files (relative to a roster's folder: there is none). `merged`: the data
    with the schema's defaults under it, for the rules across values."""
    # No roster folder to keep controller-side files in: the whole machine is the place.
    problems = value_problems(data, formats.Context(Path("/")), controller_paths=False)
    bad = {key for key, _ in problems}
    across = across_problems(data if merged is None else merged, given=set(data))
    # null means "derived from the team's name" in a roster, which resolves it before a host
    # sees it; here it would silently export no ROS_DOMAIN_ID. (Left out, it is ROS's own 0.)
    unresolved = [] if "ros_domain_id" not in data or data["ros_domain_id"] is not None else [
        ("ros_domain_id", f"must not be null here: give a number ({formats.DOMAIN_IDS}); null derives "
                          "one from the team's name in a roster, and a hand-made inventory has no teams")]
    return [*problems, *[(key, message) for key, message in across if key not in bad], *unresolved]
