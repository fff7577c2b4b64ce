"""The class lock on a host (roslab.class_lock holds the lock file itself): what a host has
installed and what its sources offer (facts), and the operations that hold it on its group's
versions: apt preferences that pin each locked package, and the installed packages moved to
their locked versions after `roslab lock --update`.
"""

from __future__ import annotations

import shlex

from pyinfra import host
from pyinfra.api import FactBase, StringCommand, operation
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import FileContents

from roslab.class_lock import NOT_LOCKED, PACKAGE_NAME, VERSION, LockedGroup
from roslab.ops.apt import DPKG_KEEP_CONFFILES, apt_get, reporting_a_signal
from roslab.ops.files import _log_diff, _upload_text
from roslab.probe import read

PREFERENCES_FILE = "/etc/apt/preferences.d/roslab-lock"


class InstalledVersions(FactBase):
    """The host's Debian architecture, then `package<TAB>version` of every installed package."""

    def command(self) -> str:
        return ("dpkg --print-architecture && dpkg-query -W "
                + shlex.quote("-f=${db:Status-Abbrev}\t${Package}\t${Architecture}\t${Version}\n"))

    def process(self, output) -> dict:
        return parse_installed(list(output))


def parse_installed(lines: list[str]) -> dict:
    """{"architecture": ..., "packages": {name: version}} from `InstalledVersions`' output: the
    packages installed ("ii") for the native architecture or "all", names and versions checked."""
    architecture = lines[0].strip() if lines else ""
    packages = {}
    for line in lines[1:]:
        fields = line.split("\t")
        if len(fields) != 4 or fields[0].strip() != "ii" or fields[2] not in (architecture, "all"):
            continue
        if (PACKAGE_NAME.fullmatch(fields[1]) and VERSION.fullmatch(fields[3])
                and fields[1] not in NOT_LOCKED):
            packages[fields[1]] = fields[3]
    return {"architecture": architecture, "packages": packages}


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
    (`available`: package -> the versions apt-cache policy lists), saying what to do. An index
    lists a version or not: the class cache (apt-cacher-ng) cannot bring back one it dropped; the
    controller's kept .debs (roslab.class_debs, `wanted` leaves those out) and ROS's snapshot
    archive (for a ROS package) can."""
    return [
        f"{name}={group.packages[name]} is locked but no apt source of the host lists it any more "
        "and the controller kept no .deb of it (class_lock_debs_dir): "
        + ("install ROS from a snapshot that has it (ros_apt_source_mode: snapshot), or " if name.startswith("ros-") else "")
        + "move the lock with `roslab lock --update`"
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
