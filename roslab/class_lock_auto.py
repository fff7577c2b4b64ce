"""The class lock taken by a run itself (issue 39), when the roster sets `class_lock_auto: true`.

A host whose (distro, architecture) group the lock beside its roster lacks gets a last step
(deploy/class_lock_taken.py) that reads, at run time and after every other step of the host,
what `roslab lock` reads (`dpkg-query`: roslab.ops.class_lock.InstalledVersions) and notes it here;
the python_env step notes the class wheelhouse's files the host was given, the sources step the
commits of the repositories it builds. At the end of the run
(roslab.reporting.summary, after the table) the controller writes classroom.lock once: each
group the lock still lacks, from the first host of the group (roster order) that converged
without failure, with the wheels and sources of the group's converged hosts, and says so in one line.
A group already in the lock is never rewritten here (moving is `roslab lock --update`'s job);
--dry executes no step, so it notes and writes nothing.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from roslab import class_lock
from roslab.controller_files import replace_file


@dataclass
class Noted:
    """What this run's hosts noted for one roster: host -> (group, packages), host -> wheels."""

    installed: dict[str, tuple[str, dict[str, str]]] = field(default_factory=dict)
    wheels: dict[str, dict[str, class_lock.LockedWheel]] = field(default_factory=dict)
    sources: dict[str, dict[str, str]] = field(default_factory=dict)  # host -> source -> commit


_guard = threading.Lock()
_noted: dict[str, Noted] = {}  # roster path -> what its hosts noted in this run


def note_installed(roster_path: str, host_name: str, key: str, packages: dict[str, str]) -> None:
    """Note host `host_name`'s group and installed packages, read after its last step."""
    with _guard:
        _noted.setdefault(roster_path, Noted()).installed[host_name] = (key, dict(packages))


def note_wheels(roster_path: str, host_name: str, files) -> None:
    """Note the class wheelhouse's files (wheelhouse.File) host `host_name` is given in this run."""
    with _guard:
        _noted.setdefault(roster_path, Noted()).wheels[host_name] = class_lock.wheels_of(files)


def note_sources(roster_path: str, host_name: str, sources: dict[str, str]) -> None:
    """Note the commits (source -> commit, class_lock.source_key) host `host_name` builds in this run."""
    with _guard:
        _noted.setdefault(roster_path, Noted()).sources[host_name] = dict(sources)


def forget() -> None:
    """Drop what was noted (a new run in the same process: the tests)."""
    with _guard:
        _noted.clear()


def taken_groups(lock: class_lock.ClassLock, noted: Noted, converged: list[str],
                 taken: str) -> tuple[class_lock.ClassLock, list[str]]:
    """`lock` with each group it lacks taken from the first of `converged` (hosts that ended
    ok or changed, in roster order) that noted it, and a phrase per group taken, sorted."""
    said = []
    for name in converged:
        if name not in noted.installed:
            continue
        key, packages = noted.installed[name]
        if key in lock.groups:  # locked already (before this run, or by an earlier host): never rewritten
            continue
        wheels: dict[str, class_lock.LockedWheel] = {}
        sources: dict[str, str] = {}
        for other in converged:  # the wheels and sources of every converged host of the group (first kept)
            if noted.installed.get(other, ("",))[0] == key:
                wheels = {**noted.wheels.get(other, {}), **wheels}
                sources = {**noted.sources.get(other, {}), **sources}
        lock, _added = class_lock.merged(lock, key, packages, sources, taken, name, wheels)
        said.append(f"{key} from {name} ({len(lock.groups[key].packages)} packages, {len(wheels)} wheels"
                    + (f", {len(sources)} sources" if sources else "") + ")")
    return lock, sorted(said)


def write_taken(converged: list[str]) -> list[str]:
    """Write each roster's lock with the groups this run took; one line per roster written.

    `converged`: the hosts that converged in this run (ok or changed), in roster order."""
    with _guard:
        noted = dict(_noted)
        _noted.clear()
    lines = []
    taken = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    for roster_path, found in sorted(noted.items()):
        path = Path(roster_path).parent / class_lock.LOCK_FILE
        lock, report = class_lock.read_lock(path)  # read again: the file as it is now
        if lock is None:
            lines.append(f"{path} was not written: it is no valid class lock now ({report.errors[0]})")
            continue
        new, said = taken_groups(lock, found, converged, taken)
        if not said:
            continue
        replace_file(path, class_lock.render_lock(new))  # a run killed here leaves the old lock whole
        lines.append(f"{path.name} now locks {', '.join(said)} (`roslab lock` keeps its .debs while the archives "
                     "list them): commit it; `roslab lock --update` moves it on purpose")
    return lines
