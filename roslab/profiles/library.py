"""The profiles a roster can name: roslab's built-in ones, and the roster's own (`profiles:`)."""

from __future__ import annotations

import difflib
import functools
import os
from pathlib import Path

from roslab.profiles import parsed_cache
from roslab.profiles.schema import Profile, read_profile
from roslab.checked.loading import Mapping, line_of, load_yaml
from roslab.checked.problems import Problem, Report

DEFAULT_PROFILE = "demo"


def data_folder() -> Path:
    """The folder of roslab's own profile files (roslab/profiles/data)."""
    return Path(__file__).resolve().parent / "data"


def builtin_files() -> list[Path]:
    """The profile files of the folder (`*.yaml`), symlinks included only when they lead to a
    file inside it (`builtin_problems` names the others)."""
    folder = data_folder()
    return sorted(path for path in folder.iterdir() if path.name.endswith(".yaml") and _inside(path, folder))


def _inside(path: Path, folder: Path) -> bool:
    real = Path(os.path.realpath(path))
    return Path(os.path.realpath(folder)) in real.parents


@functools.cache
def _builtin() -> tuple[dict[str, Profile], tuple[Problem, ...]]:
    """roslab's own profiles and the problems of the files that are not sound (_parse_builtin),
    parsed once per content on this controller (roslab.profiles.parsed_cache)."""
    return parsed_cache.cached(data_folder(), _parse_builtin)


def _parse_builtin() -> tuple[dict[str, Profile], tuple[Problem, ...]]:
    """roslab's own profiles, checked by the same schema as a roster's, and the problems of the
    files that are not: a bad file is left out (and listed), never the end of a command.

    A built-in profile may extend another built-in one (`extends:`), as a roster's may."""
    specs: dict[str, tuple] = {}
    problems = []
    folder = data_folder()
    for path in sorted(folder.iterdir()):
        if path.name.endswith(".yaml") and not _inside(path, folder):
            # never read: its lines would be shown as YAML errors (a link to /etc/shadow)
            problems.append(Problem(str(path), "a symlink that leads out of the profile folder: "
                                    "roslab reads only the folder's own files"))
    for path in builtin_files():
        report = Report(path)
        mapping = load_yaml(path, report)
        if isinstance(mapping, dict):
            specs[path.stem] = (mapping, report, path)
        elif not report.errors:
            report.error("a profile file holds a mapping (distros, settings, main, robot...)")
        problems += report.errors
    profiles: dict[str, Profile] = {}

    def read(name: str, spec, report: Report, base: Profile | None) -> Profile | None:
        mapping, _report, path = specs[name]
        profile = read_profile(mapping, report, name, "built-in", base, base_dir=path.parent)
        if profile is not None and profile.name != name:
            report.error(f"the file of profile {profile.name!r} must be named {profile.name}.yaml")
            return None
        return profile

    _read_extending({name: spec[0] for name, spec in specs.items()}, profiles, {},
                    lambda name: specs[name][1], read, "")
    for name, (_mapping, report, _path) in specs.items():
        if report.errors:
            problems += report.errors
            profiles.pop(name, None)  # a profile with a problem is not offered at all
    return profiles, tuple(dict.fromkeys(problems))


def builtin_profiles() -> dict[str, Profile]:
    """roslab's own profiles that are sound (see `builtin_problems` for the others)."""
    return _builtin()[0]


def builtin_problems() -> tuple[Problem, ...]:
    """Each problem of the profile folder's files (file:line), for `roslab check` and the roster."""
    return _builtin()[1]


def broken_builtin(name: str) -> bool:
    """Whether the profile folder's file `name`.yaml was left out for its problems."""
    return any(Path(problem.path).name == f"{name}.yaml" for problem in builtin_problems())


def _read_extending(specs: dict, profiles: dict[str, Profile], others: dict[str, Profile], report_of, read,
                    prefix: str) -> None:
    """Read every profile of `specs` (name -> mapping) into `profiles`, each after the one it
    extends: another of `specs` (in any order), else one of `others` (a roster's profile that
    extends its own name extends the built-in one). A loop is reported as one, naming the chain.

    `read(name, mapping, report, base)` checks one mapping; `report_of(name)` is its Report."""
    reader = _ExtendingReader(specs, profiles, others, report_of, read, prefix)
    for name in specs:
        reader.visit(name, [])


class _ExtendingReader:
    """One pass of _read_extending: which profiles are being read or done, so that each is read
    once, after its base, and a profile met again while it is being read closes a loop."""

    def __init__(self, specs: dict, profiles: dict[str, Profile], others: dict[str, Profile], report_of, read,
                 prefix: str):
        self.specs, self.profiles, self.others = specs, profiles, others
        self.report_of, self.read, self.prefix = report_of, read, prefix
        self.state: dict[str, str] = {}  # name -> "reading" | "done"

    def field(self, name: str) -> str:
        return f"{self.prefix}{name}.extends" if self.prefix else "extends"

    def visit(self, name: str, chain: list[str]) -> Profile | None:
        if self.state.get(name) == "done":
            return self.profiles.get(name)
        spec = self.specs[name]
        report = self.report_of(name)
        self.state[name] = "reading"
        base = None
        extends = spec.get("extends")
        if extends is not None:
            base = self.base_of(name, spec, extends, report, chain)
            if base is None:
                self.state[name] = "done"
                return None
        profile = self.read(name, spec, report, base)
        self.state[name] = "done"
        if profile is not None:
            self.profiles[name] = profile
        return profile

    def base_of(self, name: str, spec, extends, report: Report, chain: list[str]) -> Profile | None:
        """The profile `name` extends; None, reported, when it has none to extend."""
        if not isinstance(extends, str):
            report.error("must be the name of a profile", line=line_of(spec, "extends"), field=self.field(name))
            return None
        if extends in self.specs and extends != name:
            return self.base_in_specs(name, spec, extends, report, chain)
        if extends == name and extends not in self.others:
            report.error(f"extends itself: a loop ({name} -> {name})", line=line_of(spec, "extends"),
                         field=self.field(name))
            return None
        base = self.others.get(extends)
        if base is None:
            known = sorted({*self.specs, *self.others})
            close = difflib.get_close_matches(extends, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            report.error(f"extends {extends!r}, which is not a profile{hint}",
                         line=line_of(spec, "extends"), field=self.field(name))
        return base

    def base_in_specs(self, name: str, spec, extends: str, report: Report, chain: list[str]) -> Profile | None:
        """A base among the same specs, read first; None, reported, when it closes a loop or has
        problems of its own."""
        if self.state.get(extends) == "reading":
            loop = " -> ".join([*chain[chain.index(extends):], name, extends]) if extends in chain \
                else f"{name} -> {extends}"
            report.error(f"extends {extends!r}, which extends it in turn: a loop ({loop})",
                         line=line_of(spec, "extends"), field=self.field(name))
            return None
        base = self.visit(extends, [*chain, name])
        if base is None:
            report.error(f"extends {extends!r}, which has problems of its own (above)",
                         line=line_of(spec, "extends"), field=self.field(name))
        return base


def roster_profiles(mapping, report: Report, roster_dir: Path | None = None) -> dict[str, Profile]:
    """Every profile the roster can name: the built-in ones and its own under `profiles:`.

    A roster's profile may extend a built-in one or another of the roster's (in any order;
    one that extends its own name extends the built-in one it replaces).
    `roster_dir`: the folder a roster profile's `sources:` are relative to."""
    builtin = builtin_profiles()
    for problem in builtin_problems():  # listed with the roster's; a host naming the profile fails
        report.warnings.append(problem) if problem not in report.warnings else None
    profiles = dict(builtin)
    if mapping is None:
        return profiles
    if not isinstance(mapping, dict):
        report.error("'profiles' must be a mapping of profile name -> profile", line=line_of(mapping),
                     field="profiles")
        return profiles
    specs = {}
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
        specs[name] = spec

    def read(name, spec, _report, base):
        with_name = Mapping(spec)
        with_name.line, with_name.key_lines = getattr(spec, "line", None), getattr(spec, "key_lines", {})
        with_name.setdefault("profile", name)
        return read_profile(with_name, report, f"profiles.{name}", "the roster", base, base_dir=roster_dir)

    own: dict[str, Profile] = {}
    _read_extending(specs, own, builtin, lambda _name: report, read, "profiles.")
    profiles.update(own)
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


def dds_only_packages() -> dict[str, str]:
    """ROS package -> what it is, for every package a built-in profile says speaks DDS only."""
    return {package: what for profile in builtin_profiles().values()
            for package, what in profile.dds_only_packages.items()}


def builtin_debian_packages() -> set[str]:
    """Every apt package a built-in profile installs that is not a ROS one (python3-serial,
    i2c-tools; chrony for a profile with a robot base): the sandbox's Ubuntu-layout archive
    carries the real Debian packages."""
    from roslab.profiles.robot_base import BASE_PACKAGES

    names: set[str] = set()
    for profile in builtin_profiles().values():
        if getattr(profile, "base", None):
            names |= set(BASE_PACKAGES)
        for side in profile.sides.values():
            for part in [side, *(block["side"] for block in side.when)]:
                names |= {name for name in part.apt_packages if "{distro}" not in name}
    return names
