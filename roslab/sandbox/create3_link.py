"""A STAND-IN Create 3 plugged into a sandbox robot: `roslab sandbox create3 HOST start|stop|status`.

A TurtleBot 4's Pi reaches its Create 3 only over the USB-C link, `usb0` (a USB gadget network:
the Pi 192.168.186.3, the base 192.168.186.2). Here the link is a veth pair: `usb0` in the robot's
network namespace, its other end in a namespace of its own (named after the host, so `sandbox
down` removes it) holding the base's address, where the Create 3's web stand-in
(roslab/sandbox/create3.py) answers on port 80 and records what it is posted. Nothing of it is
on this machine's own network: only the robot reaches it, as on the robot.

Like plugging the cable in after roslab's first run and the reboot: `usb0` appears with no
address; roslab's robot_base step gives it 192.168.186.3/24 and configures the base.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from .create3 import recorded_posts
from .instance import Instance, SandboxHost
from .system import SandboxError, pid_alive, run, stop_recorded

BASE_ADDRESS = "192.168.186.2/24"  # the Create 3's side of usb0 (turtlebot4_setup, the Create 3 docs)
INTERFACE = "usb0"
# A firmware version as the Create 3 reports it (H.x on Humble, I.x on Jazzy), e.g. I.0.0.FastDDS.
FIRMWARE = re.compile(r"^[A-Z]\.[0-9]{1,3}\.[0-9]{1,3}(?:\.[A-Za-z0-9]{1,20})?$")
DEFAULT_FIRMWARE = "I.0.0.FastDDS"


def files(instance: Instance, host: SandboxHost) -> tuple[Path, Path]:
    """(pid file, record of the posts) of the host's Create 3 in the sandbox's state folder."""
    folder = instance.state_dir / "create3"
    return folder / f"{host.name}.pid", folder / f"{host.name}.jsonl"


def netns(instance: Instance, host: SandboxHost) -> str:
    return f"{instance.netns(host)}-c3"  # under the instance's netns prefix: `down` deletes it


def veth(instance: Instance, host: SandboxHost) -> str:
    return f"rlc{instance.short_id}{host.index}"  # <= 15 characters


def running_pid(pid_file: Path) -> int | None:
    """The stand-in's pid while it runs (and is a Create 3 stand-in), else None."""
    try:
        pid = int(pid_file.read_text())
        command = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (OSError, ValueError):
        return None
    return pid if b"roslab.sandbox.create3" in command and pid_alive(pid) else None


def plug(instance: Instance, host: SandboxHost, firmware: str = DEFAULT_FIRMWARE, timeout: float = 15) -> int:
    """Plug a stand-in Create 3 running `firmware` into `host` (a no-op when one is plugged in):
    usb0 in the host, the base's web server answering on the other end. Returns its pid."""
    if not FIRMWARE.fullmatch(firmware):
        raise SandboxError(f"create3 --firmware {firmware!r}: a Create 3 firmware version is like "
                           f"{DEFAULT_FIRMWARE} (H.x for Humble, I.x for Jazzy)")
    pid_file, record = files(instance, host)
    running = running_pid(pid_file)
    if running is not None:
        return running
    base_ns, end = netns(instance, host), veth(instance, host)
    if not Path(f"/run/netns/{instance.netns(host)}").exists():
        raise SandboxError(f"host {host.name!r} of sandbox {instance.name!r} has no network namespace: is it up?")
    if not Path(f"/run/netns/{base_ns}").exists():
        run("ip", "netns", "add", base_ns)
    links = run("ip", "netns", "exec", base_ns, "ip", "-o", "link", "show").stdout
    if f" {end}@" not in links and f" {end}:" not in links:
        run("ip", "link", "add", end, "netns", base_ns, "type", "veth", "peer", "name", INTERFACE,
            "netns", instance.netns(host))
        run("ip", "netns", "exec", base_ns, "ip", "addr", "add", BASE_ADDRESS, "dev", end)
    for device in ("lo", end):
        run("ip", "netns", "exec", base_ns, "ip", "link", "set", device, "up")
    run("ip", "netns", "exec", instance.netns(host), "ip", "link", "set", INTERFACE, "up")
    pid_file.parent.mkdir(parents=True, exist_ok=True)
    log = pid_file.with_suffix(".log")
    with open(log, "ab") as handle:
        process = subprocess.Popen(
            ["ip", "netns", "exec", base_ns, sys.executable, "-m", "roslab.sandbox.create3",
             "--address", BASE_ADDRESS.split("/")[0], "--port", "80", "--firmware", firmware, "--record", str(record)],
            stdout=handle, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
    pid_file.write_text(f"{process.pid}\n")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:  # up once it listens on the base's side
        if process.poll() is not None:
            pid_file.unlink(missing_ok=True)
            raise SandboxError(f"the Create 3 stand-in of {host.name} exited (rc {process.returncode}): "
                               f"{log.read_text(errors='replace').strip()[-500:]}")
        listening = run("ip", "netns", "exec", base_ns, "ss", "-Htln", "sport", "= :80", check=False).stdout
        if listening.strip():
            return process.pid
        time.sleep(0.1)
    raise SandboxError(f"the Create 3 stand-in of {host.name} did not listen within {timeout:.0f} s; log: {log}")


def unplug(instance: Instance, host: SandboxHost) -> bool:
    """Unplug the host's Create 3: the stand-in stopped, usb0 gone with its namespace. False: none was."""
    stopped = stop_recorded(files(instance, host)[0], running_pid)
    run("ip", "netns", "delete", netns(instance, host), check=False)  # takes the veth pair, usb0 too
    return stopped


def state(instance: Instance, host: SandboxHost) -> str:
    """In words: unplugged, or plugged in with its pid and how many posts it got."""
    pid_file, record = files(instance, host)
    pid = running_pid(pid_file)
    if pid is None:
        return "unplugged"
    return f"plugged in on {INTERFACE}, answering at {BASE_ADDRESS.split('/')[0]} (pid {pid}), " \
           f"{len(recorded_posts(record))} posts recorded in {record}"


def unplug_all(instance: Instance) -> None:
    """Stop every Create 3 stand-in of the sandbox (its `down`; the namespaces go with the network)."""
    for pid_file in sorted((instance.state_dir / "create3").glob("*.pid")):
        stop_recorded(pid_file, running_pid)
