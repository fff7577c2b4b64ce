"""`roslab opencr-update [ROSTER] --limit ROBOT`: flash a TurtleBot3's OpenCR firmware on the robot
it is attached to, with ROBOTIS's own archive and flasher.

ROBOTIS's way (e-Manual, "OpenCR setup"): download `opencr_update.tar.bz2` (gzip despite its name:
`tar -xf`, never `-xj`), unpack it on the robot's Pi and run `./update.sh <port> <firmware>.opencr`
with the board attached by USB. The archive holds `burger.opencr`, `waffle.opencr` and
`turtlebot3_manipulation.opencr` (a Waffle Pi runs `waffle`), ROBOTIS's flasher for x86-64 and
for 32-bit ARM, and `update.sh`, which picks the flasher by `uname -m` (aarch64 -> the ARM one)
and runs `<flasher> <port> 115200 <firmware>.opencr 1`.

Here the controller downloads the archive (`--url`; kept in the controller's cache under its
sha256) and refuses one whose sha256 is not the pinned one (`--sha256`) before anything reaches
a robot. For each robot, in order, each step one line:
- the port: a device that udev says is an OpenCR (USB 0483:5740); a port that does not exist,
  or that udev names as another device, is refused; one udev cannot identify only with
  `--allow-unidentified-port`;
- on a 64-bit ARM Pi (aarch64), the ARM flasher is a 32-bit armhf program: the armhf
  architecture and `libc6:armhf` are added where missing (the e-Manual's `dpkg
  --add-architecture armhf`, `apt install libc6:armhf`), nothing where present;
- the archive uploaded to a root-only folder, its sha256 checked there again, unpacked with
  `tar -xf`, and ROBOTIS's `update.sh` run; the flasher exits 0 whether or not a board answered,
  so its own output says how it went: `[OK] Download` is a flashed board, a failed board-name
  request is "no OpenCR answered on <port>".
"""

from __future__ import annotations

import argparse
import io
import re
import sys
from pathlib import Path

from pyinfra.api import FactBase

from roslab.host_settings import HostSettings
from roslab.quoting import shell_word

OPENCR_USB_ID = "0483:5740"
UPDATE_URL = ("https://github.com/ROBOTIS-GIT/OpenCR-Binaries/raw/master/turtlebot3/ROS2/latest/"
              "opencr_update.tar.bz2")
# sha256 of ROBOTIS-GIT/OpenCR-Binaries master 57ac580 (2023-01-27), turtlebot3/ROS2/latest.
ARCHIVE_SHA256 = "df13eba4e915c6ab4ed225329c8a02ebd69cd5655675e9d60f72214c4d029518"
ARCHIVE_NAME = "opencr_update.tar.bz2"
ARCHIVE_FOLDER = "opencr_update"  # the one folder the archive unpacks to
REMOTE_DIR = "/var/lib/roslab/opencr-update"  # root's, mode 0700: nobody swaps the flasher
# turtlebot3_model -> the archive's firmware (<name>.opencr): there is no waffle_pi.opencr.
FIRMWARE = {"burger": "burger", "waffle": "waffle", "waffle_pi": "waffle"}
PORT_FORMAT = re.compile(r"/dev/[A-Za-z0-9_][A-Za-z0-9_./-]*")


def firmware_name(model: str) -> str:
    """The archive's firmware for a `turtlebot3_model` (KeyError for an unknown model)."""
    return FIRMWARE[model]


def port_argument(value: str) -> str:
    """`--port`: a device path under /dev (no `..`), for argparse."""
    if not PORT_FORMAT.fullmatch(value) or "/../" in value + "/":
        raise argparse.ArgumentTypeError(f"{value!r} is not a device path under /dev (like /dev/ttyACM0)")
    return value


def sha256_argument(value: str) -> str:
    """`--sha256`: 64 hex digits, for argparse."""
    if not re.fullmatch(r"[0-9a-fA-F]{64}", value):
        raise argparse.ArgumentTypeError(f"{value!r} is not a sha256 (64 hex digits)")
    return value.lower()


class UsbSerialPort(FactBase):
    """`vendor:product` of the USB device behind a serial port, "" when udev cannot say, None when
    the port does not exist."""

    def command(self, port: str) -> str:
        quoted = shell_word(port)
        return (f"if [ -e {quoted} ]; then printf 'present '; "
                f"udevadm info -q property -n {quoted} 2>/dev/null | "
                "sed -n 's/^ID_VENDOR_ID=//p;s/^ID_MODEL_ID=//p' | tr '\\n' ' '; echo; "
                "else echo missing; fi")

    def process(self, output):
        words = " ".join(output).split()
        if not words or words[0] == "missing":
            return None
        return ":".join(words[1:3]) if len(words) >= 3 else ""


def port_problem(host_name: str, port: str, usb_id: str | None, allow_unidentified: bool = False) -> str | None:
    """Why the OpenCR cannot be flashed through `port`, in one line, or None."""
    if usb_id is None:
        return (f"no OpenCR board on {host_name}: {port} does not exist "
                "(attach the OpenCR to the Pi by USB and run this again)")
    if usb_id == "" and allow_unidentified:
        return None
    if usb_id != OPENCR_USB_ID:
        shown = usb_id or "a device udev cannot identify"
        hint = " (--allow-unidentified-port flashes through it all the same)" if not usb_id else ""
        return f"{port} on {host_name} is {shown}, not an OpenCR ({OPENCR_USB_ID}): nothing was flashed{hint}"
    return None


class FlasherArchitecture(FactBase):
    """What the flasher needs from the host: `uname -m`, whether dpkg has the armhf architecture
    and whether libc6:armhf is installed -> {"machine": str, "armhf": bool, "libc6_armhf": bool}."""

    def command(self) -> str:
        return ("uname -m; dpkg --print-foreign-architectures 2>/dev/null | tr '\\n' ' '; echo; "
                "dpkg-query -W -f '${Status}' libc6:armhf 2>/dev/null; echo")

    def process(self, output):
        lines = [*output, "", "", ""]
        return {"machine": lines[0].strip(), "armhf": "armhf" in lines[1].split(),
                "libc6_armhf": lines[2].strip() == "install ok installed"}


def armhf_commands(facts: dict) -> tuple[list[str], str]:
    """The commands that make ROBOTIS's 32-bit ARM flasher runnable on the host, and one line
    saying what they do (or why there are none)."""
    machine = facts["machine"]
    if machine != "aarch64":
        return [], f"{machine}: update.sh runs {'the ARM' if machine.startswith('arm') else 'the x86'} flasher natively"
    if facts["armhf"] and facts["libc6_armhf"]:
        return [], "aarch64: armhf and libc6:armhf already present for ROBOTIS's 32-bit ARM flasher"
    commands = [] if facts["armhf"] else ["dpkg --add-architecture armhf"]
    commands += ["apt-get update", "DEBIAN_FRONTEND=noninteractive apt-get install -y libc6:armhf"]
    added = "added the armhf architecture and " if not facts["armhf"] else ""
    return commands, f"aarch64: {added}installed libc6:armhf for ROBOTIS's 32-bit ARM flasher"


def flash_script(port: str, firmware: str, sha256: str = ARCHIVE_SHA256) -> str:
    """What runs on the robot (as root) once the archive is in REMOTE_DIR: its sha256 checked
    again, unpacked afresh with `tar -xf` (gzip), and ROBOTIS's update.sh run from its folder."""
    return " && ".join([
        f"cd {REMOTE_DIR}",
        f"echo {shell_word(f'{sha256}  {ARCHIVE_NAME}')} | sha256sum -c --quiet -",
        f"rm -rf {ARCHIVE_FOLDER}",
        f"tar -xf {ARCHIVE_NAME} --no-same-owner --no-same-permissions",
        f"cd {ARCHIVE_FOLDER}",
        f"{{ test -f {shell_word(firmware + '.opencr')} || "
        f"{{ echo 'no {firmware}.opencr in the archive'; exit 1; }}; }}",
        f"./update.sh {shell_word(port)} {shell_word(firmware + '.opencr')}",
    ])


def flasher_verdict(port: str, firmware: str, output: str) -> tuple[bool, str]:
    """(flashed?, one line) from what ROBOTIS's update.sh printed: the flasher exits 0 either way."""
    lines = [line.strip() for line in output.splitlines()]
    if any(line.startswith("[OK] Download") for line in lines) and not any(
            line.startswith("[NG] Download") for line in lines):
        return True, f"flashed {firmware}.opencr through {port}"
    if any("cmd_read_board_name fail" in line for line in lines):
        return False, f"no OpenCR answered on {port}: nothing was flashed"
    if any("Fail to open port" in line for line in lines):
        return False, f"ROBOTIS's flasher could not open {port}"
    failed = next((line for line in lines if line.startswith("[NG]")), None)
    if failed:
        return False, f"ROBOTIS's flasher failed on {port}: {' '.join(failed.split())}"
    return False, f"ROBOTIS's flasher did not report a download on {port}"


def run(args: argparse.Namespace) -> int:
    """`roslab opencr-update [ROSTER] [--limit NAME ...]`: the roster loaded and the robots
    reached as every roslab command does (roslab.reach), uploads as deploy.py makes them
    (roslab.remote_files). The archive is had and checked once, before any robot is reached;
    then each TurtleBot3 robot `--limit` selects in turn; one that fails leaves the others to go on."""
    from pyinfra.api.connect import disconnect_all

    from roslab import remote_files
    from roslab.reach import (
        RosterProblem, connected_state, limited_hosts, load_classroom_groups, stale_host_form,
    )

    stale = stale_host_form(args, "opencr-update")
    if stale:
        print(stale, file=sys.stderr)
        return 2
    try:
        classroom, groups = load_classroom_groups(args.roster, "opencr-update")
    except RosterProblem as error:
        print(error, file=sys.stderr)
        return 1
    hosts, problem = limited_hosts(classroom, args.limit, "roslab opencr-update")
    if problem:
        print(problem, file=sys.stderr)
        return 2
    robots = [host for host in hosts if turtlebot3_model(host)]
    if not robots:
        shown = ", ".join(host.name for host in hosts)
        print(f"roslab opencr-update: {shown} {'is' if len(hosts) == 1 else 'are'} not a TurtleBot3 robot "
              "in the roster (role robot with robot_profile: turtlebot3)", file=sys.stderr)
        return 2
    archive = checked_archive(args, robots[0].settings)
    if archive is None:
        return 1

    remote_files.install()  # the archive's upload: one command, never through a link
    state = connected_state(groups, [host.name for host in robots])
    try:
        reached = {target.name: target for target in state.inventory.iter_activated_hosts()
                   if target in state.active_hosts}
        failed = 0
        for host in robots:
            if host.name not in reached:
                print(f"roslab opencr-update: cannot reach {host.name}", file=sys.stderr)
                failed += 1
            elif not flash(host, reached[host.name], args, archive):
                failed += 1
        return 1 if failed else 0
    finally:
        disconnect_all(state)


def turtlebot3_model(host) -> str | None:
    """The robot's `turtlebot3_model`, or None where the host is not a TurtleBot3 robot."""
    profile = host.settings.roslab_profile
    return (profile.settings if profile is not None else {}).get("turtlebot3_model") if host.role == "robot" else None


def checked_archive(args: argparse.Namespace, typed: HostSettings) -> bytes | None:
    """ROBOTIS's archive from `--url` whose sha256 is `--sha256` (kept in the controller's cache
    under it, for the offline mode), or None after one line saying why not."""
    from roslab import downloads

    try:
        return downloads.pinned(args.url, args.sha256, Path(typed.rosdep_cache_dir).expanduser() / "opencr",
                                ARCHIVE_NAME, "--sha256", offline=bool(typed.offline))
    except downloads.DownloadError as error:
        print(f"roslab opencr-update: {error}; no robot was flashed", file=sys.stderr)
        return None


def ensure_armhf_flasher(host, target) -> bool:
    """On a 64-bit ARM Pi: the armhf architecture and libc6:armhf that ROBOTIS's 32-bit ARM
    flasher needs, added where missing; one line says what was done or why nothing was."""
    commands, line = armhf_commands(target.get_fact(FlasherArchitecture))
    for command in commands:
        ok, output = target.run_shell_command(command, _sudo=True)
        if not ok:
            last = next((text for text in reversed(output.output_lines) if text.strip()), "no output")
            print(f"{host.name}: `{command}` failed ({last.strip()}): nothing was flashed", file=sys.stderr)
            return False
    print(f"{host.name}: {line}")
    return True


def flash(host, target, args: argparse.Namespace, archive: bytes) -> bool:
    """Check the robot's port and the flasher's architecture, then run ROBOTIS's update.sh there
    with the model's firmware; one line says how it went, judged from the flasher's output."""
    model = turtlebot3_model(host)
    if model is None:  # the robots flashed are the TurtleBot3 ones (turtlebot3_model set)
        raise ValueError(f"{host.name} is not a TurtleBot3 robot")
    firmware = firmware_name(model)
    usb_id = target.get_fact(UsbSerialPort, port=args.port)
    problem = port_problem(host.name, args.port, usb_id, args.allow_unidentified_port)
    if problem:
        print(problem, file=sys.stderr)
        return False
    if usb_id == "":
        print(f"{host.name}: udev cannot identify {args.port}; flashing it as --allow-unidentified-port says")
    if not ensure_armhf_flasher(host, target):
        return False
    made, _ = target.run_shell_command(f"install -d -m 0700 -o root -g root {REMOTE_DIR}", _sudo=True)
    if not made or not target.put_file(io.BytesIO(archive), f"{REMOTE_DIR}/{ARCHIVE_NAME}", _sudo=True):
        print(f"{host.name}: could not put ROBOTIS's archive in {REMOTE_DIR}: nothing was flashed", file=sys.stderr)
        return False
    ok, output = target.run_shell_command(flash_script(args.port, firmware, args.sha256), _sudo=True,
                                          print_output=args.verbose)
    flashed, line = flasher_verdict(args.port, firmware, output.output)
    if not ok and not flashed:
        last = next((text for text in reversed(output.output_lines) if text.strip()), "no output")
        line = f"ROBOTIS's update.sh did not run on {args.port}: {last.strip()}"
    print(f"{host.name}: {line}", file=sys.stdout if flashed else sys.stderr)
    return flashed


def register(commands) -> None:
    from roslab.reach import add_roster_argument, add_stale_host_form

    parser = commands.add_parser(
        "opencr-update",
        help="flash a TurtleBot3's OpenCR firmware with ROBOTIS's archive and flasher",
        description="For each TurtleBot3 robot --limit selects: download ROBOTIS's opencr_update.tar.bz2 "
        "once (refused unless its sha256 is --sha256), check that an OpenCR (USB 0483:5740) is on --port, "
        "add armhf and libc6:armhf on a 64-bit ARM Pi, then run the archive's update.sh <port> "
        "<firmware>.opencr there (burger: burger, waffle and waffle_pi: waffle). Each step one line; "
        "the flasher's own output says whether the board was flashed.",
    )
    add_roster_argument(parser, what=" (the TurtleBot3 robots among them)")
    add_stale_host_form(parser)
    parser.add_argument("--port", default="/dev/ttyACM0", type=port_argument,
                        help="the OpenCR's port on the robot (default /dev/ttyACM0)")
    parser.add_argument("--allow-unidentified-port", action="store_true",
                        help="flash through a port udev cannot identify (not one it names as another device)")
    parser.add_argument("--url", default=UPDATE_URL,
                        help="where the controller gets opencr_update.tar.bz2 (http(s):// or file://; "
                        "default ROBOTIS's)")
    parser.add_argument("--sha256", default=ARCHIVE_SHA256, type=sha256_argument,
                        help=f"the archive's sha256 (default {ARCHIVE_SHA256[:12]}..., ROBOTIS's of 2023-01-27)")
    parser.add_argument("--verbose", action="store_true", help="show ROBOTIS's flasher output as it runs")
    parser.set_defaults(run=run)
