"""A profile's udev rules, read as udev reads them, and allowed key by key.

A profile's rules name and permit devices (the OpenCR, a lidar's adapter, the rover's
UARTs): they match a device, give it a symlink, a group and a mode, and keep ModemManager
away. They run nothing, write no sysfs attribute or sysctl, rename nothing, start no unit,
and never open a disk to the students. So a rule is parsed the way udev parses a line (keys,
operators and double-quoted values, separated by commas), each key is taken from an
allow-list with its operators, and whatever udev would read differently from what was checked
is refused: a backslash anywhere (a line ending in `\\` is joined to the next one, so `RU\\`
and `N+=` would read `RUN+=`), a key with no quotes around its value, a placeholder outside a
value (`${key}+=` filled with RUN).

`file_problems` checks the whole file as `resolve` writes it (comments and rules joined by
newlines), after the settings are filled in, so what udev reads is what was checked.
"""

from __future__ import annotations

import re

# Groups a profile may give a device or the login user: hardware access, nothing more.
# sudo, adm, shadow, disk, docker, lxd, root and the like would make a student root.
HARDWARE_GROUPS = ("dialout", "tty", "input", "video", "i2c", "gpio", "spi", "plugdev", "audio", "render",
                   "bluetooth", "uucp")
# A device of these subsystems may be opened wider (MODE, GROUP): character devices a robot's
# boards and sensors are. Block devices (disks, partitions), memory and consoles are not here.
DEVICE_SUBSYSTEMS = ("tty", "usb", "usbmisc", "hidraw", "i2c-dev", "spidev", "gpio", "input", "video4linux",
                     "sound", "iio", "pwm")
# udev's keys a profile may use, with the operators allowed for each. Match keys compare;
# assignments set only what names and permits a device. A key with {attribute} says so.
MATCH = ("==", "!=")
ALLOWED_KEYS: dict[str, tuple[str, ...]] = {
    "ACTION": MATCH, "KERNEL": MATCH, "KERNELS": MATCH, "SUBSYSTEM": MATCH, "SUBSYSTEMS": MATCH,
    "DRIVER": MATCH, "DRIVERS": MATCH, "DEVPATH": MATCH,
    "ATTR": MATCH, "ATTRS": MATCH,  # a sysfs attribute is read, never written
    "ENV": (*MATCH, "="),  # assigned: only the ENV_ASSIGNABLE names below
    "TAG": ("==", "!=", "+="), "TAGS": MATCH,
    "SYMLINK": ("==", "!=", "+="),
    "GROUP": ("=", ":="),
    "MODE": ("=", ":="),
}
WITH_ATTRIBUTE = ("ATTR", "ATTRS", "ENV")
# What ENV{...}= may set: ModemManager's "leave this port alone" (it probes serial ports and
# steals the OpenCR's or an ESP32's). SYSTEMD_WANTS, SYSTEMD_USER_WANTS and the like start units.
ENV_ASSIGNABLE = ("ID_MM_DEVICE_IGNORE", "ID_MM_PORT_IGNORE", "ID_MM_CANDIDATE")
# TAG+= "uaccess" gives the seat's user the device; "systemd" (with SYSTEMD_WANTS) starts units.
TAGS_ASSIGNABLE = ("uaccess",)
# A symlink in /dev: one plain name (no folders: /dev/disk/by-uuid/... is how fstab finds disks).
_SYMLINK = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,63}", re.ASCII)
# A mode: three octal digits, or four with a leading 0 (no setuid, setgid or sticky bit).
_MODE = re.compile(r"0?[0-7]{3}", re.ASCII)
_ASSIGNMENT = re.compile(
    r"\s*(?P<key>[A-Z_]+)(\{(?P<attribute>[A-Za-z0-9_.:/*?-]+)\})?\s*(?P<op>==|!=|\+=|-=|:=|=)\s*"
    r"\"(?P<value>[^\"]*)\"\s*(?P<end>,|$)", re.ASCII)
_PLACEHOLDER = re.compile(r"\$\{[A-Za-z0-9_]*\}")


# Kernel names that are consoles or memory, whatever the subsystem says: never opened wider.
_CONSOLES = re.compile(r"tty[0-9]*|console|ptmx|tty[0-9]+.*|mem|kmem|port|vcs.*", re.ASCII)


def _names_devices(kernel: str) -> bool:
    """Whether a KERNEL=="..." value names particular devices: each alternative (udev's `|`)
    starts with at least four plain characters (ttyUSB*, i2c-1, ttyS0) and is not a console."""
    for alternative in kernel.split("|"):
        literal = re.split(r"[*?\[]", alternative, maxsplit=1)[0]
        if len(literal) < 4 or _CONSOLES.fullmatch(literal):
            return False
    return True


def rule_problem(rule: str) -> str | None:
    """Why `rule` (one rule line, ${settings} only inside values) is not a rule a profile may
    write, or None."""
    if not rule.isascii():
        return "a udev rule is plain ASCII"
    if "\\" in rule:
        return ("a udev rule holds no backslash (udev joins a line ending in \\ to the next one, and reads "
                "escapes inside values)")
    if rule.lstrip().startswith("#") or not rule.strip():
        return "a rule is keys and values (a comment goes in 'comment')"
    pairs = _pairs(rule)
    if isinstance(pairs, str):
        return pairs
    for match in pairs:
        problem = _pair_problem(*match.group("key", "attribute", "op", "value"))
        if problem:
            return problem
    return _access_problem(pairs)


def _pairs(rule: str) -> list[re.Match] | str:
    """The rule's KEY op "value" pairs as udev reads them, or why udev would not read it so."""
    pairs = []
    position = 0
    while position < len(rule):
        match = _ASSIGNMENT.match(rule, position)
        if match is None:
            rest = rule[position:].strip()
            return (f"udev would not read {rest[:40]!r} as KEY==\"value\" or KEY=\"value\": each key's value "
                    "is in double quotes, keys are separated by commas")
        pairs.append(match)
        position = match.end()
        if match.group("end") == "" and position < len(rule):
            return "keys are separated by commas"
    if rule.rstrip().endswith(","):
        return "a rule does not end in a comma"
    return pairs


def _pair_problem(key: str, attribute: str | None, op: str, value: str) -> str | None:
    """Why one KEY{attribute} op "value" is not allowed in a profile's rule, or None."""
    named = f"{key}{{{attribute}}}" if attribute else key
    if key not in ALLOWED_KEYS:
        return (f"{named} is not a key a profile's rule may use (allowed: {', '.join(ALLOWED_KEYS)}): a "
                "profile's rules match, name and permit devices; they run nothing, write nothing, "
                "start nothing")
    if (attribute is None) == (key in WITH_ATTRIBUTE):
        return f"{named}: {key} {'needs' if key in WITH_ATTRIBUTE else 'takes no'} {{attribute}}"
    if op not in ALLOWED_KEYS[key]:
        return f"{named}{op}: {key} allows {' '.join(ALLOWED_KEYS[key])} only"
    if "%" in value or ("$" in _PLACEHOLDER.sub("", value)):
        return f"{named}: udev substitutes $ and % in values: write the value without them"
    if _PLACEHOLDER.search(value) and op not in MATCH:
        return f"{named}{op}: a setting (${{...}}) may fill a value that is compared, not one that is set"
    if key == "ENV" and op == "=" and (attribute not in ENV_ASSIGNABLE or value not in ("0", "1")):
        return (f"{named}=: a rule may set only {', '.join(ENV_ASSIGNABLE)} (to \"0\" or \"1\"); other "
                "variables start units or change how udev treats the device")
    if key == "TAG" and op == "+=" and value not in TAGS_ASSIGNABLE:
        return f"TAG+=\"{value}\": a rule may add only the tags {', '.join(TAGS_ASSIGNABLE)}"
    if key == "SYMLINK" and op == "+=" and not all(_SYMLINK.fullmatch(name) for name in value.split()):
        return (f"SYMLINK+=\"{value}\": each symlink is one plain name in /dev (letters, digits, _ . + -), "
                "no folders")
    if key == "GROUP" and value not in HARDWARE_GROUPS:
        return f"GROUP=\"{value}\" is not a hardware-access group ({', '.join(HARDWARE_GROUPS)})"
    if key == "MODE" and not _MODE.fullmatch(value):
        return f"MODE=\"{value}\" is not a plain octal mode like 0660 (no setuid, setgid or sticky bit)"
    if attribute is not None and ".." in attribute.split("/"):
        return f"{named}: an attribute is the device's own (no '..')"
    return None


def _access_problem(pairs: list[re.Match]) -> str | None:
    """A rule that sets MODE or GROUP must match a device subsystem and name its device."""
    assigns_access = any(match.group("key") in ("MODE", "GROUP") for match in pairs)
    if not assigns_access:
        return None
    subsystems = [match.group("value") for match in pairs
                  if match.group("key") == "SUBSYSTEM" and match.group("op") == "=="]
    names_the_device = any(
        match.group("op") == "==" and (
            (match.group("key") in ("ATTR", "ATTRS") and match.group("value").strip("*?[]|"))
            or (match.group("key") in ("KERNEL", "KERNELS") and _names_devices(match.group("value"))))
        for match in pairs)
    if not (subsystems and all(name in DEVICE_SUBSYSTEMS for name in subsystems)):
        return (f"a rule that sets MODE or GROUP matches SUBSYSTEM==\"...\", one of {', '.join(DEVICE_SUBSYSTEMS)}"
                " (never a disk, memory or a console)")
    if not names_the_device:
        return ("a rule that sets MODE or GROUP names its device too: ATTRS{idVendor}==, ATTRS{serial}== or "
                "KERNEL==\"ttyUSB0\" (not every device of its subsystem)")
    return None


def file_problem(text: str) -> str | None:
    """Why the udev rules file `text` (as written, settings filled in) is not what was checked,
    or None: every line a comment or an allowed rule, none continued."""
    for number, line in enumerate(text.split("\n"), 1):
        if line.endswith("\\"):
            return f"line {number} of the rules file ends in a backslash: udev would join it to the next"
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        problem = rule_problem(line)
        if problem:
            return f"line {number} of the rules file: {problem}"
    return None
