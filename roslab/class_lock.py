"""The class lock (issue 39): one set of versions per (ROS distro, architecture) group.

`classroom.lock` sits beside the roster, is YAML, sorted and meant for git:

    # roslab class lock ...
    hold:
    - ros-jazzy-nav2-bringup
    groups:
      jazzy/arm64:
        taken: '2026-11-28T22:00:00Z'
        taken_from: robot1-1
        packages:
          ros-jazzy-ros-base: 0.11.0-1noble.20250101.000000
        sources:
          turtlebot3: 0123456789abcdef0123456789abcdef01234567

Every value is hostile until checked here: a package name must be one Debian allows
(policy 5.6.1), a version one Debian allows (policy 5.6.12), a commit 40 hex digits.
A group's versions are taken once, by `roslab lock` from a converged host of the group (a
run does not take them by itself), and only ever added to (`merged`: a package a profile
gained later is locked at its first install); moving a locked version is
`roslab lock --update`'s job (`updates`), never a run's.
"""

from __future__ import annotations

import functools
import re
import shlex
from dataclasses import dataclass, field, replace
from pathlib import Path

from pyinfra import host
from pyinfra.api import FactBase, StringCommand, operation
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import FileContents

from roslab.checked.loading import load_yaml
from roslab.checked.problems import Report
from roslab.operations import DPKG_KEEP_CONFFILES, _log_diff, _upload_text, apt_get, reporting_a_signal
from roslab.probe import read

LOCK_FILE = "classroom.lock"
PREFERENCES_FILE = "/etc/apt/preferences.d/roslab-lock"
HEADER = ("# roslab class lock: the versions every host of a group installs. Written on a group's\n"
          "# first converge; move it on purpose with `roslab lock --update` (see the README).\n")

# Debian policy 5.6.1 (package names) and 5.6.12 (versions: [epoch:]upstream[-revision]).
PACKAGE_NAME = re.compile(r"[a-z0-9][a-z0-9+.-]+")
VERSION = re.compile(r"(?:[0-9]+:)?[0-9][A-Za-z0-9.+~]*(?:-[A-Za-z0-9.+~]+)*")
COMMIT = re.compile(r"[0-9a-f]{40}")
GROUP = re.compile(r"([a-z][a-z0-9]*)/([a-z0-9]+)")  # distro/architecture, e.g. jazzy/arm64
REPOSITORY = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*(?:/[A-Za-z0-9][A-Za-z0-9._-]*)*")
TIMESTAMP = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}Z")
HOST_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,62}")
GROUP_KEYS = ("taken", "taken_from", "packages", "sources")
# Installed by roslab from a downloaded .deb at the roster's ros_apt_source_version, from no apt
# archive: its version is the roster's to set (deploy/ros_apt_source.py), never the lock's.
NOT_LOCKED = frozenset({"ros2-apt-source"})
# `uname -m` (pyinfra's Arch fact) -> the Debian architecture a lock group is named by.
DEBIAN_ARCHITECTURES = {"aarch64": "arm64", "x86_64": "amd64", "armv7l": "armhf"}


@dataclass(frozen=True)
class LockedGroup:
    """One (distro, architecture) group's locked versions, and when and where they were read."""

    taken: str
    taken_from: str
    packages: dict[str, str] = field(default_factory=dict)  # Debian package -> exact version
    sources: dict[str, str] = field(default_factory=dict)  # source repository -> commit


@dataclass(frozen=True)
class ClassLock:
    groups: dict[str, LockedGroup] = field(default_factory=dict)  # "jazzy/arm64" -> its versions
    hold: tuple[str, ...] = ()  # packages `lock --update` keeps back


def group_key(distro: str, architecture: str) -> str:
    """The lock's name of a group, checked like the file's own keys."""
    key = f"{distro}/{architecture}"
    if not GROUP.fullmatch(key):
        raise ValueError(f"{key!r} is not a distro/architecture group")
    return key


# --- reading ---------------------------------------------------------------------------


def read_lock(path: Path) -> tuple[ClassLock | None, Report]:
    """The lock at `path` (an empty lock if there is none), or None with the report's errors."""
    report = Report(path)
    if not path.exists():
        return ClassLock(), report
    data = load_yaml(path, report)
    if report.errors:
        return None, report
    lock = parse_lock(data if data is not None else {}, report)
    return (None if report.errors else lock), report


def check_class_lock(classroom, report: Report) -> None:
    """A roster validator (roslab.roster.VALIDATORS): the lock beside the roster is read and
    checked with the roster, so a hostile or broken lock stops the run before any host."""
    _lock, own = read_lock(Path(classroom.path).parent / LOCK_FILE)
    for problem in own.errors:
        report.add(problem)


def parse_lock(data, report: Report) -> ClassLock:
    """A loaded lock document checked field by field; every problem goes to `report`."""
    if not isinstance(data, dict):
        report.error("a class lock is a mapping with 'groups' (and 'hold')")
        return ClassLock()
    for key in data:
        if key not in ("groups", "hold"):
            report.error(f"unknown key {key!r}: a class lock has 'groups' and 'hold'", field=str(key))
    hold = _names(data.get("hold") or [], "hold", report)
    groups: dict[str, LockedGroup] = {}
    raw_groups = data.get("groups") or {}
    if not isinstance(raw_groups, dict):
        report.error("must map distro/architecture to its versions", field="groups")
        raw_groups = {}
    for key, value in raw_groups.items():
        where = f"groups.{key}"
        if not isinstance(key, str) or not GROUP.fullmatch(key):
            report.error("a group is named distro/architecture, e.g. jazzy/arm64", field=where)
        elif (group := _group(value, where, report)) is not None:
            groups[key] = group
    return ClassLock(groups=groups, hold=tuple(hold))


def _group(value, where: str, report: Report) -> LockedGroup | None:
    if not isinstance(value, dict):
        report.error(f"must be a mapping of {', '.join(GROUP_KEYS)}", field=where)
        return None
    for key in value:
        if key not in GROUP_KEYS:
            report.error(f"unknown key {key!r}: a group has {', '.join(GROUP_KEYS)}", field=f"{where}.{key}")
    taken = _matching(value.get("taken"), TIMESTAMP, f"{where}.taken", "a UTC time like 2026-11-28T22:00:00Z",
                      report)
    taken_from = _matching(value.get("taken_from"), HOST_NAME, f"{where}.taken_from", "a host name", report)
    packages = _pairs(value.get("packages") or {}, f"{where}.packages", PACKAGE_NAME, VERSION,
                      "a Debian version ([epoch:]upstream[-revision])", report)
    for name in NOT_LOCKED & set(packages):
        report.error(f"{name} is not locked: its version is the roster's (ros_apt_source_version)",
                     field=f"{where}.packages.{name}")
    sources = _pairs(value.get("sources") or {}, f"{where}.sources", REPOSITORY, COMMIT,
                     "a 40-hex-digit commit", report)
    return LockedGroup(taken or "", taken_from or "", packages, sources)


def _matching(value, pattern: re.Pattern, where: str, wanted: str, report: Report) -> str | None:
    if not isinstance(value, str) or not pattern.fullmatch(value):
        report.error(f"{value!r} is not {wanted}", field=where)
        return None
    return value


def _pairs(value, where: str, key_pattern, value_pattern, wanted: str, report: Report) -> dict[str, str]:
    if not isinstance(value, dict):
        report.error("must be a mapping", field=where)
        return {}
    out = {}
    for key, item in value.items():
        if not isinstance(key, str) or not key_pattern.fullmatch(key):
            report.error(f"{key!r} is not a name Debian or git allows here", field=f"{where}.{key}")
        elif (checked := _matching(item, value_pattern, f"{where}.{key}", wanted, report)) is not None:
            out[key] = checked
    return out


def _names(value, where: str, report: Report) -> list[str]:
    if not isinstance(value, list):
        report.error("must be a list of package names", field=where)
        return []
    return [name for name in value
            if _matching(name, PACKAGE_NAME, where, "a Debian package name", report) is not None]


# --- writing ---------------------------------------------------------------------------


def render_lock(lock: ClassLock) -> str:
    """The lock's text: keys sorted, one package per line, so a change is a small git diff.

    Written by hand rather than by yaml.dump: every name and version was checked against its
    pattern (no quote, no newline can be in one), and each is single-quoted so that a version
    like 1.10 or a package named `yes` stays text in every YAML reader."""
    lines = [HEADER.rstrip("\n")]
    if lock.hold:
        lines += ["hold:", *(f"- '{name}'" for name in sorted(set(lock.hold)))]
    lines.append("groups:" if lock.groups else "groups: {}")
    for key, group in sorted(lock.groups.items()):
        lines += [f"  '{key}':", f"    taken: '{group.taken}'", f"    taken_from: '{group.taken_from}'"]
        for part, items in (("packages", group.packages), ("sources", group.sources)):
            lines.append(f"    {part}:" if items else f"    {part}: {{}}")
            lines += [f"      '{name}': '{value}'" for name, value in sorted(items.items())]
    return "\n".join(lines) + "\n"


def merged(lock: ClassLock, key: str, installed: dict[str, str], sources: dict[str, str],
           taken: str, taken_from: str) -> tuple[ClassLock, list[str]]:
    """`lock` with what a converged host of group `key` has installed added, and the names added.

    A group absent from the lock is taken whole; a locked group only gains the packages and
    repositories it does not name yet (a package a profile gained later is locked at its first
    install). A locked version is never changed here: that is `updates`' decision.
    """
    installed = {name: version for name, version in installed.items() if name not in NOT_LOCKED}
    old = lock.groups.get(key)
    if old is None:
        group = LockedGroup(taken, taken_from, dict(installed), dict(sources))
        return replace(lock, groups={**lock.groups, key: group}), sorted(installed) + sorted(sources)
    new_packages = {name: version for name, version in installed.items() if name not in old.packages}
    new_sources = {name: commit for name, commit in sources.items() if name not in old.sources}
    if not new_packages and not new_sources:
        return lock, []
    group = replace(old, packages={**old.packages, **new_packages}, sources={**old.sources, **new_sources})
    return replace(lock, groups={**lock.groups, key: group}), sorted(new_packages) + sorted(new_sources)


def updates(lock: ClassLock, key: str, candidates: dict[str, str]) -> list[tuple[str, str, str]]:
    """(package, locked, candidate) for each locked package of group `key` a newer archive offers,
    sorted; the lock's `hold` list keeps its packages back."""
    group = lock.groups.get(key)
    if group is None:
        return []
    return sorted((name, version, candidates[name]) for name, version in group.packages.items()
                  if name not in lock.hold and candidates.get(name) not in (None, version))


def updated(lock: ClassLock, key: str, moves: list[tuple[str, str, str]], taken: str) -> ClassLock:
    """`lock` with group `key` moved to the candidates of `moves` (from `updates`)."""
    group = lock.groups[key]
    packages = {**group.packages, **{name: new for name, _old, new in moves}}
    return replace(lock, groups={**lock.groups, key: replace(group, packages=packages, taken=taken)})


# --- on a host ---------------------------------------------------------------------------


def lock_beside(roster_path: str | None) -> ClassLock | None:
    """The lock beside the roster (checked with it: roslab.roster.VALIDATORS), or None if
    there is none (or no roster: a hand-made inventory)."""
    if not roster_path:
        return None
    path = Path(roster_path).parent / LOCK_FILE
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    return _read_once(path, stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=4)
def _read_once(path: Path, _mtime_ns: int, _size: int) -> ClassLock | None:
    """One read per run (and per change of the file) for all the hosts."""
    return read_lock(path)[0]


def host_group(roster_path: str | None, distro: str, machine: str | None) -> LockedGroup | None:
    """The locked group of a host of `distro` whose `uname -m` is `machine`, if the lock has it."""
    lock = lock_beside(roster_path)
    architecture = DEBIAN_ARCHITECTURES.get(machine or "")
    if lock is None or architecture is None:
        return None
    return lock.groups.get(f"{distro}/{architecture}")


class AptVersions(FactBase):
    """package -> the versions apt can install from the host's sources (`apt-cache madison`),
    as the host's lists have them (AptVersionsNow refreshes them first)."""

    def command(self, packages: list[str]) -> str:
        names = [name for name in packages if PACKAGE_NAME.fullmatch(name)]  # checked: never an option
        return "apt-cache madison -- " + " ".join(shlex.quote(name) for name in names) + " || true"

    def process(self, output) -> dict[str, list[str]]:
        versions: dict[str, list[str]] = {}
        for line in output:
            parts = [part.strip() for part in line.split("|")]
            if len(parts) >= 3 and parts[1] not in versions.get(parts[0], []):
                versions.setdefault(parts[0], []).append(parts[1])
        return versions


class AptVersionsNow(AptVersions):
    """AptVersions after `apt-get update` (as root): what the archives offer now, not at the
    host's last update. Read by `roslab lock --update` (once per group) and by a run whose
    locked host has packages to install or move (never on a no-op)."""

    def command(self, packages: list[str]) -> str:
        return ("DEBIAN_FRONTEND=noninteractive apt-get -q -o DPkg::Lock::Timeout=120 update >/dev/null 2>&1; "
                + super().command(packages))


def preferences_lines(group: LockedGroup) -> list[str]:
    """The apt preferences that hold a host on its group's versions: priority 1001 installs
    the locked version even where the archive offers a newer one (and downgrades to it)."""
    lines = ["# Managed by roslab: the class lock (classroom.lock). Edits here are replaced."]
    for name, version in sorted(group.packages.items()):
        lines += ["", f"Package: {name}", f"Pin: version {version}", "Pin-Priority: 1001"]
    return lines


def unmet(group: LockedGroup, wanted: list[str], available: dict[str, list[str]]) -> list[str]:
    """One line per package of `wanted` whose locked version no source of the host offers
    (`available`: package -> the versions apt-cache policy lists), saying what to do."""
    return [
        f"{name}={group.packages[name]} is locked but neither the archive nor the class cache has it: "
        f"put the .deb back in the class cache, or move the lock with `roslab lock --update`"
        for name in wanted
        if name in group.packages and group.packages[name] not in available.get(name, [])
    ]


@operation()
def locked_versions_pinned(group: LockedGroup):
    """
    Ensure apt installs the class lock's versions: the whole file
    /etc/apt/preferences.d/roslab-lock pins each locked package at its version.

    + group: the host's (distro, architecture) group of the class lock
    """
    current = host.get_fact(FileContents, path=PREFERENCES_FILE)
    desired = preferences_lines(group)
    if current == desired:
        host.noop(f"apt is pinned to the class lock's {len(group.packages)} versions")
        return
    _log_diff(PREFERENCES_FILE, current, desired)
    yield from _upload_text(PREFERENCES_FILE, desired, user="root", group="root", mode="644")


def locked_versions_pinned_reads() -> list:
    """What `locked_versions_pinned` reads (roslab.probe)."""
    return [read(FileContents, path=PREFERENCES_FILE)]


def off_lock(group: LockedGroup, installed: dict) -> list[str]:
    """The installed packages of the group's lock that are on another version, sorted
    (`installed`: pyinfra's DebPackages, package -> its installed versions)."""
    return sorted(name for name, version in group.packages.items()
                  if name in installed and version not in installed[name])


@operation()
def packages_at_locked_versions(group: LockedGroup, lock_timeout: int):
    """
    Ensure every installed package the class lock names is at its locked version: after
    `roslab lock --update` the next run moves the hosts (up, or down to a held version).

    + group: the host's (distro, architecture) group of the class lock
    + lock_timeout: seconds apt waits for the dpkg lock
    """
    moves = [f"{name}={group.packages[name]}" for name in off_lock(group, host.get_fact(DebPackages) or {})]
    if not moves:
        host.noop("the installed packages are at the class lock's versions")
        return
    install = f"{apt_get(f'{DPKG_KEEP_CONFFILES} --allow-downgrades install --', lock_timeout)} " + " ".join(
        shlex.quote(move) for move in moves)
    yield StringCommand(reporting_a_signal(install, "apt-get install"))
