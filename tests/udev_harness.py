"""Real udev rules on emulated devices: Debian's `udevadm test` under umockdev.

The rules roslab writes for a profile's devices (roslab/profiles/devices.py) are evaluated by
udev itself, not by reading their text: umockdev (`umockdev-run`) gives udevadm a sysfs of
hand-written emulated devices, stand-ins for the hardware (below: a robot's USB-serial chips,
boards and cameras, a Pi's UARTs, I2C buses and GPIO chip, and devices no profile declares: a
keyboard, the console, a virtual terminal, a USB disk, a webcam), and `udevadm test --action=add` prints what udev
would do for each: its symlinks, mode, group and the rules that set them.

It runs in a private mount namespace (`unshare --mount`) with tmpfs on /dev and /run, a devpts
with ptmx, the rules folder bind-mounted on /etc/udev/rules.d and a group file holding a Pi's
hardware groups bind-mounted on /etc/group: `udevadm test` creates symlinks and its database,
and none of that touches this machine's /dev, /run or rules. Every configuration (one rules
file each) is evaluated in one namespace and one umockdev testbed, so a whole suite takes a
few seconds. Needs root, `unshare`, `umockdev-run` and `udevadm` (scripts/install-host-tools).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

RULES_NAME = "60-roslab-profile.rules"  # as roslab.profiles.resolve.UDEV_RULES_PATH names it
# A Pi's Ubuntu has these groups; those missing here get a number of their own in the namespace.
PI_GROUPS = ("dialout", "plugdev", "i2c", "gpio", "spi", "video", "audio", "render", "bluetooth", "tty",
             "input", "disk")


@dataclass(frozen=True)
class Emulated:
    """One emulated device: the sysfs path udevadm tests and its umockdev description."""

    sys_path: str
    description: str
    declared: bool  # a device some robot profile declares (False: one no rule may match)


def _usb(path: str, vendor: str, product: str, serial: str | None, busnum: int, devnum: int) -> str:
    """A USB device (DEVTYPE usb_device): what ATTRS{idVendor}, {serial} and KERNELS match."""
    serial_line = f"A: serial={serial}\n" if serial else ""  # a CH340 reports none
    return (f"P: {path}\nN: bus/usb/{busnum:03d}/{devnum:03d}\nE: DEVNAME=/dev/bus/usb/{busnum:03d}/{devnum:03d}\n"
            f"E: DEVTYPE=usb_device\nE: DRIVER=usb\nE: PRODUCT={vendor.lstrip('0')}/{product.lstrip('0')}/100\n"
            f"E: SUBSYSTEM=usb\nE: MAJOR=189\nE: MINOR={(busnum - 1) * 128 + devnum - 1}\n"
            f"A: idVendor={vendor}\nA: idProduct={product}\n{serial_line}A: busnum={busnum}\nA: devnum={devnum}\n"
            f"A: dev=189:{(busnum - 1) * 128 + devnum - 1}\n\n")


def _interface(path: str, driver: str) -> str:
    return f"P: {path}\nE: DEVTYPE=usb_interface\nE: DRIVER={driver}\nE: SUBSYSTEM=usb\nA: bInterfaceNumber=00\n\n"


def _node(path: str, subsystem: str, name: str, major: int, minor: int, devname: str | None = None) -> str:
    devname = devname or name
    return (f"P: {path}\nN: {devname}\nE: DEVNAME=/dev/{devname}\nE: SUBSYSTEM={subsystem}\n"
            f"E: MAJOR={major}\nE: MINOR={minor}\nA: dev={major}:{minor}\n\n")


def usb_serial(port: str, vendor: str, product: str, serial: str | None, tty: str, devnum: int) -> Emulated:
    """A USB-serial chip (CP2102, CH340, CH9102, the OpenCR's STM32 CDC) on USB `port` (1-1.2)
    with its tty (ttyUSB0 for cp210x/ch341, ttyACM0 for cdc_acm)."""
    base = f"/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb1/{port}"
    driver = "cdc_acm" if tty.startswith("ttyACM") else ("ch341" if vendor == "1a86" else "cp210x")
    major, minor = (166, int(tty[6:])) if tty.startswith("ttyACM") else (188, int(tty[6:]))
    tty_path = f"{base}/{port}:1.0/tty/{tty}" if driver == "cdc_acm" else f"{base}/{port}:1.0/{tty}/tty/{tty}"
    return Emulated(f"/sys{tty_path}", _usb(base, vendor, product, serial, 1, devnum)
                    + _interface(f"{base}/{port}:1.0", driver) + _node(tty_path, "tty", tty, major, minor), True)


def usb_device(port: str, vendor: str, product: str, devnum: int, bus: int = 1) -> Emulated:
    """A USB device a program opens through libusb (/dev/bus/usb/...): the OAK-D, a DFU board."""
    base = f"/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb{bus}/{port}"
    return Emulated(f"/sys{base}", _usb(base, vendor, product, None, bus, devnum), True)


def _undeclared(sys_path: str, description: str) -> Emulated:
    return Emulated(sys_path, description, False)


def _keyboard() -> Emulated:
    base = "/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb1/1-5"
    event = f"{base}/1-5:1.0/0003:046D:C31C.0001/input/input3/event3"
    return _undeclared(f"/sys{event}", _usb(base, "046d", "c31c", None, 1, 20) + _interface(f"{base}/1-5:1.0", "usbhid")
                       + _node(event, "input", "event3", 13, 67, "input/event3"))


def _disk() -> Emulated:
    base = "/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb2/2-2"
    block = f"{base}/2-2:1.0/host0/target0:0:0/0:0:0:0/block/sda"
    return _undeclared(f"/sys{block}", _usb(base, "0781", "5567", "4C530001", 2, 21)
                       + _interface(f"{base}/2-2:1.0", "usb-storage")
                       + _node(block, "block", "sda", 8, 0).replace("E: SUBSYSTEM=block\n",
                                                                    "E: SUBSYSTEM=block\nE: DEVTYPE=disk\n"))


def _webcam() -> Emulated:
    base = "/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb1/1-6"
    video = f"{base}/1-6:1.0/video4linux/video0"
    return _undeclared(f"/sys{video}", _usb(base, "046d", "0825", "ABCD1234", 1, 22)
                       + _interface(f"{base}/1-6:1.0", "uvcvideo") + _node(video, "video4linux", "video0", 81, 0))


def _kernel_device(path: str, subsystem: str, name: str, major: int, minor: int, declared: bool = True) -> Emulated:
    return Emulated(f"/sys{path}", _node(path, subsystem, name, major, minor), declared)


# The emulated devices, by the name the tests use. The hub (1-1) the first USB-serial chips
# share is described too, so a USB port path names a real place in the tree.
HUB = _usb("/devices/platform/scb/fd500000.pcie/pci0000:00/0000:00:00.0/0000:01:00.0/usb1/1-1",
           "2109", "3431", None, 1, 2)
DEVICES: dict[str, Emulated] = {
    "cp2102_a": usb_serial("1-1.1", "10c4", "ea60", "0001", "ttyUSB0", 3),
    "cp2102_b": usb_serial("1-1.2", "10c4", "ea60", "0002", "ttyUSB1", 4),
    "cp2102_no_serial": usb_serial("1-1.3", "10c4", "ea60", None, "ttyUSB2", 5),
    "ch340": usb_serial("1-1.4", "1a86", "7523", None, "ttyUSB3", 6),
    "ch9102": usb_serial("1-2", "1a86", "55d4", "54D2012345", "ttyACM1", 7),
    "opencr": usb_serial("1-3", "0483", "5740", "FFFFFFFEFFFF", "ttyACM0", 8),
    "opencr_dfu": usb_device("1-4", "0483", "df11", 9),
    "oakd": usb_device("2-1", "03e7", "2485", 10, bus=2),
    "gpiochip0": _kernel_device("/devices/platform/soc/fe200000.gpio/gpiochip0", "gpio", "gpiochip0", 254, 0),
    "i2c-1": _kernel_device("/devices/platform/soc/fe804000.i2c/i2c-1/i2c-dev/i2c-1", "i2c-dev", "i2c-1", 89, 1),
    "i2c-3": _kernel_device("/devices/platform/i2c@0/i2c-3/i2c-dev/i2c-3", "i2c-dev", "i2c-3", 89, 3),
    "ttyAMA0": _kernel_device("/devices/platform/soc/fe201000.serial/tty/ttyAMA0", "tty", "ttyAMA0", 204, 64),
    "ttyS0": _kernel_device("/devices/platform/soc/fe215040.serial/tty/ttyS0", "tty", "ttyS0", 4, 64),
    "keyboard": _keyboard(),
    "console": _kernel_device("/devices/virtual/tty/console", "tty", "console", 5, 1, declared=False),
    "tty1": _kernel_device("/devices/virtual/tty/tty1", "tty", "tty1", 4, 1, declared=False),
    "i2c-0": _kernel_device("/devices/platform/soc/fe205000.i2c/i2c-0/i2c-dev/i2c-0", "i2c-dev", "i2c-0", 89, 0,
                            declared=False),
    "sda": _disk(),
    "webcam": _webcam(),
}
UNDECLARED = tuple(name for name, device in DEVICES.items() if not device.declared)


@dataclass
class Outcome:
    """What udev did for one device under one rules file."""

    links: list[str] = field(default_factory=list)  # symlinks in /dev any rule gave it
    mode: str | None = None  # the last MODE set (None: udev's default)
    group: str | None = None  # the last GROUP set, by name
    roslab_device: str | None = None  # ENV{ROSLAB_DEVICE}: the declared device roslab matched
    roslab_lines: list[str] = field(default_factory=list)  # what roslab's rules file did to it
    properties: dict[str, str] = field(default_factory=dict)  # the device's udev properties after the rules
    output: str = ""

    @property
    def matched_by_roslab(self) -> bool:
        return bool(self.roslab_lines) or self.roslab_device is not None


def unavailable() -> str | None:
    """Why the harness cannot run here, or None."""
    missing = [tool for tool in ("unshare", "umockdev-run", "udevadm") if shutil.which(tool) is None]
    if missing:
        return f"{', '.join(missing)} missing: run scripts/install-host-tools (make setup)"
    if os.geteuid() != 0:
        return "udevadm in a private mount namespace needs root"
    return None


_MARK = "@@@roslab-udev-harness"
_PROPERTY = re.compile(r"[A-Z][A-Z0-9_]*=")
_APPLIED = re.compile(r"^[^:]+: (?P<file>/\S+):(?P<line>\d+) (?P<what>GROUP|MODE|LINK) '?(?P<value>[^']*)'?$")


def evaluate(configurations: dict[str, str], names: tuple[str, ...] = tuple(DEVICES)) -> dict[str, dict[str, Outcome]]:
    """{configuration: {device name: Outcome}}: each rules file's text evaluated by `udevadm test`
    on each emulated device of `names`, in one private namespace and testbed."""
    with tempfile.TemporaryDirectory(prefix="roslab-udev-") as temp:
        work = Path(temp)
        groups = _group_file(work / "group")
        arguments = []
        for index, name in enumerate(DEVICES):
            (work / f"{index}.umockdev").write_text(DEVICES[name].description)
            arguments += ["-d", str(work / f"{index}.umockdev")]
        (work / "hub.umockdev").write_text(HUB)
        keys = list(configurations)
        for index, key in enumerate(keys):
            folder = work / "rules" / str(index)
            folder.mkdir(parents=True)
            if configurations[key]:
                (folder / RULES_NAME).write_text(configurations[key])
        blocks = []
        for index in range(len(keys)):
            blocks.append(f"mount --bind {work}/rules/{index} /etc/udev/rules.d\n"
                          "rm -rf /run/udev; find /dev -maxdepth 1 -type l ! -name ptmx -delete\n"
                          + "".join(f"echo '{_MARK} {index} {name}'\n"
                                    f"udevadm test --action=add {DEVICES[name].sys_path} 2>&1 || true\n"
                                    for name in names)
                          + "umount /etc/udev/rules.d\n")
        (work / "inner.sh").write_text("".join(blocks))
        (work / "outer.sh").write_text(
            "set -e\nmount --make-rprivate /\n"
            "mount -t tmpfs tmpfs /dev\nmkdir /dev/pts\n"
            "mount -t devpts -o newinstance,ptmxmode=0666 devpts /dev/pts\nln -s pts/ptmx /dev/ptmx\n"
            "mount -t tmpfs tmpfs /run\n"
            f"mount --bind {groups} /etc/group\n"
            f"exec umockdev-run -d {work}/hub.umockdev {' '.join(arguments)} -- sh {work}/inner.sh\n")
        result = subprocess.run(["unshare", "--mount", "sh", str(work / "outer.sh")], capture_output=True,
                                text=True, timeout=120)
        if _MARK not in result.stdout:
            raise RuntimeError(f"the udev harness did not run: {result.stdout[-2000:]}{result.stderr[-2000:]}")
        return _parse(result.stdout, keys, _group_names(groups))


def _group_file(path: Path) -> Path:
    """This machine's /etc/group with a Pi's hardware groups it lacks added."""
    lines = Path("/etc/group").read_text().splitlines()
    names = {line.split(":")[0] for line in lines}
    used = {int(line.split(":")[2]) for line in lines if line.count(":") >= 3 and line.split(":")[2].isdigit()}
    free = (gid for gid in range(990, 100, -1) if gid not in used)
    lines += [f"{name}:x:{next(free)}:" for name in PI_GROUPS if name not in names]
    path.write_text("\n".join(lines) + "\n")
    return path


def _group_names(path: Path) -> dict[str, str]:
    return {line.split(":")[2]: line.split(":")[0] for line in path.read_text().splitlines() if line.count(":") >= 3}


def _parse(stdout: str, keys: list[str], group_names: dict[str, str]) -> dict[str, dict[str, Outcome]]:
    results: dict[str, dict[str, Outcome]] = {key: {} for key in keys}
    for chunk in stdout.split(_MARK)[1:]:
        head, _, output = chunk.partition("\n")
        index, name = head.split()
        outcome = Outcome(output=output)
        for line in output.splitlines():
            applied = _APPLIED.match(line)
            if _PROPERTY.match(line):
                key, value = line.split("=", 1)
                outcome.properties[key] = value
                if key == "ROSLAB_DEVICE":
                    outcome.roslab_device = value
            if applied is None:
                continue
            if applied.group("file").endswith(RULES_NAME):
                outcome.roslab_lines.append(line)
            what, value = applied.group("what"), applied.group("value")
            if what == "LINK":
                outcome.links.append(value)
            elif what == "MODE":
                outcome.mode = value
            else:
                outcome.group = group_names.get(value, value)
        results[keys[int(index)]][name] = outcome
    return results
