"""Load and validate a classroom roster (YAML) before any host is touched.

A roster describes a classroom: classroom-wide settings, then teams, each with
its settings and its hosts (see docs/architecture.md, "Roster format"). Every
setting is a key of some deploy's DEFAULTS (`deploy.ALL_DEFAULTS`) and may be
set at three levels, later wins: classroom < team < host.

`load_roster(path)` checks everything it can without a network, collects every
problem and raises one `RosterError` listing them all, one per line, each naming
file:line, team, host and field. `inventory_groups(classroom)` turns a valid
classroom into pyinfra inventory groups.

Decisions worth knowing:
- Team names become pyinfra groups, so they must be identifier-like; a `-` in a
  team name becomes `_` in its group name (`team-1` -> `--limit team_1`).
- Host names become pyinfra host names and the Pis' hostnames: RFC 1123 labels.
- `ros_domain_id` is a team setting (a team's hosts share it). With more than
  one team, every team needs its own: teams on one domain disturb each other.
- Host data holds only what the roster set (plus `roslab_*` identity and
  connection keys), so each deploy's `data_defaults` supply the rest.
"""

from __future__ import annotations

import difflib
import importlib
import ipaddress
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import yaml

import deploy
from roslab import distro as distros
from roslab import secrets

ROLES = ("main", "robot")

# Where pyinfra reaches a host; allowed at every level. Name -> expected type.
CONNECTION_KEYS = {
    "ssh_user": str,
    "ssh_port": int,
    "ssh_key": str,
    "ssh_known_hosts_file": str,
    "ssh_strict_host_key_checking": str,
    "sudo_password_secret": str,
}
# Connection keys holding controller-side paths, resolved against the roster's directory.
PATH_KEYS = ("ssh_key", "ssh_known_hosts_file")
CLASSROOM_KEYS = {"name": str, "secrets_file": str}
TEAM_KEYS = {"hosts": dict}
HOST_KEYS = {"role": str, "address": str}
LEVEL_KEYS = {"classroom": CLASSROOM_KEYS, "team": TEAM_KEYS, "host": HOST_KEYS}
TOP_LEVEL_KEYS = ("classroom", "teams")
STRICT_HOST_KEY_CHECKING = ("yes", "no", "off", "ask", "accept-new")
DOMAIN_ID_RANGE = range(0, 102)
DEFAULT_ROSTER = Path("inventories/lab.yaml")
CLASSROOM_ROSTER = Path("inventories/classroom.yaml")
DEFAULT_SECRETS_FILE = "secrets.yaml"

# Group names pyinfra or roslab already use; a team may not take them.
RESERVED_GROUPS = {"all", *ROLES, *distros.DISTRO_RELEASES}

_HOST_LABEL = re.compile(r"^[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?$", re.IGNORECASE)
_TEAM_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")


def setting_defaults() -> dict:
    """Every roster-settable setting and its default."""
    return dict(deploy.ALL_DEFAULTS)


def default_roster_path(base: Path | None = None) -> Path:
    """The roster to use: $ROSLAB_ROSTER, else a real classroom.yaml, else the example."""
    if os.environ.get("ROSLAB_ROSTER"):
        return Path(os.environ["ROSLAB_ROSTER"])
    base = Path.cwd() if base is None else base
    if (base / CLASSROOM_ROSTER).exists():
        return base / CLASSROOM_ROSTER
    return base / DEFAULT_ROSTER


def display_path(path: Path | str) -> str:
    """A path as the user would type it: relative to the working directory if inside it."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


# --- problems -----------------------------------------------------------------


@dataclass(frozen=True)
class Problem:
    """One error or warning, located as precisely as the roster allows."""

    path: str
    message: str
    line: int | None = None
    team: str | None = None
    host: str | None = None
    field: str | None = None

    def __str__(self) -> str:
        where = f"{self.path}:{self.line}" if self.line else self.path
        context = []
        if self.team is not None:
            context.append(f"team {self.team!r}")
        if self.host is not None:
            context.append(f"host {self.host!r}")
        if self.field is not None:
            context.append(f"field {self.field!r}")
        if not context:
            return f"{where}: {self.message}"
        return f"{where}: {', '.join(context)}: {self.message}"


class RosterError(Exception):
    """A roster that must not be deployed; `problems` lists every error found."""

    def __init__(self, problems: list[Problem]):
        self.problems = problems
        super().__init__("\n".join(str(problem) for problem in problems))


class Report:
    """Collects problems so that a roster's errors are all reported together."""

    def __init__(self, path: Path | str):
        self.path = display_path(path)
        self.errors: list[Problem] = []
        self.warnings: list[Problem] = []

    def error(self, message: str, **where) -> None:
        problem = Problem(self.path, message, **where)
        if problem not in self.errors:
            self.errors.append(problem)

    def warning(self, message: str, **where) -> None:
        problem = Problem(self.path, message, **where)
        if problem not in self.warnings:
            self.warnings.append(problem)


# Checks that run on a loaded classroom, each `(classroom, report)`, reporting
# through `report.error(message, team=, host=, field=, line=host.lines.get(field))`.
Validator = Callable[["Classroom", Report], None]
VALIDATORS: list[Validator] = []
# Modules whose `validate_roster(classroom, report)`, if they have one, runs too.
VALIDATOR_MODULES = ("roslab.netcheck",)


def registered_validators() -> list[Validator]:
    """VALIDATORS plus each present VALIDATOR_MODULES module's `validate_roster`."""
    validators = list(VALIDATORS)
    for name in VALIDATOR_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        if hasattr(module, "validate_roster"):
            validators.append(module.validate_roster)
    return validators


# --- the classroom -------------------------------------------------------------


@dataclass
class Host:
    name: str
    team: str
    role: str
    address: str
    ubuntu_release: str | None
    distro: str | None
    variant: str | None
    ros_domain_id: int | None
    # What pyinfra gets as host data.
    data: dict = field(repr=False)
    # Roster line of the host's entry.
    line: int | None = None
    # Roster line where each resolved field was set, for validators' messages.
    lines: dict = field(default_factory=dict, repr=False)


@dataclass
class Team:
    name: str
    group: str
    ros_domain_id: int | None
    hosts: list[Host]
    # Whether the roster chose the domain (team or classroom), not the deploy default.
    domain_set: bool = True


@dataclass
class Classroom:
    name: str | None
    path: Path
    teams: list[Team]
    warnings: list[Problem] = field(default_factory=list)

    @property
    def hosts(self) -> list[Host]:
        return [host for team in self.teams for host in team.hosts]


# --- strict YAML -----------------------------------------------------------------


class _Mapping(dict):
    """A YAML mapping that remembers where it and its keys are, and repeated keys."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.line: int | None = None
        self.key_lines: dict = {}
        self.duplicates: list = []  # (key, line, line of the first)


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that keeps line numbers and records duplicate keys.

    PyYAML keeps the last of two equal keys without a word; a roster typo like a
    second `address:` would silently win.
    """


def _construct_mapping(loader: StrictLoader, node: yaml.MappingNode):
    mapping = _Mapping()
    mapping.line = node.start_mark.line + 1
    mapping.key_lines = {}
    mapping.duplicates = []
    yield mapping
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            continue  # construct_mapping below reports it
        line = key_node.start_mark.line + 1
        if key in mapping.key_lines:
            mapping.duplicates.append((key, line, mapping.key_lines[key]))
        else:
            mapping.key_lines[key] = line
    mapping.update(loader.construct_mapping(node, deep=True))


StrictLoader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)


def load_yaml(path: Path, report: Report):
    """Parse a YAML file strictly; problems go to `report`, the result may be None."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        report.error(f"cannot read the file: {exc.strerror}")
        return None
    try:
        return yaml.load(text, Loader=StrictLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        report.error(f"not valid YAML: {exc.problem}", line=mark.line + 1 if mark else None)
    except yaml.YAMLError:
        report.error("not valid YAML")  # no excerpt: the file may hold secrets
    return None


def _line(mapping, key=None) -> int | None:
    if not isinstance(mapping, _Mapping):
        return None
    return mapping.key_lines.get(key, mapping.line) if key is not None else mapping.line


# --- value checks -----------------------------------------------------------------


def _type_name(kind) -> str:
    return {str: "a string", int: "an integer", float: "a number", bool: "true or false",
            list: "a list", dict: "a mapping"}.get(kind, kind.__name__)


def _type_problem(value, kind) -> str | None:
    """Why `value` is not of `kind`, or None. bool is not an int here."""
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if ok:
        return None
    hint = ""
    if kind is str and isinstance(value, (int, float)) and not isinstance(value, bool):
        hint = f' (YAML reads {value} as a number: quote it, "{value}")'
    return f"must be {_type_name(kind)}, not {value!r}{hint}"


def is_valid_hostname(name: str) -> bool:
    """An RFC 1123 DNS name (labels of letters, digits and inner hyphens)."""
    labels = name.rstrip(".").split(".")
    if len(name) > 253 or not all(_HOST_LABEL.match(label) for label in labels):
        return False
    # All-numeric names are malformed IP addresses, not host names.
    return not all(label.isdigit() for label in labels)


def _check_address(value: str) -> str | None:
    try:
        ipaddress.ip_address(value)
        return None
    except ValueError:
        pass
    if is_valid_hostname(value):
        return None
    return f"{value!r} is neither an IP address nor a valid host name"


def _check_network_address(value: str) -> str | None:
    # The prefix may come from another setting; the network checks see to that.
    try:
        ipaddress.ip_interface(value)
    except ValueError:
        return f"{value!r} is not an IP address (with prefix length), e.g. '192.168.50.11/24'"
    return None


def _check_ip(value: str) -> str | None:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return f"{value!r} is not an IP address"
    return None


def _check_release(value: str) -> str | None:
    try:
        distros.codename_for(value)
    except distros.DistroError as exc:
        return str(exc)
    return None


def _check_distro_name(value: str) -> str | None:
    if value not in distros.DISTRO_RELEASES:
        known = ", ".join(sorted(distros.DISTRO_RELEASES))
        return f"ROS 2 distro {value!r} does not exist (known: {known})"
    return None


def _check_variant(value: str) -> str | None:
    if value not in distros.VARIANTS:
        return f"{value!r} is not a ROS 2 install variant (one of: {', '.join(distros.VARIANTS)})"
    return None


def _check_domain_id(value: int) -> str | None:
    if value not in DOMAIN_ID_RANGE:
        return f"ROS_DOMAIN_ID {value} is outside 0 to 101"
    return None


def _check_port(value: int) -> str | None:
    return None if 0 < value < 65536 else f"port {value} is outside 1 to 65535"


def _check_strict_host_key_checking(value: str) -> str | None:
    if value not in STRICT_HOST_KEY_CHECKING:
        return f"{value!r} is not one of: {', '.join(STRICT_HOST_KEY_CHECKING)}"
    return None


def _check_role(value: str) -> str | None:
    return None if value in ROLES else f"{value!r} is not a role (one of: {', '.join(ROLES)})"


# Types of keys whose default is None, so the default cannot tell.
_NONE_DEFAULT_TYPES = {
    "ros_distro": str,
    "ros_variant": str,
    "ros_domain_id": int,
    "network_address": str,
    "network_gateway": str,
}

# Value checks by key, run where the key is set.
_VALUE_CHECKS: dict[str, Callable] = {
    "ubuntu_release": _check_release,
    "ros_distro": _check_distro_name,
    "ros_variant": _check_variant,
    "ros_variant_main": _check_variant,
    "ros_variant_robot": _check_variant,
    "ros_domain_id": _check_domain_id,
    "network_address": _check_network_address,
    "network_gateway": _check_ip,
    "ssh_port": _check_port,
    "ssh_strict_host_key_checking": _check_strict_host_key_checking,
    "role": _check_role,
    "address": _check_address,
}


# --- loading ----------------------------------------------------------------------


@dataclass
class _Setting:
    value: object
    line: int | None
    team: str | None  # where it was set: None for the classroom level
    host: str | None


class _RosterReader:
    def __init__(self, path: Path):
        self.path = Path(path)
        self.report = Report(path)
        self.defaults = setting_defaults()
        self.secrets_file: Path | None = None
        self.secrets_line: int | None = None
        self._secrets: dict | None = None
        self._secrets_read = False

    # Keys allowed at each level, and the kind each must have.
    def allowed(self, level: str) -> dict:
        own = LEVEL_KEYS[level]
        settings = {
            key: _NONE_DEFAULT_TYPES.get(key) if default is None else type(default)
            for key, default in self.defaults.items()
        }
        return {**settings, **CONNECTION_KEYS, **own}

    def read_level(self, mapping, level: str, team=None, host=None) -> dict[str, _Setting]:
        """Check one level's keys and values; return the valid ones."""
        where = {"team": team, "host": host}
        self.report_duplicates(mapping, **where)
        allowed = self.allowed(level)
        valid = {}
        for key, value in mapping.items():
            line = _line(mapping, key)
            if not isinstance(key, str):
                self.report.error(f"key {key!r} is not a name", line=line, **where)
                continue
            if key not in allowed:
                self.report.error(self.unknown_key_message(key, level, allowed), line=line,
                                  field=key, **where)
                continue
            if key == "ssh_strict_host_key_checking" and isinstance(value, bool):
                value = "yes" if value else "no"  # YAML 1.1 reads yes/no/off as booleans
            if key == "ros_domain_id" and host is not None:
                self.report.error(
                    "ros_domain_id is a team setting (a team's hosts share one domain); "
                    "set it on the team", line=line, field=key, **where)
                continue
            kind = allowed[key]
            if value is None and self.defaults.get(key, "") is None:
                valid[key] = _Setting(value, line, team, host)  # explicitly the default
                continue
            problem = _type_problem(value, kind) if kind else None
            if problem is None and key in _VALUE_CHECKS:
                problem = _VALUE_CHECKS[key](value)
            if problem is None and secrets.is_secret_reference(key):
                problem = self.secret_problem(value)
            if problem:
                self.report.error(problem, line=line, field=key, **where)
                continue
            valid[key] = _Setting(value, line, team, host)
        return valid

    def unknown_key_message(self, key: str, level: str, allowed: dict) -> str:
        for other, own in LEVEL_KEYS.items():
            if other != level and key in own:
                return f"{key!r} can only be set on a {other}, not on a {level}"
        message = f"unknown key {key!r}"
        close = difflib.get_close_matches(key, list(allowed), n=1)
        if close:
            message += f" (did you mean {close[0]!r}?)"
        return message

    def report_duplicates(self, mapping, **where) -> None:
        """Report keys a level's mapping, or a mapping inside one of its values, repeats."""
        for key, line, first in getattr(mapping, "duplicates", []):
            self.report.error(
                f"set twice (also at line {first}); YAML would silently keep the last",
                line=line, field=str(key), **where)
        for key, value in mapping.items():
            for nested in _nested_mappings(value):
                for _, line, first in nested.duplicates:
                    self.report.error(
                        f"a key inside it is set twice (lines {first} and {line}); "
                        "YAML would silently keep the last", line=line, field=str(key), **where)

    # --- secrets ---

    def secret_problem(self, name: str) -> str | None:
        """Why the secret `name` cannot be resolved, or None. Never shows a value."""
        if not self._secrets_read:
            self._secrets = self.read_secrets()
            self._secrets_read = True
        if self._secrets is None:
            return (f"names secret {name!r}, but the secrets file "
                    f"{display_path(self.secrets_file)} is missing or unusable")
        if name not in self._secrets:
            return f"names secret {name!r}, which {display_path(self.secrets_file)} does not define"
        return None

    def read_secrets(self) -> dict | None:
        """The secrets file's entries, or None (with the reasons reported)."""
        path = self.secrets_file
        shown = display_path(path)
        where = {"field": "secrets_file", "line": self.secrets_line}
        if not path.exists():
            example = display_path(
                path.with_name(Path(DEFAULT_SECRETS_FILE).stem + secrets.EXAMPLE_SUFFIX))
            self.report.error(f"secrets file {shown} does not exist (copy {example}, "
                              "fill it in, and chmod 600 it)", **where)
            return None
        problem = secrets.permission_problem(path, shown)
        if problem and secrets.is_example(path):
            self.report.warning(f"{problem} (allowed for an example holding placeholders)",
                                **where)
        elif problem:
            self.report.error(problem, **where)
            return None
        # The secrets file's own problems name that file and the entry, never a value.
        own_report = Report(path)
        content = load_yaml(path, own_report)
        if not isinstance(content, dict):
            own_report.error("must be a mapping of secret name -> value")
            content = {}
        for key, line, first in getattr(content, "duplicates", []):
            own_report.error(f"secret {key!r} is defined twice (also at line {first})", line=line)
        for key, value in content.items():
            if not isinstance(value, str):
                own_report.error(f"secret {key!r}: the value must be a string (quote it)",
                                 line=_line(content, key))
        self.report.errors.extend(own_report.errors)
        return None if own_report.errors else dict(content)

    # --- the whole roster ---

    def read(self) -> Classroom | None:
        roster = load_yaml(self.path, self.report)
        if roster is None:
            if not self.report.errors:
                self.report.error("the roster is empty")
            return None
        if not isinstance(roster, dict):
            self.report.error("a roster is a mapping with 'classroom' and 'teams'")
            return None
        self.report_duplicates_top(roster)
        for key in roster:
            if key not in TOP_LEVEL_KEYS:
                close = difflib.get_close_matches(str(key), TOP_LEVEL_KEYS, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.report.error(f"unknown top-level key {key!r}{hint}",
                                  line=_line(roster, key), field=str(key))

        classroom_map = roster.get("classroom") or _Mapping()
        if not isinstance(classroom_map, dict):
            self.report.error("'classroom' must be a mapping of settings",
                              line=_line(roster, "classroom"), field="classroom")
            classroom_map = _Mapping()
        secrets_name = classroom_map.get("secrets_file", DEFAULT_SECRETS_FILE)
        if not isinstance(secrets_name, str):
            secrets_name = DEFAULT_SECRETS_FILE  # read_level reports the type
        self.secrets_file = self.path.parent / secrets_name
        self.secrets_line = getattr(classroom_map, "key_lines", {}).get("secrets_file")
        classroom = self.read_level(classroom_map, "classroom")

        teams_map = roster.get("teams")
        if not isinstance(teams_map, dict) or not teams_map:
            self.report.error("'teams' must be a mapping of team name -> team",
                              line=_line(roster, "teams"), field="teams")
            teams_map = {}

        teams = [self.read_team(str(name), team_map, classroom, _line(teams_map, name))
                 for name, team_map in teams_map.items()]
        teams = [team for team in teams if team is not None]
        name = classroom.get("name")
        result = Classroom(name.value if name else None, self.path, teams)
        self.check_classroom(result, teams_map)
        _add_host_lists(result)
        return result

    def report_duplicates_top(self, roster) -> None:
        for key, line, first in getattr(roster, "duplicates", []):
            self.report.error(f"{key!r} appears twice (also at line {first})", line=line)
        for key, line, first in getattr(roster.get("teams"), "duplicates", []):
            self.report.error(
                f"the team appears twice (also at line {first}); "
                "YAML would silently keep the last", line=line, team=str(key))

    def read_team(self, name: str, team_map, classroom: dict, line) -> Team | None:
        if not _TEAM_NAME.match(name):
            self.report.error(
                "a team name starts with a letter and holds only letters, digits, '_' and '-' "
                "(it becomes a pyinfra group)", team=name, line=line)
            return None
        if not isinstance(team_map, dict):
            self.report.error("a team must be a mapping with 'hosts'", team=name, line=line)
            return None
        hosts_map = team_map.get("hosts")
        for key, dup_line, first in getattr(hosts_map, "duplicates", []):
            self.report.error(
                f"host {key!r} appears twice in this team (also at line {first})",
                team=name, host=str(key), line=dup_line)
        team_settings = self.read_level(_without(team_map, "hosts"), "team", team=name)
        if not isinstance(hosts_map, dict) or not hosts_map:
            self.report.error("a team needs at least one host under 'hosts'",
                              team=name, field="hosts",
                              line=getattr(team_map, "key_lines", {}).get("hosts", line))
            hosts_map = {}

        domain = team_settings.get("ros_domain_id") or classroom.get("ros_domain_id")
        domain_id = domain.value if domain else self.defaults.get("ros_domain_id")
        team = Team(name, name.replace("-", "_"), domain_id, [], domain_set=domain is not None)
        mains = []
        for host_name, host_map in hosts_map.items():
            host = self.read_host(str(host_name), host_map, team, [classroom, team_settings],
                                  _line(hosts_map, host_name))
            if host is None:
                continue
            if host.role == "main":
                mains.append(host.name)
                if len(mains) > 1:
                    self.report.error(
                        f"a team has at most one main host, and {mains[0]!r} already is",
                        team=name, host=host.name, field="role", line=host.lines.get("role"))
            team.hosts.append(host)
        return team

    def read_host(self, name: str, host_map, team: Team, outer: list[dict], line) -> Host | None:
        where = {"team": team.name, "host": name}
        if not _HOST_LABEL.match(name):
            self.report.error(
                "a host name is a valid hostname: letters, digits and inner '-', "
                "at most 63 characters (it becomes the Pi's hostname)", line=line, **where)
            return None
        if host_map is None:
            host_map = _Mapping()
        if not isinstance(host_map, dict):
            self.report.error("a host must be a mapping with at least 'role'", line=line, **where)
            return None
        own = self.read_level(host_map, "host", **where)
        if "role" not in own:
            if "role" not in host_map:
                self.report.error("every host needs a role (main or robot)", field="role",
                                  line=_line(host_map) or line, **where)
            return None

        resolved: dict[str, _Setting] = {}
        for level in (*outer, own):
            resolved.update(level)
        lines = {key: setting.line for key, setting in resolved.items()}
        role = own["role"].value
        address = own["address"].value if "address" in own else name

        release = self.setting(resolved, "ubuntu_release")
        codename = distros.UBUNTU_CODENAMES.get(str(release))
        override = self.setting(resolved, "ros_distro")
        expected = None
        if codename:
            expected = override or distros.DEFAULT_DISTRO.get(codename)
            if override and override in distros.DISTRO_RELEASES:
                try:
                    distros.check_distro(override, codename)
                except distros.DistroError as exc:
                    self.report.error(str(exc), field="ros_distro",
                                      line=resolved["ros_distro"].line, **where)
        variant = self.setting(resolved, "ros_variant") or self.setting(
            resolved, f"ros_variant_{role}")

        data = {
            "roslab_team": team.name,
            "roslab_role": role,
            "roslab_hostname": name,
            "roslab_ubuntu_release": release,
            "roslab_expected_distro": expected,
            "roslab_roster_path": str(self.path.resolve()),
            "ssh_hostname": address,
        }
        for key, setting in resolved.items():
            if key in HOST_KEYS or key in CLASSROOM_KEYS:
                continue
            value = setting.value
            if key in PATH_KEYS and isinstance(value, str):
                value = str(self.path.parent / Path(value).expanduser())
            data[key] = value
            if secrets.is_secret_reference(key) and value in (self._secrets or {}):
                data[secrets.resolved_key(key)] = secrets.wrap(key, self._secrets[value])
        if data.get("ssh_user") not in (None, "root"):
            data["_sudo"] = True  # a Pi's default user provisions through sudo
        return Host(name, team.name, role, address, release, expected, variant,
                    team.ros_domain_id, data, line, lines)

    def setting(self, resolved: dict, key: str):
        if key in resolved:
            return resolved[key].value
        return self.defaults.get(key)

    def check_classroom(self, classroom: Classroom, teams_map) -> None:
        self.check_groups(classroom, teams_map)
        self.check_domain_ids(classroom, teams_map)
        self.check_unique(classroom, None, lambda host: host.name.lower())
        self.check_unique(classroom, "address", _address_key)
        self.check_unique(classroom, "network_address", _network_ip_key)

    def check_groups(self, classroom: Classroom, teams_map) -> None:
        groups: dict[str, str] = {}
        for team in classroom.teams:
            line = _line(teams_map, team.name)
            if team.group in RESERVED_GROUPS:
                self.report.error(
                    f"the team's group {team.group!r} is already a pyinfra group "
                    f"(reserved: {', '.join(sorted(RESERVED_GROUPS))}); rename the team",
                    team=team.name, line=line)
            elif team.group in groups:
                self.report.error(
                    f"the team's group {team.group!r} is also team {groups[team.group]!r}'s "
                    "('-' becomes '_'); rename one of them", team=team.name, line=line)
            groups[team.group] = team.name
        group_names = set(groups) | RESERVED_GROUPS
        for host in classroom.hosts:
            if host.name in group_names:
                self.report.error(
                    f"{host.name!r} is also a group name, so --limit {host.name} would be "
                    "ambiguous; rename the host", team=host.team, host=host.name)

    def check_domain_ids(self, classroom: Classroom, teams_map) -> None:
        owners: dict[int, str] = {}
        for team in classroom.teams:
            team_lines = getattr(teams_map.get(team.name), "key_lines", {})
            line = team_lines.get("ros_domain_id") or _line(teams_map, team.name)
            if not team.domain_set and len(classroom.teams) > 1:
                self.report.error(
                    "set a ros_domain_id (0 to 101) for each team: teams on one "
                    "domain see and disturb each other's topics",
                    team=team.name, field="ros_domain_id", line=line)
                continue
            if team.ros_domain_id is None:
                continue
            if team.ros_domain_id in owners:
                self.report.error(
                    f"ROS_DOMAIN_ID {team.ros_domain_id} is already team "
                    f"{owners[team.ros_domain_id]!r}'s; teams on one domain see and disturb "
                    "each other's topics", team=team.name, field="ros_domain_id", line=line)
            else:
                owners[team.ros_domain_id] = team.name

    def check_unique(self, classroom: Classroom, field_name: str | None, key_of) -> None:
        """Report hosts sharing a name (field_name None) or a field's value."""
        seen: dict = {}
        for host in classroom.hosts:
            key = key_of(host)
            if key is None:
                continue
            if key not in seen:
                seen[key] = host
                continue
            other = seen[key]
            what = "the host name" if field_name is None else str(key)
            self.report.error(
                f"{what} is already used by host {other.name!r} of team {other.team!r}",
                team=host.team, host=host.name, field=field_name,
                line=host.lines.get(field_name) if field_name else host.line)


def _without(mapping: dict, key) -> _Mapping:
    """A copy of a mapping without `key`, keeping its line numbers."""
    copy = _Mapping((k, v) for k, v in mapping.items() if k != key)
    copy.line = getattr(mapping, "line", None)
    copy.key_lines = getattr(mapping, "key_lines", {})
    copy.duplicates = getattr(mapping, "duplicates", [])
    return copy


def _nested_mappings(value):
    """Every mapping inside a setting's value (a dict or list of them)."""
    if isinstance(value, _Mapping):
        yield value
    children = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
    for child in children:
        yield from _nested_mappings(child)


def _address_key(host: Host):
    try:
        return ipaddress.ip_address(host.address)
    except ValueError:
        return host.address.lower().rstrip(".")


def _network_ip_key(host: Host):
    value = host.data.get("network_address")
    return ipaddress.ip_interface(value).ip if value else None


def _host_ip(host: Host) -> str | None:
    """The address other hosts reach this host at, for /etc/hosts: an IP or None."""
    if host.data.get("network_address"):
        return str(ipaddress.ip_interface(host.data["network_address"]).ip)
    try:
        return str(ipaddress.ip_address(host.address))
    except ValueError:
        return None


def _add_host_lists(classroom: Classroom) -> None:
    everyone = [{"name": host.name, "address": _host_ip(host)} for host in classroom.hosts]
    for team in classroom.teams:
        members = [{"name": host.name, "address": _host_ip(host), "role": host.role}
                   for host in team.hosts]
        for host in team.hosts:
            host.data["roslab_classroom_hosts"] = everyone
            host.data["roslab_team_hosts"] = members


def load_roster(path: Path | str, validators: list[Validator] | None = None) -> Classroom:
    """Load and validate a roster; raise RosterError listing every problem."""
    reader = _RosterReader(Path(path))
    classroom = reader.read()
    if classroom is not None:
        for validator in registered_validators() if validators is None else validators:
            validator(classroom, reader.report)
    if reader.report.errors:
        raise RosterError(reader.report.errors)
    classroom.warnings = reader.report.warnings
    return classroom


def inventory_groups(classroom: Classroom) -> dict[str, list[tuple[str, dict]]]:
    """pyinfra inventory groups: `main`, `robot`, one per team, one per expected distro.

    A host the network deploy has moved is reached at its last confirmed address
    (recorded beside the roster), not at the roster's now stale `address`.
    """
    from roslab.netstate import last_known_address

    groups: dict[str, list[tuple[str, dict]]] = {role: [] for role in ROLES}
    for team in classroom.teams:
        groups[team.group] = []
        for host in team.hosts:
            moved_to = last_known_address(classroom.path, host.name)
            entry = (host.name, {**host.data, "ssh_hostname": moved_to or host.address})
            groups[team.group].append(entry)
            groups[host.role].append(entry)
            if host.distro:
                groups.setdefault(host.distro, []).append(entry)
    return groups
