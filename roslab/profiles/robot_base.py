"""A robot's base computer on its own link (profile `base:`): the TurtleBot 4's iRobot Create 3.

The Create 3 is a second computer on the Pi's USB-C port: the Pi's `usb0` (a USB gadget, with
the profile's boot config) at 192.168.186.3/24, the Create 3 at 192.168.186.2. Only the Pi
reaches it. turtlebot4_setup (humble and jazzy, `turtlebot4_setup/turtlebot4_setup`,
`update_create3`) configures it with form POSTs from the Pi:

- `/ros-config-save-main`: `ros_domain_id`, `ros_namespace` (on Jazzy always `<ns>/_do_not_use`:
  turtlebot4's republisher carries the base's topics into the robot's namespace; on Humble only
  with the discovery server), `rmw_implementation`;
- `/beta-ntp-conf-save`: `config=server 192.168.186.3 prefer iburst minpoll 4 maxpoll 6`;
- `/api/reboot`: the base restarts with them.

and the Pi serves time to it (etc/turtlebot4/chrony.conf: `allow 192.168.186.0/24`). The base's
firmware generation must match the distro (`I.*` for Jazzy, turtlebot4_setup's jazzy README;
`H.*` for Humble); turtlebot4_setup does not read it, roslab reads it from `/api/about` (the
page third-party setup scripts grep for `I.0.0.FastDDS`: not proven on a robot here).

This module is the data and the text (checked profile data, the netplan and chrony files, the
POSTs' bodies, the firmware check); deploy/robot_base.py applies them.
"""

from __future__ import annotations

import ipaddress
import json
import re
from dataclasses import dataclass, field

BASE_KEYS = ("kind", "interface", "pi_address", "base_address", "ntp_allow", "firmware", "namespace_suffix")
BASE_KINDS = ("create3",)
_INTERFACE = re.compile(r"usb[0-9]", re.ASCII)
_GENERATION = re.compile(r"[A-Z]", re.ASCII)
_NAMESPACE = re.compile(r"(/[A-Za-z][A-Za-z0-9_]{0,62}){1,8}", re.ASCII)
_SUFFIX = re.compile(r"(/[a-z_][a-z0-9_]{0,30}){1,2}", re.ASCII)
# The middlewares the Create 3's firmware offers (its ros-config page).
CREATE3_MIDDLEWARES = ("rmw_fastrtps_cpp", "rmw_cyclonedds_cpp")
# A Create 3 firmware version as /api/about shows it: generation letter, numbers, middleware.
FIRMWARE_VERSION = re.compile(r"\b([A-Z])\.([0-9]+)\.([0-9]+)(\.[A-Za-z]+)?\b", re.ASCII)
# On the Pi: what roslab last posted to the base (root-only; the deploy's idempotence record).
POSTED_RECORD = "/var/lib/roslab/create3-posted.json"


@dataclass(frozen=True)
class RobotBase:
    """A profile's `base:` (checked): the link and the Create 3's settings."""

    kind: str
    interface: str  # the Pi's end of the link (usb0)
    pi_address: str  # with its prefix: 192.168.186.3/24
    base_address: str  # 192.168.186.2
    ntp_allow: str  # the network the Pi's chrony serves: 192.168.186.0/24
    firmware: dict[str, str] = field(default_factory=dict)  # distro -> generation letter
    namespace_suffix: dict[str, str] = field(default_factory=dict)  # distro -> "/_do_not_use"

    @classmethod
    def from_data(cls, data) -> RobotBase | None:
        return cls(**{key: data[key] for key in BASE_KEYS}) if data else None

    @property
    def pi_ip(self) -> str:
        return self.pi_address.split("/")[0]


def base_problems(value) -> list[tuple[str, str]]:
    """(key, problem) for each thing wrong with a profile's `base:` mapping."""
    if not isinstance(value, dict):
        return [("", f"must be a mapping ({', '.join(BASE_KEYS)})")]
    problems = [(key, "unknown key") for key in value if key not in BASE_KEYS]
    problems += [(key, "missing") for key in BASE_KEYS[:5] if key not in value]
    if problems:
        return problems
    checks = {
        "kind": lambda v: v in BASE_KINDS or f"must be one of {', '.join(BASE_KINDS)}",
        "interface": lambda v: isinstance(v, str) and bool(_INTERFACE.fullmatch(v)) or "must be usb0..usb9",
        "pi_address": _interface_address_problem,
        "base_address": lambda v: _address_problem(v, "an IPv4 address"),
        "ntp_allow": _network_problem,
        "firmware": lambda v: _distro_map_problem(v, _GENERATION, "a firmware generation letter (I)"),
        "namespace_suffix": lambda v: _distro_map_problem(v, _SUFFIX, "a namespace suffix (/_do_not_use)"),
    }
    for key, check in checks.items():
        if key in value:
            result = check(value[key])
            if result is not True and result is not None:
                problems.append((key, result))
    if not problems:
        network = ipaddress.ip_interface(value["pi_address"]).network
        if ipaddress.ip_address(value["base_address"]) not in network:
            problems.append(("base_address", f"must be on the Pi's link network {network}"))
        if ipaddress.ip_network(value["ntp_allow"]) != network:
            problems.append(("ntp_allow", f"must be the Pi's link network {network}"))
    return problems


def _address_problem(value, what: str) -> str | None:
    try:
        ipaddress.IPv4Address(value if isinstance(value, str) else "")
    except ValueError:
        return f"must be {what}"
    return None


def _interface_address_problem(value) -> str | None:
    try:
        address = ipaddress.IPv4Interface(value if isinstance(value, str) and "/" in value else "")
    except ValueError:
        return "must be an IPv4 address with its prefix (192.168.186.3/24)"
    return None if address.network.is_private else "must be a private address"


def _network_problem(value) -> str | None:
    try:
        ipaddress.IPv4Network(value if isinstance(value, str) else "")
    except ValueError:
        return "must be an IPv4 network (192.168.186.0/24)"
    return None


def _distro_map_problem(value, pattern, what: str) -> str | None:
    from roslab.ros.distro import DISTRO_RELEASES

    if not isinstance(value, dict) or not all(
            distro in DISTRO_RELEASES and isinstance(item, str) and pattern.fullmatch(item)
            for distro, item in value.items()):
        return f"must map distros to {what}"
    return None


# --- the Pi's side: usb0 and time ----------------------------------------------------------------

def netplan_text(base: RobotBase) -> str:
    """The netplan file that gives the Pi's end of the link its address (turtlebot4_setup's
    etc/netplan/40-ethernets.yaml, usb0 only; optional: a Pi boots without the base)."""
    return (f"# roslab: the link to the robot's base ({base.kind} at {base.base_address})\n"
            "network:\n  version: 2\n  ethernets:\n"
            f"    {base.interface}:\n      addresses: [{base.pi_address}]\n      dhcp4: false\n"
            "      optional: true\n")


# What a host with a robot base gets installed (deploy/robot_base.py): chrony serves the base its time.
BASE_PACKAGES = ("chrony",)


def chrony_text(base: RobotBase) -> str:
    """chrony's drop-in that serves time to the base (turtlebot4_setup's chrony.conf `allow`)."""
    return f"# roslab: the robot's base ({base.kind}) takes its time from this Pi\nallow {base.ntp_allow}\n"


# --- the Create 3's settings ------------------------------------------------------------------------

def create3_wanted(base: RobotBase, distro: str, environment: dict[str, str]) -> dict[str, str]:
    """The form fields roslab posts, in the order turtlebot4_setup sends them, from the team's
    environment (ROS_DOMAIN_ID, RMW_IMPLEMENTATION, ROBOT_NAMESPACE when the roster sets it).
    ValueError: a middleware the Create 3 has not."""
    rmw = environment.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if rmw not in CREATE3_MIDDLEWARES:
        raise ValueError(f"the Create 3 runs only {' or '.join(CREATE3_MIDDLEWARES)}, not the team's {rmw}")
    namespace = environment.get("ROBOT_NAMESPACE", "").rstrip("/")
    if namespace and not _NAMESPACE.fullmatch(namespace):
        raise ValueError(f"ROBOT_NAMESPACE {namespace!r} is not a ROS namespace (/name/name: letters, digits, _)")
    return {
        "ros_domain_id": environment.get("ROS_DOMAIN_ID", "0"),
        "ros_namespace": namespace + base.namespace_suffix.get(distro, ""),
        "rmw_implementation": rmw,
        "ntp": f"server {base.pi_ip} prefer iburst minpoll 4 maxpoll 6",
    }


def create3_posts(wanted: dict[str, str], posted: dict | None) -> list[tuple[str, str]]:
    """(path, form body) for each POST the base needs, given what was posted last (None:
    nothing known): the ROS settings, the NTP server, then a reboot when either was posted."""
    from urllib.parse import urlencode

    posted = posted or {}
    posts = []
    ros = {key: wanted[key] for key in ("ros_domain_id", "ros_namespace", "rmw_implementation")}
    if {key: posted.get(key) for key in ros} != ros:
        posts.append(("/ros-config-save-main", urlencode(ros)))
    if posted.get("ntp") != wanted["ntp"]:
        posts.append(("/beta-ntp-conf-save", urlencode({"config": wanted["ntp"]})))
    if posts:
        posts.append(("/api/reboot", ""))
    return posts


def record_text(wanted: dict[str, str]) -> str:
    return json.dumps(wanted, sort_keys=True)


def firmware_generation(about: str | None) -> str | None:
    """The firmware version in /api/about's answer (I.0.0.FastDDS), or None."""
    match = FIRMWARE_VERSION.search(about or "")
    return match.group(0) if match else None


def firmware_problem(version: str | None, distro: str, base: RobotBase) -> str | None:
    """One line when the base's firmware generation is not the distro's (None: it is, or the
    profile names none for the distro)."""
    wanted = base.firmware.get(distro)
    if not wanted or not version:
        return None
    if version[0] != wanted:
        return (f"Create 3 firmware {version} on a {distro.capitalize()} class: update it to {wanted}.* "
                "(iRobot's Create 3 firmware page; turtlebot4_setup's scripts/create_update.sh)")
    return None
