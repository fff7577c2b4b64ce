"""`roslab opencr-update HOST`: flash a TurtleBot3's OpenCR firmware on the robot it is attached to.

ROBOTIS's way (e-Manual, "OpenCR setup"): download `opencr_update.tar.bz2`, unpack it on the
robot's Pi and run `./update.sh <port> <model>.opencr` with the board attached by USB; on a
64-bit Pi the tool is 32-bit ARM, so it needs `libc6:armhf`. Here the controller downloads the
archive once (kept for the offline mode, like rosdep's data), and the command first checks the
robot: a port that does not exist, or that is not an OpenCR (USB 0483:5740), is refused in one
line naming the device, before anything is copied or run.
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

from pyinfra.api import FactBase

from roslab.quoting import shell_word

OPENCR_USB_ID = "0483:5740"
UPDATE_URL = ("https://github.com/ROBOTIS-GIT/OpenCR-Binaries/raw/master/turtlebot3/ROS2/latest/"
              "opencr_update.tar.bz2")
REMOTE_DIR = "/tmp/roslab-opencr-update"


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


def port_problem(host_name: str, port: str, usb_id: str | None) -> str | None:
    """Why the OpenCR cannot be flashed through `port`, in one line, or None."""
    if usb_id is None:
        return (f"no OpenCR board on {host_name}: {port} does not exist "
                "(attach the OpenCR to the Pi by USB and run this again)")
    if usb_id != OPENCR_USB_ID:
        shown = usb_id or "an unknown device"
        return f"{port} on {host_name} is {shown}, not an OpenCR ({OPENCR_USB_ID}): nothing was flashed"
    return None


def update_script(port: str, model: str) -> str:
    """What runs on the robot: armhf's libc where the Pi is 64-bit, then ROBOTIS's update.sh."""
    return " && ".join([
        f"cd {REMOTE_DIR}",
        "tar -xjf opencr_update.tar.bz2",
        "if [ \"$(dpkg --print-architecture)\" = arm64 ] && ! dpkg -s libc6:armhf >/dev/null 2>&1; then "
        "dpkg --add-architecture armhf && apt-get update && apt-get install -y libc6:armhf; fi",
        "cd opencr_update",
        f"./update.sh {shell_word(port)} {shell_word(model + '.opencr')}",
    ])


def run(args: argparse.Namespace) -> int:
    """`roslab opencr-update HOST [ROSTER]`: the roster loaded and the robot reached as every
    roslab command does (roslab.reach), uploads as deploy.py makes them (roslab.remote_files)."""
    from pyinfra.api.connect import disconnect_all

    from roslab import downloads, remote_files
    from roslab.reach import RosterProblem, connected_state, load_classroom_groups

    try:
        classroom, groups = load_classroom_groups(args.roster, "opencr-update")
    except RosterProblem as problem:
        print(problem, file=sys.stderr)
        return 1
    host = next((h for h in classroom.hosts if h.name == args.host), None)
    if host is None:
        print(f"roslab opencr-update: {args.host!r} is not a host of {classroom.path}", file=sys.stderr)
        return 2
    profile = host.data.get("roslab_profile") or {}
    model = (profile.get("settings") or {}).get("turtlebot3_model")
    if host.role != "robot" or not model:
        print(f"roslab opencr-update: {host.name} is not a TurtleBot3 robot in the roster "
              "(robot_profile: turtlebot3 with turtlebot3_model)", file=sys.stderr)
        return 2

    remote_files.install()  # the archive's upload: one command, never through a link
    state = connected_state(groups, [host.name])
    try:
        (target,) = [h for h in state.inventory.iter_activated_hosts() if h in state.active_hosts] or [None]
        if target is None:
            print(f"roslab opencr-update: cannot reach {host.name}", file=sys.stderr)
            return 1
        problem = port_problem(host.name, args.port, target.get_fact(UsbSerialPort, port=args.port))
        if problem:
            print(problem, file=sys.stderr)
            return 1
        try:
            archive = downloads.kept(args.url, Path(host.data["rosdep_cache_dir"]).expanduser() / "opencr",
                                     offline=bool(host.data.get("offline"))).data
        except downloads.DownloadError as error:
            print(f"roslab opencr-update: {error}", file=sys.stderr)
            return 1
        target.run_shell_command(f"mkdir -p {REMOTE_DIR}", _sudo=True)
        target.put_file(io.BytesIO(archive), f"{REMOTE_DIR}/opencr_update.tar.bz2", _sudo=True)
        ok, output = target.run_shell_command(update_script(args.port, model), _sudo=True, print_output=True)
        print(f"{host.name}: OpenCR {'flashed with ' + model + '.opencr' if ok else 'update failed'}")
        return 0 if ok else 1
    finally:
        disconnect_all(state)


def register(commands) -> None:
    from roslab.reach import add_roster_argument

    parser = commands.add_parser(
        "opencr-update",
        help="flash a TurtleBot3's OpenCR firmware on the robot it is attached to",
        description="Check that the robot's OpenCR is attached (USB 0483:5740 on --port), then run "
        "ROBOTIS's update.sh <port> <turtlebot3_model>.opencr there. Refuses in one line, naming the "
        "device, where no OpenCR is attached.",
    )
    parser.add_argument("host", metavar="HOST", help="the robot (a host of the roster)")
    add_roster_argument(parser, limit=False)
    parser.add_argument("--port", default="/dev/ttyACM0", help="the OpenCR's port (default /dev/ttyACM0)")
    parser.add_argument("--url", default=UPDATE_URL, help="where the controller downloads opencr_update.tar.bz2")
    parser.set_defaults(run=run)
