"""One profile mapping, checked: every key known, every value of its type and format.

Problems go to a `Report` with the line of the offending key (the profile's own file for a
built-in one, the roster for a roster's), so a typo in a profile reads like one in a roster.
"""

from __future__ import annotations

import difflib
import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

import re2

from roslab import boards, formats, settings
from roslab.ros.distro import BY_NAME, DISTRO_RELEASES
from roslab.profiles import devices as device_data
from roslab.checked.loading import line_of
from roslab.checked.problems import Report

SIDES = ("main", "robot")
BOARDS = boards.NAMES
DISCOVERY = ("localhost",)  # room for issue 20's modes (static, discovery_server...)

_NAME = re.compile(r"[a-z][a-z0-9_]{0,62}")
_VALUE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.:+-]{0,127}")
_ROS_PACKAGE = re.compile(r"[a-z][a-z0-9_]*|\$\{gazebo\}")
# The commands a profile may bring (`tools:`): the modules of roslab/robot_tools, as `roslab <tool>`
# spells them. Read from the folder, not imported: those commands sit above the profiles.
TOOLS_DIR = Path(__file__).resolve().parent.parent / "robot_tools"
TOOL_NAME = re.compile(r"[a-z][a-z0-9]*(-[a-z0-9]+){0,5}", re.ASCII)


@functools.cache
def known_tools() -> list[str]:
    return sorted(path.stem.replace("_", "-") for path in TOOLS_DIR.glob("*.py") if path.stem != "__init__")


def tool_problem(name) -> str | None:
    """Why `name` is not a tool a profile may name, or None."""
    if not isinstance(name, str) or not TOOL_NAME.fullmatch(name) or name not in known_tools():
        return f"{name!r} is not a robot tool roslab has (known: {', '.join(known_tools())})"
    return None


# `distros: all`: the profile runs on every distro roslab has a record of (roslab.ros.distro).
ALL_DISTROS = "all"
# Conditions a `when` block may test besides the profile's settings.
BUILTIN_CONDITIONS = ("distro", "board")

TOP_KEYS = ("profile", "extends", "description", "distros", "tools", "boards", "middlewares", "dds_only_packages",
            "discovery", "verify_topic", "verify_type", "verify_if", "verify_source", "verify_publisher",
            "underlay_build_memory_mb", "settings", "base", *SIDES)
# `underlay_build_memory_mb`: the memory (MiB) a host needs to build the profile's underlay;
# a smaller host never builds it, it receives the build of a host of its group (issue 31).
UNDERLAY_BUILD_MEMORY_MB = (256, 65536)
SETTING_KEYS = ("doc", "allowed", "pattern", "describe", "required", "default")
SIDE_KEYS = ("variant", "boards", "ros_packages", "apt_packages", "remove_apt_packages", "environment", "groups",
             "devices", "udev_rules", "boot_config", "services", "launch", "launch_arguments", "checklist",
             "os_tweaks", "sources", "cmake_args", "build_dependencies", "skip_packages", "python_packages",
             "python_venv", "when")
WHEN_KEYS = ("if", "launch", "launch_arguments", "ros_packages", "apt_packages", "remove_apt_packages", "environment",
             "groups", "devices", "udev_rules", "boot_config", "services", "sources", "cmake_args",
             "build_dependencies", "skip_packages", "checklist")
# An underlay package's name in `cmake_args`, `build_dependencies` and `skip_packages` (a ROS
# package name, or a plain CMake package's as its colcon.pkg gives it).
_UNDERLAY_PACKAGE = re.compile(r"[a-z][a-z0-9_]{0,99}", re.ASCII)
# `cmake_args`: CMake cache settings for one package of the underlay (colcon.meta's
# "cmake-args"), each `-DNAME=value` or `-DNAME:TYPE=value`, plain ASCII, one shell word.
_CMAKE_ARG = re.compile(r"-D[A-Za-z_][A-Za-z0-9_]{0,63}(:(BOOL|STRING|PATH|FILEPATH))?=[A-Za-z0-9_.,/+:@%-]{0,200}",
                        re.ASCII)
# The middlewares a class may run (roslab.settings ros_middleware); a profile may allow fewer.
MIDDLEWARES = ("rmw_fastrtps_cpp", "rmw_cyclonedds_cpp", "rmw_zenoh_cpp")
# A Pi's boot configuration (deploy/profile_extras.py): lines kept in a marked block of
# config.txt, words taken out of cmdline.txt. Both are read by the firmware and the kernel,
# which know no quoting: a line or a word is plain ASCII without spaces or comments.
BOOT_CONFIG_KEYS = ("config_txt", "cmdline_add", "cmdline_remove")
_CONFIG_LINE = re.compile(r"\[[a-z0-9_]{1,30}\]|[A-Za-z0-9_][A-Za-z0-9_.,:=+-]{0,119}", re.ASCII)
_CMDLINE_WORD = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.,:=/+-]{0,119}", re.ASCII)
# config.txt is the firmware's: a line roslab writes sets one of these keys (never kernel=,
# initramfs, cmdline=, os_prefix=, include, device_tree=, which choose what boots), in one of
# these sections; a dtoverlay or dtparam line names an overlay or parameter of these lists, its
# parameters' values plain words (_OVERLAY_VALUE).
CONFIG_TXT_KEYS = frozenset({"enable_uart", "dtoverlay", "dtparam", "gpu_mem", "camera_auto_detect",
                             "display_auto_detect", "start_x", "disable_splash"})
CONFIG_TXT_SECTIONS = frozenset({"all", "pi3", "pi4", "pi400", "pi5", "cm4", "cm5", "pi02"})
DT_OVERLAYS = frozenset({
    "dwc2", "i2c-gpio", "disable-bt", "miniuart-bt", "uart0", "uart1", "uart2", "uart3", "uart4", "uart5",
    "i2c0", "i2c1", "i2c3", "i2c4", "i2c5", "i2c6", "spi0-1cs", "spi0-2cs", "spi1-1cs", "spi1-2cs", "pwm",
    "pwm-2chan", "gpio-shutdown", "w1-gpio", "vc4-kms-v3d", "imx219", "imx477", "imx708", "ov5647"})
DT_PARAMS = frozenset({"i2c_arm", "i2c_arm_baudrate", "i2c", "i2c_baudrate", "i2c_vc", "spi", "audio",
                       "uart0", "uart1"})
_OVERLAY_PARAM = re.compile(r"[a-z][a-z0-9_-]{0,39}", re.ASCII)
_OVERLAY_VALUE = re.compile(r"[A-Za-z0-9_.-]{1,40}", re.ASCII)
# cmdline.txt words a profile may add: the kernel modules loaded at boot (systemd's
# modules-load=, a comma-separated list from KERNEL_MODULES_AT_BOOT), nothing that changes the
# root, init or console.
KERNEL_MODULES_AT_BOOT = frozenset({"dwc2", "g_ether", "g_serial", "libcomposite", "i2c-dev", "spidev"})
def config_line_problem(line: str) -> str | None:
    """Why `line` is not a config.txt line a profile may write (None: it is): a [section] of
    CONFIG_TXT_SECTIONS or key=value with a key of CONFIG_TXT_KEYS, a dtoverlay's overlay and a
    dtparam's parameters from DT_OVERLAYS / DT_PARAMS, every value a plain word."""
    if not _CONFIG_LINE.fullmatch(line):
        return (f"{line!r} is not a config.txt line roslab writes (key=value or [section]: ASCII letters, digits, "
                "_ . , : = + -, no spaces or comments)")
    if line.startswith("["):
        return None if line[1:-1] in CONFIG_TXT_SECTIONS else \
            f"{line!r}: a config.txt section roslab writes is one of {', '.join(sorted(CONFIG_TXT_SECTIONS))}"
    key, _, value = line.partition("=")
    if key not in CONFIG_TXT_KEYS:
        return f"{line!r}: a config.txt key roslab writes is one of {', '.join(sorted(CONFIG_TXT_KEYS))}"
    if key == "dtoverlay":
        name, *params = value.split(",")
        if name not in DT_OVERLAYS:
            return f"{line!r}: the overlay {name!r} is not one roslab writes ({', '.join(sorted(DT_OVERLAYS))})"
        return next(filter(None, (overlay_param_problem(line, param, None) for param in params)), None)
    if key == "dtparam":
        return next(filter(None, (overlay_param_problem(line, param, DT_PARAMS) for param in value.split(","))),
                    None)
    return None if _OVERLAY_VALUE.fullmatch(value) else f"{line!r}: the value is not a plain word"


def overlay_param_problem(line: str, param: str, names: frozenset | None) -> str | None:
    """Why one `name[=value]` of a dtoverlay/dtparam line is refused (names: the allowed names,
    None: any parameter name of the overlay's own)."""
    name, sep, value = param.partition("=")
    if not _OVERLAY_PARAM.fullmatch(name) or (names is not None and name not in names):
        allowed = f" ({', '.join(sorted(names))})" if names is not None else ""
        return f"{line!r}: {name!r} is not a parameter roslab writes{allowed}"
    if sep and not _OVERLAY_VALUE.fullmatch(value):
        return f"{line!r}: the value of {name!r} is not a plain word"
    return None


def cmdline_add_problem(word: str) -> str | None:
    """Why `word` is not a cmdline.txt word a profile may add (None: it is): modules-load= with
    kernel modules from KERNEL_MODULES_AT_BOOT."""
    key, sep, modules = word.partition("=")
    if key != "modules-load" or not sep:
        return f"{word!r}: a cmdline.txt word roslab adds is modules-load=<modules>"
    unknown = [module for module in modules.split(",") if module not in KERNEL_MODULES_AT_BOOT]
    if unknown or not modules:
        return (f"{word!r}: modules-load names kernel modules from {', '.join(sorted(KERNEL_MODULES_AT_BOOT))}"
                f"{' (not ' + ', '.join(map(repr, unknown)) + ')' if unknown else ''}")
    return None



# A profile's own services (deploy/profile_extras.py): one unit per entry.
SERVICE_KEYS = ("name", "description", "command", "environment", "enabled_if")
_SERVICE_NAME = re.compile(r"[a-z][a-z0-9_-]{0,62}", re.ASCII)
# Names of units roslab itself writes, or the system has: a profile's service cannot take
# them over (a service named like one would replace the system's unit in /etc/systemd/system).
RESERVED_SERVICES = frozenset("""
    roslab-nodes roslab-discovery roslab-network-rollback ssh sshd systemd systemd-udevd systemd-networkd
    dbus dbus-broker udev polkit rsyslog cron atd anacron getty serial-getty console-getty container-getty
    avahi-daemon bluetooth wpa_supplicant networking networkd-dispatcher netplan cloud-init cloud-config
    cloud-final thermald irqbalance rng-tools haveged chrony ntp ntpsec unattended-upgrades snapd lxd docker
    containerd apparmor ufw nftables iptables netfilter-persistent mdadm lvm2 multipathd fstrim e2scrub kmod
    procps keyboard-setup console-setup setvtrgb plymouth emergency rescue reboot poweroff halt shutdown
    kexec suspend hibernate sleep basic sysinit multi-user graphical default network network-online local-fs
    remote-fs swap tmp dmesg finalrd pollinate motd-news apport whoopsie packagekit fwupd accounts-daemon
    gdm gdm3 lightdm sddm display-manager user login sudo init apt-daily apt-daily-upgrade
""".split())
# Prefixes of system units (systemd-journald, dbus-org.freedesktop..., getty@, user@...).
RESERVED_SERVICE_PREFIXES = ("roslab", "systemd-", "dbus", "getty", "serial-getty", "ssh", "cloud-", "snapd",
                             "apt-", "initrd-")
# What a service's command may name besides the profile's settings.
COMMAND_PLACEHOLDERS = ("distro",)
# What a service's environment may name besides the profile's settings: the host's own ROS
# domain (its ROS_DOMAIN_ID), filled in when the unit is written (deploy/profile_services.py);
# the micro-ROS agent's XRCE_DOMAIN_ID_OVERRIDE takes it.
SERVICE_ENVIRONMENT_PLACEHOLDERS = ("ros_domain_id",)
# What a checklist item may name besides the profile's settings: the host it is for and the
# class's middleware (filled in by the roster loader, so a command in it can be copied as it is,
# and a step that sets the middleware says which).
CHECKLIST_PLACEHOLDERS = ("host", "ros_middleware")
# Opt-in OS changes a robot's maker recommends (applied when the roster sets profile_os_tweaks).
OS_TWEAK_KEYS = ("mask_units", "swap_mb", "swap_if_memory_mb_at_most")
# Units a tweak may mask: an allow-list of what a robot's maker turns off (ROBOTIS's e-Manual:
# the wait for the network at boot, sleep; background updates, modem and printer daemons that
# take serial ports or CPU). Nothing reaching the host needs is here: no ssh, systemd-* (but
# the network's boot-time waits), dbus, network, getty, mount or other target.
MASKABLE_UNITS = (
    "systemd-networkd-wait-online.service", "NetworkManager-wait-online.service",
    "sleep.target", "suspend.target", "hibernate.target", "hybrid-sleep.target", "suspend-then-hibernate.target",
    "unattended-upgrades.service", "apt-daily.service", "apt-daily.timer", "apt-daily-upgrade.service",
    "apt-daily-upgrade.timer", "motd-news.service", "motd-news.timer", "man-db.timer",
    "ModemManager.service", "cups.service", "cups.socket", "cups.path", "cups-browsed.service",
    "bluetooth.service", "snapd.service", "snapd.socket", "snapd.seeded.service", "packagekit.service",
    "fwupd.service", "fwupd-refresh.timer", "apport.service", "whoopsie.service", "kerneloops.service",
    "plymouth-quit-wait.service", "brltty.service", "brltty-udev.service",
)
# A swap file: at least 64 MiB, at most 8 GiB. A Pi has at most 16 GiB of memory and a 2 GiB one
# needs 2 GiB (ROBOTIS); more is wear on the card and a card that fills up.
SWAP_MB_RANGE = (64, 8192)
# A setting's pattern runs on every value (at load, for every host): RE2, which matches in
# time linear in the value whatever the pattern, and a bounded pattern.
MAX_SETTING_PATTERN = 500
_RE2_OPTIONS = re2.Options()
_RE2_OPTIONS.log_errors = False  # a bad pattern is reported once, in the roster's words


@dataclass(frozen=True)
class ProfileSetting:
    name: str
    doc: str = ""
    allowed: tuple[str, ...] = ()
    pattern: str | None = None
    required: bool = False
    default: str | None = None
    describe: str = ""  # the pattern in words: no message shows the pattern itself

    def problem(self, value) -> str | None:
        """Why `value` is not a legal value of this setting, or None.

        Whatever a profile allows, a value is a word (letters, digits, _ . : + -): it is filled
        into udev rules, shell and systemd lines, where no quoting of a profile's text happens.
        """
        if not isinstance(value, str):
            return f"must be a string, not {value!r}"
        if not _VALUE.fullmatch(value):
            return f"{value!r} is not a word (letters, digits and _ . : + -, at most 128)"
        if self.allowed and value not in self.allowed:
            close = difflib.get_close_matches(value, self.allowed, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            return f"{value!r} is not one of {', '.join(self.allowed)}{hint}"
        if self.pattern and not setting_pattern(self.pattern).fullmatch(value):
            wanted = self.describe or f"a value of {self.name} (see its doc in the profile)"
            return f"{value!r} is not {wanted}"
        return None


@dataclass
class Side:
    """What one side (main or robot) of a profile installs and runs."""

    ros_packages: list[str] = field(default_factory=list)
    apt_packages: list[str] = field(default_factory=list)
    environment: dict[str, str] = field(default_factory=dict)
    groups: list[str] = field(default_factory=list)
    devices: list[device_data.Device] = field(default_factory=list)  # roslab writes their udev rules
    launch: str | None = None
    # `ros2 launch PKG FILE name:=value`: {name: value}, values may hold ${setting} placeholders
    launch_arguments: dict[str, str] = field(default_factory=dict)
    variant: str | None = None  # ros-<distro>-<variant>: desktop, ros-base...
    checklist: list[str] = field(default_factory=list)
    os_tweaks: dict = field(default_factory=dict)  # OS_TWEAK_KEYS
    # vcstool .repos files filling the login user's underlay (roslab/sources/repos.py), as
    # (folder, name): beside a built-in profile's YAML, or relative to the roster
    sources: list[tuple[Path, str]] = field(default_factory=list)
    # CMake cache settings per underlay package ({package: ["-DNAME=value", ...]}), given to
    # colcon in a colcon.meta: the micro-ROS agent's superbuild switched off, say
    cmake_args: dict[str, list[str]] = field(default_factory=dict)
    # Build-order edges a package's own manifest forgets ({package: [packages it needs built
    # first]}), colcon.meta's "dependencies": micro_ros_agent after microxrcedds_agent, say
    build_dependencies: dict[str, list[str]] = field(default_factory=dict)
    # Packages of the side's sources that are neither copied to the host nor built (a ROS 1
    # leftover, a simulator package on a robot)
    skip_packages: list[str] = field(default_factory=list)
    when: list[dict] = field(default_factory=list)  # {"if": {...}, and the list/env keys above}
    # pip requirements pinned `name==version` (deploy/python_env.py), and the venv they go into:
    # a directory relative to the login user's home (None: `<profile>_venv`).
    python_packages: list[str] = field(default_factory=list)
    python_venv: str | None = None
    boards: tuple[str, ...] | None = None  # this side's boards, when narrower than the profile's
    remove_apt_packages: list[str] = field(default_factory=list)  # removed where installed (brltty)
    boot_config: dict = field(default_factory=dict)  # {"config_txt": [...], "cmdline_remove": [...]}
    services: list[dict] = field(default_factory=list)  # SERVICE_KEYS

    def launches(self) -> list[str]:
        """Every launch this side may run: its own, then those its `when` blocks choose."""
        return [launch for launch in [self.launch, *(block["side"].launch for block in self.when)] if launch]


@dataclass
class Profile:
    name: str
    description: str = ""
    # The distros it supports as the file lists them; ("all",): every distro roslab has a record
    # of, now or later (`distros` reads the records each time).
    declared_distros: tuple[str, ...] = ()
    boards: tuple[str, ...] = BOARDS
    middlewares: tuple[str, ...] = MIDDLEWARES
    discovery: str | None = None
    verify_topic: str | None = None
    verify_type: str = "std_msgs/msg/String"  # a greeting (roslab's talker), else any message passes
    verify_if: dict = field(default_factory=dict)  # setting -> value: verify only then (a board is present)
    settings: dict[str, ProfileSetting] = field(default_factory=dict)
    sides: dict[str, Side] = field(default_factory=dict)
    source: str = ""  # where it was defined, for messages ("built-in", "the roster")
    line: int | None = None
    # What publishes the verify topic, named when the main hears nothing (one line of text; the
    # profile's ${settings} filled): "the ESP32 board, through micro_ros_agent on ...".
    verify_source: str = ""
    # The node that must publish the verify topic (one ROS name; the profile's ${settings} and
    # ${team}, the team's name as a ROS name, filled): "esp32_board_${team}", the node name the
    # ESP32 firmware is flashed with. Empty: any publisher.
    verify_publisher: str = ""
    # Commands the robot brings (roslab/robot_tools): `roslab opencr-update` for a TurtleBot3.
    tools: tuple[str, ...] = ()
    # ROS packages of this robot that speak DDS only, with what they are in words: a roster that
    # names one (its nodes_launch, ros_extra_packages) under rmw_zenoh_cpp is refused.
    dds_only_packages: dict[str, str] = field(default_factory=dict)
    # The memory (MiB) a host needs to build the underlay (None: any host may build it).
    underlay_build_memory_mb: int | None = None
    # The robot's base computer on its own link (roslab/profiles/robot_base.py): the TurtleBot 4's Create 3.
    base: dict | None = None

    @property
    def distros(self) -> tuple[str, ...]:
        """The distros it supports (every known one for `distros: all`)."""
        if self.declared_distros == (ALL_DISTROS,):
            return tuple(BY_NAME)
        return self.declared_distros


# A profile's text refers to its settings as ${name} (braces only: udev's own $attr{...} and
# shell text stay as they are).
PLACEHOLDER = re.compile(r"\$\{([A-Za-z0-9_]*)\}")


def placeholders(text: str) -> list[str]:
    """The ${names} a text refers to."""
    return PLACEHOLDER.findall(text)


def launch_argument_template(value) -> str | None:
    """A launch argument's value as a profile writes it: formats.launch_argument_value, where a
    ${setting} stands for a part of it (the filled value is checked again: resolve.py)."""
    if not isinstance(value, str):
        return "must be a string (quote a number: \"8888\")"
    return formats.launch_argument_value(PLACEHOLDER.sub("x", value))


class ProfileReader:
    """Checks one profile mapping; problems go to `report` with `field` prefixed by `prefix`."""

    def __init__(self, report: Report, prefix: str, base_dir: Path | None = None):
        self.report = report
        self.prefix = prefix
        self.base_dir = base_dir  # where its .repos files are (sources:)
        self.problems = 0  # how many it reported (the report keeps each problem once)

    @property
    def ok(self) -> bool:
        return self.problems == 0

    def error(self, message: str, mapping, key=None, path: str = "") -> None:
        self.problems += 1
        self.report.error(message, line=line_of(mapping, key),
                          field=".".join(part for part in (self.prefix, path) if part))

    def unknown_keys(self, mapping, allowed, path: str) -> None:
        for key in mapping:
            if key not in allowed:
                close = difflib.get_close_matches(str(key), allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.error(f"unknown key {key!r} in a profile{hint}", mapping, key,
                           f"{path}.{key}".lstrip("."))

    def string_list(self, mapping, key, path, check=None) -> list[str]:
        value = mapping.get(key)
        if value is None:
            return []
        if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
            self.error("must be a list of strings", mapping, key, path)
            return []
        for item in value:
            problem = check(item) if check else None
            if problem:
                self.error(problem, mapping, key, path)
        return list(value)

    # --- the parts ---

    def read_settings(self, mapping) -> dict[str, ProfileSetting]:
        value = mapping.get("settings") or {}
        if not isinstance(value, dict):
            self.error("must be a mapping of setting name -> {doc, allowed, pattern, required, default}",
                       mapping, "settings", "settings")
            return {}
        result = {}
        for name, spec in value.items():
            path = f"settings.{name}"
            if not isinstance(name, str) or not _NAME.fullmatch(name):
                self.error("a profile setting's name is lower-case letters, digits and _", value, name, path)
                continue
            if not isinstance(spec, dict):
                self.error("must be a mapping (doc, allowed, pattern, required, default)", value, name, path)
                continue
            if name in settings.SETTINGS or name in ("hosts", "role", "address"):
                self.error(f"{name!r} is a roslab setting: a profile's settings need names of their own",
                           value, name, path)
                continue
            self.unknown_keys(spec, SETTING_KEYS, path)
            allowed = self.string_list(spec, "allowed", f"{path}.allowed")
            pattern = spec.get("pattern")
            if pattern is not None:
                problem = pattern_problem(pattern)
                if problem:
                    self.error(problem, spec, "pattern", f"{path}.pattern")
                    pattern = None
            if allowed and pattern:
                self.error("give allowed or pattern, not both", spec, "pattern", f"{path}.pattern")
            if not allowed and not pattern:
                self.error("a profile setting needs allowed values or a pattern (values are written into "
                           "files and commands)", spec, None, path)
            describe = spec.get("describe", "")
            if not isinstance(describe, str) or formats.single_line(describe or "x") or len(describe) > 200:
                self.error("describe is the pattern in words: one line of text, at most 200 characters",
                           spec, "describe", f"{path}.describe")
                describe = ""
            required = spec.get("required", False)
            if not isinstance(required, bool):
                self.error("must be true or false", spec, "required", f"{path}.required")
                required = False
            default = spec.get("default")
            setting = ProfileSetting(name, str(spec.get("doc") or ""), tuple(allowed), pattern, required,
                                     default if isinstance(default, str) else None, describe)
            if default is not None and setting.problem(default):
                self.error(f"the default: {setting.problem(default)}", spec, "default", f"{path}.default")
            if default is not None and required:
                self.error("a required setting has no default", spec, "default", f"{path}.default")
            result[name] = setting
        return result

    def check_text(self, text: str, known: set[str], mapping, key, path) -> None:
        """A text's ${placeholders} name the profile's settings."""
        for name in placeholders(text):
            if name not in known:
                close = difflib.get_close_matches(name, sorted(known), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.error(f"names ${{{name}}}, which is not a setting of this profile{hint}",
                           mapping, key, path)

    def read_checked(self, mapping, key: str, path: str, check) -> str | None:
        """A string value that `check` (a roslab.formats check) accepts; None: absent or reported."""
        value = mapping.get(key)
        if value is None:
            return None
        problem = check(value) if isinstance(value, str) else "must be a string"
        if problem:
            self.error(problem, mapping, key, f"{path}.{key}")
            return None
        return value

    def read_launch(self, mapping, path: str, side: Side, known: set[str]) -> None:
        """`launch: <package> <file>.launch.py` and `launch_arguments: {name: value}`, into `side`."""
        side.launch = self.read_checked(mapping, "launch", path, formats.launch) or side.launch
        arguments = mapping.get("launch_arguments")
        if arguments is None:
            return
        if not isinstance(arguments, dict):
            self.error("must be a mapping of argument name -> value", mapping, "launch_arguments",
                       f"{path}.launch_arguments")
            return
        for name, value in arguments.items():
            where = f"{path}.launch_arguments.{name}"
            problem = (formats.launch_argument_name(name) if isinstance(name, str) else "must be a name") or (
                launch_argument_template(value))
            if problem:
                self.error(problem, arguments, name, where)
                continue
            self.check_text(value, known, arguments, name, where)
            side.launch_arguments[name] = value

    def read_parts(self, mapping, path: str, known: set[str], side: Side, when_ok: bool) -> None:
        """The list and environment keys of a side or a `when` block, into `side`."""
        side.ros_packages += self.string_list(
            mapping, "ros_packages", f"{path}.ros_packages",
            lambda name: None if _ROS_PACKAGE.fullmatch(name) else
            f"{name!r} is not a ROS package name (lower-case letters, digits, _; or ${{gazebo}})")
        side.apt_packages += self.string_list(mapping, "apt_packages", f"{path}.apt_packages",
                                              formats.package_template)
        side.groups += self.string_list(mapping, "groups", f"{path}.groups", login_group_problem)
        side.checklist += self.string_list(mapping, "checklist", f"{path}.checklist", formats.single_line)
        for item in mapping.get("checklist") or []:
            if isinstance(item, str):
                self.check_text(item, known | set(CHECKLIST_PLACEHOLDERS), mapping, "checklist",
                                f"{path}.checklist")
        self.read_environment(mapping, path, known, side)
        self.read_devices(mapping, path, known, side)
        side.remove_apt_packages += self.string_list(mapping, "remove_apt_packages", f"{path}.remove_apt_packages",
                                                     formats.debian_package)
        kept = set(side.apt_packages) & set(side.remove_apt_packages)
        if kept:
            self.error(f"{', '.join(sorted(kept))} is both installed and removed", mapping,
                       "remove_apt_packages", f"{path}.remove_apt_packages")
        self.read_boot_config(mapping, path, side)
        self.read_services(mapping, path, known, side)
        self.read_cmake_args(mapping, path, side)
        self.read_build_dependencies(mapping, path, side)
        side.skip_packages += [name for name in self.string_list(
            mapping, "skip_packages", f"{path}.skip_packages",
            lambda name: None if _UNDERLAY_PACKAGE.fullmatch(name) else
            f"{name!r} is not a package name (lower-case letters, digits, _)")
            if _UNDERLAY_PACKAGE.fullmatch(name) and name not in side.skip_packages]
        if not when_ok and "when" in mapping:
            self.error("a when block cannot hold another", mapping, "when", f"{path}.when")

    def read_environment(self, mapping, path: str, known: set[str], side: Side) -> None:
        """`environment`: {VARIABLE: value} for the nodes, each value's placeholders checked, into `side`."""
        env = mapping.get("environment") or {}
        if not isinstance(env, dict):
            self.error("must be a mapping of VARIABLE -> value", mapping, "environment", f"{path}.environment")
            env = {}
        for name, value in env.items():
            where = f"{path}.environment.{name}"
            problem = variable_problem(name, value)
            if problem:
                self.error(problem, env, name, where)
                continue
            self.check_text(value, known, env, name, where)
            side.environment[name] = value

    def read_devices(self, mapping, path: str, known: set[str], side: Side) -> None:
        """`devices`: the devices the side opens, as data (roslab/profiles/devices.py), into `side`.
        `udev_rules` (rule text) is refused: roslab writes the rules from the devices."""
        if "udev_rules" in mapping:
            self.error("a profile declares its devices, not udev rule text: write each device under `devices:` "
                       "(kind, usb_ids, identify_by, symlink, group, mode; see roslab/profiles/devices.py) and "
                       "roslab writes its rule", mapping, "udev_rules", f"{path}.udev_rules")
        specs = mapping.get("devices") or []
        if not isinstance(specs, list):
            self.error("must be a list of devices (name, kind, ...)", mapping, "devices", f"{path}.devices")
            specs = []
        for index, spec in enumerate(specs, 1):
            here = f"{path}.devices[{index}]"
            device, problems = device_data.read_device(spec, known)
            for key, message in problems:
                self.error(message, spec if isinstance(spec, dict) and key in spec else mapping,
                           key if isinstance(spec, dict) and key in spec else "devices",
                           f"{here}.{key}" if key else here)
            if device is not None:
                side.devices.append(device)

    def read_cmake_args(self, mapping, path: str, side: Side) -> None:
        """`cmake_args`: {ROS package name: ["-DNAME=value", ...]} for the underlay's build."""
        value = mapping.get("cmake_args")
        if value is None:
            return
        where = f"{path}.cmake_args"
        if not isinstance(value, dict):
            self.error("must be a mapping of ROS package -> list of -DNAME=value", mapping, "cmake_args", where)
            return
        for package, args in value.items():
            if not isinstance(package, str) or not _UNDERLAY_PACKAGE.fullmatch(package):
                self.error(f"{package!r} is not a ROS package name (lower-case letters, digits, _)",
                           value, package, where)
                continue
            items = self.string_list(
                value, package, f"{where}.{package}",
                lambda arg: formats.install_location_problem(arg) or (None if _CMAKE_ARG.fullmatch(arg) else
                f"{arg[:80]!r} is not a CMake cache setting: -DNAME=value or -DNAME:TYPE=value "
                "(ASCII letters, digits and _ . , / + : @ % - in the value)"))
            if items and all(_CMAKE_ARG.fullmatch(arg) and not formats.install_location_problem(arg)
                             for arg in items):
                merged = side.cmake_args.setdefault(package, [])
                merged += [arg for arg in items if arg not in merged]

    def read_build_dependencies(self, mapping, path: str, side: Side) -> None:
        """`build_dependencies`: {package: [packages colcon must build before it]}."""
        value = mapping.get("build_dependencies")
        if value is None:
            return
        where = f"{path}.build_dependencies"
        if not isinstance(value, dict):
            self.error("must be a mapping of package -> list of the packages built before it", mapping,
                       "build_dependencies", where)
            return
        for package, needs in value.items():
            if not isinstance(package, str) or not _UNDERLAY_PACKAGE.fullmatch(package):
                self.error(f"{package!r} is not a package name (lower-case letters, digits, _)", value, package,
                           where)
                continue
            items = self.string_list(
                value, package, f"{where}.{package}",
                lambda name: None if _UNDERLAY_PACKAGE.fullmatch(name) and name != package else
                f"{name!r} is not another package's name (lower-case letters, digits, _)")
            if items and all(_UNDERLAY_PACKAGE.fullmatch(name) and name != package for name in items):
                merged = side.build_dependencies.setdefault(package, [])
                merged += [name for name in items if name not in merged]

    def read_boot_config(self, mapping, path: str, side: Side) -> None:
        """`boot_config`: config.txt lines (a marked block) and cmdline.txt words to remove."""
        value = mapping.get("boot_config")
        if value is None:
            return
        where = f"{path}.boot_config"
        if not isinstance(value, dict):
            self.error(f"must be a mapping ({', '.join(BOOT_CONFIG_KEYS)})", mapping, "boot_config", where)
            return
        self.unknown_keys(value, BOOT_CONFIG_KEYS, where)
        lines = self.string_list(
            value, "config_txt", f"{where}.config_txt",
            config_line_problem)
        added = self.string_list(value, "cmdline_add", f"{where}.cmdline_add", cmdline_add_problem)
        words = self.string_list(
            value, "cmdline_remove", f"{where}.cmdline_remove",
            lambda word: None if _CMDLINE_WORD.fullmatch(word) else
            f"{word!r} is not one word of cmdline.txt (ASCII letters, digits, _ . , : = / + -)")
        for word in set(added) & set(words):
            self.error(f"{word!r} is both added to and removed from cmdline.txt", value, "cmdline_add",
                       f"{where}.cmdline_add")
        for key, items in (("config_txt", lines), ("cmdline_add", added), ("cmdline_remove", words)):
            known_items = side.boot_config.setdefault(key, [])
            known_items += [item for item in items if item not in known_items]
        side.boot_config = {key: items for key, items in side.boot_config.items() if items}

    def read_services(self, mapping, path: str, known: set[str], side: Side) -> None:
        """`services`: units the profile runs besides the nodes' service (the rover's, an agent)."""
        value = mapping.get("services")
        if value is None:
            return
        where = f"{path}.services"
        if not isinstance(value, list):
            self.error("must be a list of {name, description, command, environment, enabled_if}", mapping,
                       "services", where)
            return
        for index, spec in enumerate(value, 1):
            here = f"{where}[{index}]"
            if not isinstance(spec, dict):
                self.error("each service is a mapping (name, description, command, environment, enabled_if)",
                           mapping, "services", here)
                continue
            self.unknown_keys(spec, SERVICE_KEYS, here)
            service = self.read_service(spec, here, known)
            if service is None:
                continue
            if any(other["name"] == service["name"] for other in side.services):
                self.error(f"a second service named {service['name']!r}", spec, "name", f"{here}.name")
                continue
            side.services.append(service)

    def read_service(self, spec: dict, here: str, known: set[str]) -> dict | None:
        """One service: {name, description, command, environment, enabled_if}, or None (reported)."""
        name = spec.get("name")
        if not isinstance(name, str) or not _SERVICE_NAME.fullmatch(name):
            self.error("a service's name is lower-case letters, digits, _ and - (the unit is <name>.service)",
                       spec, "name", f"{here}.name")
            return None
        if name in RESERVED_SERVICES or name.startswith(RESERVED_SERVICE_PREFIXES):
            self.error(f"{name!r} is a unit roslab or the system owns: give the service a name of its own",
                       spec, "name", f"{here}.name")
            return None
        problems_before = self.problems
        command = spec.get("command")
        problem = formats.ascii_text(command) if isinstance(command, str) and command.strip() else \
            "must be a command line (one line of text)"
        problem = problem or (formats.single_line(command) if isinstance(command, str) else None)
        if problem or not isinstance(command, str):  # a command that is not text has its problem
            self.error(problem or "must be a command line (one line of text)", spec, "command", f"{here}.command")
        else:
            self.check_text(command, known | set(COMMAND_PLACEHOLDERS), spec, "command", f"{here}.command")
        description = spec.get("description") or ""
        if not isinstance(description, str) or (description and formats.single_line(description)):
            self.error("must be one line of text", spec, "description", f"{here}.description")
        else:
            self.check_text(description, known, spec, "description", f"{here}.description")
        env = self.read_service_environment(spec, here, known)
        condition = self.read_enabled_if(spec, here, known)
        if self.problems != problems_before:
            return None
        return {"name": name, "description": description or "", "command": command,
                "environment": env, "enabled_if": condition}

    def read_service_environment(self, spec: dict, here: str, known: set[str]) -> dict:
        env = spec.get("environment") or {}
        if not isinstance(env, dict):
            self.error("must be a mapping of VARIABLE -> value", spec, "environment", f"{here}.environment")
            return {}
        for variable, text in env.items():
            problem = variable_problem(variable, text, service=True)
            if problem:
                self.error(problem, env, variable, f"{here}.environment.{variable}")
            else:
                self.check_text(text, known | set(SERVICE_ENVIRONMENT_PLACEHOLDERS), env, variable,
                                f"{here}.environment.{variable}")
        return dict(env)

    def read_enabled_if(self, spec: dict, here: str, known: set[str]) -> dict:
        condition = spec.get("enabled_if") or {}
        if not isinstance(condition, dict) or not all(
                isinstance(wanted, str) or (isinstance(wanted, list) and all(isinstance(w, str) for w in wanted))
                for wanted in condition.values()):
            self.error("must be a mapping of setting -> value (or list of values)", spec, "enabled_if",
                       f"{here}.enabled_if")
            return {}
        for setting in condition:
            if setting not in known:
                self.error(f"tests {setting!r}, which is not a setting of this profile", condition, setting,
                           f"{here}.enabled_if")
        return dict(condition)

    def read_os_tweaks(self, mapping, side: str) -> dict:
        """A side's `os_tweaks`: units to mask, a swap file and the memory below which it is made."""
        value = mapping.get("os_tweaks")
        path = f"{side}.os_tweaks"
        if value is None:
            return {}
        if not isinstance(value, dict):
            self.error(f"must be a mapping ({', '.join(OS_TWEAK_KEYS)})", mapping, "os_tweaks", path)
            return {}
        self.unknown_keys(value, OS_TWEAK_KEYS, path)
        tweaks: dict = {}
        units = self.string_list(value, "mask_units", f"{path}.mask_units", maskable_unit_problem)
        if units and not any(maskable_unit_problem(unit) for unit in units):
            tweaks["mask_units"] = units
        for key, low, high in (("swap_mb", *SWAP_MB_RANGE), ("swap_if_memory_mb_at_most", 256, 65536)):
            number = value.get(key)
            if number is None:
                continue
            if isinstance(number, bool) or not isinstance(number, int) or not low <= number <= high:
                self.error(f"must be a whole number of MiB from {low} to {high}", value, key, f"{path}.{key}")
                continue
            tweaks[key] = number
        return tweaks

    def read_sources(self, mapping, side: str) -> list[tuple[Path, str]]:
        """The side's .repos files (checked to exist where they are relative to; their content
        is read by the roster loader, for the hosts that use the profile)."""
        from roslab.sources.repos import name_problem

        names = self.string_list(mapping, "sources", f"{side}.sources")
        if self.base_dir is None:
            return [(Path("."), name) for name in names]
        result = []
        for name in names:
            problem = name_problem(name, self.base_dir)
            if problem:
                self.error(problem, mapping, "sources", f"{side}.sources")
            else:
                result.append((self.base_dir, name))
        return result
    def read_python_packages(self, mapping, side: str) -> list[str]:
        """A side's `python_packages`: each pinned `name==version`, each project named once."""
        path = f"{side}.python_packages"
        packages = self.string_list(mapping, "python_packages", path, formats.pinned_requirement)
        if len(packages) > settings.MAX_ITEMS:
            self.error(f"has {len(packages)} entries; at most {settings.MAX_ITEMS} are allowed",
                       mapping, "python_packages", path)
            return []
        result: dict[str, str] = {}
        for item in packages:
            if formats.pinned_requirement(item):
                continue  # reported by string_list
            name = formats.requirement_name(item)
            if name in result:
                self.error(f"names {name!r} twice ({result[name]}, {item}): pin one version",
                           mapping, "python_packages", path)
                continue
            result[name] = canonical_requirement(item)
        return list(result.values())

    def read_side(self, mapping, name: str, known: set[str]) -> Side | None:
        value = mapping.get(name)
        if value is None:
            return None
        if not isinstance(value, dict):
            self.error(f"must be a mapping of what the {name} gets", mapping, name, name)
            return None
        self.unknown_keys(value, SIDE_KEYS, name)
        side = Side()
        self.read_parts(value, name, known, side, when_ok=True)
        self.read_launch(value, name, side, known)
        side.variant = self.read_checked(value, "variant", name, formats.ros_variant) or side.variant
        side.os_tweaks = self.read_os_tweaks(value, name)
        side.sources = self.read_sources(value, name)
        side.python_packages = self.read_python_packages(value, name)
        venv = self.read_checked(value, "python_venv", name, formats.venv_dir)
        if venv is not None:
            side.python_venv = venv[2:] if venv.startswith("~/") else venv.rstrip("/")
        boards = value.get("boards")
        if boards is not None:
            if not isinstance(boards, list) or not boards or not all(b in BOARDS for b in boards):
                self.error(f"must be a list of boards ({', '.join(BOARDS)})", value, "boards", f"{name}.boards")
            else:
                side.boards = tuple(boards)
        blocks = value.get("when") or []
        if not isinstance(blocks, list):
            self.error("must be a list of {if: {setting: value}, ...}", value, "when", f"{name}.when")
            blocks = []
        for index, block in enumerate(blocks, 1):
            path = f"{name}.when[{index}]"
            if not isinstance(block, dict) or not isinstance(block.get("if"), dict):
                self.error("each when block is a mapping with 'if' (setting: value)", value, "when", path)
                continue
            self.unknown_keys(block, WHEN_KEYS, path)
            for setting, wanted in block["if"].items():
                if setting not in known and setting not in BUILTIN_CONDITIONS:
                    close = difflib.get_close_matches(str(setting), sorted(known), n=1)
                    hint = f" (did you mean {close[0]!r}?)" if close else ""
                    self.error(f"tests {setting!r}, which is not a setting of this profile{hint}",
                               block["if"], setting, f"{path}.if")
                elif not (wanted is None or isinstance(wanted, str) or
                          (isinstance(wanted, list) and all(isinstance(w, str) for w in wanted))):
                    self.error("a condition is a value, a list of values, '*' (set) or null (unset)",
                               block["if"], setting, f"{path}.if")
            part = Side()
            self.read_parts(block, path, known, part, when_ok=False)
            part.sources = self.read_sources(block, path)
            self.read_launch(block, path, part, known)  # a setting may choose the launch (a model's own)
            side.when.append({"if": dict(block["if"]), "side": part})
        return side


def merged_cmake_args(parts: list[dict[str, list[str]]]) -> dict[str, list[str]]:
    """Each package's CMake settings from every part, in order; a later `-DNAME=` replaces
    an earlier one for the same NAME."""
    merged: dict[str, dict[str, str]] = {}
    for part in parts:
        for package, args in part.items():
            settings_of = merged.setdefault(package, {})
            for arg in args:
                settings_of[arg.split("=", 1)[0].split(":", 1)[0]] = arg
    return {package: list(args.values()) for package, args in merged.items() if args}


def merged_build_dependencies(parts: list[dict[str, list[str]]]) -> dict[str, list[str]]:
    """Each package's extra build dependencies from every part, in order, once each."""
    merged: dict[str, list[str]] = {}
    for part in parts:
        for package, needs in part.items():
            merged[package] = list(dict.fromkeys([*merged.get(package, []), *needs]))
    return {package: needs for package, needs in merged.items() if needs}


def canonical_requirement(requirement: str) -> str:
    """`name==version` without spaces (a checked requirement)."""
    name, _, version = requirement.partition("==")
    return f"{name.strip()}=={version.strip()}"


def merged_requirements(base: list[str], own: list[str]) -> list[str]:
    """`base`'s requirements with `own`'s added; a project both name takes `own`'s version."""
    merged = {formats.requirement_name(item): item for item in base}
    merged.update({formats.requirement_name(item): item for item in own})
    return list(merged.values())


def variable_problem(name, value, service: bool = False) -> str | None:
    """Why `name: value` cannot be an environment variable roslab writes, or None.

    `service`: a profile's own service may name the middleware it runs on (the micro-ROS
    agent is built on Fast DDS, whatever the class's middleware): one of MIDDLEWARES."""
    if service and name == "RMW_IMPLEMENTATION":
        if value not in MIDDLEWARES:
            return f"RMW_IMPLEMENTATION of a service is one of {', '.join(MIDDLEWARES)}, not {value!r}"
        return None
    return formats.variable(name, value)


def login_group_problem(group: str) -> str | None:
    """Why a profile may not put the login user (the students' account) in `group`, or None:
    hardware-access groups only (devices.LOGIN_GROUPS); sudo, adm, disk, shadow, docker, lxd
    and the like would make every student root."""
    problem = formats.linux_user(group)
    if problem:
        return problem
    if group not in device_data.LOGIN_GROUPS:
        return (f"{group!r} is not a hardware-access group a profile may give the login user "
                f"({', '.join(device_data.LOGIN_GROUPS)})")
    return None


def maskable_unit_problem(unit: str) -> str | None:
    """Why an OS tweak may not mask `unit`, or None (MASKABLE_UNITS)."""
    if unit in MASKABLE_UNITS:
        return None
    return (f"{unit!r} is not a unit an OS tweak may mask ({', '.join(MASKABLE_UNITS)}): never what "
            "reaching the host needs (ssh, systemd-*, dbus, the network, getty, targets)")


def pattern_problem(pattern) -> str | None:
    """Why `pattern` cannot be a setting's pattern, or None: a string RE2 compiles, bounded."""
    if not isinstance(pattern, str):
        return f"must be a regular expression (a string), not {pattern!r}"
    if len(pattern) > MAX_SETTING_PATTERN or not pattern.isascii() or formats.single_line(pattern):
        return f"must be one line of ASCII, at most {MAX_SETTING_PATTERN} characters"
    try:
        setting_pattern(pattern)
    except re2.error as exc:
        reason = exc.args[0].decode("utf-8", "replace") if exc.args and isinstance(exc.args[0], bytes) else exc
        return (f"is not a regular expression roslab runs ({reason}): RE2's syntax, which matches in "
                "linear time (no backreferences or lookaround)")
    return None


_patterns: dict[str, object] = {}


def setting_pattern(pattern: str):
    """`pattern` compiled by RE2 (re2.error if it does not compile), kept once compiled."""
    if pattern not in _patterns:
        _patterns[pattern] = re2.compile(pattern, options=_RE2_OPTIONS)
    return _patterns[pattern]


def read_profile(mapping, report: Report, prefix: str, source: str, base: Profile | None = None,
                 base_dir: Path | None = None) -> Profile | None:
    """A checked Profile from a mapping (extending `base` if given), or None with problems reported.

    `base_dir`: the folder its `sources:` (.repos files) are relative to."""
    reader = ProfileReader(report, prefix, base_dir)
    reader.unknown_keys(mapping, TOP_KEYS, "")
    name = mapping.get("profile", prefix.rsplit(".", 1)[-1])
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        reader.error("a profile's name is lower-case letters, digits and _", mapping, "profile", "profile")
        return None
    settings = dict(base.settings) if base else {}
    settings.update(reader.read_settings(mapping))
    known = set(settings)
    distros = _read_distros(reader, mapping, base)
    boards, middlewares, discovery = _read_placement(reader, mapping, base)
    topic, message_type, verify_if, verify_source, verify_publisher = _read_verify(reader, mapping, base, known)
    tools, dds_only = _read_tools(reader, mapping, base)
    build_memory = _read_build_memory(reader, mapping, base)
    robot_base = _read_base(reader, mapping, base)
    sides = _read_sides(reader, mapping, base, known)
    description = mapping.get("description", base.description if base else "")
    if not reader.ok:
        return None
    return Profile(name, str(description or ""), tuple(distros), tuple(boards), tuple(middlewares), discovery,
                   topic, message_type, dict(verify_if), settings, sides, source, line_of(mapping),
                   verify_source=verify_source, verify_publisher=verify_publisher, tools=tuple(tools),
                   dds_only_packages=dict(dds_only), underlay_build_memory_mb=build_memory, base=robot_base)


def _read_base(reader: ProfileReader, mapping, base: Profile | None) -> dict | None:
    """`base:` the robot's base computer on its own link (roslab/profiles/robot_base.py), or None."""
    from roslab.profiles.robot_base import BASE_KEYS, base_problems

    value = mapping.get("base", base.base if base else None)
    if value is None:
        return None
    problems = base_problems(value)
    for key, problem in problems:
        reader.error(problem, value if key and isinstance(value, dict) else mapping, key or "base",
                     f"base.{key}" if key else "base")
    if problems:
        return None
    return {key: (dict(value[key]) if isinstance(value.get(key), dict) else value.get(key, {}))
            for key in BASE_KEYS}


def _read_distros(reader: ProfileReader, mapping, base: Profile | None) -> list[str]:
    """`distros:` the distros it supports, or `all` (every release record's, now or later)."""
    distros = mapping.get("distros", list(base.declared_distros) if base else None)
    if distros in (ALL_DISTROS, [ALL_DISTROS]):
        return [ALL_DISTROS]
    if not isinstance(distros, list) or not distros or not all(d in DISTRO_RELEASES for d in distros):
        reader.error(f"must list the distros the profile supports (of {', '.join(sorted(DISTRO_RELEASES))}), "
                     f"or be {ALL_DISTROS!r}", mapping, "distros", "distros")
        return []
    return distros


def _read_placement(reader: ProfileReader, mapping, base: Profile | None) -> tuple[list, list, str | None]:
    """(`boards:`, `middlewares:`, `discovery:`): where the profile runs."""
    boards = mapping.get("boards", list(base.boards) if base else list(BOARDS))
    if not isinstance(boards, list) or not all(b in BOARDS for b in boards):
        reader.error(f"must be a list of boards ({', '.join(BOARDS)})", mapping, "boards", "boards")
        boards = list(BOARDS)
    middlewares = mapping.get("middlewares", list(base.middlewares) if base else list(MIDDLEWARES))
    if not isinstance(middlewares, list) or not middlewares or not all(m in MIDDLEWARES for m in middlewares):
        reader.error(f"must be a list of middlewares ({', '.join(MIDDLEWARES)})", mapping, "middlewares",
                     "middlewares")
        middlewares = list(MIDDLEWARES)
    discovery = mapping.get("discovery", base.discovery if base else None)
    if discovery is not None and discovery not in DISCOVERY:
        reader.error(f"must be {', '.join(DISCOVERY)} or absent", mapping, "discovery", "discovery")
    return boards, middlewares, discovery


def _read_verify(reader: ProfileReader, mapping, base: Profile | None, known: set[str]) -> tuple:
    """(`verify_topic:`, `verify_type:`, `verify_if:`, `verify_source:`, `verify_publisher:`): what
    `roslab verify` hears, and from which node."""
    topic = mapping.get("verify_topic", base.verify_topic if base else None)
    if topic is not None and (not isinstance(topic, str) or formats.ros_topic(topic)):
        reader.error("must be a ROS topic name (or null: nothing to verify)", mapping, "verify_topic",
                     "verify_topic")
    message_type = mapping.get("verify_type", base.verify_type if base else Profile.verify_type)
    if not isinstance(message_type, str) or formats.ros_message_type(message_type):
        reader.error("must be a ROS message type (like sensor_msgs/msg/LaserScan)", mapping, "verify_type",
                     "verify_type")
    verify_if = mapping.get("verify_if", dict(base.verify_if) if base else {})
    if not isinstance(verify_if, dict) or not all(isinstance(v, str) for v in verify_if.values()):
        reader.error("must be a mapping of setting -> value", mapping, "verify_if", "verify_if")
        verify_if = {}
    for setting in verify_if:
        if setting not in known:
            reader.error(f"tests {setting!r}, which is not a setting of this profile", verify_if, setting,
                         "verify_if")
    verify_source = mapping.get("verify_source", base.verify_source if base else "")
    if not isinstance(verify_source, str) or (verify_source and formats.single_line(verify_source)):
        reader.error("must be one line of text", mapping, "verify_source", "verify_source")
        verify_source = ""
    elif verify_source:
        reader.check_text(verify_source, known, mapping, "verify_source", "verify_source")
    verify_publisher = mapping.get("verify_publisher", base.verify_publisher if base else "")
    if not isinstance(verify_publisher, str) or (
            verify_publisher and not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", PLACEHOLDER.sub("x", verify_publisher))):
        reader.error("must be a ROS node name (letters, digits and _; ${settings} and ${team} filled in)", mapping,
                     "verify_publisher", "verify_publisher")
        verify_publisher = ""
    elif verify_publisher:
        reader.check_text(verify_publisher, known | {"team"}, mapping, "verify_publisher", "verify_publisher")
    return topic, message_type, verify_if, verify_source, verify_publisher


def _read_tools(reader: ProfileReader, mapping, base: Profile | None) -> tuple[list[str], dict[str, str]]:
    """(`tools:`, `dds_only_packages:`): the commands the robot brings, its DDS-only packages."""
    tools = mapping.get("tools", list(base.tools) if base else [])
    problems = [tool_problem(tool) for tool in tools] if isinstance(tools, list) else ["must be a list"]
    if any(problems):
        reader.error(next(problem for problem in problems if problem), mapping, "tools", "tools")
        tools = []
    dds_only = mapping.get("dds_only_packages", dict(base.dds_only_packages) if base else {})
    if not isinstance(dds_only, dict) or not all(
            isinstance(package, str) and _UNDERLAY_PACKAGE.fullmatch(package) and isinstance(what, str)
            and not formats.single_line(what) and len(what) <= 80 for package, what in dds_only.items()):
        reader.error("must map ROS package names to what they are, in a few words", mapping,
                     "dds_only_packages", "dds_only_packages")
        dds_only = {}
    return tools, dds_only


def _read_build_memory(reader: ProfileReader, mapping, base: Profile | None) -> int | None:
    """`underlay_build_memory_mb`: the memory a host needs to build the underlay (None: any host)."""
    build_memory = mapping.get("underlay_build_memory_mb", base.underlay_build_memory_mb if base else None)
    low, high = UNDERLAY_BUILD_MEMORY_MB
    if build_memory is not None and (isinstance(build_memory, bool) or not isinstance(build_memory, int)
                                     or not low <= build_memory <= high):
        reader.error(f"must be the memory in MiB a host needs to build the underlay ({low} to {high}), "
                     f"not {build_memory!r}", mapping, "underlay_build_memory_mb", "underlay_build_memory_mb")
        return None
    return build_memory


def _read_sides(reader: ProfileReader, mapping, base: Profile | None, known: set[str]) -> dict[str, Side]:
    """`main:` and `robot:`, each extending the base profile's side of its name."""
    sides: dict[str, Side] = {}
    for side_name in SIDES:
        own = reader.read_side(mapping, side_name, known)
        inherited = base.sides.get(side_name) if base else None
        if own and inherited:
            own = merged_side(inherited, own)
        side = own or inherited
        if side:
            sides[side_name] = side
            tweaks = side.os_tweaks
            if "swap_if_memory_mb_at_most" in tweaks and "swap_mb" not in tweaks:
                reader.error("names a memory limit for a swap file but no swap_mb",
                             mapping.get(side_name) or mapping, "os_tweaks", f"{side_name}.os_tweaks")
    if not sides:
        reader.error("a profile needs a main or a robot side", mapping, None, "")
    return sides


def merged_side(base: Side, own: Side) -> Side:
    """A side extending `base`: lists appended (once), environment merged, launch replaced if given."""
    def union(a, b):
        return list(dict.fromkeys([*a, *b]))
    return Side(
        ros_packages=union(base.ros_packages, own.ros_packages),
        apt_packages=union(base.apt_packages, own.apt_packages),
        environment={**base.environment, **own.environment},
        groups=union(base.groups, own.groups),
        devices=[*base.devices, *own.devices],
        launch=own.launch or base.launch,
        launch_arguments={**base.launch_arguments, **own.launch_arguments},
        variant=own.variant or base.variant,
        checklist=[*base.checklist, *own.checklist],
        os_tweaks={**base.os_tweaks, **own.os_tweaks},
        sources=list(dict.fromkeys([*base.sources, *own.sources])),
        cmake_args=merged_cmake_args([base.cmake_args, own.cmake_args]),
        build_dependencies=merged_build_dependencies([base.build_dependencies, own.build_dependencies]),
        skip_packages=union(base.skip_packages, own.skip_packages),
        when=[*base.when, *own.when],
        python_packages=merged_requirements(base.python_packages, own.python_packages),
        python_venv=own.python_venv or base.python_venv,
        boards=own.boards or base.boards,
        remove_apt_packages=union(base.remove_apt_packages, own.remove_apt_packages),
        boot_config={key: union(base.boot_config.get(key, []), own.boot_config.get(key, []))
                     for key in BOOT_CONFIG_KEYS if base.boot_config.get(key) or own.boot_config.get(key)},
        services=[*(s for s in base.services if s["name"] not in {o["name"] for o in own.services}),
                  *own.services],
    )
