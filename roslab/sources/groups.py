"""A class compiles once: the hosts that need the same underlay, and which one of them builds it.

Hosts whose underlays would come out the same form a *group*: the same ROS distro, machine
architecture (`uname -m`), repositories at the same pins (each archive's sha256), colcon
arguments, per-package CMake settings, build-order edges and skipped packages, and the same
install path (the login user's home and `sources_underlay_dir`: colcon and CMake write the
install path into the tree, so a tree works only where it was built). The group's *input
digest* (`input_digest`) names what it builds; the controller keeps each group's build as a
tar under `sources_cache_dir` keyed by it (deploy/sources.py).

One host per group builds (`choose_builder`): the one the roster names (`underlay_builder`),
else the first of the group in roster order whose memory is at least the profile's
`underlay_build_memory_mb`. A host under that never builds; when no host of a group may build,
the group's hosts fail naming what to do.

The roster knows all of this but the architecture and the archives' digests, so the roster
check (`check_underlay_builders`) groups hosts by what the roster says (`roster_inputs`) and
refuses, before any host is touched, a named builder that is not a host of the roster, needs
no underlay, or needs another one than the host naming it; and two hosts of one group naming
different builders. What only the hosts can tell (architecture, memory) is checked when the
deploy plans, still before any host is changed.
"""

from __future__ import annotations

import difflib
import hashlib
import json
from dataclasses import dataclass
from typing import Any, Protocol

from roslab.checked.problems import Report

FIELD = "underlay_builder"
# The digest as `roslab status` and messages show it.
SHORT = 12
# Bumped when what a shipped tree holds changes (an old cache entry is then never used).
FORMAT = "roslab-underlay-1"


def short(digest: str | None) -> str:
    return (digest or "")[:SHORT]


class UnderlayProfile(Protocol):
    """What a group reads of a host's resolved robot profile (roslab.profiles.resolve.ResolvedProfile)."""

    @property
    def cmake_args(self) -> dict[str, list[str]]: ...
    @property
    def build_dependencies(self) -> dict[str, list[str]]: ...
    @property
    def skip_packages(self) -> list[str]: ...


class UnderlaySettings(Protocol):
    """What a group reads of a host's typed settings: roslab.host_settings.HostSettings has these
    fields (named here, not imported: roslab.profiles, which HostSettings holds, builds on sources/)."""

    @property
    def sources_enabled(self) -> bool: ...
    @property
    def roslab_sources(self) -> list[dict[str, Any]] | None: ...
    @property
    def ros_distro(self) -> str | None: ...
    @property
    def roslab_expected_distro(self) -> str | None: ...
    @property
    def workspace_colcon_args(self) -> list[str]: ...
    @property
    def login_user(self) -> str | None: ...
    @property
    def ssh_user(self) -> str | None: ...
    @property
    def sources_underlay_dir(self) -> str: ...
    @property
    def roslab_profile(self) -> UnderlayProfile | None: ...


def roster_inputs(settings: UnderlaySettings) -> str | None:
    """What the roster says a host's underlay is built from (one canonical text), or None when
    the host builds no underlay. Hosts with the same text form a group, as far as the roster
    can tell (the architecture and the archives' digests are known only when the deploy runs)."""
    if not settings.sources_enabled:
        return None
    repositories = settings.roslab_sources or []
    if not repositories:
        return None
    profile = settings.roslab_profile
    return json.dumps({
        "distro": settings.ros_distro or settings.roslab_expected_distro,
        "repositories": sorted([repo["path"], repo["url"], repo["version"]] for repo in repositories),
        "colcon_args": list(settings.workspace_colcon_args or []),
        "cmake_args": (profile.cmake_args if profile else None) or {},
        "build_dependencies": (profile.build_dependencies if profile else None) or {},
        "skip_packages": sorted((profile.skip_packages if profile else None) or []),
        "user": settings.login_user or settings.ssh_user,
        "underlay_dir": settings.sources_underlay_dir,
    }, sort_keys=True)


def input_digest(build_stamp: str, machine: str, underlay_dir: str) -> str:
    """The group's name: the build stamp (archives, distro, colcon and CMake settings:
    roslab.sources.underlay.build_stamp), the machine architecture and the install path."""
    text = "\0".join([FORMAT, build_stamp, machine, underlay_dir])
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class Member:
    """A host of a group, as the deploy sees it: its name, memory (MiB; None: unknown) and
    whether it holds the group's build already (`holds`: the same build stamp, installed)."""

    name: str
    memory_mb: int | None = None
    holds: bool = False


@dataclass(frozen=True)
class Choice:
    """The group's builder, or why there is none (`problem`, one line saying what to do)."""

    builder: str | None
    problem: str | None = None


def may_build(member: Member, min_memory_mb: int | None) -> bool:
    """A host builds only with the memory the profile asks for (unknown memory: it may)."""
    return min_memory_mb is None or member.memory_mb is None or member.memory_mb >= min_memory_mb


def choose_builder(members: list[Member], named: str | None = None, min_memory_mb: int | None = None,
                   profile: str = "") -> Choice:
    """The builder of a group (`members` in roster order): the first member that holds the build
    already (nothing is compiled: its tree is shipped, whatever its memory, even where another
    host is `named`), else `named` if it is a member with enough memory, else the first member
    with enough memory."""
    holder = next((member for member in members if member.holds), None)
    if holder is not None:
        return Choice(holder.name)
    need = f"the {min_memory_mb} MiB" + (f" profile {profile!r}" if profile else " the profile") + \
        " asks for to build the underlay"
    if named:
        member = next((m for m in members if m.name == named), None)
        if member is None:
            names = ", ".join(m.name for m in members)
            return Choice(None, f"{FIELD} {named!r} is not a host of this group in this run "
                                f"(same distro, architecture, sources and build settings: {names})")
        if not may_build(member, min_memory_mb):
            return Choice(None, f"{FIELD} {named!r} has {member.memory_mb} MiB of memory, under {need}: "
                                "name a host with more memory (a desktop main, say)")
        return Choice(named)
    for member in members:
        if may_build(member, min_memory_mb):
            return Choice(member.name)
    return Choice(None, f"no host of this group has {need} (a host with less never builds it): name a host "
                        f"with more memory as {FIELD} (a desktop main, say) with the same distro and sources")


def check_underlay_builders(classroom, report: Report) -> None:
    """One of the roster's checks across hosts (`classroom`: a roslab.roster Classroom, read as
    the other concerns' checks read it, so sources/ needs nothing of roster/).

    `underlay_builder` names a host of the roster that needs the same underlay as the host it
    is set on; the hosts of one group name the same builder. One error per host, naming the
    roster line, team, host and field.

    A host's inputs come from its typed settings (`host.settings`, roslab.roster.Host's), read
    only for the hosts a named builder concerns: a check of 10,000 hosts builds no others."""
    by_name = {host.name: host for host in classroom.hosts}
    inputs: dict[str, str | None] = {}

    def inputs_of(name: str) -> str | None:
        if name not in inputs:
            inputs[name] = roster_inputs(by_name[name].settings)
        return inputs[name]

    named_by_group: dict[str, tuple[str, str]] = {}
    for host in classroom.hosts:
        named = host.data.get(FIELD)  # the roster's value, read before any host's settings are built
        own = inputs_of(host.name) if named else None
        if not named or own is None:
            continue  # a host without an underlay builds nothing: a classroom-wide value is fine
        where = {"team": host.team, "host": host.name, "field": FIELD, "line": host.lines.get(FIELD)}
        builder = by_name.get(named)
        if builder is None:
            close = difflib.get_close_matches(named, sorted(by_name), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            report.error(f"{named!r} is not a host of this roster{hint}", **where)
            continue
        if inputs_of(named) is None:
            report.error(f"{named!r} builds no underlay (no sources, or sources_enabled false), so it cannot "
                         f"build {host.name!r}'s", **where)
            continue
        if inputs[named] != own:
            report.error(f"{named!r} needs another underlay than {host.name!r} "
                         f"({difference(builder.settings, host.settings)}): "
                         "a builder must be a host of the same group (same distro, sources and build settings)",
                         **where)
            continue
        first = named_by_group.setdefault(own, (named, host.name))
        if first[0] != named:
            report.error(f"names {named!r}, but {first[1]!r} of the same group names {first[0]!r}: "
                         "a group has one builder", **where)


def difference(builder: UnderlaySettings, host: UnderlaySettings) -> str:
    """What differs between two hosts' underlay inputs, in words (the first difference)."""
    a, b = json.loads(roster_inputs(builder) or "{}"), json.loads(roster_inputs(host) or "{}")
    for key in ("distro", "repositories", "user", "underlay_dir", "colcon_args", "cmake_args",
                "build_dependencies", "skip_packages"):
        if a.get(key) != b.get(key):
            if key == "repositories":
                theirs, ours = {r[0]: r[2] for r in a[key]}, {r[0]: r[2] for r in b[key]}
                for path in sorted(set(theirs) | set(ours)):
                    if theirs.get(path) != ours.get(path):
                        return f"repository {path!r}: {theirs.get(path) or 'none'} there, {ours.get(path) or 'none'} here"
            return f"{key}: {a.get(key)!r} there, {b.get(key)!r} here"
    return "inputs differ"


def cache_group(repositories, distro: str, machine: str, directory: str) -> str:
    """The controller cache's group of a build: the same repositories (by path, at any pin),
    distro, architecture and install path. Its newest few builds are kept (ship.pruned)."""
    text = json.dumps([sorted(repositories), distro, machine, directory])
    return hashlib.sha256(text.encode()).hexdigest()[:16]
