"""A host's profile, resolved for its side, distro and settings into plain host data
(`ResolvedProfile`'s keys; a deploy reads it as that dataclass).

`resolve()` returns what the deploys read as `host.data.roslab_profile`: Debian package
names for the distro, the environment with the settings filled in, the udev rules file's
text, the groups, the launch, the verify topic and the checklist. A setting's value is
checked against the profile's declaration first (allowed values or pattern), so what is
filled into a file or a command is one of the values the profile allows.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields

from roslab import formats
from roslab.ros.distro import DISTRO_RELEASES, PLATFORMS
from roslab.profiles import devices as device_data
from roslab.profiles.schema import (
    BOOT_CONFIG_KEYS,
    PLACEHOLDER,
    SERVICE_ENVIRONMENT_PLACEHOLDERS,
    Profile,
    Side,
    merged_build_dependencies,
    merged_cmake_args,
)
from roslab.quoting import shell_word

UDEV_RULES_PATH = "/etc/udev/rules.d/60-roslab-profile.rules"


def _fields_of(cls, data: Mapping) -> dict:
    """Each field of dataclass `cls` from the mapping `data` (KeyError: one without a default is
    missing)."""
    return {name: data[name] for name, required in _field_names(cls) if required or name in data}


@functools.cache
def _field_names(cls) -> tuple[tuple[str, bool], ...]:
    """(name, required) of each field of dataclass `cls`: read once, as every host's settings
    make its resolved profile's dataclass (roslab check builds them all)."""
    return tuple((item.name, item.default is MISSING and item.default_factory is MISSING) for item in fields(cls))


@dataclass(frozen=True)
class PythonEnv:
    venv: str | None  # relative to the login user's home; None: no venv
    requirements: list[str]  # "name==version"

    @classmethod
    def from_data(cls, data: Mapping) -> PythonEnv:
        return cls(**_fields_of(cls, data))


@dataclass(frozen=True)
class ResolvedService:
    name: str  # the unit is <name>.service
    description: str
    command: str  # settings filled in, each a shell word
    environment: dict[str, str]
    enabled: bool  # its enabled_if settings hold here
    disabled_because: str  # why not, in words ("" when enabled)

    @classmethod
    def from_data(cls, data: Mapping) -> ResolvedService:
        return cls(**_fields_of(cls, data))


@dataclass(frozen=True)
class ResolvedProfile:
    """What one host gets from its robot profile, settings filled in.

    `resolve_host` makes it as a plain mapping with these keys: that is what travels in pyinfra's
    host data (`host.data.roslab_profile`: its JSON output, `--data` and a hand-made inventory give
    plain mappings). Everything else reads this dataclass, made by `from_data`: a deploy and
    `roslab verify` as `roslab.host_settings.host_settings(host).roslab_profile`, the roster's
    checks and `roslab status` as a roster host's `settings.roslab_profile`."""

    name: str
    distro: str
    settings: dict[str, str]  # the profile's settings: the roster's values, else the defaults
    ros_packages: list[str]  # ROS package names (${gazebo} filled)
    packages: list[str]  # the Debian packages: ros-<distro>-..., then the profile's apt packages
    environment: dict[str, str]  # the profile's variables for shells and units
    groups: list[str]  # the login user's hardware groups
    udev_rules: str  # the rules file's text ("" for none)
    launch: str | None  # "<package> <file>.launch.py" the host's nodes service runs, or None
    variant: str | None  # the side's ROS variant (desktop, ros-base...)
    verify_topic: str | None  # what `roslab verify` listens for on the main, None: nothing
    verify_type: str
    verify_source: str  # what publishes it, for a main that hears nothing
    verify_publisher: str  # the node that must publish it ("": any), ${team} left for the roster to fill
    discovery: str | None  # the profile's discovery mode (sim: localhost), or None
    checklist: list[str]  # hardware steps by hand, ${host} filled
    os_tweaks: dict  # mask_units, swap_mb, swap_if_memory_mb_at_most
    sources: list[dict]  # the underlay's repositories (the roster loader fills them)
    cmake_args: dict[str, list[str]]  # package -> -DNAME=value, for the underlay's build
    build_dependencies: dict[str, list[str]]  # package -> packages built before it
    skip_packages: list[str]  # packages of the sources not built
    python: PythonEnv
    remove_apt_packages: list[str]
    boot_config: dict[str, list[str]]  # config_txt lines, cmdline_add and cmdline_remove words
    services: list[ResolvedService]
    underlay_build_memory_mb: int | None  # a host with less memory never builds the underlay
    base: dict | None = None  # the robot's base on its own link (roslab/profiles/robot_base.py), robot side only
    # `ros2 launch` arguments of the side's launch, {name: value}, settings filled and checked
    launch_arguments: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_data(cls, data: Mapping) -> ResolvedProfile:
        """The dataclass of a resolved profile's mapping (host data's roslab_profile).
        KeyError when a key is missing, TypeError when a part is not a mapping."""
        values = _fields_of(cls, data)
        values["python"] = PythonEnv.from_data(values["python"])
        values["services"] = [ResolvedService.from_data(service) for service in values["services"]]
        return cls(**values)


@dataclass(frozen=True)
class ResolveError(Exception):
    field: str
    message: str


def gazebo_package(distro: str) -> str:
    """The ROS package of the distro's Gazebo, from roslab.ros.distro's records."""
    for platform in PLATFORMS:
        if platform.distro == distro:
            return platform.gazebo.ros_package
    return "ros_gz"  # a non-LTS distro (kilted): Gazebo through ros_gz


def debian_name(distro: str, ros_package: str) -> str:
    return f"ros-{distro}-{ros_package.replace('_', '-')}"


def _matches(conditions: dict, values: dict) -> bool:
    for name, wanted in conditions.items():
        value = values.get(name)
        if wanted is None:
            ok = value is None
        elif wanted == "*":
            ok = value is not None
        elif isinstance(wanted, list):
            ok = value in wanted
        else:
            ok = value == wanted
        if not ok:
            return False
    return True


def used_settings(side: Side | None) -> set[str]:
    """The profile settings a side refers to (its texts and its when blocks' conditions)."""
    if side is None:
        return set()
    texts = [*side.environment.values(), *side.checklist]
    for service in side.services:
        texts += [service["command"], *service["environment"].values()]
    names = {name for text in texts for name in PLACEHOLDER.findall(text)}
    names |= {name for device in side.devices for name in device.settings()}
    names |= {name for service in side.services for name in service["enabled_if"]}
    for block in side.when:
        names |= set(block["if"]) | used_settings(block["side"])
    return names


def setting_values(profile: Profile, given: dict, side: Side | None = None) -> tuple[dict, list[ResolveError]]:
    """The profile's settings for a host: given values checked, defaults filled in, and the
    required ones that this side uses present."""
    values, problems = {}, []
    used = used_settings(side) if side is not None else set(profile.settings)
    for name, setting in profile.settings.items():
        value = given.get(name, setting.default)
        if value is None:
            if setting.required and name in used:
                allowed = f" ({', '.join(setting.allowed)})" if setting.allowed else ""
                problems.append(ResolveError(name, f"profile {profile.name!r} needs {name}{allowed}: "
                                                   f"{setting.doc or 'set it for the team or the host'}"))
            continue
        problem = setting.problem(value)
        if problem:
            problems.append(ResolveError(name, problem))
            continue
        values[name] = value
    return values, problems


def fill(text: str, values: dict) -> str:
    """`text` with each ${setting} replaced by its (checked) value."""
    return PLACEHOLDER.sub(lambda match: str(values.get(match.group(1), "")), text)


def resolve(profile: Profile, given: dict, *, distro: str, role: str, board: str | None = None) -> dict | None:
    """`host.data.roslab_profile` for a host of `role` on `distro` (None: a distro roslab has no
    release record for); ResolveError list via `problems`.

    Raises ExceptionGroup-free: returns (data, problems) through `resolve_host`.
    """
    data, problems = resolve_host(profile, given, distro=distro, role=role, board=board)
    if problems:
        raise problems[0]
    return data


def side_parts(side: Side, values: dict, distro: str, board: str | None) -> list[Side]:
    """The side and those of its `when` blocks whose conditions hold for these setting values,
    distro and board: what a host of this side gets, in order."""
    conditions = {**values, "distro": distro, "board": board}
    return [side, *(block["side"] for block in side.when if _matches(block["if"], conditions))]


def placement_problems(profile: Profile, *, distro: str, role: str, board: str | None) -> list[ResolveError]:
    """Why a host of this distro, role and board cannot run `profile` (none: it can)."""
    problems: list[ResolveError] = []
    if distro not in profile.distros:
        works = " or ".join(f"{p.release} ({p.distro})" for p in PLATFORMS if p.distro in profile.distros)
        other = [d for d in profile.distros if d not in {p.distro for p in PLATFORMS}]
        if other:
            works = ", ".join([works, *(f"ros_distro: {d}" for d in other)]).strip(", ")
        problems.append(ResolveError(
            "robot_profile", f"profile {profile.name!r} supports {', '.join(profile.distros)}, not {distro} "
                             f"(this host's distro): set ubuntu_release to {works}, or another robot_profile"))
    side = profile.sides.get(role)
    boards = (side.boards if side is not None and side.boards else None) or profile.boards
    if board is not None and board not in boards:
        whose = f"profile {profile.name!r}" if boards == profile.boards else f"the {role} of profile {profile.name!r}"
        problems.append(ResolveError(
            "board", f"{whose} does not run on a {board} (it runs on: {', '.join(boards)})"))
    if side is None:
        has = " and ".join(profile.sides)
        problems.append(ResolveError(
            "robot_profile", f"profile {profile.name!r} has no {role} side (only {has}): give this host "
                             "another robot_profile (e.g. demo), or leave it out of the team"))
    return problems


def merged_parts(parts: list[Side]) -> Side:
    """The side and its matching `when` blocks as one: lists joined (each item once), the
    environment merged, a later service replacing an earlier one of its name. The checklist
    lists the blocks' items (how this host is set up: flash, plug in) before the side's own (what
    every host of the side does once it is: try it)."""
    merged = Side()
    for part in parts[1:] + parts[:1]:
        merged.checklist += part.checklist
    for part in parts:
        merged.ros_packages += [p for p in part.ros_packages if p not in merged.ros_packages]
        merged.apt_packages += [p for p in part.apt_packages if p not in merged.apt_packages]
        merged.environment.update(part.environment)
        merged.groups += [g for g in part.groups if g not in merged.groups]
        merged.devices = [d for d in merged.devices if d.name not in {p.name for p in part.devices}]
        merged.devices += part.devices
        merged.remove_apt_packages += [p for p in part.remove_apt_packages if p not in merged.remove_apt_packages]
        for key in BOOT_CONFIG_KEYS:
            items = merged.boot_config.setdefault(key, [])
            items += [item for item in part.boot_config.get(key, []) if item not in items]
        merged.services = [s for s in merged.services if s["name"] not in {p["name"] for p in part.services}]
        merged.services += part.services
    return merged


def launch_arguments(parts: list[Side], values: dict) -> tuple[dict[str, str], list[ResolveError]]:
    """The side's and its matching `when` blocks' launch arguments (a later one replaces an
    earlier one of its name), settings filled; a filled value is checked again, as a setting's
    value may hold what a launch argument must not."""
    arguments: dict[str, str] = {}
    for part in parts:
        arguments.update({name: fill(value, values) for name, value in part.launch_arguments.items()})
    problems = [ResolveError(f"launch_arguments.{name}", f"launch argument {name}: {problem}")
                for name, value in arguments.items() if (problem := formats.launch_argument_value(value))]
    return arguments, problems


def udev_file(profile: Profile, devices: list, values: dict) -> tuple[str, str | None]:
    """(the udev rules file's text roslab writes for the side's devices, settings filled in, ""
    for none; why a device's setting cannot fill its rule, or None)."""
    result = []
    for device in devices:
        done = device_data.filled(device, values)
        if isinstance(done, str):
            return "", done
        result.append(done)
    return device_data.rules_file(profile.name, result), None


def checklist_items(items: list[str], values: dict, host: str | None, middleware: str | None) -> list[str]:
    """The checklist's items with the settings' values, the host's name and the class's middleware in."""
    return [fill(item, {**values, "host": host or "HOST", "ros_middleware": middleware or "the class's middleware"})
            for item in items]


def resolve_host(profile: Profile, given: dict, *, distro: str, role: str,
                 board: str | None = None, host: str | None = None, middleware: str | None = None
                 ) -> tuple[dict | None, list[ResolveError]]:
    """What a host of this distro, role and board gets from `profile` with the roster's setting
    values `given` (host.data.roslab_profile), or None and the problems. `host`: the host's
    name, for the checklist's ${host} (else the word HOST); `middleware`: the class's
    ros_middleware, for its ${ros_middleware} (else the words "the class's middleware")."""
    problems = placement_problems(profile, distro=distro, role=role, board=board)
    side = profile.sides.get(role)
    values, value_problems = setting_values(profile, given, side)
    problems += value_problems
    if problems or side is None or distro not in DISTRO_RELEASES:  # no side: a placement problem
        return None, problems
    parts = side_parts(side, values, distro, board)
    merged = merged_parts(parts)
    rules, problem = udev_file(profile, merged.devices, values)
    if problem:
        return None, [ResolveError("devices", f"profile {profile.name!r}'s {problem}")]
    build_dependencies = merged_build_dependencies([part.build_dependencies for part in parts])
    skip_packages = list(dict.fromkeys(name for part in parts for name in part.skip_packages))
    logic = underlay_logic_problems(profile.name, build_dependencies, skip_packages, merged.services)
    if logic:
        return None, logic
    ros_packages = [fill(name, {"gazebo": gazebo_package(distro)}) for name in merged.ros_packages]
    arguments, problems = launch_arguments(parts, values)
    if problems:
        return None, problems
    return {
        "name": profile.name,
        "distro": distro,
        "settings": values,
        "ros_packages": ros_packages,
        "packages": list(dict.fromkeys([debian_name(distro, name) for name in ros_packages]
                                       + [name.replace("{distro}", distro) for name in merged.apt_packages])),
        "environment": {name: fill(value, values) for name, value in merged.environment.items()},
        "groups": merged.groups,
        "udev_rules": rules,
        "launch": next((part.launch for part in reversed(parts) if part.launch), None),
        "launch_arguments": arguments,
        "variant": side.variant,
        **verify_fields(profile, values),
        "discovery": profile.discovery,
        "checklist": checklist_items(merged.checklist, values, host, middleware),
        "os_tweaks": dict(side.os_tweaks),
        # the side's .repos files' repositories: filled by the roster loader (roslab/sources/repos.py),
        # which reads the files; here only for hand-made data
        "sources": [],
        # {package: ["-DNAME=value", ...]} for the underlay's build (deploy/sources.py)
        "cmake_args": merged_cmake_args([part.cmake_args for part in parts]),
        # {package: [packages built before it]} and the packages not built (deploy/sources.py)
        "build_dependencies": build_dependencies,
        "skip_packages": skip_packages,
        # the memory (MiB) a host needs to build the underlay; a smaller one receives it
        "underlay_build_memory_mb": profile.underlay_build_memory_mb,
        "python": python_data(profile, side),
        "remove_apt_packages": merged.remove_apt_packages,
        "boot_config": {key: items for key, items in merged.boot_config.items() if items},
        "services": [resolved_service(service, values, distro, profile.name) for service in merged.services],
        "base": profile.base if role == "robot" else None,
    }, []


def verify_fields(profile: Profile, values: dict) -> dict:
    """What `roslab verify` listens for on a host of `profile` with these setting values: the
    topic (None where its `verify_if` does not match), type, source and publisher."""
    return {
        "verify_topic": profile.verify_topic if _matches(profile.verify_if, values) else None,
        "verify_type": profile.verify_type,
        "verify_source": fill(profile.verify_source, values),
        "verify_publisher": fill(profile.verify_publisher, {**values, "team": "${team}"}),
    }


_RUNS_PACKAGE = re.compile(r"\bros2 (?:run|launch) ([a-z][a-z0-9_]*)", re.ASCII)


def dependency_cycle(graph: dict[str, list[str]]) -> list[str] | None:
    """A cycle of `graph` (package -> packages built before it) as its chain, first package
    repeated at the end, or None. Iterative: a long chain cannot exhaust the stack."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    for start in graph:
        if state.get(start):
            continue
        path, stack = [start], [iter(graph.get(start, ()))]
        state[start] = 1
        while stack:
            following = next(stack[-1], None)
            if following is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(following) == 1:
                return [*path[path.index(following):], following]
            elif not state.get(following):
                state[following] = 1
                path.append(following)
                stack.append(iter(graph.get(following, ())))
    return None


def underlay_logic_problems(name: str, build_dependencies: dict[str, list[str]], skip_packages: list[str],
                            services: list[dict]) -> list[ResolveError]:
    """The underlay's build as a host of this profile gets it: no build_dependencies cycle (colcon
    would wait forever or refuse), and no skipped package that one of the profile's services runs."""
    problems = []
    cycle = dependency_cycle(build_dependencies)
    if cycle:
        problems.append(ResolveError("robot_profile", f"profile {name!r}'s build_dependencies go round in a "
                                                      f"circle: {' -> '.join(cycle)}"))
    for service in services:
        for package in _RUNS_PACKAGE.findall(str(service.get("command") or "")):
            if package in skip_packages:
                problems.append(ResolveError("robot_profile", f"profile {name!r} skips {package} (skip_packages), "
                                             f"which its service {service.get('name')!r} runs"))
    return problems


def python_data(profile: Profile, side: Side) -> dict:
    """The side's Python requirements and their venv (deploy/python_env.py).

    {"venv": directory relative to the login user's home, "requirements": ["name==version", ...]};
    no requirements and no python_venv: nothing to do (requirements empty, venv None).
    """
    requirements = list(side.python_packages)
    venv = side.python_venv
    if venv is None and requirements:
        venv = f"{profile.name}_venv"
    return {"venv": venv, "requirements": requirements}


# A service's environment's placeholders that only the host knows (schema.SERVICE_ENVIRONMENT_PLACEHOLDERS),
# kept as they are: deploy/profile_services.py fills them from the host's ROS environment.
HOST_KEPT = {name: f"${{{name}}}" for name in SERVICE_ENVIRONMENT_PLACEHOLDERS}


def resolved_service(service: dict, values: dict, distro: str, profile_name: str) -> dict:
    """A profile's service for one host: its command with ${distro} and the settings filled in
    (each value one shell word), its environment filled in, and whether it is enabled here
    (its `enabled_if` settings have the values it names) and, if not, why."""
    words = {name: shell_word(str(value)) for name, value in values.items()}
    words["distro"] = shell_word(distro)
    missing = []
    for name, wanted in service["enabled_if"].items():
        allowed = wanted if isinstance(wanted, list) else [wanted]
        if values.get(name) not in allowed:
            missing.append(f"{name} is {values.get(name) or 'unset'} (it runs when {name}: {' or '.join(allowed)})")
    return {
        "name": service["name"],
        "description": fill(service["description"], values) or f"{service['name']} (robot profile {profile_name})",
        "command": fill(service["command"], words),
        # the host's own placeholders (${ros_domain_id}) stay for the unit's writer to fill
        "environment": {name: fill(text, {**HOST_KEPT, **values}) for name, text in service["environment"].items()},
        "enabled": not missing,
        "disabled_because": "; ".join(missing),
    }
