"""Walk a loaded roster into a Classroom, checking every key and value where it is set.

A roster: `classroom:` settings, then `teams:`, each with settings and `hosts:`
(see docs/architecture.md, "Roster format"). A setting may be set at the levels its
schema entry allows, later wins: classroom < team < host. Each host's data gets every
deploy setting's default merged in once, here; controller-side paths become absolute
and teacher key files are read, so no deploy needs the roster's location for them.
"""

from __future__ import annotations

import difflib
import functools
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roslab.ros import distro as distros
from roslab import formats, secrets, settings
from roslab.controller_files import MAX_SMALL_FILE_BYTES, UnreadableFile, read_regular_file
from roslab.roster import overrides
from roslab.roster.checks import unknown_key_message
from roslab.checked.loading import (
    Ambiguous,
    Mapping,
    ambiguous_inside,
    line_of,
    load_yaml,
    name_problem,
    nested_mappings,
    without,
)
from roslab.roster.model import Classroom, Host, Team
from roslab.checked.problems import Problem, Report, display_path

TOP_LEVEL_KEYS = ("classroom", "teams", "profiles")
# Role-named keys kept as aliases of the role-free ones (a warning says which to set instead).
DEPRECATED = {"ros_variant_main": "ros_variant", "ros_variant_robot": "ros_variant",
              "nodes_launch_main": "nodes_launch", "nodes_launch_robot": "nodes_launch"}
DEFAULT_SECRETS_FILE = "secrets.yaml"
_TEAM_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,62}", re.ASCII)
# Connection keys pyinfra reads from host data under the same name.
CONNECTION_KEYS = tuple(s.key for s in settings.SCHEMA if s.concern == "connection")


@dataclass
class Value:
    value: Any  # a roster value, checked against its setting where it is read
    line: int | None


def _is_controller_path(setting: settings.Setting) -> bool:
    return getattr(setting.check, "controller_path", False)


def settled_yaml_value(setting: settings.Setting, value):
    """The value the teacher meant, or a problem when YAML's reading of it is ambiguous.

    A switch (a boolean setting) written yes/no/on/off means true/false; a text setting
    whose allowed values include the word written (ssh_strict_host_key_checking: no)
    means that word. Anything else YAML 1.1 and 1.2 read differently (010, 08, 1:30,
    0x10, 1_000, yes as text) is refused with what YAML would make of it.
    """
    if isinstance(value, Ambiguous):
        if setting.kind is bool and isinstance(value.yaml11, bool):
            return value.yaml11, None
        if setting.kind is str and str(value) in (getattr(setting.check, "choices", None) or ()):
            return str(value), None
        wanted = "number" if setting.kind is int or setting.item is int else "text"
        return value, value.hint(wanted)
    if setting.kind is str and isinstance(value, bool) and setting.key == "ssh_strict_host_key_checking":
        return ("yes" if value else "no"), None  # true/false for the policy's yes/no
    inner = ambiguous_inside(value)
    if inner is not None:
        wanted = "number" if setting.item is int else "text"
        return value, f"holds {str(inner)!r}: {inner.hint(wanted)}"
    return value, None


COMMAND_LINE = "pyinfra's command line"


class RosterReader:
    def __init__(self, path: Path, command_line: list | None = None):
        self.path = Path(path)
        self.report = Report(path)
        # pyinfra's --data/--user/--port/--key values: (option, key, text, value), checked
        # as the level that wins over every other (roslab.roster.overrides).
        self.command_line_data = list(command_line or [])
        self.command_line: dict[str, Value] = {}
        self._command_line_shown: dict[str, tuple[str, str]] = {}  # key -> (option, text as given)
        self.context = formats.Context(self.path.parent, self.path)
        self.defaults = settings.defaults()
        self.secrets_file: Path | None = None
        self.secrets_line: int | None = None
        self._secrets: dict | None = None
        self._secrets_read = False
        self.secrets_refused = False
        self.secrets_default_problem: str | None = None
        self._key_files: dict[str, list[str]] = {}  # teacher_ssh_keys entry -> its key lines
        self.profiles: dict = {}  # name -> roslab.profiles.Profile (built-in and the roster's)
        self.profile_settings: dict[str, list[str]] = {}  # profile setting -> profiles declaring it

    @functools.cached_property
    def resolved_path(self) -> str:
        """Every host's roslab_roster_path: one lookup of the file, not one per host."""
        return str(self.path.resolve())

    # --- one level ---

    def read_level(self, mapping, level: str, team=None, host=None) -> dict[str, Value]:
        """Check one level's keys and values; return the valid ones."""
        where = {"team": team, "host": host}
        self.report_duplicates(mapping, **where)
        allowed = settings.keys_at(level)
        valid = {}
        for key, value in mapping.items():
            line = line_of(mapping, key)
            problem = name_problem(key, "key")
            if problem:
                self.report.error(problem, line=line, **where)
                continue
            if key == "hosts" and level == "team":
                continue
            setting = allowed.get(key)
            if setting is None and key in self.profile_settings:
                # A profile's own setting (lds_model...): checked against the host's profile once
                # its profile is known (read_host); here only its type. YAML's true/false and
                # whole numbers (osr_calibrated: true, a port) are their words.
                value = profile_setting_word(value)
                if not isinstance(value, str):
                    self.report.error(settings.type_problem(value, str) or "must be a string",
                                      line=line, field=key, **where)
                else:
                    valid[key] = Value(value, line)
                continue
            if setting is None:
                self.report.error(unknown_key_message(key, level), line=line, field=key, **where)
                continue
            value, problem = settled_yaml_value(setting, value)
            if problem is None:
                problem = settings.check_value(setting, value, self.context)
            if problem is None and secrets.is_secret_reference(key) and value is not None:
                problem = self.secret_problem(value)
            if problem:
                self.report.error(problem, line=line, field=key, **where)
                continue
            valid[key] = Value(value, line)
        return valid

    def report_duplicates(self, mapping, **where) -> None:
        """Report keys a level's mapping, or a mapping inside one of its values, repeats."""
        for key, line, first in getattr(mapping, "duplicates", []):
            self.report.error(
                f"set twice (also at line {first}); YAML would silently keep the last",
                line=line, field=str(key), **where)
        for key, value in mapping.items():
            if key == "hosts":
                continue
            for nested in nested_mappings(value):
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
                    f"{display_path(self.secrets_file or DEFAULT_SECRETS_FILE)} is missing or unusable")
        if name not in self._secrets:
            return f"names secret {name!r}, which {display_path(self.secrets_file or DEFAULT_SECRETS_FILE)} does not define"
        return None

    def read_secrets(self) -> dict | None:
        """The secrets file's entries, or None (with the reasons reported)."""
        path = self.secrets_file
        if path is None:  # read_level names it before any secret is looked up
            return None
        shown = display_path(path)
        where = {"field": "secrets_file", "line": self.secrets_line}
        if self.secrets_refused:
            if self.secrets_default_problem:
                self.report.error(f"the default secrets file: {self.secrets_default_problem}", **where)
            return None  # a path outside its place is never read (read_level reported a named one)
        if not path.is_file() and os.path.lexists(path):
            try:
                read_regular_file(path)
            except UnreadableFile as exc:
                self.report.error(f"secrets file {shown}: {exc}", **where)
                return None
        if not path.is_file():
            example = display_path(
                path.with_name(Path(DEFAULT_SECRETS_FILE).stem + secrets.EXAMPLE_SUFFIX))
            self.report.error(f"secrets file {shown} does not exist (copy {example}, "
                              "fill it in, and chmod 600 it)", **where)
            return None
        problem = secrets.permission_problem(path, shown)
        if problem and secrets.is_example(path):
            self.report.warning(f"{problem} (allowed for an example holding placeholders)", **where)
        elif problem:
            self.report.error(problem, **where)
            return None
        # The secrets file's own problems name that file and the entry, never a value.
        own = Report(path)
        content = load_yaml(path, own, secret=True, limit=MAX_SMALL_FILE_BYTES)
        if not isinstance(content, dict):
            if not own.errors:
                own.error("must be a mapping of secret name -> value")
            content = {}
        for key, line, first in getattr(content, "duplicates", []):
            own.error(f"secret {key!r} is defined twice (also at line {first})", line=line)
        for key, value in content.items():
            if not isinstance(key, str) or formats.secret_name(key):
                own.error("a secret's name must be letters, digits, _ . -", line=line_of(content, key))
            elif not isinstance(value, str):
                own.error(f"secret {key!r}: the value must be a string (quote it)",
                          line=line_of(content, key))
            elif formats.single_line(value):
                own.error(f"secret {key!r}: the value must be one line of text", line=line_of(content, key))
        self.report.extend(own)
        # Plain text from here on (an ambiguous-looking secret is the text written, like any other).
        return None if own.errors else {str(key): str(value) for key, value in content.items()}

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
        for key, line, first in getattr(roster, "duplicates", []):
            self.report.error(f"{key!r} appears twice (also at line {first})", line=line)
        for key in roster:
            if key_problem := name_problem(key, "key"):
                self.report.error(key_problem, line=line_of(roster, key))
            elif key not in TOP_LEVEL_KEYS:
                close = difflib.get_close_matches(str(key), TOP_LEVEL_KEYS, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.report.error(f"unknown top-level key {key!r}{hint}",
                                  line=line_of(roster, key), field=str(key))

        from roslab.profiles.library import profile_setting_names, roster_profiles  # profiles read rosters' YAML

        self.profiles = roster_profiles(roster.get("profiles"), self.report, self.path.parent)
        self.profile_settings = profile_setting_names(self.profiles)
        classroom_map = roster.get("classroom") or Mapping()
        if not isinstance(classroom_map, dict):
            self.report.error("'classroom' must be a mapping of settings",
                              line=line_of(roster, "classroom"), field="classroom")
            classroom_map = Mapping()
        secrets_name = classroom_map.get("secrets_file", DEFAULT_SECRETS_FILE)
        if not isinstance(secrets_name, str) or formats.single_line(secrets_name):
            secrets_name = DEFAULT_SECRETS_FILE  # read_level reports it
        self.secrets_file = self.context.controller_path(secrets_name)
        # The default secrets.yaml keeps to the same place as a named one (a symlink out of
        # the roster's folder is refused too); read_level reports a named one's problem.
        problem = settings.check_value(settings.SETTINGS["secrets_file"], secrets_name, self.context)
        self.secrets_refused = bool(problem)
        self.secrets_default_problem = problem if "secrets_file" not in classroom_map else None
        self.secrets_line = getattr(classroom_map, "key_lines", {}).get("secrets_file")
        classroom = self.read_level(classroom_map, "classroom")
        self.command_line = self.read_command_line()

        teams_map = roster.get("teams")
        if not isinstance(teams_map, dict) or not teams_map:
            self.report.error("'teams' must be a mapping of team name -> team",
                              line=line_of(roster, "teams"), field="teams")
            teams_map = {}
        for key, line, first in getattr(teams_map, "duplicates", []):
            self.report.error(f"the team appears twice (also at line {first}); "
                              "YAML would silently keep the last", line=line, team=str(key))

        teams = []
        for name, team_map in teams_map.items():
            problem = name_problem(name, "team name")
            if problem:
                self.report.error(problem, team=str(name), line=line_of(teams_map, name))
                continue
            teams.append(self.read_team(name, team_map, classroom, line_of(teams_map, name)))
        name = classroom.get("name")
        return Classroom(name.value if name else None, self.path, [t for t in teams if t])

    def read_team(self, name: str, team_map, classroom: dict, line) -> Team | None:
        if not _TEAM_NAME.fullmatch(name):
            self.report.error(
                "a team name starts with a letter and holds only letters, digits, '_' and '-', "
                "at most 63 characters (it becomes a pyinfra group)", team=name, line=line)
            return None
        if not isinstance(team_map, dict):
            self.report.error("a team must be a mapping with 'hosts'", team=name, line=line)
            return None
        hosts_map = team_map.get("hosts")
        for key, dup_line, first in getattr(hosts_map, "duplicates", []):
            self.report.error(f"host {key!r} appears twice in this team (also at line {first})",
                              team=name, host=str(key), line=dup_line)
        team_settings = self.read_level(without(team_map, "hosts"), "team", team=name)
        if not isinstance(hosts_map, dict) or not hosts_map:
            self.report.error("a team needs at least one host under 'hosts'", team=name,
                              field="hosts", line=getattr(team_map, "key_lines", {}).get("hosts", line))
            hosts_map = {}

        domain = (self.command_line.get("ros_domain_id") or team_settings.get("ros_domain_id")
                  or classroom.get("ros_domain_id"))
        team = Team(name, name.replace("-", "_"),
                    domain.value if domain else None, [],
                    domain_set=domain is not None, line=line,
                    domain_line=domain.line if domain else None)
        mains = []
        for host_name, host_map in hosts_map.items():
            host = self.read_host(host_name, host_map, team, [classroom, team_settings],
                                  line_of(hosts_map, host_name))
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

    def read_host(self, name, host_map, team: Team, outer: list[dict], line) -> Host | None:
        where = {"team": team.name, "host": str(name)}
        own = self.read_host_level(name, host_map, line, where)
        if own is None:
            return None
        self.check_host_discovery_mode(own, where)
        resolved: dict[str, Value] = {}
        for level in (*outer, own, self.command_line):
            resolved.update(level)
        role = own["role"].value
        address = own["address"].value if own.get("address") and own["address"].value else name

        data = self.host_data(resolved)
        release = data["ubuntu_release"]
        codename = distros.UBUNTU_CODENAMES.get(str(release))
        expected = (data["ros_distro"] or distros.DEFAULT_DISTRO.get(codename)) if codename else None
        variant = data["ros_variant"] or data[f"ros_variant_{role}"]
        data.update({
            "roslab_team": team.name,
            "roslab_role": role,
            "roslab_hostname": name,
            "roslab_ubuntu_release": release,
            "roslab_expected_distro": expected,
            "roslab_roster_path": self.resolved_path,
            "ros_domain_id": team.ros_domain_id,
            "ssh_hostname": address,
        })
        if data.get("ssh_user") not in (None, "root"):
            data["_sudo"] = True  # a Pi's default user provisions through sudo
        lines = {key: item.line for key, item in resolved.items()}
        self.warn_deprecated(outer, own, lines, team)
        set_here = {key for level in (*outer[1:], own) for key in level}  # team and host, not classroom
        self.apply_profile(data, resolved, set_here, lines, line, where)
        self.apply_sources(data, resolved, lines, line, where)
        variant = data["ros_variant"] or variant
        return Host(name, team.name, role, address, release, expected, variant, data, line, lines)

    def read_host_level(self, name, host_map, line, where: dict) -> dict[str, Value] | None:
        """The host's own checked values; None (reported) when its name or mapping is unusable or
        it has no role, so nothing else is read for it."""
        ambiguous = isinstance(name, (Ambiguous, bool)) or name is None
        problem = (name_problem(name, "host name") if ambiguous else None) or formats.host_label(name)
        if problem:
            self.report.error(problem, line=line, **where)
            return None
        if host_map is None:
            host_map = Mapping()
        if not isinstance(host_map, dict):
            self.report.error("a host must be a mapping with at least 'role'", line=line, **where)
            return None
        own = self.read_level(host_map, "host", **where)
        if "role" not in own:
            if "role" not in host_map:
                self.report.error("every host needs a role (main or robot)", field="role",
                                  line=line_of(host_map) or line, **where)
            return None
        return own

    def check_host_discovery_mode(self, own: dict[str, Value], where: dict) -> None:
        """A host of its own may only keep discovery on itself (localhost); other modes are the team's."""
        own_mode = own.get("ros_discovery_mode")
        if own_mode is not None and own_mode.value != "localhost":
            # A team's hosts share one mode (one server or router, each other as peers).
            self.report.error(f"a host may only be set to localhost (a simulation-only host); set "
                              f"{own_mode.value} on its team, where its team mates get it too",
                              field="ros_discovery_mode", line=own_mode.line, **where)

    def host_data(self, resolved: dict[str, Value]) -> dict:
        """roslab's defaults with the host's resolved settings over them: controller paths made
        absolute, secrets resolved, pins merged with roslab's known ones."""
        data = dict(self.defaults)
        for key, item in resolved.items():
            if key in ("name", "secrets_file", "role", "address") or key not in settings.SETTINGS:
                continue
            setting = settings.SETTINGS[key]
            value = item.value
            if isinstance(value, str) and _is_controller_path(setting):
                value = str(self.context.controller_path(value))
            if value is None and key in CONNECTION_KEYS:
                continue  # pyinfra's own default
            data[key] = value
            known = self._secrets or {}
            if secrets.is_secret_reference(key) and value in known:
                data[secrets.resolved_key(key)] = secrets.wrap(key, known[value])
        if "ros_apt_source_sha256" in resolved and \
                data["ros_apt_source_version"] == self.defaults["ros_apt_source_version"]:
            # A pin the roster adds (e.g. resolute's) keeps roslab's known ones for the other releases.
            data["ros_apt_source_sha256"] = {**self.defaults["ros_apt_source_sha256"],
                                             **(data["ros_apt_source_sha256"] or {})}
        data["teacher_ssh_keys"] = self.teacher_keys(data["teacher_ssh_keys"])
        if data["ros_apt_source_cache_dir"]:
            data["ros_apt_source_cache_dir"] = os.path.expanduser(data["ros_apt_source_cache_dir"])
        return data

    def warn_deprecated(self, outer: list[dict], own: dict[str, Value], lines: dict, team: Team) -> None:
        """One warning per deprecated key the classroom, team or host sets (the command line's are
        not the roster's to fix)."""
        levels = (*outer, own)
        if not any(DEPRECATED.keys() & level.keys() for level in levels):
            return  # the common case, said at C speed for each host
        for old_key, new_key in DEPRECATED.items():
            if any(level.get(old_key) is not None and level[old_key].value is not None for level in levels):
                self.report.warning(f"{old_key} is deprecated: set {new_key} (on the host, or in a robot "
                                    "profile's side); it is honoured for now", field=old_key,
                                    line=lines.get(old_key), team=team.name)

    # --- pyinfra's command line ---

    def read_command_line(self) -> dict[str, Value]:
        """Check pyinfra's --data (and --user, --port, --key) values like roster values."""
        report = Report(COMMAND_LINE)
        valid: dict[str, Value] = {}
        for option, key, text, value in self.command_line_data:
            shown = f"{option} {key}={text}" if option == "--data" else f"{option} {text}"
            if option == "--data" and key in self.profile_settings and key not in settings.SETTINGS:
                # A profile's own setting (lds_model...): checked against each host's profile like
                # a roster value (apply_profile); here only its type.
                value = profile_setting_word(value)
                if isinstance(value, str):
                    valid[key] = Value(value, None)
                else:
                    report.error(f"{shown}: {settings.type_problem(value, str) or 'must be a string'}", field=key)
                continue
            problem = overrides.key_problem(key)
            setting = settings.SETTINGS.get(key)
            if problem is None and value is None:
                # pyinfra puts the null itself on top of every host's data, over roslab's resolved
                # value (ros_domain_id: no ROS_DOMAIN_ID at all, every team on domain 0).
                problem = overrides.NULL_PROBLEM
            if problem is None and setting is not None:
                problem = overrides.text_problem(setting, text, value) or settings.check_value(
                    setting, value, self.context)
            if problem:
                report.error(f"{shown}: {problem}", field=key)
            elif setting is not None:
                valid[key] = Value(value, None)
        self.report.extend(report)
        self._command_line_shown = {key: (option, text) for option, key, text, _ in self.command_line_data}
        return valid

    def check_command_line(self, classroom: Classroom) -> None:
        """pyinfra puts each command-line value back on top of the host data as it was given:
        refuse a value roslab's host data holds differently (a path relative to the roster,
        a .pub file read into key lines), so what runs is what was checked."""
        report = Report(COMMAND_LINE)
        for key, item in self.command_line.items():
            if key not in settings.SETTINGS:
                continue  # a profile's setting: in the host's resolved profile, not its own data
            for host in classroom.hosts:
                if host.data.get(key) != item.value:
                    option, text = self._command_line_shown[key]
                    shown = f"{option} {key}={text}" if option == "--data" else f"{option} {text}"
                    report.error(f"{shown}: roslab reads it as {host.data.get(key)!r} for the hosts, and pyinfra "
                                 "would hand them the text as given: set it in the roster (or give an "
                                 "absolute path, key lines)", field=key)
                    break
        self.report.extend(report)

    def blame_command_line(self) -> None:
        """A check across hosts (roslab.roster.VALIDATORS) reports a value by its roster line; one
        that came from pyinfra's command line has none there: name `--data key=value` instead of
        the roster file."""
        errors = []
        for problem in self.report.errors:
            shown = self._command_line_shown.get(problem.field or "")
            if shown is None or problem.line is not None or problem.path != self.report.path \
                    or problem.field not in self.command_line:
                errors.append(problem)
                continue
            option, text = shown
            given = f"{option} {problem.field}={text}" if option == "--data" else f"{option} {text}"
            errors.append(Problem(COMMAND_LINE, f"{given}: {problem.message}", None, problem.team,
                                  problem.host, problem.field))
        self.report.errors[:] = errors

    def teacher_keys(self, entries: list[str]) -> list[str]:
        """Key lines of `teacher_ssh_keys`: lines as they are, .pub files read (checked already)."""
        keys: list[str] = []
        for entry in entries:
            entry = entry.strip()
            if formats.PUBLIC_KEY.fullmatch(entry):
                keys.append(entry)
                continue
            if entry not in self._key_files:  # a classroom-wide file: read once, not per host
                try:
                    text = read_regular_file(self.context.controller_path(entry)).decode("utf-8")
                except (UnreadableFile, UnicodeDecodeError):
                    text = ""  # reported by the value check
                self._key_files[entry] = formats.public_key_lines(text) or []
            keys.extend(self._key_files[entry])
        return keys

    def host_error(self, message: str, field: str, resolved: dict, lines: dict, line, where: dict) -> None:
        """A host's problem with `field`: blamed on pyinfra's command line when the value came
        from there (--data), else on the roster's line that sets it (or the host's profile)."""
        item = resolved.get(field)
        if item is not None and self.command_line.get(field) is item:
            option, text = self._command_line_shown[field]
            shown = f"{option} {field}={text}" if option == "--data" else f"{option} {text}"
            report = Report(COMMAND_LINE)
            report.error(f"{shown}: {message}", field=field, **where)
            self.report.extend(report)
            return
        self.report.error(message, field=field, line=lines.get(field) or lines.get("robot_profile") or line,
                          **where)

    def apply_sources(self, data: dict, resolved: dict, lines: dict, line, where: dict) -> None:
        """Read the host's .repos files (its profile side's `sources`, the roster's
        `workspace_sources`) into `roslab_profile["sources"]` and `roslab_sources`; a problem
        names the .repos file and line, the host and the field."""
        from roslab.sources import repos as sources
        from roslab.profiles.resolve import side_parts

        if not hasattr(self, "_repos_files"):
            self._repos_files = sources.ReposFiles()
        profile = data.get("roslab_profile")
        side = None
        if profile is not None:
            definition = self.profiles.get(profile["name"])
            side = definition.sides.get(data["roslab_role"]) if definition else None
        # the side's own .repos files and those of its when blocks that hold for this host
        parts = side_parts(side, profile["settings"], profile["distro"], data.get("board")) \
            if side and profile is not None else []
        profile_sources = list(dict.fromkeys(item for part in parts for item in part.sources))
        own, every, problems = sources.host_sources(data, profile_sources, self.path.parent, self._repos_files)
        for field, problem in problems:
            if isinstance(problem, str):
                self.host_error(problem, field, resolved, lines, line, where)
            else:
                inner = f"{field}: {problem.field}" if problem.field else field
                self.report.add(Problem(problem.path, problem.message, problem.line,
                                        where.get("team"), where.get("host"), inner))
        if profile is not None:
            profile["sources"] = own
        data["roslab_sources"] = every

    def apply_profile(self, data: dict, resolved: dict, set_here: set, lines: dict, line, where: dict) -> None:
        """Resolve the host's robot profile into `data["roslab_profile"]` (problems reported)."""
        from roslab.profiles.resolve import resolve_host

        def error(message, field):
            self.host_error(message, field, resolved, lines, line, where)

        name = data["robot_profile"]
        profile = self.profiles.get(name)
        if profile is None:
            from roslab.profiles.library import broken_builtin

            close = difflib.get_close_matches(name, sorted(self.profiles), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            if broken_builtin(name):
                hint = " (its file in roslab's profile folder has the problems listed: fix them)"
            error(f"{name!r} is not a robot profile (known: {', '.join(sorted(self.profiles))}){hint}",
                  "robot_profile")
            data["roslab_profile"] = None
            return
        given = self.profile_settings_given(name, profile, resolved, set_here, error)
        distro = data["roslab_expected_distro"]
        if distro is None:  # an unknown release: reported by its own check
            data["roslab_profile"] = None
            return
        result, problems = resolve_host(profile, given, distro=distro, role=data["roslab_role"],
                                        board=data.get("board"), host=data.get("roslab_hostname"),
                                        middleware=data.get("ros_middleware"))
        for problem in problems:
            error(problem.message, problem.field)
        middleware = data.get("ros_middleware")
        if middleware and middleware not in profile.middlewares:
            error(f"profile {name!r} does not work with {middleware} (it works with: "
                  f"{', '.join(profile.middlewares)}): set ros_middleware to one of them, or another robot_profile",
                  "ros_middleware")
            data["roslab_profile"] = result = None
        data["roslab_profile"] = result
        if result is None:
            return
        apply_profile_defaults(data, resolved, result)
        venv = (result.get("python") or {}).get("venv")
        workspace = str(data.get("workspace_dir") or "")[2:].rstrip("/")
        if venv and workspace and (workspace == venv or workspace.startswith(venv + "/")):
            # The venv's COLCON_IGNORE (and a venv made anew) would take the workspace with it.
            error(f"profile {name!r} puts its Python venv in ~/{venv}, which holds the workspace "
                  f"(workspace_dir ~/{workspace}): give the profile's python_venv another directory",
                  "workspace_dir")
        apply_profile_verify_and_discovery(data, resolved, set_here, result)

    def profile_settings_given(self, name: str, profile, resolved: dict, set_here: set, error) -> dict:
        """The values the roster gives the profile's own settings. One the team or host sets for
        another profile is an error; one from the classroom or command line, meant for the other
        teams' profiles, is dropped quietly."""
        given = {key: item.value for key, item in resolved.items() if key in self.profile_settings}
        for key in sorted(set(given) - set(profile.settings)):
            if key in set_here:
                owners = ", ".join(self.profile_settings[key])
                error(f"{key} is a setting of profile {owners}, not of this host's profile {name!r}", key)
            del given[key]
        return given


def apply_profile_defaults(data: dict, resolved: dict, result) -> None:
    """The resolved profile's side fills the host's launch file and ROS variant."""
    role = data["roslab_role"]
    # Role-free keys: the host's own value, else the deprecated role-named key the roster set,
    # else the profile's side.
    for key, profile_value in (("nodes_launch", result["launch"]), ("ros_variant", result["variant"])):
        old_key = f"{key}_{role}"
        if data.get(key) is None and old_key in resolved and data.get(old_key) is not None:
            data[key] = data[old_key]
        elif data.get(key) is None:
            data[key] = profile_value or data.get(old_key)


def ros_name(text: str) -> str:
    """`text` as part of a ROS name: each character a name cannot hold becomes `_`."""
    return re.sub(r"[^A-Za-z0-9_]", "_", text)


def apply_profile_verify_and_discovery(data: dict, resolved: dict, set_here: set, result) -> None:
    """The resolved profile's topic for `roslab verify` and its discovery, where the roster
    sets neither."""
    if data.get("nodes_verify_topic") is None:
        data["nodes_verify_topic"] = result["verify_topic"]
    if data.get("nodes_verify_type") is None:
        data["nodes_verify_type"] = result["verify_type"]
    # what publishes the profile's topic, for `roslab verify` to name when nothing comes
    data["roslab_verify_source"] = result["verify_source"] if data["nodes_verify_topic"] == \
        result["verify_topic"] else ""
    # the node that must publish it (the ESP32 board's flashed name), the team's name as a ROS name
    data["roslab_verify_publisher"] = result["verify_publisher"].replace(
        "${team}", ros_name(data["roslab_team"])) if data["nodes_verify_topic"] == result["verify_topic"] else ""
    if result["discovery"] == "localhost" and "ros_automatic_discovery_range" not in resolved \
            and "ros_discovery_mode" not in set_here:
        # The profile keeps discovery on the host (sim) unless the team or host chose a mode.
        data["ros_discovery_mode"] = "localhost"
        data["ros_automatic_discovery_range"] = "LOCALHOST"


def profile_setting_word(value):
    """A profile setting's value as the word a profile compares: YAML's true/false as "true"/
    "false", a whole number as its digits; anything else as it is (checked by the caller)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    return value
