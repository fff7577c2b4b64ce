"""Every ROS package a roster or a profile names, checked against the distro's rosdistro file.

A name that is not in the distro (`ros-jazzy-turtlebot3-bringupp`, or TurtleBot3's bringup on
Lyrical, which has none) would otherwise be refused by apt on every host after the long
install before it. The controller reads the rosdistro index (`rosdistro_index_url`, else the
official one) and the distribution file of each distro the classroom uses, through the same
download cache as rosdep's data (`rosdep_cache_dir`: offline, the copy from the last online
run), and reports each unknown name with the closest known one. Where the files cannot be
had, the roster gets a warning saying the names were not checked, never a silent pass.
"""

from __future__ import annotations

import difflib
import re
import threading
from pathlib import Path
from typing import Protocol
from urllib.parse import urljoin

import yaml

from roslab import downloads
from roslab.ros import discovery
from roslab.profiles.resolve import ResolvedProfile
from roslab.ros.rosdep_data import OFFICIAL_INDEX_URL

_lock = threading.Lock()
_parsed: dict[tuple, set[str] | str] = {}
_ROS_DEB = re.compile(r"ros-(\{distro\}|[a-z]+)-([a-z0-9][a-z0-9-]*)")
# Metapackages every host gets (the variants) are checked like any other name.

_Loader: type[yaml.CSafeLoader] | type[yaml.SafeLoader]
try:
    _Loader = yaml.CSafeLoader
except AttributeError:  # PyYAML without libyaml
    _Loader = yaml.SafeLoader


class PackagesUnavailable(Exception):
    """The distro's package list cannot be read (the message says why)."""


def packages_of_distribution(text: str | bytes) -> set[str]:
    """The ROS package names a distribution.yaml releases (a repository's own name if it lists none)."""
    document = yaml.load(text, Loader=_Loader)
    packages: set[str] = set()
    for name, repository in (document.get("repositories") or {}).items():
        release = (repository or {}).get("release") or {}
        if "version" not in release:  # listed, but not released into this distro
            continue
        packages.update(release.get("packages") or [name])
    return packages


def distro_packages(index_url: str | None, distro: str, cache_dir: Path, offline: bool = False) -> set[str]:
    """The ROS packages of `distro` per the rosdistro index at `index_url` (once per run)."""
    index_url = index_url or OFFICIAL_INDEX_URL
    key = (index_url, distro, str(cache_dir), offline)
    with _lock:
        known = _parsed.get(key)
    if isinstance(known, str):
        raise PackagesUnavailable(known)
    if known is not None:
        return known
    try:
        index = yaml.load(downloads.kept(index_url, cache_dir, offline=offline).data, Loader=_Loader)
        entry = index["distributions"][distro]
        files = entry.get("distribution") or []
        files = [files] if isinstance(files, str) else files
        packages: set[str] = set()
        for relative in files:
            packages |= packages_of_distribution(downloads.kept(urljoin(index_url, relative), cache_dir,
                                                                offline=offline).data)
        result: set[str] | str = packages
    except downloads.DownloadError as error:
        result = str(error)
    except (yaml.YAMLError, KeyError, TypeError, AttributeError):
        result = f"the rosdistro index {index_url} has no readable entry for {distro}"
    with _lock:
        _parsed[key] = result
    if isinstance(result, str):
        raise PackagesUnavailable(result)
    return result


class PackageSettings(Protocol):
    """What the package check reads of a host's settings: roslab.host_settings.HostSettings has
    these fields (named here, not imported: HostSettings holds this folder's ResolvedProfile)."""

    @property
    def ros_extra_packages(self) -> list[str]: ...
    @property
    def ros_middleware(self) -> str: ...
    @property
    def roslab_profile(self) -> ResolvedProfile | None: ...


def named_packages(typed: PackageSettings, distro: str) -> list[tuple[str, str, str]]:
    """(Debian name, ROS name, field) for each ROS package a host's settings and profile name."""
    named = []
    for template in typed.ros_extra_packages:
        match = _ROS_DEB.fullmatch(template.replace("{distro}", distro))
        if match and match.group(1) == distro:
            named.append((match.group(0), match.group(2).replace("-", "_"), "ros_extra_packages"))
    middleware = discovery.middleware_ros_package(typed.ros_middleware)
    package = discovery.middleware_package(middleware, distro) if middleware else None
    if middleware and package:  # both or neither: Fast DDS comes with ros-base
        named.append((package, middleware, "ros_middleware"))
    profile = typed.roslab_profile
    for ros_name in profile.ros_packages if profile else ():
        named.append((f"ros-{distro}-{ros_name.replace('_', '-')}", ros_name, "robot_profile"))
    ros_debs = {debian for debian, _, _ in named}
    for debian in profile.packages if profile else ():  # a profile's apt_packages, {distro} filled in
        match = _ROS_DEB.fullmatch(debian)
        if match and match.group(1) == distro and debian not in ros_debs:
            named.append((debian, match.group(2).replace("-", "_"), "robot_profile"))
    return named


def unknown_package_message(debian: str, ros_name: str, distro: str, known: set[str], source: str) -> str:
    """What to say about a name `known` lacks, with the closest known name."""
    candidates = {name.replace("_", "-"): name for name in known}
    close = difflib.get_close_matches(ros_name.replace("_", "-"), list(candidates), n=1, cutoff=0.8)
    hint = f" (did you mean ros-{distro}-{close[0]}?)" if close else ""
    return f"{debian} is not a package of ROS 2 {distro} ({source}){hint}"


def check_classroom(classroom, report) -> None:
    """Validator: every host's named ROS packages exist in its distro (roslab.roster.VALIDATORS)."""
    unavailable: set[tuple] = set()
    for host in classroom.hosts:
        typed = host.settings
        distro = typed.roslab_expected_distro
        if not distro or not typed.ros_packages_check or not typed.ros_install_enabled:
            continue
        named = named_packages(typed, distro)
        if not named:
            continue
        index_url = typed.rosdistro_index_url
        cache_dir = Path(str(typed.rosdep_cache_dir or "~/.cache/roslab/rosdep")).expanduser()
        offline = typed.offline
        try:
            known = distro_packages(index_url, distro, cache_dir, offline)
        except PackagesUnavailable as error:
            key = (index_url, distro)
            if key not in unavailable:
                unavailable.add(key)
                report.warning(f"the ROS package names of the {distro} hosts were not checked against "
                               f"rosdistro: {error} (set ros_packages_check: false to skip the check)",
                               field="ros_packages_check", line=host.lines.get("ros_packages_check"))
            continue
        source = f"rosdistro {index_url or OFFICIAL_INDEX_URL}"
        profile_name = typed.roslab_profile.name if typed.roslab_profile else None
        for debian, ros_name, field in named:
            if ros_name in known:
                continue
            message = unknown_package_message(debian, ros_name, distro, known, source)
            if field == "robot_profile":
                message = f"profile {profile_name!r} installs {message}"
            report.error(message, team=host.team, host=host.name, field=field,
                         line=host.lines.get(field) or host.line)
