"""`roslab sandbox board TEAM` for an osr team: the STAND-IN RoboClaws inside the team's robot.

The rover's real roboclaw_wrapper (osr-rover-code v4.1.0) opens /dev/serial1 and talks to the
RoboClaws at 128, 129 and 130 (ROS/osr_bringup/config/roboclaw_params.yaml). A sandbox robot has
no UART: this copies roslab/sandbox/roboclaw_board.py (the stand-in, standard library only) into
the robot over SSH, under /run (gone at the host's reboot, as a board's power would be), and runs
it there as a transient systemd unit of the host's own systemd: it makes a pty, links
/dev/serial1 to it (dialout's, 0660, as the osr profile's udev rule makes the UART) and answers
as the controllers do, so the wrapper's next start (the launch respawns it) finds them and
publishes /drive_state and /status. The unit is the record: `stop` stops it, and a host's
stop (`sandbox down`, reset, reboot) takes it with everything else the host runs.
"""

from __future__ import annotations

import shlex
import subprocess
import time
from pathlib import Path

from . import lifecycle
from .instance import Instance
from .system import SandboxError

PROFILE = "osr"
STANDIN = Path(__file__).resolve().parent / "roboclaw_board.py"
HOST_DIR = "/run/roslab-roboclaw"
UNIT = "roslab-roboclaw-standin"
# What roboclaw_wrapper opens at v4.1.0 (roboclaw_params.yaml: device, addresses), and the
# osr profile's roboclaw_uart device links there (roslab/profiles/data/osr.yaml).
PORT = "/dev/serial1"
ADDRESSES = (128, 129, 130)


def robot_host(classroom, team: str):
    """The roster host of team `team` that carries the rover (the osr profile's robot), or None."""
    for host in classroom.hosts:
        profile = host.settings.roslab_profile
        if host.team == team and host.role == "robot" and profile is not None and profile.name == PROFILE:
            return host
    return None


def describe(team: str, host_name: str) -> str:
    """What the stand-in is and where, in one line."""
    return (f"{team}: stand-in RoboClaws {', '.join(map(str, ADDRESSES))} on {PORT} of {host_name} "
            "(the rover's roboclaw_wrapper publishes /drive_state and /status)")


def _on_host(instance: Instance, host_name: str, command: str, data: bytes | None = None,
             check: bool = True) -> subprocess.CompletedProcess:
    address = lifecycle.load(instance).host(host_name).address
    argv = lifecycle.ssh_argv(instance, address, command, host_name=host_name)
    done = subprocess.run(argv, input=data, capture_output=True, timeout=60)
    if check and done.returncode:
        raise SandboxError(f"{host_name}: `{command}` failed (rc {done.returncode}): "
                           f"{done.stderr.decode(errors='replace').strip()[-500:]}")
    return done


def _unit_state(instance: Instance, host_name: str) -> tuple[str, int]:
    """(ActiveState, MainPID) of the stand-in's unit on the host."""
    shown = _on_host(instance, host_name, f"systemctl show -p ActiveState -p MainPID {UNIT}.service",
                     check=False).stdout.decode(errors="replace")
    values = dict(line.split("=", 1) for line in shown.splitlines() if "=" in line)
    return values.get("ActiveState", "inactive"), int(values.get("MainPID", "0") or 0)


def start(instance: Instance, host_name: str, timeout: float = 20) -> int:
    """Run the stand-in in the host (a no-op when it runs) until PORT links to its pty; its pid there."""
    active, pid = _unit_state(instance, host_name)
    if active == "active" and pid:
        return pid
    script = f"{HOST_DIR}/{STANDIN.name}"
    _on_host(instance, host_name, f"sudo sh -c {shlex.quote(f'mkdir -p {HOST_DIR} && cat > {script}')}",
             data=STANDIN.read_bytes())
    addresses = " ".join(f"--address {address}" for address in ADDRESSES)
    _on_host(instance, host_name, f"sudo systemctl reset-failed {UNIT}.service 2>/dev/null; "
             f"sudo systemd-run --unit={UNIT} --description='roslab sandbox: stand-in RoboClaws on {PORT}' "
             f"python3 {script} --link {PORT} {addresses}")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        active, pid = _unit_state(instance, host_name)
        if active not in ("active", "activating"):
            log = _on_host(instance, host_name, f"sudo journalctl -u {UNIT} -n 20 --no-pager", check=False)
            raise SandboxError(f"{host_name}: the RoboClaw stand-in stopped ({active}): "
                               f"{log.stdout.decode(errors='replace').strip()[-800:]}")
        if pid and _on_host(instance, host_name, f"test -c {PORT}", check=False).returncode == 0:
            return pid
        time.sleep(0.5)
    raise SandboxError(f"{host_name}: the RoboClaw stand-in did not link {PORT} within {timeout:.0f} s "
                       f"(`journalctl -u {UNIT}` there)")


def stop(instance: Instance, host_name: str) -> bool:
    """Stop the stand-in (it removes its link); False: none was running."""
    active, _ = _unit_state(instance, host_name)
    if active not in ("active", "activating"):
        return False
    _on_host(instance, host_name, f"sudo systemctl stop {UNIT}.service")
    return True


def state(instance: Instance, host_name: str) -> str:
    """In words: stopped, or answering (with its pid in the host)."""
    active, pid = _unit_state(instance, host_name)
    if active == "active" and pid:
        return f"answering (pid {pid} in {host_name}, unit {UNIT})"
    return "stopped" if active in ("inactive", "") else f"stopped ({active})"
