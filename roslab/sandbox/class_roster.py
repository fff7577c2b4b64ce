"""`roslab sandbox up --roster FILE`: a sandbox that looks like a teacher's own class.

The class's roster gives the hosts (names, teams, roles, Ubuntu releases, in its order); the
sandbox's roster is the class's own, with what the sandbox must serve itself put in place:

- the connection (`ssh_*`), each host's `address` (the sandbox's subnet) and the sandbox's
  archives, indexes and middleware (`Upstream.roster_settings`) replace the class's; a class
  on a ROS snapshot gets the sandbox's stand-in snapshot (`Upstream.snapshot_settings`);
- the network settings (`network_*`, WiFi) and secrets are left out: the sandbox's hosts
  keep its addresses, and it has no WiFi and no sudo password;
- a controller path written relative to the class's roster (a key file, a cache, the nodes'
  folder) is left out: the sandbox's roster lives elsewhere; an absolute one is kept.

Every setting left out or replaced that the class had set is one note line (the caller logs
them), e.g. Fast DDS on a distro the sandbox's real ROS runtime serves only with Cyclone DDS
(roslab's default Fast DDS too, when the class sets no middleware).
"""

from __future__ import annotations

from pathlib import Path

from roslab import formats, settings
from roslab.ros.distro import BY_RELEASE

from .system import SandboxError

# Settings the sandbox sets itself for every host (besides Upstream.roster_settings).
SANDBOX_OWN = ("ssh_user", "ssh_port", "ssh_key", "ssh_known_hosts_file", "ssh_strict_host_key_checking",
               "ssh_password", "address")
# Controller paths: kept only when absolute (a relative one is relative to the class's roster).
PATH_CHECKS = {getattr(formats, name, None) for name in (
    "secrets_file", "private_key_file", "known_hosts_file", "openpgp_key_file", "cache_dir", "nodes_dir")} - {None}
DEFAULT_RELEASE = "24.04"


def members(classroom) -> tuple[list[dict], list[str]]:
    """The sandbox hosts a loaded class roster asks for, in its order, and a note for each host
    whose release the sandbox does not emulate (it gets DEFAULT_RELEASE)."""
    hosts, notes = [], []
    for host in classroom.hosts:
        release = str(host.ubuntu_release or DEFAULT_RELEASE)
        if release not in BY_RELEASE:
            notes.append(f"{host.name}: Ubuntu {release} is not a release the sandbox emulates: it runs "
                         f"{DEFAULT_RELEASE}")
            release = DEFAULT_RELEASE
        hosts.append({"name": host.name, "team": host.team, "role": host.role, "release": release,
                      "board": host.settings.board})
    return hosts, notes


def _plain(value, key=None):
    """The strict loader's values as plain YAML data again (an Ambiguous scalar as the boolean a
    switch means, else its text)."""
    from roslab.checked.loading import Ambiguous

    if isinstance(value, Ambiguous):
        setting = settings.SETTINGS.get(key)
        if setting is not None and setting.kind is bool and isinstance(value.yaml11, bool):
            return value.yaml11
        return str(value)
    if isinstance(value, dict):
        return {str(k): _plain(v, k) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(item, key) for item in value]
    return value


def why_left_out(key: str, value, replaced: dict) -> str | None:
    """Why the sandbox does not keep a class setting (None: it keeps it)."""
    if key == "name":
        return None  # the sandbox's name, with the class's in brackets
    if key in SANDBOX_OWN:
        return None if key == "address" else f"{key}: the sandbox's own connection is used"
    if key in replaced:
        if replaced[key] == value:
            return None
        if key == "ros_middleware":
            return (f"ros_middleware {value}: the sandbox's real ROS runtime serves {replaced[key]} only "
                    "(its Humble has no Fast DDS); the sandbox runs that")
        return f"{key}: the sandbox serves its own"
    setting = settings.SETTINGS.get(key)
    if key.endswith("_secret") or key == "secrets_file":
        return f"{key}: the sandbox has no secrets (no WiFi, no sudo password)"
    if setting is not None and setting.concern == "network":
        return f"{key}: the sandbox's hosts keep its subnet's addresses"
    if key == "teacher_ssh_keys":
        return f"{key}: the sandbox's own key logs in"
    if setting is not None and setting.check in PATH_CHECKS and isinstance(value, str) \
            and not value.startswith(("/", "~")):
        return f"{key}: {value} is relative to your roster's folder, not the sandbox's"
    return None


def default_middleware_note(class_settings: dict, replaced: dict) -> str | None:
    """The note for a class on roslab's default middleware (its roster sets none) that the
    sandbox runs on another (its real ROS runtime's Cyclone DDS), or None."""
    default = settings.SETTINGS["ros_middleware"].default
    if "ros_middleware" in class_settings or replaced.get("ros_middleware", default) == default:
        return None  # set by the class: why_left_out says it; or the sandbox runs the default
    return (f"classroom: ros_middleware (not set: roslab's default {default}): the sandbox's real ROS runtime "
            f"serves {replaced['ros_middleware']} only (its Humble has no Fast DDS); the sandbox runs that")


def uses_snapshot(raw: dict) -> bool:
    """Whether any level of a class roster (as read) sets the ROS source's snapshot mode."""
    levels = [raw.get("classroom") or {}]
    for team in (raw.get("teams") or {}).values():
        levels += [team or {}, *((team or {}).get("hosts") or {}).values()]
    return any(isinstance(level, dict) and level.get("ros_apt_source_mode") == "snapshot" for level in levels)


def sandbox_roster(class_path: Path, base: dict, addresses: dict[str, str],
                   releases: dict[str, str], snapshot: dict | None = None) -> tuple[dict, list[str]]:
    """The sandbox's roster for the class at `class_path`: `base` is the roster the sandbox
    writes for its own hosts (its classroom settings win), `addresses` and `releases` each
    host's in the sandbox; `snapshot`: the settings of the sandbox's stand-in snapshot server,
    which replace the class's own when it installs ROS from a snapshot (snapshots.ros.org is
    out of the sandbox's reach). Returns the roster and the notes."""
    from roslab.checked.loading import load_yaml
    from roslab.checked.problems import Report

    report = Report(class_path)
    raw = _plain(load_yaml(class_path, report))
    if report.errors or not isinstance(raw, dict):
        raise SandboxError(f"{class_path}: cannot read the roster")
    replaced = dict(base["classroom"])
    if snapshot and uses_snapshot(raw):
        replaced.update(snapshot)
    notes: list[str] = []

    def kept(mapping: dict, where: str) -> dict:
        result = {}
        for key, value in (mapping or {}).items():
            if key in ("teams", "hosts"):
                continue
            reason = why_left_out(key, value, replaced)
            if reason:
                note = f"{where}: {reason}"
                if note not in notes:
                    notes.append(note)
                continue
            if key not in SANDBOX_OWN and key not in replaced:
                result[key] = value
        return result

    classroom = {**kept(raw.get("classroom") or {}, "classroom"), **replaced}
    default_note = default_middleware_note(raw.get("classroom") or {}, replaced)
    if default_note:
        notes.append(default_note)
    if raw.get("classroom", {}).get("name"):
        classroom["name"] = f"{replaced.get('name')} ({raw['classroom']['name']})"
    teams = {}
    for team_name, team in (raw.get("teams") or {}).items():
        team_data = kept(team, f"team {team_name}")
        hosts = {}
        for host_name, host in (team.get("hosts") or {}).items():
            host_data = kept(host, host_name)
            host_data["address"] = addresses[host_name]
            host_data["ubuntu_release"] = releases[host_name]  # the release it runs here
            hosts[host_name] = host_data
        team_data.pop("ubuntu_release", None)  # each host carries the release it runs here
        team_data["hosts"] = hosts
        teams[team_name] = team_data
    roster = {"classroom": classroom, "teams": teams}
    if raw.get("profiles"):
        roster["profiles"] = raw["profiles"]
        notes.append("profiles: your roster's own profiles are copied; a file one names by a relative path "
                     "is looked for beside the sandbox's roster")
    return roster, notes
