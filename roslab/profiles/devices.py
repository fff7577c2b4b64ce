"""A profile's devices, declared as data; the udev rules for them are written by roslab only.

A robot opens a few devices: a lidar's USB-serial adapter, a microcontroller board, a camera,
the Pi's UARTs, I2C buses and GPIO chip. A profile names each under `devices:` (in a side or a
`when` block), one mapping of these keys:

    name          what the device is, a word (lidar, opencr, esp32): each rule roslab writes
                  for it sets ENV{ROSLAB_DEVICE}="<name>", so `udevadm info` tells what roslab matched
    kind          one of KINDS (below): what udev matches the device by
    usb_ids       usb_serial, usb, joystick: ["vvvv:pppp", ...] (hex; pppp may be * for `usb`)
    identify_by   usb_serial: serial (its chip's serial number), port (the USB port path, for a
                  chip without a serial number: a CH340) or only (the only such chip on the host)
    serial        identify_by serial: the serial number, or a profile setting (${lds_usb_serial})
    port_path     identify_by port: the USB port path (1-1.2), or a profile setting
    kernel        i2c, spi, gpio, uart: the kernel's name (i2c-3, spidev0.0, gpiochip0, ttyAMA0)
    symlink       the name in /dev the robot's software opens (tb3_lidar, RPLIDAR, serial1)
    group, mode   who may open it: GROUPS and MODES only
    modemmanager  ignore: ModemManager never probes it (it steals a board's serial port)
    comment       one line, written above the rules

No profile writes rule text (`udev_rules:` is refused, pointing here): a rule's text decides
what it matches, and a keyboard, a console or a disk is one wrong glob away.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from roslab import formats

# Where a profile's rules are read from and what udev matches each kind by.
KINDS = ("usb_serial", "usb", "i2c", "spi", "gpio", "uart", "joystick")
USB_KINDS = ("usb_serial", "usb", "joystick")
# A kernel-named device's subsystem and the names it may have (a Pi's UARTs, buses and chips).
KERNEL_NAMES = {
    "i2c": ("i2c-dev", re.compile(r"i2c-[0-9]{1,2}", re.ASCII)),
    "spi": ("spidev", re.compile(r"spidev[0-9]\.[0-9]", re.ASCII)),
    "gpio": ("gpio", re.compile(r"gpiochip[0-9]{1,2}", re.ASCII)),
    "uart": ("tty", re.compile(r"ttyAMA[0-9]|ttyS0", re.ASCII)),
}
IDENTIFY_BY = ("serial", "port", "only")
# Groups a device may be given: hardware access, nothing more. Never input (every keyboard),
# tty (every console), disk, kmem, shadow, sudo, adm, root.
GROUPS = ("dialout", "plugdev", "i2c", "gpio", "spi", "video", "audio", "render", "bluetooth")
MODES = ("0600", "0640", "0644", "0660", "0664", "0666")
# Groups a profile may give the login user (`groups:`): these, and tty and input, which a
# Pi's UART and a joystick have on Ubuntu by default.
LOGIN_GROUPS = (*GROUPS, "tty", "input", "uucp")
DEVICE_KEYS = ("name", "kind", "usb_ids", "identify_by", "serial", "port_path", "kernel", "symlink", "group",
               "mode", "modemmanager", "comment")
_NAME = re.compile(r"[a-z][a-z0-9_]{0,30}", re.ASCII)
_USB_ID = re.compile(r"(?P<vendor>[0-9a-f]{4}):(?P<product>[0-9a-f]{4}|\*)", re.ASCII)
_SERIAL = re.compile(r"[A-Za-z0-9_.-]{1,64}", re.ASCII)
_PORT_PATH = re.compile(r"[0-9]{1,2}-[0-9]{1,2}(\.[0-9]{1,2}){0,5}", re.ASCII)
_SETTING = re.compile(r"\$\{([a-z][a-z0-9_]{0,62})\}", re.ASCII)
_SYMLINK = re.compile(r"[A-Za-z][A-Za-z0-9_.+-]{0,63}", re.ASCII)
# Names in /dev that are the system's (devices, or links the system keeps): never a symlink.
_SYSTEM_NAMES = re.compile(
    r"(tty|sd|hd|vd|nvme|mmcblk|loop|ram|vcs|dm-|md|sr|nbd|zram|console|ptmx|std|mem|kmem|null|zero|random"
    r"|urandom|full|fd|core|log|initctl|shm|pts|mqueue|hugepages|kvm|fuse|uinput|rtc|watchdog|snd|dri|input"
    r"|i2c-|spidev|gpiochip|gpiomem|disk|block|char|bus|cpu|port|tpm|vhost|net|mapper|serial/).*", re.ASCII)


@dataclass(frozen=True)
class Device:
    """One declared device; serial and port_path may be ${settings}, filled at resolve."""

    name: str
    kind: str
    usb_ids: tuple[str, ...] = ()
    identify_by: str = "only"
    serial: str | None = None
    port_path: str | None = None
    kernel: str | None = None
    symlink: str | None = None
    group: str | None = None
    mode: str | None = None
    modemmanager: str | None = None
    comment: str = ""

    def settings(self) -> list[str]:
        """The profile settings it names."""
        return [name for text in (self.serial, self.port_path) if text for name in _SETTING.findall(text)]


def read_device(spec, known: set[str]) -> tuple[Device | None, list[tuple[str | None, str]]]:
    """A Device from one `devices:` entry, or None; and its problems as (key, message)."""
    if not isinstance(spec, dict):
        return None, [(None, f"each device is a mapping ({', '.join(DEVICE_KEYS)})")]
    problems = [(key, f"unknown key {key!r} in a device (keys: {', '.join(DEVICE_KEYS)})")
                for key in spec if key not in DEVICE_KEYS]
    kind = spec.get("kind")
    if kind not in KINDS:
        return None, [*problems, ("kind", f"{kind!r} is not a device kind roslab writes rules for "
                                          f"({', '.join(KINDS)})")]
    for key, check in (("name", _name_problem), ("symlink", _symlink_problem), ("group", _group_problem),
                       ("mode", _mode_problem), ("comment", _comment_problem),
                       ("modemmanager", lambda v: None if v == "ignore" else "is 'ignore' or absent")):
        value = spec.get(key)
        if value is not None or key == "name":
            problem = check(value) if isinstance(value, str) else "must be a string"
            if problem:
                problems.append((key, problem))
    problems += _kind_problems(kind, spec, known)
    if problems:
        return None, problems
    return Device(spec["name"], kind, tuple(spec.get("usb_ids") or ()), spec.get("identify_by", "only"),
                  spec.get("serial"), spec.get("port_path"), spec.get("kernel"), spec.get("symlink"),
                  spec.get("group"), spec.get("mode"), spec.get("modemmanager"), spec.get("comment") or ""), []


def _kind_problems(kind: str, spec: dict, known: set[str]) -> list[tuple[str, str]]:
    """What a device of `kind` needs and may not have: ids or a kernel name, how it is identified."""
    problems = []
    usb_keys = ("usb_ids",) if kind in USB_KINDS else ()
    serial_keys = ("identify_by", "serial", "port_path") if kind == "usb_serial" else ()
    kernel_keys = ("kernel",) if kind in KERNEL_NAMES else ()
    for key in ("usb_ids", "identify_by", "serial", "port_path", "kernel"):
        if key in spec and key not in (*usb_keys, *serial_keys, *kernel_keys):
            problems.append((key, f"a {kind} device has no {key}"))
    if usb_keys:
        problems += _usb_ids_problems(kind, spec.get("usb_ids"))
    if kernel_keys:
        subsystem, pattern = KERNEL_NAMES[kind]
        kernel = spec.get("kernel")
        if not isinstance(kernel, str) or not pattern.fullmatch(kernel):
            problems.append(("kernel", f"{kernel!r} is not the kernel's name of a {kind} device "
                                       f"({pattern.pattern})"))
    if serial_keys:
        problems += _identify_problems(spec, known)
    return problems


def _usb_ids_problems(kind: str, ids) -> list[tuple[str, str]]:
    if not isinstance(ids, list) or not ids or not all(isinstance(item, str) for item in ids):
        return [("usb_ids", 'must be a list of USB vendor:product ids ("10c4:ea60")')]
    for item in ids:
        match = _USB_ID.fullmatch(item)
        if match is None:
            return [("usb_ids", f"{item!r} is not a USB vendor:product id (four lower-case hex digits each, "
                                '"10c4:ea60")')]
        if match.group("product") == "*" and kind != "usb":
            return [("usb_ids", f"{item!r}: a {kind} device names its product (only a usb device may be "
                                "every product of a vendor)")]
    return []


def _identify_problems(spec: dict, known: set[str]) -> list[tuple[str, str]]:
    """A USB-serial chip told apart by its serial number, its USB port path, or as the only one."""
    identify = spec.get("identify_by", "only")
    if identify not in IDENTIFY_BY:
        return [("identify_by", f"{identify!r} is not one of {', '.join(IDENTIFY_BY)}")]
    problems = []
    for key, needed_by, pattern in (("serial", "serial", _SERIAL), ("port_path", "port", _PORT_PATH)):
        value = spec.get(key)
        if (value is None) == (identify == needed_by):
            problems.append((key, f"identify_by {needed_by} needs {key}" if value is None else
                                  f"{key} is given only with identify_by {needed_by}"))
        elif value is not None:
            problems += [(key, problem) for problem in [_value_problem(value, pattern, known)] if problem]
    return problems


def _value_problem(value, pattern: re.Pattern, known: set[str]) -> str | None:
    """A literal value of `pattern`, or one ${setting} of the profile."""
    if not isinstance(value, str):
        return "must be a string"
    setting = _SETTING.fullmatch(value)
    if setting:
        return None if setting.group(1) in known else f"names ${{{setting.group(1)}}}, not a setting of this profile"
    return None if pattern.fullmatch(value) else f"{value!r} is not a value of {pattern.pattern} or one ${{setting}}"


def _name_problem(value: str) -> str | None:
    return None if _NAME.fullmatch(value) else "a device's name is lower-case letters, digits and _ (lidar, opencr)"


def _symlink_problem(value: str) -> str | None:
    if not _SYMLINK.fullmatch(value):
        return f"{value!r} is not one plain name in /dev (letters, digits, _ . + -; no folders)"
    if _SYSTEM_NAMES.fullmatch(value):
        return f"{value!r} is a name the system's own devices have in /dev: give the device a name of its own"
    return None


def _group_problem(value: str) -> str | None:
    return None if value in GROUPS else f"{value!r} is not a group a device may be given ({', '.join(GROUPS)})"


def _mode_problem(value: str) -> str | None:
    return None if value in MODES else f"{value!r} is not a mode a device may be given ({', '.join(MODES)})"


def _comment_problem(value: str) -> str | None:
    problem = formats.single_line(value) or ("" if value.isascii() else "must be plain ASCII")
    return problem or ("holds a backslash" if "\\" in value else None)


def filled(device: Device, values: dict) -> Device | str:
    """`device` with its ${settings} filled from `values` (checked), or why it cannot be."""
    changes = {}
    for key, pattern in (("serial", _SERIAL), ("port_path", _PORT_PATH)):
        text = getattr(device, key)
        setting = _SETTING.fullmatch(text) if text else None
        if setting:
            value = values.get(setting.group(1))
            if value is None or not pattern.fullmatch(str(value)):
                return (f"device {device.name!r}: {key} ${{{setting.group(1)}}} is "
                        f"{'unset' if value is None else repr(value)}, not a value of {pattern.pattern}")
            changes[key] = str(value)
    return Device(**{**device.__dict__, **changes})


def rules(device: Device) -> list[str]:
    """The udev rules for one (filled) device: one per USB id, else one."""
    assign = [f'ENV{{ROSLAB_DEVICE}}="{device.name}"']
    if device.modemmanager == "ignore":
        assign.insert(0, 'ENV{ID_MM_DEVICE_IGNORE}="1"')
    assign += [f'{key}="{value}"' for key, value in (("GROUP", device.group), ("MODE", device.mode)) if value]
    if device.symlink:
        assign.append(f'SYMLINK+="{device.symlink}"')
    if device.kind in KERNEL_NAMES:
        matches = [[f'SUBSYSTEM=="{KERNEL_NAMES[device.kind][0]}"', f'KERNEL=="{device.kernel}"']]
    else:
        matches = [_usb_match(device, usb_id) for usb_id in device.usb_ids]
    return [", ".join([*match, *assign]) for match in matches]


def _usb_match(device: Device, usb_id: str) -> list[str]:
    vendor, product = usb_id.split(":")
    if device.kind == "usb":  # the USB device itself (libusb opens /dev/bus/usb/...)
        match = ['SUBSYSTEM=="usb"', 'ENV{DEVTYPE}=="usb_device"', f'ATTR{{idVendor}}=="{vendor}"']
        return match + ([f'ATTR{{idProduct}}=="{product}"'] if product != "*" else [])
    subsystem = 'SUBSYSTEM=="tty"' if device.kind == "usb_serial" else 'SUBSYSTEM=="input", KERNEL=="js[0-9]*"'
    match = [subsystem, f'ATTRS{{idVendor}}=="{vendor}"', f'ATTRS{{idProduct}}=="{product}"']
    if device.identify_by == "serial":
        match.append(f'ATTRS{{serial}}=="{device.serial}"')
    elif device.identify_by == "port":
        match.append(f'KERNELS=="{device.port_path}"')
    return match


def rules_file(profile_name: str, devices: list[Device]) -> str:
    """The rules file's text for these (filled) devices, "" for none."""
    if not devices:
        return ""
    lines = [f"# managed by roslab (deploy/robot_profile.py) for robot profile {profile_name!r}, written from "
             "its devices:", "# edits here are overwritten; set the profile's settings in the roster instead."]
    for device in devices:
        lines.append(f"# {device.name} ({device.kind}){': ' + device.comment if device.comment else ''}")
        lines += rules(device)
    return "\n".join(lines) + "\n"


# What each line roslab writes looks like, to read a rules file back (a hand-made inventory's
# or --data's `roslab_profile.udev_rules` was not written here): a comment, or one device's rule.
_HEX = "[0-9a-f]{4}"
_USB_SERIAL_MATCH = (rf'SUBSYSTEM=="tty", ATTRS\{{idVendor\}}=="{_HEX}", ATTRS\{{idProduct\}}=="{_HEX}"'
                     rf'(, ATTRS\{{serial\}}=="{_SERIAL.pattern}"|, KERNELS=="{_PORT_PATH.pattern}")?')
_JOYSTICK_MATCH = (rf'SUBSYSTEM=="input", KERNEL=="js\[0-9\]\*", ATTRS\{{idVendor\}}=="{_HEX}", '
                   rf'ATTRS\{{idProduct\}}=="{_HEX}"(, ATTRS\{{serial\}}=="{_SERIAL.pattern}"|, '
                   rf'KERNELS=="{_PORT_PATH.pattern}")?')
_USB_MATCH = rf'SUBSYSTEM=="usb", ENV\{{DEVTYPE\}}=="usb_device", ATTR\{{idVendor\}}=="{_HEX}"(, ATTR\{{idProduct\}}=="{_HEX}")?'
_KERNEL_MATCH = "|".join(rf'SUBSYSTEM=="{re.escape(subsystem)}", KERNEL=="({pattern.pattern})"'
                         for subsystem, pattern in KERNEL_NAMES.values())
_RULE_LINE = re.compile(
    rf'({_USB_SERIAL_MATCH}|{_JOYSTICK_MATCH}|{_USB_MATCH}|{_KERNEL_MATCH})'
    rf'(, ENV\{{ID_MM_DEVICE_IGNORE\}}="1")?, ENV\{{ROSLAB_DEVICE\}}="{_NAME.pattern}"'
    rf'(, GROUP="({"|".join(GROUPS)})")?(, MODE="({"|".join(MODES)})")?(, SYMLINK\+="{_SYMLINK.pattern}")?', re.ASCII)


def rules_text_problem(text: str) -> str | None:
    """Why `text` is not a rules file roslab writes from devices (a line it would not write), or None."""
    for number, line in enumerate(text.split("\n"), 1):
        if not line or (line.startswith("# ") and "\\" not in line and line.isascii()):
            continue
        if not _RULE_LINE.fullmatch(line):
            return (f"line {number} of its udev rules is not one roslab writes from a profile's devices "
                    f"({line[:60]!r}): declare devices in a profile instead")
        symlink = re.search(r'SYMLINK\+="([^"]*)"', line)
        if symlink and _SYSTEM_NAMES.fullmatch(symlink.group(1)):
            return f"line {number} of its udev rules names a system device's name as a symlink"
    return None
