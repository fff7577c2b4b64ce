"""The profiles a roster can name: roslab's built-in ones, and the roster's own (`profiles:`)."""

from __future__ import annotations

import difflib
import functools
from importlib import resources
from pathlib import Path

from roslab.profiles.schema import Profile, read_profile
from roslab.roster.loading import Mapping, line_of, load_yaml
from roslab.roster.problems import Report, RosterError

DATA = "roslab.profiles.data"
DEFAULT_PROFILE = "demo"


def builtin_files() -> list[Path]:
    return sorted(Path(str(entry)) for entry in resources.files(DATA).iterdir()
                  if entry.name.endswith(".yaml"))


@functools.cache
def builtin_profiles() -> dict[str, Profile]:
    """roslab's own profiles, checked by the same schema as a roster's (a problem is a bug: it raises)."""
    profiles: dict[str, Profile] = {}
    problems = []
    for path in builtin_files():
        report = Report(path)
        mapping = load_yaml(path, report)
        profile = read_profile(mapping, report, path.stem, "built-in", base_dir=path.parent) \
            if isinstance(mapping, dict) else None
        if profile is not None and profile.name != path.stem:
            report.error(f"the file of profile {profile.name!r} must be named {profile.name}.yaml")
        problems += report.errors
        if profile is not None:
            profiles[profile.name] = profile
    if problems:
        raise RosterError(problems)
    return profiles


def roster_profiles(mapping, report: Report, roster_dir: Path | None = None) -> dict[str, Profile]:
    """Every profile the roster can name: the built-in ones and its own under `profiles:`.

    `roster_dir`: the folder a roster profile's `sources:` are relative to."""
    profiles = dict(builtin_profiles())
    if mapping is None:
        return profiles
    if not isinstance(mapping, dict):
        report.error("'profiles' must be a mapping of profile name -> profile", line=line_of(mapping),
                     field="profiles")
        return profiles
    for name, spec in mapping.items():
        prefix = f"profiles.{name}"
        if not isinstance(spec, dict):
            report.error("a profile is a mapping (distros, settings, main, robot...)",
                         line=line_of(mapping, name), field=prefix)
            continue
        if "profile" in spec and spec["profile"] != name:
            report.error(f"names itself {spec['profile']!r}, not {name!r}", line=line_of(spec, "profile"),
                         field=f"{prefix}.profile")
            continue
        base = None
        extends = spec.get("extends")
        if extends is not None:
            base = profiles.get(extends) if extends != name else builtin_profiles().get(extends)
            if base is None:
                close = difflib.get_close_matches(str(extends), sorted(profiles), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                report.error(f"extends {extends!r}, which is not a profile{hint}",
                             line=line_of(spec, "extends"), field=f"{prefix}.extends")
                continue
        with_name = Mapping(spec)
        with_name.line, with_name.key_lines = getattr(spec, "line", None), getattr(spec, "key_lines", {})
        with_name.setdefault("profile", name)
        profile = read_profile(with_name, report, prefix, "the roster", base, base_dir=roster_dir)
        if profile is not None:
            profiles[name] = profile
    return profiles


def profile_setting_names(profiles: dict[str, Profile] | None = None) -> dict[str, list[str]]:
    """setting name -> the profiles that declare it."""
    names: dict[str, list[str]] = {}
    for profile in (profiles or builtin_profiles()).values():
        for name in profile.settings:
            names.setdefault(name, []).append(profile.name)
    return names


def every_ros_package(profile: Profile, distro: str) -> set[str]:
    """Every ROS package `profile` can install on `distro`: each side, each when block (any value)."""
    from roslab.profiles.resolve import fill, gazebo_package

    names: set[str] = set()
    for side in profile.sides.values():
        for part in [side, *(block["side"] for block in side.when)]:
            names |= {fill(name, {"gazebo": gazebo_package(distro)}) for name in part.ros_packages}
    return names


def builtin_ros_packages(distro: str) -> set[str]:
    """Every ROS package a built-in profile can install on `distro` (the sandbox's stand-ins)."""
    return {name for profile in builtin_profiles().values() if distro in profile.distros
            for name in every_ros_package(profile, distro)}


def builtin_debian_packages() -> set[str]:
    """Every apt package a built-in profile installs that is not a ROS one (python3-serial,
    i2c-tools): the sandbox's Ubuntu-layout archive carries the real Debian packages."""
    names: set[str] = set()
    for profile in builtin_profiles().values():
        for side in profile.sides.values():
            for part in [side, *(block["side"] for block in side.when)]:
                names |= {name for name in part.apt_packages if "{distro}" not in name}
    return names
