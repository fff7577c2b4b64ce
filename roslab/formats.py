"""Format checks for roster values: each says why a value is not of its format, or None.

A check runs where its setting is declared (`roslab.settings`), before any host is
touched, and matches the whole value (`fullmatch`): a value that passes holds only
what its destination can carry without changing meaning. Writing it is then a matter
of the destination's escaping (`roslab.quoting`), never of filtering.

Every check takes the value (already of the declared type) and a `Context`; checks of
controller-side paths resolve them against the roster's directory.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
import socket
import tempfile
import unicodedata
from collections.abc import Callable
from typing import Any, Protocol, TypeVar
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlsplit

from roslab.ros import distro as distros
from roslab.controller_files import MAX_SMALL_FILE_BYTES, UnreadableFile, read_regular_file

C = TypeVar("C")


class Check(Protocol):
    """A format check: the value (of its setting's declared type) and a Context in; the problem,
    or None when it passes. Some carry what the docs say they allow (`describe`)."""

    def __call__(self, value: Any, context: Context | None = None, /) -> str | None: ...


def describe(check: C, **attributes: object) -> C:
    """`check` with `attributes` set on it, read with getattr where present (roslab.settings):
    `allowed` (what the settings table says a value may be), `choices`, `whole`."""
    for name, value in attributes.items():
        setattr(check, name, value)
    return check


# The classroom's own state beside the roster (roslab.ssh.identity, roslab.network.state).
STATE_DIR = ".roslab-state"


@dataclass(frozen=True)
class Context:
    """What a check may know besides the value: where the roster is."""

    roster_dir: Path = Path(".")
    roster_file: Path | None = None

    def controller_path(self, value: str) -> Path:
        """A controller-side path: `~` expanded, relative to the roster's directory."""
        return self.roster_dir / Path(value).expanduser()

    @property
    def state_dir(self) -> Path:
        return self.roster_dir / STATE_DIR


# --- building blocks ------------------------------------------------------------------

# Characters that end or break a line in some reader: C0/C1 controls, DEL, and
# Unicode's line and paragraph separators (Python's splitlines() splits on them too).
def _breaks_lines(char: str) -> bool:
    return unicodedata.category(char) in ("Cc", "Zl", "Zp")


def single_line(value: str, _context: Context | None = None) -> str | None:
    """One line of text: no newline, no control character, not empty."""
    if value == "":
        return "must not be empty"
    if value.isprintable():  # no control, separator or surrogate in it (the common case, at C speed)
        return None
    for char in value:
        if _breaks_lines(char):
            return (f"must be a single line of text without control characters "
                    f"(it holds {char!r})")
        if unicodedata.category(char) == "Cs":  # a "\ud800" escape: no file can hold it as UTF-8
            return f"holds a lone surrogate (U+{ord(char):04X}), which is not a character"
    return None


def ascii_text(value: str, _context: Context | None = None) -> str | None:
    """Only ASCII characters: a format that means ASCII says so.

    Python's regular expressions match Unicode by default: with IGNORECASE, `[a-z]`
    also matches the dotless ı, the long s ſ and the Kelvin sign K, and `\\d`/`\\w`
    match every script's digits and letters. Each ASCII format checks this first.
    """
    for char in value:
        if not char.isascii():
            return (f"{value!r} holds {char!r} (U+{ord(char):04X}), which is not an ASCII "
                    "character: type it with plain ASCII letters and digits")
    return None


def pattern(regex: str, description: str) -> Check:
    """A check that the whole value is ASCII and matches `regex` (compiled with re.ASCII, at its
    first use: every run imports the formats, few use each)."""

    def check(value: str, context: Context | None = None) -> str | None:
        problem = single_line(value) or ascii_text(value)
        if problem:
            return problem
        if not re.fullmatch(regex, value, re.ASCII):  # re's own cache keeps it compiled
            return f"{value!r} is not {description}"
        return None

    check.__doc__ = f"The whole value is {description}."
    describe(check, allowed=description)
    return check


# ISO 3166-1 alpha-2 country codes (as tzdata's iso3166.tab lists them), the codes a WiFi
# regulatory domain is named by (wireless-regdb), plus "00", the world domain.
COUNTRY_CODES = frozenset("""
    AD AE AF AG AI AL AM AO AQ AR AS AT AU AW AX AZ BA BB BD BE BF BG BH BI BJ BL BM BN BO BQ
    BR BS BT BV BW BY BZ CA CC CD CF CG CH CI CK CL CM CN CO CR CU CV CW CX CY CZ DE DJ DK DM
    DO DZ EC EE EG EH ER ES ET FI FJ FK FM FO FR GA GB GD GE GF GG GH GI GL GM GN GP GQ GR GS
    GT GU GW GY HK HM HN HR HT HU ID IE IL IM IN IO IQ IR IS IT JE JM JO JP KE KG KH KI KM KN
    KP KR KW KY KZ LA LB LC LI LK LR LS LT LU LV LY MA MC MD ME MF MG MH MK ML MM MN MO MP MQ
    MR MS MT MU MV MW MX MY MZ NA NC NE NF NG NI NL NO NP NR NU NZ OM PA PE PF PG PH PK PL PM
    PN PR PS PT PW PY QA RE RO RS RU RW SA SB SC SD SE SG SH SI SJ SK SL SM SN SO SR SS ST SV
    SX SY SZ TC TD TF TG TH TJ TK TL TM TN TO TR TT TV TW TZ UA UG UM US UY UZ VA VC VE VG VI
    VN VU WF WS YE YT ZA ZM ZW
""".split()) | {"00"}


def country_code(value: str, context: Context | None = None) -> str | None:
    """An ISO 3166-1 alpha-2 country code in capitals (like DE, GB, US), or 00 (the world)."""
    problem = single_line(value)
    if problem:
        return problem
    if value not in COUNTRY_CODES:
        hint = f" (did you mean {value.upper()!r}?)" if value.isascii() and value.upper() in COUNTRY_CODES else ""
        return f"{value!r} is not a country code like DE, GB or US{hint}"
    return None


describe(country_code, allowed="a two-letter country code in capitals (ISO 3166-1), like DE; 00: the world")


def choice(*choices) -> Check:
    def check(value, context: Context | None = None) -> str | None:
        if value not in choices:
            return f"{value!r} is not one of: {', '.join(map(str, choices))}"
        return None

    describe(check, choices=choices)
    return check


def int_range(low: int, high: int, unit: str = "") -> Check:
    def check(value: int, context: Context | None = None) -> str | None:
        if not low <= value <= high:
            return f"{value}{unit} is outside {low} to {high}{unit}"
        return None

    describe(check, allowed=f"{low} to {high}{unit}")
    return check


# --- names ------------------------------------------------------------------------------

# Debian policy 5.6.1: lower case letters, digits, + - . ; at least two characters,
# starting with an alphanumeric. A leading `-` (an apt option) cannot pass.
debian_package = pattern(r"[a-z0-9][a-z0-9+.-]+", "a Debian package name (like ros-jazzy-turtlesim)")
# A suite suffix: noble-<suffix>.
apt_suite_suffix = pattern(r"[a-z0-9]+", "a suite suffix of lower-case letters and digits (like updates)")
# useradd's default NAME_REGEX, which Ubuntu keeps.
linux_user = pattern(r"[a-z_][a-z0-9_-]{0,31}", "a Linux user name (like ubuntu)")
# A secret's name in the secrets file.
secret_name = pattern(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}", "a secret name (letters, digits, _ . -)")
# REP 144 package names; launch files by file name only (no path). `ros2 launch` takes a file
# whose name ends in launch.py or a frontend's extension (Jazzy's ros2launch/api/api.py,
# is_launch_file); packages name them <name>.launch.<ext> or <name>_launch.<ext> (rplidar_ros's
# rplidar_c1_launch.py, osr_bringup's osr_launch.py): those two forms, for py, xml and yaml.
ros_package = pattern(r"[a-z][a-z0-9_]*", "a ROS package name")
launch_file_name = pattern(r"[A-Za-z0-9_][A-Za-z0-9_.-]*[._]launch\.(py|xml|yaml)",
                           "a launch file name (like main.launch.py or rplidar_c1_launch.py)")
# A launch argument (`ros2 launch PKG FILE name:=value`): a name as DeclareLaunchArgument's are
# written, a value of one shell word with no `=` (so never a second `name:=`); ros2launch refuses
# an empty value (`name:=`), and so does roslab.
launch_argument_name = pattern(r"[A-Za-z_][A-Za-z0-9_]{0,63}", "a launch argument name (like serial_port)")
_LAUNCH_ARGUMENT_VALUE = re.compile(r"[A-Za-z0-9_@+:,./-]{1,200}", re.ASCII)


def launch_argument_value(value: str, context: Context | None = None) -> str | None:
    """A launch argument's value: 1 to 200 of ASCII letters, digits and _ @ + : , . / -."""
    if not isinstance(value, str):
        return "must be a string"
    if ":=" in value or "=" in value:
        return f"{value!r} holds '=': a value cannot carry another launch argument (name:=value)"
    if not _LAUNCH_ARGUMENT_VALUE.fullmatch(value):
        return (f"{value!r} is not a launch argument value (1 to 200 of ASCII letters, digits and "
                "_ @ + : , . / -; no spaces, quotes or shell characters)")
    return None
# ROS 2 topic names (absolute or relative), no substitutions.
ros_topic = pattern(r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*", "a ROS topic name (like /chatter)")
ros_message_type = pattern(r"[a-z][a-z0-9_]*/msg/[A-Z][A-Za-z0-9]*",
                           "a ROS message type (like sensor_msgs/msg/LaserScan)")
version = pattern(r"[0-9]+(\.[0-9]+){1,3}", "a version like 1.2.0")
sha256_hex = pattern(r"[0-9a-f]{64}", "a sha256 (64 lower-case hex digits)")


def ros_snapshot(value: str, context: Context | None = None) -> str | None:
    """A snapshot of the ROS archive as snapshots.ros.org names it: a sync's date or `final`."""
    if not isinstance(value, str):
        return "must be a string"
    if value == "final":
        return None
    try:  # the round trip refuses what fromisoformat also takes (20260807, 2026-W32-5)
        if datetime.date.fromisoformat(value).isoformat() == value:
            return None
    except ValueError:
        pass
    return (f"{value!r} is not a snapshot name: a sync's date (YYYY-MM-DD, as snapshots.ros.org "
            "lists them) or final")


describe(ros_snapshot, allowed="YYYY-MM-DD or final")
interface_name = pattern(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,14}", "a network interface name (like eth0)")
# A colcon argument: option or value, no shell or line syntax needed.
colcon_argument = pattern(r"[A-Za-z0-9_@%+=:,./-]+", "a colcon argument (letters, digits, _ @ % + = : , . / -)")
# The whole list is then checked against the allow-list (colcon_arguments, below).

# The `colcon build` options a class needs, each with what its value must be (None: a flag). A
# path option (--base-paths, --install-base, --build-base, --log-base, --merge-install...) is
# not among them: roslab decides where colcon reads, builds, installs and logs.
_CMAKE_DEFINE = re.compile(r"-D([A-Za-z_][A-Za-z0-9_]{0,63})(:(BOOL|STRING))?=[A-Za-z0-9_.,+:@%-]{0,200}", re.ASCII)
# CMake variables that say where a build installs (or looks for what it installed).
_INSTALL_LOCATION = re.compile(r"CMAKE_INSTALL_.*|CMAKE_STAGING_PREFIX|CMAKE_SYSROOT|CMAKE_FIND_ROOT_PATH|"
                               r"CMAKE_PREFIX_PATH|CMAKE_.*_OUTPUT_DIRECTORY|.*_DIR|DESTDIR", re.ASCII)
MAX_PARALLEL_WORKERS = 64
COLCON_OPTIONS = {
    "--executor": ("sequential", "parallel"),
    "--parallel-workers": "count",
    "--event-handlers": "handlers",
    "--cmake-args": "defines",
    "--symlink-install": None,
    "--continue-on-error": None,
    "--cmake-force-configure": None,
    "--cmake-clean-cache": None,
}
_EVENT_HANDLER = re.compile(r"[a-z_]{1,40}[+-]", re.ASCII)


def _colcon_value_problem(option: str, value: str) -> str | None:
    wanted = COLCON_OPTIONS[option]
    if isinstance(wanted, tuple):
        return None if value in wanted else f"{option} takes {' or '.join(wanted)}, not {value!r}"
    if wanted == "count":
        if value.isascii() and value.isdigit() and 1 <= int(value) <= MAX_PARALLEL_WORKERS:
            return None
        return f"{option} takes a number from 1 to {MAX_PARALLEL_WORKERS}, not {value[:20]!r}"
    if wanted == "handlers":
        return None if _EVENT_HANDLER.fullmatch(value) else \
            f"{option} takes event handler names ending in + or - (console_direct+), not {value[:40]!r}"
    problem = install_location_problem(value)
    if problem:
        return problem
    if not _CMAKE_DEFINE.fullmatch(value):
        return (f"{option} takes -DNAME=value (ASCII letters, digits and _ . , + : @ % - in the value), "
                f"not {value[:40]!r}")
    return None


def install_location_problem(define: str) -> str | None:
    """Why a CMake `-DNAME=value` may not be given (it sets where a build installs or finds its
    parts: CMAKE_INSTALL_PREFIX and the like), or None. Shared by workspace_colcon_args and a
    profile's cmake_args."""
    match = re.match(r"-D([A-Za-z_][A-Za-z0-9_]{0,63})", define, re.ASCII)
    if match and _INSTALL_LOCATION.fullmatch(match.group(1)):
        return f"{match.group(1)} says where a build installs or finds its parts: roslab decides that"
    return None


def colcon_arguments(values: list, _context: Context | None = None) -> str | None:
    """`colcon build` options from roslab's allow-list (COLCON_OPTIONS), each with its value."""
    option = None
    for value in values:
        if not isinstance(value, str):
            return None  # the item's type is reported on its own
        name, eq, inline = value.partition("=")
        if name in COLCON_OPTIONS:
            option = name if COLCON_OPTIONS[name] is not None else None
            if eq and option is None:
                return f"{name} takes no value"
            if eq:
                problem = _colcon_value_problem(name, inline)
                if problem:
                    return problem
                option = name if COLCON_OPTIONS[name] in ("handlers", "defines") else None
            continue
        if value.startswith("--") or option is None:
            return (f"{value.split('=')[0][:40]!r} is not a colcon option roslab allows (allowed: "
                    f"{', '.join(COLCON_OPTIONS)}; roslab decides where colcon builds and installs)")
        problem = _colcon_value_problem(option, value)
        if problem:
            return problem
        if COLCON_OPTIONS[option] not in ("handlers", "defines"):
            option = None  # one value only
    return None


# ASCII only: with re.IGNORECASE alone, `[a-z]` would match ı, ſ and the Kelvin sign.
_HOST_LABEL = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?", re.ASCII)


def _all_ascii_digits(text: str) -> bool:
    return text.isascii() and text.isdigit()


def hostname(value: str, context: Context | None = None) -> str | None:
    """An RFC 1123 host name; all-numeric names are malformed addresses, not names."""
    problem = single_line(value) or ascii_text(value)
    if problem:
        return problem
    labels = value[:-1].split(".") if value.endswith(".") else value.split(".")
    if (len(value) > 253 or not all(_HOST_LABEL.fullmatch(label) for label in labels)
            or all(_all_ascii_digits(label) for label in labels)):
        return f"{value!r} is not a valid host name"
    return None


def host_label(value: str, context: Context | None = None) -> str | None:
    """One DNS label: what a Pi's own hostname is."""
    if isinstance(value, str) and value and ascii_text(value):
        return f"{ascii_text(value)} (it becomes the Pi's hostname)"
    if not isinstance(value, str) or not _HOST_LABEL.fullmatch(value) or _all_ascii_digits(value):
        return (f"{value!r} is not a valid hostname: letters, digits and inner '-', "
                "at most 63 characters, not all digits (it becomes the Pi's hostname)")
    return None


def _loose_ipv4(value: str) -> str | None:
    """The dotted-quad IPv4 address a resolver makes of `value` when it is not written as one
    (inet_aton's hex, octal and short forms: 0x7f.0.0.11, 017.0.0.1, 127.11, 2130706443),
    else None: such a name reaches that address, so it would pass a duplicate check as text."""
    if not value.isascii() or not value or not value[0].isdigit() or not all(
            char in "0123456789abcdefxABCDEFX." for char in value):
        return None
    try:
        packed = socket.inet_aton(value)
    except (OSError, ValueError):
        return None
    return socket.inet_ntoa(packed)


_BROADCAST = ipaddress.IPv4Address("255.255.255.255")


def _non_canonical_ip(value: str, ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str | None:
    """Why an address ipaddress accepts (`ip`, read from `value`) is not in the one form roslab
    compares, or None: IPv4 as a dotted quad, IPv6 in its canonical (lower-case, compressed, no
    zone) form."""
    if ip.version == 6 and ip.ipv4_mapped:
        return f"{value!r} is an IPv4 address in IPv6's clothes: write {str(ip.ipv4_mapped)!r}"
    if ip.version == 6 and str(ip) != value:
        return f"{value!r} is not written in IPv6's canonical form: write {str(ip)!r}"
    return None


def ip_address(value: str, context: Context | None = None) -> str | None:
    """An IP address: IPv4 as a dotted quad, IPv6 in canonical form."""
    return _ip_problem(value)[0]


def _ip_problem(value: str) -> tuple[str | None, ipaddress.IPv4Address | ipaddress.IPv6Address | None]:
    """(ip_address's problem, the address read) of `value`: read once (a roster's check reads
    every host's address)."""
    try:
        ip = ipaddress.ip_address(value)
    except ValueError:
        loose = _loose_ipv4(value) if isinstance(value, str) else None
        if loose:
            return (f"{value!r} is not an IP address written as four decimal numbers (a resolver "
                    f"would read it as {loose!r})"), None
        return f"{value!r} is not an IP address", None
    return _non_canonical_ip(value, ip), ip


def address(value: str, context: Context | None = None) -> str | None:
    """Where SSH reaches a host: an IP address (one a host can have: loopback is fine, the
    unspecified, multicast, broadcast or reserved addresses are not) or a host name."""
    problem, ip = _ip_problem(value)
    if problem is None:
        if ip is not None and (ip.is_unspecified or ip.is_multicast or ip.is_reserved
                               or (ip.version == 4 and ip == _BROADCAST)):
            return f"{value!r} is not an address a host can have (unspecified, multicast, broadcast or reserved)"
        return None
    if "written" in problem or "resolver" in problem or "clothes" in problem:  # 0x7f.0.0.11, 127.11, FD00::1: an address, in a form not compared
        return problem
    if hostname(value) is None:
        return None
    return f"{value!r} is neither an IP address nor a valid host name"


def ip_interface(value: str, context: Context | None = None) -> str | None:
    """An IP address with or without a prefix length (the prefix may come from network_prefix)."""
    try:
        ipaddress.ip_interface(value)
    except ValueError:
        return f"{value!r} is not an IP address (with prefix length), e.g. '192.168.50.11/24'"
    address_part, _, prefix = value.partition("/")
    if prefix and not (prefix.isascii() and prefix.isdigit() and str(int(prefix)) == prefix):
        return f"{value!r}: the prefix length is a plain decimal number, e.g. '192.168.50.11/24'"
    return _non_canonical_ip(address_part, ipaddress.ip_address(address_part))


def ubuntu_release(value: str, context: Context | None = None) -> str | None:
    try:
        distros.codename_for(value)
    except distros.DistroError as exc:
        return str(exc)
    return None


def ros_distro(value: str, context: Context | None = None) -> str | None:
    if value not in distros.DISTRO_RELEASES:
        return f"ROS 2 distro {value!r} does not exist (known: {', '.join(sorted(distros.DISTRO_RELEASES))})"
    return None


ros_variant = choice(*distros.VARIANTS)

# ROS_DOMAIN_ID: 0-101 everywhere; 215-232 also work on Linux (7400 + 250 x ID stays
# below the ephemeral ports). One definition for the roster and every deploy.
DOMAIN_ID_RANGES = (range(0, 102), range(215, 233))


def domain_id(value: int, context: Context | None = None) -> str | None:
    if not any(value in allowed for allowed in DOMAIN_ID_RANGES):
        return f"ROS_DOMAIN_ID {value} is outside 0 to 101 and 215 to 232"
    return None


DOMAIN_IDS = "0 to 101, 215 to 232"
describe(domain_id, allowed=DOMAIN_IDS)


# --- names from a database: locales and time zones ---------------------------------------

_DATA = Path(__file__).resolve().parent / "data"


def _data_names(file_name: str) -> frozenset[str]:
    text = (_DATA / file_name).read_text(encoding="ascii")
    return frozenset(line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#"))


_LOCALE_FORM = pattern(r"[A-Za-z]{1,8}(_[A-Z]{2,3})?\.UTF-8(@[a-z]{1,16})?",
                       "a UTF-8 locale name like en_US.UTF-8")
_locales: frozenset[str] | None = None


def utf8_locale(value: str, context: Context | None = None) -> str | None:
    """A UTF-8 locale glibc supports (language[_TERRITORY].UTF-8[@modifier]).

    Checked against glibc's list of supported locales (roslab/data/locales-utf8.txt,
    Debian 12's /usr/share/i18n/SUPPORTED), shipped with roslab so the check is the same
    on any controller: a name `locale-gen` does not know would pass here and fail on
    every Pi, or set a LANG nothing provides.
    """
    global _locales
    problem = _LOCALE_FORM(value)
    if problem:
        return problem
    if _locales is None:
        _locales = _data_names("locales-utf8.txt")
    if value not in _locales:
        import difflib

        close = difflib.get_close_matches(value, sorted(_locales), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"{value!r} is not a UTF-8 locale glibc supports{hint}"
    return None


_TIMEZONE_FORM = pattern(r"[A-Za-z][A-Za-z0-9_+-]*(/[A-Za-z0-9_+-]+){0,2}",
                         "a time zone name (like Europe/Berlin or Etc/UTC)")
_timezones: frozenset[str] | None = None


def known_timezones() -> frozenset[str]:
    """IANA zone names: roslab's shipped list and whatever this machine's tzdata adds."""
    global _timezones
    if _timezones is None:
        names = set(_data_names("timezones.txt"))
        try:
            import zoneinfo

            names |= zoneinfo.available_timezones()
        except Exception:  # no tzdata on this controller: the shipped list decides
            pass
        names -= {"localtime", "posixrules"}  # links to "whatever this machine uses", not zones

        _timezones = frozenset(names)
    return _timezones


def timezone(value: str, context: Context | None = None) -> str | None:
    """An IANA time zone that exists (tzdata), like Europe/Berlin or Etc/UTC.

    Checked against roslab/data/timezones.txt (tzdata 2025b) plus the controller's own
    zoneinfo database, never by opening a file named by the value.
    """
    problem = _TIMEZONE_FORM(value)
    if problem:
        return problem
    if value not in known_timezones():
        import difflib

        close = difflib.get_close_matches(value, sorted(known_timezones()), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"{value!r} is not a time zone in the tz database{hint}"
    return None


describe(utf8_locale, allowed="a UTF-8 locale glibc supports, like en_US.UTF-8")
describe(timezone, allowed="a tz database zone, like Europe/Berlin")


# --- URLs and paths ---------------------------------------------------------------------

# RFC 3986's characters, without space, quotes, backslash or anything a deb822 field,
# a shell or a YAML scalar would read as syntax on its own.
_URL_CHARACTERS = re.compile(r"[A-Za-z0-9._~:/?#\[\]@!$&'()*+,;=%-]+", re.ASCII)


def url(schemes: tuple[str, ...], placeholders: tuple[str, ...] = (), file_suffix: str | None = None) -> Check:
    """A URL of one of `schemes`; `{name}` placeholders are allowed and filled in first.

    A `file://` URL (the controller reads it and copies what it holds to every Pi) must
    name a file inside the roster's folder ending in `file_suffix`, with no `..`.
    """

    def check(value: str, context: Context | None = None) -> str | None:
        problem = single_line(value)
        if problem:
            return problem
        filled = value
        for name in placeholders:
            filled = filled.replace("{" + name + "}", "x")
        if "{" in filled or "}" in filled:
            allowed = ", ".join("{" + name + "}" for name in placeholders) or "none"
            return f"{value!r} has a placeholder roslab does not fill (allowed: {allowed})"
        parts = urlsplit(filled)
        if parts.scheme not in schemes or not _URL_CHARACTERS.fullmatch(filled):
            return f"{value!r} is not a {' or '.join(schemes)} URL"
        if parts.scheme != "file" and not parts.netloc:
            return f"{value!r} has no host"
        if parts.scheme == "file":
            return _file_url_problem(value, parts, context or Context(), file_suffix)
        return None

    allowed = " or ".join(f"{scheme}://" for scheme in schemes) + " URL"
    if "file" in schemes:
        allowed += f" (file:// a {file_suffix or ''} file in the roster's folder)".replace("a  ", "a ")
    return describe(check, allowed=allowed)


def _file_url_problem(value: str, parts, context: Context, file_suffix: str | None) -> str | None:
    return file_url_problem(value, context.roster_dir, "the roster's folder", file_suffix=file_suffix,
                            why="a file:// URL may name only a file kept beside the roster (it is copied "
                                "to every Pi)")


def file_url_problem(url: str, folder: Path, named: str, *, file_suffix: str | None = None,
                     why: str = "what the controller fetches is copied to every Pi") -> str | None:
    """Why a file:// `url` (a URL or a URL prefix) does not lead inside `folder` (the roster's, or
    a .repos file's), or None; not a file:// URL: None. Never into the roster's .roslab-state.
    The one check of where a file:// URL may lead: settings, .repos files and rewrites alike."""
    parts = urlsplit(url)
    if parts.scheme != "file":
        return None
    if parts.netloc not in ("", "localhost") or parts.query or parts.fragment:
        return f"{url!r}: a file:// URL names a path on this machine only (file:///...)"
    path = Path(unquote(parts.path))
    if not path.is_absolute() or ".." in path.parts or "." in parts.path.split("/"):
        return f"{url!r}: a file:// URL needs an absolute path without '..'"
    if file_suffix and not path.name.endswith(file_suffix):
        return f"{url!r}: a file:// URL here names a {file_suffix} file"
    if not within(path, folder, strictly=False) or within(path, Path(folder) / STATE_DIR, strictly=False):
        return f"{url!r} leads outside {named} ({_real(folder)}): {why}"
    return None


http_url = url(("http", "https"))

# One path component inside the home directory: no `..`, no hidden tricks.
# Linux's limits (limits.h): one name of a path, and a whole path with its terminating NUL.
NAME_MAX, PATH_MAX = 255, 4096
MAX_HOME_PATH = 1024  # a folder in the home: the home's own path and the tree inside fit in PATH_MAX
_PATH_COMPONENT = re.compile(r"[A-Za-z0-9_+][A-Za-z0-9_.+-]*", re.ASCII)


def home_path(value: str, context: Context | None = None) -> str | None:
    """`~/` and a relative path that stays inside the login user's home."""
    problem = single_line(value)
    if problem:
        return problem
    if not value.startswith("~/"):
        return f"{value!r} must start with ~/ (a directory inside the login user's home)"
    components = [part for part in value[2:].split("/") if part]
    if not components:
        return f"{value!r} is the home directory itself; name a directory inside it"
    if len(value.encode()) > MAX_HOME_PATH:
        return (f"the path is {len(value.encode())} bytes long; at most {MAX_HOME_PATH} (PATH_MAX is {PATH_MAX}, "
                "with room for the home folder and the files inside)")
    for part in components:
        if len(part.encode()) > NAME_MAX:
            return f"{part[:40]!r}... is {len(part.encode())} bytes long: a folder name holds at most {NAME_MAX}"
        if part in (".", "..") or not _PATH_COMPONENT.fullmatch(part):
            return (f"{value!r}: {part!r} is not a plain directory name "
                    "(letters, digits, _ . + -, not starting with . or -)")
    return None


# Controller paths: each has a purpose and a place. A path is compared by where it
# really leads (symlinks resolved), and a file is read only as what it must be: a
# regular file of bounded size, opened without waiting (roslab.controller_files).

def _real(path: Path) -> Path:
    return Path(os.path.realpath(path))  # never raises, even on a symlink loop


def within(path: Path, folder: Path, strictly: bool = True) -> bool:
    """Whether `path` leads inside `folder` (both resolved); `strictly`: not the folder itself."""
    path, folder = _real(path), _real(folder)
    return (path != folder or not strictly) and (path == folder or folder in path.parents)


def _controller(check, allowed: str):
    """Mark `check` as a controller-path check: the loader makes its value absolute."""
    check.controller_path = True
    describe(check, allowed=allowed)
    return check


def controller_path(kind: str = "any") -> Check:
    """A path on the machine running pyinfra; `kind` "file"/"dir" must exist as such.

    Only for paths with no purpose of their own; every roster setting has a specific
    check below that says where its path may lead and what it must hold.
    """

    def check(value: str, context: Context | None = None) -> str | None:
        problem = single_line(value)
        if problem:
            return problem
        if kind == "any":
            return None
        path = (context or Context()).controller_path(value)
        if kind == "file" and not path.is_file():
            return f"{value!r}: no such file on this machine ({path})"
        if kind == "dir" and not path.is_dir():
            return f"{value!r}: no such directory on this machine ({path})"
        return None

    return _controller(check, {"any": "a path on this machine", "file": "an existing file on this machine",
                               "dir": "an existing directory on this machine"}[kind])


def _read_controller_file(value: str, path: Path, limit: int = MAX_SMALL_FILE_BYTES) -> bytes | str:
    """The file's bytes, or (a str) the problem reading it."""
    try:
        return read_regular_file(path, limit)
    except UnreadableFile as exc:
        return f"{value!r} ({path}) {exc}" if str(exc).startswith("is ") else f"{value!r} ({path}): {exc}"


def secrets_file(value: str, context: Context | None = None) -> str | None:
    """A .yaml file inside the roster's folder (not the roster itself, not .roslab-state)."""
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    path = context.controller_path(value)
    if path.suffix not in (".yaml", ".yml"):
        return f"{value!r} is not a .yaml file: the secrets file is YAML, like secrets.yaml"
    if not within(path, context.roster_dir) or within(path, context.state_dir, strictly=False):
        return (f"{value!r} leads outside the roster's folder ({_real(context.roster_dir)}): "
                "keep the secrets file beside the roster (or in a folder below it)")
    if context.roster_file is not None and _real(path) == _real(context.roster_file):
        return f"{value!r} is the roster itself"
    return None


# known_hosts lines: [marker] host patterns, key type, base64 key (blobs start with AAAA), comment.
_KNOWN_HOSTS_LINE = re.compile(
    r"(@(cert-authority|revoked) +)?[^\s#@][^\s]* +"
    r"(ssh-(ed25519|rsa|dss)|ecdsa-sha2-nistp(256|384|521)|sk-ssh-ed25519@openssh\.com"
    r"|sk-ecdsa-sha2-nistp256@openssh\.com|[a-z0-9-]+-cert-v01@openssh\.com) +AAAA[A-Za-z0-9+/]*={0,3}( .*)?",
    re.ASCII)
MAX_KNOWN_HOSTS_BYTES = 4 * 1024 * 1024


def known_hosts_file(value: str, context: Context | None = None) -> str | None:
    """/dev/null, or a file named *known_hosts holding only known_hosts lines (or not there yet).

    pyinfra reads it, prints lines it cannot parse, and appends new keys to it: pointed
    at the secrets file it printed a WiFi password, pointed at any other file it wrote
    into it. So it must be named like one and hold nothing else.
    """
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    if value == os.devnull:
        return None
    path = context.controller_path(value)
    if not path.name.endswith("known_hosts"):
        return (f"{value!r} is not a known_hosts file: its name must end in known_hosts "
                "(like .roslab-state/known_hosts or ~/.ssh/known_hosts), or be /dev/null")
    if not os.path.lexists(path):
        return None  # pyinfra (or roslab trust) creates it
    data = _read_controller_file(value, path, MAX_KNOWN_HOSTS_BYTES)
    if isinstance(data, str):
        return data  # the problem reading it
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return f"{value!r} ({path}) is not a known_hosts file (not text)"
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#") and not _KNOWN_HOSTS_LINE.fullmatch(line):
            return f"{value!r} ({path}) is not a known_hosts file: line {number} is not a host key line"
    return None


_PRIVATE_KEY_HEADER = re.compile(rb"-----BEGIN (OPENSSH |RSA |EC |DSA |ENCRYPTED )?PRIVATE KEY-----", re.ASCII)


def private_key_file(value: str, context: Context | None = None) -> str | None:
    """An existing SSH private key file (PEM or OpenSSH format) on this machine."""
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    path = context.controller_path(value)
    data = _read_controller_file(value, path)
    if isinstance(data, str):
        return data  # the problem reading it
    if not _PRIVATE_KEY_HEADER.fullmatch(data.lstrip().split(b"\n", 1)[0].strip()):
        return f"{value!r} ({path}) is not an SSH private key (no -----BEGIN ... PRIVATE KEY----- line)"
    return None


_ARMORED_KEY = b"-----BEGIN PGP PUBLIC KEY BLOCK-----"
MAX_SIGNING_KEY_BYTES = 1024 * 1024


def openpgp_key_file(value: str, context: Context | None = None) -> str | None:
    """An OpenPGP public key file (ASCII-armored or binary) on this machine: it is copied to every Pi."""
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    path = context.controller_path(value)
    data = _read_controller_file(value, path, MAX_SIGNING_KEY_BYTES)
    if isinstance(data, str):
        return data  # the problem reading it
    # Binary: the first packet is a public key (tag 6), old (0x98-0x9b) or new (0xc6) format.
    if not (data.lstrip().startswith(_ARMORED_KEY) or (data[:1] and (data[0] in range(0x98, 0x9c) or data[0] == 0xC6))):
        return (f"{value!r} ({path}) is not an OpenPGP public key (neither "
                "'-----BEGIN PGP PUBLIC KEY BLOCK-----' nor a binary key)")
    return None


def _home() -> Path:
    return Path(os.path.expanduser("~"))


def cache_dir(value: str, context: Context | None = None) -> str | None:
    """A folder of its own for the controller's downloads: inside the home directory, the
    roster's folder or the temporary directory (not one of them itself), never in ~/.ssh,
    ~/.gnupg or the classroom's .roslab-state, never a folder that holds the roster's.
    (roslab.roster.checks: no two caches share a folder, none is in workspace_nodes_dir.)"""
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    path = context.controller_path(value)
    places = (_home(), context.roster_dir, Path(tempfile.gettempdir()))
    # inside one of the places, and none of them itself nor holding one (a home under /tmp: ~ is
    # inside the temporary directory, and still the whole home)
    if not any(within(path, place) for place in places) or any(within(place, path, strictly=False)
                                                                for place in places[::2]):
        return (f"{value!r} ({_real(path)}) is not a folder of its own inside your home directory, "
                "the roster's folder or the temporary directory")
    for private in (_home() / ".ssh", _home() / ".gnupg", context.state_dir):
        if within(path, private, strictly=False):
            return f"{value!r} is inside {private}, which is not a cache"
    if within(context.roster_dir, path, strictly=False):
        return (f"{value!r} ({_real(path)}) holds the roster's folder (its secrets and .roslab-state): "
                "a cache is a folder of its own")
    return None


def nodes_dir(value: str, context: Context | None = None) -> str | None:
    """An existing folder of ROS packages (top-level folders with a package.xml), never
    the filesystem root, the home directory or a folder holding the roster."""
    context = context or Context()
    problem = single_line(value)
    if problem:
        return problem
    path = context.controller_path(value)
    if not path.is_dir():
        return f"{value!r}: no such directory on this machine ({path})"
    real = _real(path)
    if real == Path(real.anchor) or real == _real(_home()):
        return f"{value!r} is {real}: name the folder that holds your ROS packages"
    if within(context.roster_dir, real, strictly=False):
        return (f"{value!r} ({real}) holds the roster's folder (its secrets and .roslab-state): "
                "name the folder that holds only your ROS packages")
    try:
        has_package = any((entry / "package.xml").is_file() and not entry.is_symlink()
                          for entry in path.iterdir())
    except OSError as exc:
        return f"{value!r}: cannot list {path}: {exc.strerror or exc}"
    if not has_package:
        return f"{value!r} ({path}) holds no ROS package (a folder with a package.xml)"
    return None


_controller(secrets_file, "a .yaml file in the roster's folder")
_controller(known_hosts_file, "a *known_hosts file, or /dev/null")
_controller(private_key_file, "an SSH private key file")
_controller(openpgp_key_file, "an OpenPGP public key file")
_controller(cache_dir, "a folder of its own (apart from the other caches) in ~, the roster's folder or the temp dir")
_controller(nodes_dir, "a folder of ROS packages")


# --- composite values ---------------------------------------------------------------------

# An environment variable a roster or a profile may set: an allow-list. A name is words of
# capitals and digits joined by `_`, at least two of them (TURTLEBOT3_MODEL, LDS_MODEL,
# GAZEBO_MODEL_PATH, a lab's own LAB_ROBOT_COLOUR): every one-word name a shell, the C
# library or a common tool reads (PATH, HOME, PS1, ENV, IFS, EDITOR, PAGER, TMPDIR, LANG, TZ,
# PYTHONSTARTUP, PERL5OPT, LESSOPEN...) is left out by its form. The names roslab writes and
# the families below are refused whatever their form, each naming what governs it instead: the
# ROS/middleware variables roslab writes from its own settings, and whatever makes a shell, the
# loader or an interpreter run code or look elsewhere for it.
_VARIABLE_NAME = re.compile(r"[A-Z][A-Z0-9]*(_[A-Z0-9]+)+", re.ASCII)
MAX_VARIABLE_NAME = 64
# Names roslab writes, and the roster setting that governs each.
OWNED_VARIABLES = {
    "RMW_IMPLEMENTATION": "the class's `ros_middleware` setting",
    "ROS_DOMAIN_ID": "the team's `ros_domain_id` setting",
    "ROS_LOCALHOST_ONLY": "the `ros_discovery_mode` setting (localhost)",
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "the `ros_discovery_mode` setting",
    "ROS_STATIC_PEERS": "the `ros_static_peers` setting",
    "ROS_DISCOVERY_SERVER": "the `ros_discovery_mode` setting (discovery_server)",
    "ROS_SUPER_CLIENT": "the `ros_discovery_mode` setting (discovery_server)",
    "ROS_DISTRO": "the `ros_distro` setting",
    "ROSDISTRO_INDEX_URL": "the `rosdistro_index_url` setting",
    "ROSDEP_SOURCES_LIST": "the `rosdep_sources_list_url` setting",
    "FASTRTPS_DEFAULT_PROFILES_FILE": "the `ros_discovery_mode` setting (roslab writes Fast DDS's profiles)",
    "FASTDDS_DEFAULT_PROFILES_FILE": "the `ros_discovery_mode` setting (roslab writes Fast DDS's profiles)",
    "CYCLONEDDS_URI": "the `ros_discovery_mode` setting (roslab writes Cyclone DDS's configuration)",
    "ZENOH_CONFIG_OVERRIDE": "the `ros_discovery_mode` setting (roslab configures Zenoh)",
    "ZENOH_ROUTER_CONFIG_URI": "the `ros_discovery_mode` setting (roslab configures Zenoh)",
    "ZENOH_SESSION_CONFIG_URI": "the `ros_discovery_mode` setting (roslab configures Zenoh)",
    "VIRTUAL_ENV": "the robot profile's `python_venv`",
    "CMAKE_PREFIX_PATH": "the ROS setup roslab sources (the underlay and the workspace)",
    "PKG_CONFIG_PATH": "the ROS setup roslab sources (the underlay and the workspace)",
    "LIBRARY_PATH": "the ROS setup roslab sources (the underlay and the workspace)",
}
# Families, each a regular expression over the whole name and what governs it instead; the
# first that matches says why. They run before the form, so PS1 or PYTHONHOME is named as what
# it is, not only as a one-word name.
_MIDDLEWARE = "the middleware's variables are set by the `ros_middleware` and `ros_discovery_mode` settings"
_WORKSPACE = "the workspace's paths are set by the ROS setup roslab sources (the underlay and the workspace)"
REFUSED_VARIABLE_FAMILIES = tuple((re.compile(regex, re.ASCII), governs) for regex, governs in (
    (r"ROS_.*", "ROS 2's own variables are set by the roster's ROS settings (ros_distro, ros_domain_id, "
                "ros_discovery_mode, ros_static_peers)"),
    (r"RMW_.*", "the middleware's variables are set by the class's `ros_middleware` setting"),
    (r"(FASTRTPS|FASTDDS|CYCLONEDDS|ZENOH|RTI|CONNEXTDDS|NDDS)_.*", _MIDDLEWARE),
    (r"(AMENT|COLCON|CATKIN|CMAKE|PKG_CONFIG)_.*", _WORKSPACE),
    (r"ROSDEP_.*", "rosdep's variables are set by the rosdep settings (rosdep_*)"),
    (r"ROSDISTRO_.*", "it is set by the `rosdistro_index_url` setting"),
    (r"PS[0-9]|PROMPT_.*", "the shell's prompt runs what it holds, in every student shell"),
    (r"ENV|BASH|BASH_.*|BASHOPTS|SHELLOPTS|IFS|CDPATH|GLOBIGNORE|EXECIGNORE|FUNCNEST|INPUTRC|TMOUT|COMP_.*"
     r"|HIST[A-Z]*|MAIL[A-Z]*|POSIXLY_CORRECT|TERM|TERMINFO|TERMCAP",
     "the shell reads it to run code or to behave otherwise (the login shell is the student's)"),
    (r"PATH|HOME|SHELL|USER|LOGNAME|PWD|OLDPWD|TMPDIR|EDITOR|VISUAL|PAGER|BROWSER|DISPLAY|XAUTHORITY",
     "the system sets it for the login user's account"),
    (r"LD_.*|GLIBC_.*|MALLOC_.*|GCONV_PATH|LOCPATH|NLSPATH|HOSTALIASES|LOCALDOMAIN|RES_OPTIONS|GETCONF_DIR",
     "the loader's and the C library's variables load code into (or change) every program"),
    (r"PYTHON.*|PIP_.*|VIRTUAL_ENV|CONDA_.*",
     "Python's variables run code or move its library (a profile's `python_packages` and `python_venv` "
     "set up its Python)"),
    (r"PERL.*|RUBY(OPT|LIB|_.*)|GEM_.*|NODE_.*|NPM_.*|LUA_.*|JAVA_.*|JDK_.*|CLASSPATH|TCL(LIBPATH|_.*)",
     "an interpreter's variables run code or move its library"),
    (r"GIT_.*", "git's variables run commands (sources are set by source_url_rewrites and source_pins)"),
    (r"SSH_.*|SUDO_.*|SYSTEMD_.*|DBUS_.*|XDG_.*|LESS(OPEN|CLOSE|KEY|SECURE|_.*)?|MAN(PAGER|PATH|OPT|_.*)",
     "the login's tools run commands from these, or find the login's own files"),
    (r"LC_.*|LANG|LANGUAGE", "it is set by the `locale` setting"),
    (r"TZ|TZDIR", "it is set by the `timezone` setting"),
))


def variable(name, value) -> str | None:
    """One environment variable roslab may write: a name of the allowed form, not a family
    that roslab's own settings govern or that runs code, and one line of text."""
    if not isinstance(name, str) or not name.isascii():
        return f"{name!r} is not a variable name (plain ASCII capitals, digits and _)"
    if name in OWNED_VARIABLES:
        return f"{name} is not set through an environment mapping: it is set by {OWNED_VARIABLES[name]}"
    for family, governs in REFUSED_VARIABLE_FAMILIES:
        if family.fullmatch(name):
            return f"{name} is not set through an environment mapping: {governs}"
    if not _VARIABLE_NAME.fullmatch(name) or len(name) > MAX_VARIABLE_NAME:
        return (f"{name!r} is not a variable name roslab sets: capitals and digits in at least two words "
                f"joined by _ (like TURTLEBOT3_MODEL or LAB_ROBOT_NAME), at most {MAX_VARIABLE_NAME} "
                "characters; one-word names (PATH, PS1, EDITOR...) belong to the shell and the system")
    if not isinstance(value, str):
        return f"the value of {name} must be a string (quote it), not {value!r}"
    problem = single_line(value)
    return f"the value of {name} {problem}" if problem else None


def environment(value: dict, context: Context | None = None) -> str | None:
    """VARIABLE: value, each value one line of text; names like LAB_ROBOT_NAME (two or more
    words of capitals and digits), not ROS's, the middleware's, the shell's, the loader's or an
    interpreter's."""
    for name, text in value.items():
        problem = variable(name, text)
        if problem:
            return problem
    return None


def launch(value: str, context: Context | None = None) -> str | None:
    """`<package> <launch file>`, e.g. 'roslab_bringup main.launch.py' or 'rplidar_ros rplidar_c1_launch.py'."""
    problem = single_line(value)
    if problem:
        return problem
    words = value.split(" ")
    if len(words) != 2 or ros_package(words[0]) or launch_file_name(words[1]):
        return (f"{value!r} is not '<package> <launch file>' "
                "like 'roslab_bringup main.launch.py' or 'rplidar_ros rplidar_c1_launch.py'")
    return None


# Public key lines authorized_keys takes (type, base64 body, optional comment).
PUBLIC_KEY = re.compile(
    r"(ssh-(ed25519|rsa|dss)|ecdsa-sha2-nistp(256|384|521)|sk-ssh-ed25519@openssh\.com"
    r"|sk-ecdsa-sha2-nistp256@openssh\.com) [A-Za-z0-9+/]+={0,3}( [^\x00-\x1f\x7f]*)?", re.ASCII)


def public_key_lines(text: str) -> list[str] | None:
    """The key lines of a .pub file, or None when a line is not a public key."""
    keys = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if not PUBLIC_KEY.fullmatch(line):
            return None
        keys.append(line)
    return keys


def teacher_key(value: str, context: Context | None = None) -> str | None:
    """A public key line, or a controller-side .pub file holding only key lines."""
    problem = single_line(value)
    if problem:
        return problem
    if PUBLIC_KEY.fullmatch(value.strip()):
        return None
    path = (context or Context()).controller_path(value)
    if path.suffix != ".pub":
        return f"{value!r} is neither a public key line nor a readable .pub file (its name ends in .pub)"
    data = _read_controller_file(value, path)
    if isinstance(data, str):
        return data  # the problem reading it
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return f"{value!r} is neither a public key line nor a readable .pub file on this machine"
    if public_key_lines(text) is None:
        return f"{value!r}: {path} holds a line that is not a public key"
    return None


# A ROS static peer is reached the way SSH reaches a host: an IP address or a host name.
static_peer = address


def wifi_ssid(value: str, context: Context | None = None) -> str | None:
    """An SSID: 1 to 32 bytes of UTF-8, no control characters."""
    problem = single_line(value)
    if problem:
        return problem
    if len(value.encode("utf-8")) > 32:
        return f"{value!r} is longer than an SSID can be (32 bytes)"
    return None


def package_template(value: str, context: Context | None = None) -> str | None:
    """A Debian package name that may hold `{distro}` (e.g. ros-{distro}-turtlesim)."""
    problem = single_line(value)
    if problem:
        return problem
    if debian_package(value.replace("{distro}", "jazzy")):
        return (f"{value!r} is not a Debian package name "
                "(lower-case letters, digits, + . -; '{distro}' is filled in)")
    return None


# A pip requirement pinned to one release: PEP 508's name (letters, digits, . _ -, starting and
# ending with a letter or digit) and `==` with a PEP 440 version (no wildcard, no local
# `+label`, no environment marker, no extras, no URL): a class installs exactly what was
# downloaded once for it, and each part is a plain word in a pip command and a requirements file.
_PYPI_NAME = re.compile(r"[A-Za-z0-9]|[A-Za-z0-9][A-Za-z0-9._-]*[A-Za-z0-9]", re.ASCII)
_PEP440_VERSION = re.compile(
    r"([0-9]+!)?[0-9]+(\.[0-9]+)*((a|b|rc)[0-9]+)?(\.post[0-9]+)?(\.dev[0-9]+)?", re.ASCII)


def pinned_requirement(value: str, context: Context | None = None) -> str | None:
    """A pip requirement pinned to one version: name==version (e.g. RPi.GPIO==0.7.1)."""
    problem = single_line(value) or ascii_text(value)
    if problem:
        return problem
    name, separator, version = value.partition("==")
    name, version = name.strip(), version.strip()
    if not _PYPI_NAME.fullmatch(name) or len(name) > 100:
        return (f"{value!r} does not start with a Python package name (letters, digits, . _ -, "
                "starting and ending with a letter or digit; no extras, URLs or markers)")
    if not separator:
        return (f"{value!r} is not pinned: write {name}==<version> (the class installs exactly the "
                "release the controller downloaded once)")
    if not _PEP440_VERSION.fullmatch(version) or len(version) > 64:
        return (f"{value!r}: {version!r} is not one exact release (like 1.3.17, 0.7.1, 1.1.post2; "
                "no ranges, wildcards, local versions or markers)")
    return None


def requirement_name(requirement: str) -> str:
    """The normalized project name (PEP 503) of a checked `name==version`."""
    return re.sub(r"[-_.]+", "-", requirement.partition("==")[0].strip()).lower()


def venv_dir(value: str, context: Context | None = None) -> str | None:
    """A directory inside the login user's home, given relative to it (like osr_venv)."""
    problem = single_line(value) or ascii_text(value)
    if problem:
        return problem
    relative = value[2:] if value.startswith("~/") else value
    components = relative.split("/")
    if not relative or value.startswith("/") or any(not part for part in components[:-1]):
        return f"{value!r} must be a directory inside the login user's home, like osr_venv"
    for part in (part for part in components if part):
        if part in (".", "..") or not _PATH_COMPONENT.fullmatch(part):
            return (f"{value!r}: {part!r} is not a plain directory name "
                    "(letters, digits, _ . + -, not starting with . or -)")
    return None


def sha256_pins(value: dict, context: Context | None = None) -> str | None:
    """Ubuntu codename -> sha256."""
    codenames = set(distros.UBUNTU_CODENAMES.values())
    for codename, digest in value.items():
        if codename not in codenames:
            return f"{codename!r} is not an Ubuntu codename roslab knows ({', '.join(sorted(codenames))})"
        if not isinstance(digest, str) or sha256_hex(digest):
            return f"the sha256 for {codename} is not 64 lower-case hex digits"
    return None


# How each plain-function check reads in the settings table's "allowed" column.
for _check, _words in {
    single_line: "one line of text",
    hostname: "a host name",
    ip_address: "an IP address",
    address: "an IP address or a host name",
    ip_interface: "an IP address[/prefix]",
    home_path: "~/ and a path inside the home",
    launch: "<package> <file>.launch.py",
    teacher_key: "key lines or .pub files",
    wifi_ssid: "1 to 32 bytes, one line",
    package_template: "Debian package names",
}.items():
    describe(_check, allowed=_words)


describe(colcon_argument, whole=colcon_arguments)
