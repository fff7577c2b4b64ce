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
          https://github.com/nasa-jpl/osr-rover-code.git@4.1.0: 0123456789abcdef0123456789abcdef01234567
        wheels:
          rpi-gpio: {version: '0.7.1', sha256: '<64 hex digits>'}

Every value is hostile until checked here: a package name must be one Debian allows
(policy 5.6.1), a version one Debian allows (policy 5.6.12), a commit 40 hex digits; a source is
`URL@VERSION` as a .repos file pins it (a URL the .repos files accept, a tag or commit), locked
to the commit the controller fetched for it (roslab.sources.fetch: a tag upstream moved away from
it stops the hosts that build it); a wheel's
name is PEP 503-normalised, its version a PEP 440 public version, its sha256 64 hex digits.
A group's versions are taken once, by `roslab lock` from a converged host of the group, or by
a run itself when the roster sets `class_lock_auto: true` (roslab.class_lock_auto), and only
ever added to (`merged`: a package a profile gained later is locked at its first install);
moving a locked version (or a wheel's hash) is `roslab lock --update`'s job (`updates`), never
a run's.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

from roslab.checked.loading import load_yaml
from roslab.checked.problems import Report
from roslab.sources import repos

LOCK_FILE = "classroom.lock"
HEADER = ("# roslab class lock: the versions every host of a group installs. A group is taken by\n"
          "# `roslab lock`, or by a run at its first converge when the roster sets class_lock_auto: true;\n"
          "# move it on purpose with `roslab lock --update` (see docs/class-cache.md).\n")

# Debian policy 5.6.1 (package names) and 5.6.12 (versions: [epoch:]upstream[-revision]).
PACKAGE_NAME = re.compile(r"[a-z0-9][a-z0-9+.-]+")
VERSION = re.compile(r"(?:[0-9]+:)?[0-9][A-Za-z0-9.+~]*(?:-[A-Za-z0-9.+~]+)*")
COMMIT = re.compile(r"[0-9a-f]{40}")
GROUP = re.compile(r"([a-z][a-z0-9]*)/([a-z0-9]+)")  # distro/architecture, e.g. jazzy/arm64
TIMESTAMP = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}T[0-9]{2}:[0-9]{2}:[0-9]{2}Z")
HOST_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,62}")
GROUP_KEYS = ("taken", "taken_from", "packages", "sources", "wheels")
# A Python distribution's name after PEP 503 normalisation, a PEP 440 public version as a
# wheel's file name carries it (normalised; no local `+label`), a sha256 in hex.
WHEEL_NAME = re.compile(r"[a-z0-9]+(?:-[a-z0-9]+)*")
WHEEL_VERSION = re.compile(r"(?:[0-9]+!)?[0-9]+(?:\.[0-9]+)*(?:(?:a|b|rc)[0-9]+)?(?:\.post[0-9]+)?(?:\.dev[0-9]+)?")
SHA256 = re.compile(r"[0-9a-f]{64}")
# Installed by roslab from a downloaded .deb at the roster's ros_apt_source_version, from no apt
# archive: its version is the roster's to set (deploy/ros_apt_source.py), never the lock's.
NOT_LOCKED = frozenset({"ros2-apt-source"})
# `uname -m` (pyinfra's Arch fact) -> the Debian architecture a lock group is named by.
DEBIAN_ARCHITECTURES = {"aarch64": "arm64", "x86_64": "amd64", "armv7l": "armhf"}


@dataclass(frozen=True)
class LockedWheel:
    """One file of the class's wheelhouse (a wheel, or an sdist the host builds): its version and hash."""

    version: str
    sha256: str


@dataclass(frozen=True)
class LockedGroup:
    """One (distro, architecture) group's locked versions, and when and where they were read."""

    taken: str
    taken_from: str
    packages: dict[str, str] = field(default_factory=dict)  # Debian package -> exact version
    sources: dict[str, str] = field(default_factory=dict)  # source repository -> commit
    wheels: dict[str, LockedWheel] = field(default_factory=dict)  # PEP 503 name -> version and sha256


@dataclass(frozen=True)
class ClassLock:
    groups: dict[str, LockedGroup] = field(default_factory=dict)  # "jazzy/arm64" -> its versions
    hold: tuple[str, ...] = ()  # packages and wheels (PEP 503 names) `lock --update` keeps back


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
    sources = _sources(value.get("sources") or {}, f"{where}.sources", report)
    wheels = _wheels(value.get("wheels") or {}, f"{where}.wheels", report)
    return LockedGroup(taken or "", taken_from or "", packages, sources, wheels)


def _wheels(value, where: str, report: Report) -> dict[str, LockedWheel]:
    if not isinstance(value, dict):
        report.error("must map each wheel's name to its version and sha256", field=where)
        return {}
    out = {}
    for name, item in value.items():
        here = f"{where}.{name}"
        if not isinstance(name, str) or not WHEEL_NAME.fullmatch(name):
            report.error(f"{name!r} is not a Python package name as PEP 503 normalises it (e.g. rpi-gpio)",
                         field=here)
            continue
        if not isinstance(item, dict) or set(item) != {"version", "sha256"}:
            report.error("must be a mapping of version and sha256", field=here)
            continue
        version = _matching(item["version"], WHEEL_VERSION, f"{here}.version", "a PEP 440 public version", report)
        sha256 = _matching(item["sha256"], SHA256, f"{here}.sha256", "a sha256 (64 hex digits)", report)
        if version is not None and sha256 is not None:
            out[name] = LockedWheel(version, sha256)
    return out


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


def source_key(url: str, version: str) -> str:
    """A source's name in the lock: `URL@VERSION`, as the .repos file pins it."""
    return f"{url}@{version}"


def _sources(value, where: str, report: Report) -> dict[str, str]:
    if not isinstance(value, dict):
        report.error("must map each source (URL@VERSION) to its commit", field=where)
        return {}
    out = {}
    for key, item in value.items():
        url, _, version = key.rpartition("@") if isinstance(key, str) else ("", "", "")
        problem = (repos.url_problem(url) if url else f"{key!r} is not URL@VERSION"
                   ) or (repos.version_problem(version) if version else f"{key!r} names no version after @")
        if problem:
            report.error(f"{problem} (a source is URL@VERSION as a .repos file pins it)", field=f"{where}.{key}")
        elif (checked := _matching(item, COMMIT, f"{where}.{key}", "a 40-hex-digit commit", report)) is not None:
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
        if group.wheels:  # a group without a profile's Python requirements has none
            lines.append("    wheels:")
            lines += [f"      '{name}': {{version: '{wheel.version}', sha256: '{wheel.sha256}'}}"
                      for name, wheel in sorted(group.wheels.items())]
    return "\n".join(lines) + "\n"


def merged(lock: ClassLock, key: str, installed: dict[str, str], sources: dict[str, str],
           taken: str, taken_from: str,
           wheels: dict[str, LockedWheel] | None = None) -> tuple[ClassLock, list[str]]:
    """`lock` with what a converged host of group `key` has installed added, and the names added.

    A group absent from the lock is taken whole; a locked group only gains the packages,
    repositories and wheels it does not name yet (a package a profile gained later is locked at
    its first install). A locked version is never changed here: that is `updates`' decision.
    """
    installed = {name: version for name, version in installed.items() if name not in NOT_LOCKED}
    wheels = wheels or {}
    old = lock.groups.get(key)
    if old is None:
        group = LockedGroup(taken, taken_from, dict(installed), dict(sources), dict(wheels))
        return (replace(lock, groups={**lock.groups, key: group}),
                sorted(installed) + sorted(sources) + sorted(wheels))
    new_packages = {name: version for name, version in installed.items() if name not in old.packages}
    new_sources = {name: commit for name, commit in sources.items() if name not in old.sources}
    new_wheels = {name: wheel for name, wheel in wheels.items() if name not in old.wheels}
    if not new_packages and not new_sources and not new_wheels:
        return lock, []
    group = replace(old, packages={**old.packages, **new_packages}, sources={**old.sources, **new_sources},
                    wheels={**old.wheels, **new_wheels})
    return (replace(lock, groups={**lock.groups, key: group}),
            sorted(new_packages) + sorted(new_sources) + sorted(new_wheels))


def updates(lock: ClassLock, key: str, candidates: dict[str, str]) -> list[tuple[str, str, str]]:
    """(package, locked, candidate) for each locked package of group `key` a newer archive offers,
    sorted; the lock's `hold` list keeps its packages back."""
    group = lock.groups.get(key)
    if group is None:
        return []
    return sorted((name, version, candidates[name]) for name, version in group.packages.items()
                  if name not in lock.hold and candidates.get(name) not in (None, version))


def updated(lock: ClassLock, key: str, moves: list[tuple[str, str, str]], taken: str,
            wheels: dict[str, LockedWheel] | None = None,
            sources: dict[str, str] | None = None) -> ClassLock:
    """`lock` with group `key` moved to the candidates of `moves` (from `updates`), to the
    wheels of `wheels` (from `wheel_updates`) and to the commits of `sources` (from
    `source_updates`)."""
    group = lock.groups[key]
    packages = {**group.packages, **{name: new for name, _old, new in moves}}
    return replace(lock, groups={**lock.groups, key: replace(
        group, packages=packages, wheels={**group.wheels, **(wheels or {})},
        sources={**group.sources, **(sources or {})}, taken=taken)})


def source_updates(group: LockedGroup, upstream: dict[str, str]) -> list[tuple[str, str, str]]:
    """(source, locked commit, upstream's) for each locked source whose tag upstream now names
    another commit, sorted (`lock --update` moves them). `upstream`: source -> the commit its
    tag names upstream now (a source pinned to a commit never moves)."""
    return sorted((name, commit, upstream[name]) for name, commit in group.sources.items()
                  if upstream.get(name) not in (None, commit))


# --- wheels ------------------------------------------------------------------------------


def wheel_entry(file_name: str) -> tuple[str, str] | None:
    """(PEP 503 name, version) of a wheelhouse file (`name-version(-build)-py-abi-platform.whl`,
    or an sdist `name-version.tar.gz`/`.zip`), or None when either is not one the lock allows
    (a local version like `2.1+cpu`: such a file is not locked)."""
    if file_name.endswith(".whl"):
        parts = file_name[: -len(".whl")].split("-")
        if len(parts) not in (5, 6):
            return None
        name, version = parts[0], parts[1]
    else:
        stem = next((file_name[: -len(end)] for end in (".tar.gz", ".zip") if file_name.endswith(end)), None)
        if stem is None or "-" not in stem:
            return None
        name, version = stem.rsplit("-", 1)
    name = re.sub(r"[-_.]+", "-", name).lower()
    if not WHEEL_NAME.fullmatch(name) or not WHEEL_VERSION.fullmatch(version):
        return None
    return name, version


def wheels_of(files) -> dict[str, LockedWheel]:
    """name -> LockedWheel of a wheelhouse's files (roslab.python_env.wheelhouse.File: name,
    sha256); a file whose name the lock cannot hold is left out, the first of a name kept."""
    found: dict[str, LockedWheel] = {}
    for item in files:
        entry = wheel_entry(item.name)
        if entry is not None and SHA256.fullmatch(item.sha256) and entry[0] not in found:
            found[entry[0]] = LockedWheel(entry[1], item.sha256)
    return found


def wheel_updates(group: LockedGroup, current: dict[str, LockedWheel],
                  hold: tuple[str, ...] = ()) -> list[tuple[str, str, str]]:
    """(wheel, locked, now) for each locked wheel the class's wheelhouse now has at another
    version or hash, sorted (`lock --update` moves them); a wheel whose PEP 503 name the lock's
    `hold` list names is kept back, as a package of that name is."""
    def text(wheel: LockedWheel) -> str:
        return f"{wheel.version} sha256:{wheel.sha256[:12]}"

    return sorted((name, text(wheel), text(current[name])) for name, wheel in group.wheels.items()
                  if name in current and current[name] != wheel and name not in hold)


def wheel_mismatches(group: LockedGroup, files) -> list[str]:
    """One line per file of the wheelhouse a host would install whose hash differs from the
    locked one of its name and version, naming the file, both hashes and what to do."""
    lines = []
    for item in files:
        entry = wheel_entry(item.name)
        locked = group.wheels.get(entry[0]) if entry else None
        if entry is None or locked is None or locked.version != entry[1] or locked.sha256 == item.sha256:
            continue
        lines.append(f"{item.name} has sha256 {item.sha256} in the class's wheelhouse but the class lock has "
                     f"{locked.sha256} for {entry[0]} {entry[1]}: nothing was installed; put the locked file back "
                     f"in the wheelhouse, or take the new one with `roslab lock --update`")
    return lines


# --- a host's group ---------------------------------------------------------------------------


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
    key = host_group_key(distro, machine)
    if lock is None or key is None:
        return None
    return lock.groups.get(key)


def host_group_key(distro: str, machine: str | None) -> str | None:
    """The lock's name of the group of a host of `distro` whose `uname -m` is `machine` (None: an
    architecture the lock has no name for)."""
    architecture = DEBIAN_ARCHITECTURES.get(machine or "")
    return f"{distro}/{architecture}" if architecture else None
