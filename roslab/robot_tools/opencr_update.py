"""`roslab opencr-update [ROSTER] --limit ROBOT`: flash a TurtleBot3's OpenCR firmware on the robot
it is attached to.

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
    """`roslab opencr-update [ROSTER] [--limit NAME ...]`: the roster loaded and the robots
    reached as every roslab command does (roslab.reach), uploads as deploy.py makes them
    (roslab.remote_files). Each TurtleBot3 robot `--limit` selects in turn; one that fails
    leaves the others to go on."""
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
    except RosterProblem as problem:
        print(problem, file=sys.stderr)
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
            elif not flash(host, reached[host.name], args):
                failed += 1
        return 1 if failed else 0
    finally:
        disconnect_all(state)


def turtlebot3_model(host) -> str | None:
    """The robot's `turtlebot3_model`, or None where the host is not a TurtleBot3 robot."""
    profile = host.data.get("roslab_profile") or {}
    return (profile.get("settings") or {}).get("turtlebot3_model") if host.role == "robot" else None


def flash(host, target, args: argparse.Namespace) -> bool:
    """Check the robot's port, then run ROBOTIS's update there; one line says how it went."""
    from roslab import downloads

    model = turtlebot3_model(host)
    problem = port_problem(host.name, args.port, target.get_fact(UsbSerialPort, port=args.port))
    if problem:
        print(problem, file=sys.stderr)
        return False
    try:
        archive = downloads.kept(args.url, Path(host.data["rosdep_cache_dir"]).expanduser() / "opencr",
                                 offline=bool(host.data.get("offline"))).data
    except downloads.DownloadError as error:
        print(f"roslab opencr-update: {error}", file=sys.stderr)
        return False
    target.run_shell_command(f"mkdir -p {REMOTE_DIR}", _sudo=True)
    target.put_file(io.BytesIO(archive), f"{REMOTE_DIR}/opencr_update.tar.bz2", _sudo=True)
    ok, _ = target.run_shell_command(update_script(args.port, model), _sudo=True, print_output=True)
    print(f"{host.name}: OpenCR {'flashed with ' + model + '.opencr' if ok else 'update failed'}")
    return ok


def register(commands) -> None:
    from roslab.reach import add_roster_argument, add_stale_host_form

    parser = commands.add_parser(
        "opencr-update",
        help="flash a TurtleBot3's OpenCR firmware on the robot it is attached to",
        description="For each TurtleBot3 robot --limit selects: check that its OpenCR is attached "
        "(USB 0483:5740 on --port), then run ROBOTIS's update.sh <port> <turtlebot3_model>.opencr "
        "there. Refuses in one line, naming the device, where no OpenCR is attached.",
    )
    add_roster_argument(parser, what=" (the TurtleBot3 robots among them)")
    add_stale_host_form(parser)
    parser.add_argument("--port", default="/dev/ttyACM0", help="the OpenCR's port (default /dev/ttyACM0)")
    parser.add_argument("--url", default=UPDATE_URL, help="where the controller downloads opencr_update.tar.bz2")
    parser.set_defaults(run=run)
