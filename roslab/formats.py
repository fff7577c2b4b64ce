"""Format checks for roster values: each says why a value is not of its format, or None.

A check runs where its setting is declared (`roslab.settings`), before any host is
touched, and matches the whole value (`fullmatch`): a value that passes holds only
what its destination can carry without changing meaning. Writing it is then a matter
of the destination's escaping (`roslab.quoting`), never of filtering.

Every check takes the value (already of the declared type) and a `Context`; checks of
controller-side paths resolve them against the roster's directory.
"""

from __future__ import annotations

import ipaddress
import re
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from roslab import distro as distros

Check = Callable[[object, "Context"], "str | None"]


@dataclass(frozen=True)
class Context:
    """What a check may know besides the value: where the roster is."""

    roster_dir: Path = Path(".")

    def controller_path(self, value: str) -> Path:
        """A controller-side path: `~` expanded, relative to the roster's directory."""
        return self.roster_dir / Path(value).expanduser()


# --- building blocks ------------------------------------------------------------------

# Characters that end or break a line in some reader: C0/C1 controls, DEL, and
# Unicode's line and paragraph separators (Python's splitlines() splits on them too).
def _breaks_lines(char: str) -> bool:
    return unicodedata.category(char) in ("Cc", "Zl", "Zp")


def single_line(value: str, _context: Context | None = None) -> str | None:
    """One line of text: no newline, no control character, not empty."""
    if value == "":
        return "must not be empty"
    for char in value:
        if _breaks_lines(char):
            return (f"must be a single line of text without control characters "
                    f"(it holds {char!r})")
    return None


def pattern(regex: str, description: str) -> Check:
    """A check that the whole value matches `regex`."""
    compiled = re.compile(regex)

    def check(value: str, context: Context | None = None) -> str | None:
        problem = single_line(value)
        if problem:
            return problem
        if not compiled.fullmatch(value):
            return f"{value!r} is not {description}"
        return None

    check.__doc__ = f"The whole value is {description}."
    check.allowed = description
    return check


def choice(*choices) -> Check:
    def check(value, context: Context | None = None) -> str | None:
        if value not in choices:
            return f"{value!r} is not one of: {', '.join(map(str, choices))}"
        return None

    check.choices = choices
    return check


def int_range(low: int, high: int, unit: str = "") -> Check:
    def check(value: int, context: Context | None = None) -> str | None:
        if not low <= value <= high:
            return f"{value}{unit} is outside {low} to {high}{unit}"
        return None

    check.allowed = f"{low} to {high}{unit}"
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
# glibc locale names roslab accepts: language[_TERRITORY][@modifier].UTF-8
utf8_locale = pattern(r"[a-z]{2,3}(_[A-Z]{2})?(@[a-z]+)?\.UTF-8", "a UTF-8 locale name like en_US.UTF-8")
# REP 144 package names; launch files by file name only (no path).
ros_package = pattern(r"[a-z][a-z0-9_]*", "a ROS package name")
launch_file_name = pattern(r"[A-Za-z0-9_][A-Za-z0-9_.-]*\.launch\.(py|xml|yaml)",
                           "a launch file name (like main.launch.py)")
# ROS 2 topic names (absolute or relative), no substitutions.
ros_topic = pattern(r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*", "a ROS topic name (like /chatter)")
version = pattern(r"[0-9]+(\.[0-9]+){1,3}", "a version like 1.2.0")
sha256_hex = pattern(r"[0-9a-f]{64}", "a sha256 (64 lower-case hex digits)")
interface_name = pattern(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,14}", "a network interface name (like eth0)")
# A colcon argument: option or value, no shell or line syntax needed.
colcon_argument = pattern(r"[A-Za-z0-9_@%+=:,./-]+", "a colcon argument (letters, digits, _ @ % + = : , . / -)")

_HOST_LABEL = re.compile(r"[a-z0-9]([a-z0-9-]{0,61}[a-z0-9])?", re.IGNORECASE)


def hostname(value: str, context: Context | None = None) -> str | None:
    """An RFC 1123 host name; all-numeric names are malformed addresses, not names."""
    problem = single_line(value)
    if problem:
        return problem
    labels = value[:-1].split(".") if value.endswith(".") else value.split(".")
    if (len(value) > 253 or not all(_HOST_LABEL.fullmatch(label) for label in labels)
            or all(label.isdigit() for label in labels)):
        return f"{value!r} is not a valid host name"
    return None


def host_label(value: str, context: Context | None = None) -> str | None:
    """One DNS label: what a Pi's own hostname is."""
    if not isinstance(value, str) or not _HOST_LABEL.fullmatch(value) or value.isdigit():
        return (f"{value!r} is not a valid hostname: letters, digits and inner '-', "
                "at most 63 characters, not all digits (it becomes the Pi's hostname)")
    return None


def ip_address(value: str, context: Context | None = None) -> str | None:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return f"{value!r} is not an IP address"
    return None


def address(value: str, context: Context | None = None) -> str | None:
    """Where SSH reaches a host: an IP address or a host name."""
    if ip_address(value) is None or hostname(value) is None:
        return None
    return f"{value!r} is neither an IP address nor a valid host name"


def ip_interface(value: str, context: Context | None = None) -> str | None:
    """An IP address with or without a prefix length (the prefix may come from network_prefix)."""
    try:
        ipaddress.ip_interface(value)
    except ValueError:
        return f"{value!r} is not an IP address (with prefix length), e.g. '192.168.50.11/24'"
    return None


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


domain_id.allowed = "0 to 101, 215 to 232"


# --- URLs and paths ---------------------------------------------------------------------

# RFC 3986's characters, without space, quotes, backslash or anything a deb822 field,
# a shell or a YAML scalar would read as syntax on its own.
_URL_CHARACTERS = re.compile(r"[A-Za-z0-9._~:/?#\[\]@!$&'()*+,;=%-]+")


def url(schemes: tuple[str, ...], placeholders: tuple[str, ...] = ()) -> Check:
    """A URL of one of `schemes`; `{name}` placeholders are allowed and filled in first."""

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
        return None

    check.allowed = " or ".join(f"{scheme}://" for scheme in schemes) + " URL"
    return check


http_url = url(("http", "https"))

# One path component inside the home directory: no `..`, no hidden tricks.
_PATH_COMPONENT = re.compile(r"[A-Za-z0-9_+][A-Za-z0-9_.+-]*")


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
    for part in components:
        if part in (".", "..") or not _PATH_COMPONENT.fullmatch(part):
            return (f"{value!r}: {part!r} is not a plain directory name "
                    "(letters, digits, _ . + -, not starting with . or -)")
    return None


def controller_path(kind: str = "any") -> Check:
    """A path on the machine running pyinfra; `kind` "file"/"dir" must exist as such."""

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

    check.controller_path = True  # the loader makes it absolute in host data
    check.allowed = {"any": "a path on this machine", "file": "an existing file on this machine",
                     "dir": "an existing directory on this machine"}[kind]
    return check


# --- composite values ---------------------------------------------------------------------

_VARIABLE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,127}")
# Variables roslab writes from its own settings, or that would change what runs: never set
# through an environment mapping.
RESERVED_VARIABLES = frozenset({
    "ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY",
    "ROSDISTRO_INDEX_URL", "HOME", "USER", "LOGNAME", "PATH", "SHELL", "LD_PRELOAD", "LD_LIBRARY_PATH",
    "PYTHONPATH", "AMENT_PREFIX_PATH", "BASH_ENV", "ENV", "IFS", "PROMPT_COMMAND",
})


def variable(name, value) -> str | None:
    """One environment variable roslab may write: a plain name, not roslab's own, one line of text."""
    if not isinstance(name, str) or not _VARIABLE_NAME.fullmatch(name):
        return f"{name!r} is not a variable name (letters, digits and _, not starting with a digit)"
    if name in RESERVED_VARIABLES:
        return f"{name} is not set through an environment mapping (roslab sets it from its own setting)"
    if not isinstance(value, str):
        return f"the value of {name} must be a string (quote it), not {value!r}"
    problem = single_line(value)
    return f"the value of {name} {problem}" if problem else None


def environment(value: dict, context: Context | None = None) -> str | None:
    """VARIABLE: value, each value one line of text."""
    for name, text in value.items():
        problem = variable(name, text)
        if problem:
            return problem
    return None


def launch(value: str, context: Context | None = None) -> str | None:
    """`<package> <launch file>`, e.g. 'roslab_bringup main.launch.py'."""
    problem = single_line(value)
    if problem:
        return problem
    words = value.split(" ")
    if len(words) != 2 or ros_package(words[0]) or launch_file_name(words[1]):
        return (f"{value!r} is not '<package> <launch file>' "
                "like 'roslab_bringup main.launch.py'")
    return None


# Public key lines authorized_keys takes (type, base64 body, optional comment).
PUBLIC_KEY = re.compile(
    r"(ssh-(ed25519|rsa|dss)|ecdsa-sha2-nistp(256|384|521)|sk-ssh-ed25519@openssh\.com"
    r"|sk-ecdsa-sha2-nistp256@openssh\.com) [A-Za-z0-9+/]+={0,3}( [^\x00-\x1f\x7f]*)?")


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
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
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


def sha256_pins(value: dict, context: Context | None = None) -> str | None:
    """Ubuntu codename -> sha256."""
    codenames = set(distros.UBUNTU_CODENAMES.values())
    for codename, digest in value.items():
        if codename not in codenames:
            return f"{codename!r} is not an Ubuntu codename roslab knows ({', '.join(sorted(codenames))})"
        if not isinstance(digest, str) or sha256_hex(digest):
            return f"the sha256 for {codename} is not 64 lower-case hex digits"
    return None


# How each plain-function check reads in the README's "allowed" column.
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
    _check.allowed = _words
