#!/usr/bin/env python3
"""On-host network change with automatic rollback (uploaded and run by roslab).

Standard library only: this file is copied to the host and run with the host's
python3. The controller (roslab.network_ops) stages the new files and a plan
(JSON) under the run directory, then:

    python3 network_apply.py validate PLAN   # over SSH: check staged files, change nothing
    systemd-run --unit=roslab-network-apply python3 network_apply.py apply PLAN

`apply` runs detached from the SSH session (a dropped connection cannot kill it):
it backs up the files it replaces, installs the new ones, applies them, checks
the host got its address and can reach its gateway, then waits for the
controller to write the plan's token into the confirmation file over a *new*
connection at the new address. Without that, within the plan's timeout, it
restores the backup and applies the old configuration again. Its progress is in
the status file (JSON), which the controller reads to report what happened.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Neighbour states meaning the gateway answered ARP (ip-neighbour(8)).
NEIGHBOUR_ANSWERED = {"REACHABLE", "STALE", "DELAY", "PROBE", "PERMANENT", "NOARP"}

STATE_VALIDATING = "validating"
STATE_APPLYING = "applying"
STATE_WAITING = "waiting-for-confirmation"
STATE_CONFIRMED = "confirmed"
STATE_ROLLED_BACK = "rolled-back"
STATE_ROLLBACK_FAILED = "rollback-failed"


class ApplyError(Exception):
    """The new configuration did not come up as planned."""


def load_plan(path: str | Path) -> dict:
    return json.loads(Path(path).read_text())


def staged_path(plan: dict, target: str) -> Path:
    """Where the controller uploaded the new content of `target`."""
    return Path(plan["run_dir"]) / "staging" / target.lstrip("/")


def write_status(plan: dict, state: str, message: str = "", **extra) -> None:
    status = {"token": plan["token"], "state": state, "message": message, **extra}
    path = Path(plan["run_dir"]) / "status.json"
    temporary = path.with_suffix(".tmp")
    temporary.write_text(json.dumps(status))
    os.replace(temporary, path)


def run(command: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout)


def _copy_private(source: Path, destination: Path, mode: int = 0o600) -> None:
    """Copy a file so that it is never readable by others, then move it into place."""
    destination.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=destination.parent, prefix=".roslab-")
    try:
        with os.fdopen(fd, "wb") as out, open(source, "rb") as data:
            shutil.copyfileobj(data, out)
        os.chmod(temporary, mode)
        os.replace(temporary, destination)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


# Validation


def validation_root(plan: dict) -> Path:
    """A staging root holding the netplan directory as it will be after the change."""
    root = Path(plan["run_dir"]) / "validate"
    shutil.rmtree(root, ignore_errors=True)
    netplan_dir = Path(plan["netplan_dir"])
    staged_netplan = root / str(netplan_dir).lstrip("/")
    staged_netplan.mkdir(parents=True, mode=0o700)
    replaced = set(plan["superseded"]) | set(plan["files"])
    for existing in sorted(netplan_dir.glob("*.yaml")) if netplan_dir.is_dir() else []:
        if str(existing) not in replaced:
            _copy_private(existing, staged_netplan / existing.name)
    for target in plan["files"]:
        if Path(target).parent == netplan_dir:
            _copy_private(staged_path(plan, target), staged_netplan / Path(target).name)
    return root


def validate(plan: dict) -> list[str]:
    """Check the staged files with the tools that will read them; return the problems."""
    problems = []
    if plan["layout"] != "networkmanager-keyfile":
        root = validation_root(plan)
        result = run(["netplan", "generate", "--root-dir", str(root)])
        shutil.rmtree(root, ignore_errors=True)
        if result.returncode != 0:
            message = (result.stderr or result.stdout).strip().replace(str(root), "")
            problems.append(f"netplan generate rejected the new configuration: {message}")
    for target in plan["files"]:
        if target.endswith(".nmconnection"):
            problems.extend(check_keyfile(staged_path(plan, target), target))
    return problems


def check_keyfile(path: Path, target: str) -> list[str]:
    """NetworkManager's own parser, without the daemon (nmcli --offline, NM >= 1.40)."""
    # `connection modify` with --offline reads a keyfile on stdin, checks it, prints it back.
    with open(path, "rb") as keyfile:
        result = subprocess.run(
            ["nmcli", "--offline", "connection", "modify", "connection.autoconnect", "yes"],
            stdin=keyfile,
            capture_output=True,
            text=True,
            timeout=30,
        )
    if result.returncode != 0:
        return [f"NetworkManager rejected {target}: {(result.stderr or result.stdout).strip()}"]
    return []


# Backup, install, restore


def backup(plan: dict) -> Path:
    """Copy every file the change replaces or creates into a new backup directory."""
    stamp = time.strftime("%Y%m%dT%H%M%S")
    directory = Path(plan["backup_root"]) / f"{stamp}-{plan['token'][:8]}"
    directory.mkdir(parents=True, mode=0o700)
    os.chmod(plan["backup_root"], 0o700)
    manifest = {}
    for target in list(plan["files"]) + list(plan["superseded"]):
        source = Path(target)
        manifest[target] = source.exists()
        if source.exists():
            copy = directory / "files" / target.lstrip("/")
            _copy_private(source, copy, mode=source.stat().st_mode & 0o7777)
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return directory


def install(plan: dict) -> None:
    """Put the staged files in place (root-owned, 0600) and move superseded files away."""
    for target in plan["files"]:
        _copy_private(staged_path(plan, target), Path(target))
    for superseded in plan["superseded"]:
        # Already copied into the backup directory by backup().
        Path(superseded).unlink(missing_ok=True)


def restore(plan: dict, backup_dir: Path) -> None:
    """Put every file back as it was before install()."""
    manifest = json.loads((backup_dir / "manifest.json").read_text())
    for target, existed in manifest.items():
        if existed:
            copy = backup_dir / "files" / target.lstrip("/")
            _copy_private(copy, Path(target), mode=copy.stat().st_mode & 0o7777)
        else:
            Path(target).unlink(missing_ok=True)


# Applying


def _first_success(attempts: list[list[list[str]]]) -> str | None:
    """Run each attempt (a list of commands) until one fully succeeds.

    Returns None on success, else every attempt's failing command and message.
    """
    errors = []
    for commands in attempts:
        for command in commands:
            try:
                result = run(command, timeout=120)
            except (OSError, subprocess.TimeoutExpired) as exc:
                errors.append(f"{' '.join(command)}: {exc}")
                break
            if result.returncode != 0:
                errors.append(f"{' '.join(command)}: {(result.stderr or result.stdout).strip()}")
                break
        else:
            return None
    return "; ".join(errors)


def apply_commands(plan: dict) -> list[list[list[str]]]:
    """Ways to make the installed files take effect, best first.

    On Ubuntu `netplan apply` is the right tool. Where it cannot run (containers:
    its `udevadm trigger` fails on a read-only /sys) the same result comes from
    `netplan generate` and asking the renderer to reload and reconfigure the link.
    """
    interface = plan["interface"]
    layout = plan["layout"]
    # `netplan apply` stops NetworkManager before its udev trigger; when the trigger fails
    # NetworkManager stays stopped, so the fallbacks (re)start it rather than only asking
    # a daemon that may be gone to reload. The rollback takes the same path back.
    restart_networkmanager = [
        ["systemctl", "restart", "NetworkManager"],
        ["nmcli", "--wait", "20", "device", "connect", interface],
    ]
    if layout == "networkmanager-keyfile":
        return [
            [["nmcli", "connection", "reload"], ["nmcli", "device", "connect", interface]],
            restart_networkmanager,
        ]
    if layout == "netplan-networkmanager":
        return [
            [["netplan", "apply"]],
            [["netplan", "generate"], *restart_networkmanager],
        ]
    return [
        [["netplan", "apply"]],
        [["netplan", "generate"], ["networkctl", "reload"], ["networkctl", "reconfigure", interface]],
        [["netplan", "generate"], ["systemctl", "restart", "systemd-networkd"]],
    ]


def apply_files(plan: dict) -> None:
    error = _first_success(apply_commands(plan))
    if error:
        raise ApplyError(f"could not apply the configuration: {error}")


def interface_addresses(interface: str) -> list[str]:
    result = run(["ip", "-o", "-4", "address", "show", "dev", interface])
    return [fields[3] for fields in (line.split() for line in result.stdout.splitlines()) if len(fields) > 3]


def gateway_answers(gateway: str, interface: str, wait: float = 6.0) -> bool:
    """Whether the gateway answers ARP on the interface (ICMP may be filtered, ARP is not)."""
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        # Any datagram makes the kernel resolve the gateway's link-layer address.
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.sendto(b"", (gateway, 9))
            except OSError:
                pass
        time.sleep(1)
        result = run(["ip", "neigh", "show", "to", gateway, "dev", interface])
        states = set(result.stdout.split())
        if states & NEIGHBOUR_ANSWERED:
            return True
    return False


def check_running(plan: dict, wait: float) -> None:
    """Raise ApplyError unless the interface has the planned address and the gateway answers."""
    expected = plan.get("expect_address")
    interface = plan["interface"]
    if expected:
        deadline = time.monotonic() + wait
        while expected not in interface_addresses(interface):
            if time.monotonic() > deadline:
                raise ApplyError(f"{interface} did not get {expected} within {wait:.0f} s")
            time.sleep(0.5)
    gateway = plan.get("gateway")
    if gateway and not gateway_answers(gateway, interface):
        raise ApplyError(f"gateway {gateway} does not answer on {interface}")


def wait_for_confirmation(plan: dict, deadline: float) -> bool:
    confirmation = Path(plan["run_dir"]) / "confirmed"
    while time.monotonic() < deadline:
        try:
            if confirmation.read_text().strip() == plan["token"]:
                return True
        except FileNotFoundError:
            pass
        time.sleep(0.5)
    return False


def apply(plan: dict) -> int:
    """Back up, install, apply, and keep the change only if the controller confirms it."""
    deadline = time.monotonic() + plan["confirm_timeout"]
    Path(plan["run_dir"], "confirmed").unlink(missing_ok=True)
    write_status(plan, STATE_APPLYING)
    try:
        backup_dir = backup(plan)
    except Exception as exc:
        write_status(plan, STATE_ROLLED_BACK, f"nothing changed: could not back up the old files: {exc}")
        return 1
    try:
        install(plan)
        apply_files(plan)
        check_running(plan, wait=min(30.0, plan["confirm_timeout"] / 2))
        write_status(plan, STATE_WAITING, backup=str(backup_dir))
        if not wait_for_confirmation(plan, deadline):
            raise ApplyError(
                f"the controller did not confirm within {plan['confirm_timeout']} s "
                "that it reaches the host at its new address"
            )
    except Exception as exc:  # any failure, even our own bug, must end in a rollback
        reason = str(exc) or type(exc).__name__
        try:
            restore(plan, backup_dir)
            apply_files(plan)
        except Exception as rollback_exc:
            write_status(
                plan, STATE_ROLLBACK_FAILED, f"{reason}; rollback failed too: {rollback_exc}",
                backup=str(backup_dir),
            )
            return 2
        write_status(plan, STATE_ROLLED_BACK, reason, backup=str(backup_dir))
        return 1
    write_status(plan, STATE_CONFIRMED, backup=str(backup_dir))
    shutil.rmtree(Path(plan["run_dir"]) / "staging", ignore_errors=True)
    return 0


def main(argv: list[str]) -> int:
    if len(argv) != 3 or argv[1] not in ("validate", "apply"):
        print(f"usage: {argv[0]} validate|apply PLAN", file=sys.stderr)
        return 64
    plan = load_plan(argv[2])
    if argv[1] == "validate":
        problems = validate(plan)
        for problem in problems:
            print(problem, file=sys.stderr)
        return 1 if problems else 0
    return apply(plan)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
