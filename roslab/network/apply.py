#!/usr/bin/env python3
"""On-host network change with automatic rollback (uploaded and run by roslab).

Standard library only, and no roslab imports: this file is copied to the host and
run with the host's python3. It is also where the controller and the host agree:
the layout names, the plan's fields (`Plan`), the status file's fields and states
(`Status`) and the host's paths are defined here, once, and the controller's
modules (roslab.network.render, .operation, .confirm) import them from here.

The controller (roslab.network.operation) stages the new files and a plan (JSON)
under the run directory, then:

    python3 network_apply.py start PLAN < FILES  # over SSH: stage, validate, launch:
        systemd-run --unit=roslab-network-apply python3 network_apply.py apply PLAN

`start` reads the new files (they may hold a WiFi password) as JSON on its stdin and
writes them root's and 0600 from their first byte; nothing of them ever sits in a
temporary file of the login user's. Staged files are removed whatever happens: when
validation fails, when the launch fails, and when `apply` ends.

`apply` runs detached from the SSH session (a dropped connection cannot kill it):
it backs up the files it replaces (keeping only the plan's `backups_keep` newest
backups), installs the new ones, applies them, checks the host got its address
and can reach its gateway, then waits for the controller to write the plan's
token into the confirmation file over a *new* connection at the new address.
Without that, within the plan's timeout, it restores the backup and applies the
old configuration again. Its progress is in the status file (JSON), which the
controller reads to report what happened.

A change survives a power cut: before installing anything, `apply` records the change
in `STATE_DIR/pending.json` (persistent, beside the backup it restores from) and makes
sure the boot unit `roslab-network-rollback.service` exists and is enabled. If the host
restarts before the change is confirmed, that unit runs `network_apply.py recover` early
at boot (before any network daemon starts): it restores the previous files, regenerates
netplan's output, and leaves `STATE_DIR/recovered.json`, which the next run reports.
The pending record is removed before the change counts as confirmed, so a confirmed
change is never undone by a later restart.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, fields as dataclass_fields
from pathlib import Path, PurePosixPath

# Layouts: who renders the configuration, and in which file.
NETPLAN_NETWORKD = "netplan-networkd"  # Ubuntu Server: netplan, rendered by systemd-networkd
NETPLAN_NM = "netplan-networkmanager"  # Ubuntu Desktop >= 23.10: NM profiles are netplan files
NM_KEYFILE = "networkmanager-keyfile"  # Ubuntu Desktop 22.04: NM keyfiles
LAYOUTS = (NETPLAN_NETWORKD, NETPLAN_NM, NM_KEYFILE)

# Where things are on the host.
RUN_DIR = "/run/roslab/network"
BACKUP_ROOT = "/var/backups/roslab/network"
# Its directories: `<time stamp>-<token prefix>` (backup()), so their names sort oldest first.
BACKUP_NAME = re.compile(r"[0-9]{8}T[0-9]{6}-[0-9A-Za-z_-]{1,8}", re.ASCII)
NETPLAN_DIR = "/etc/netplan"
# Persistent: what the boot unit needs after a power cut (a change not yet confirmed).
STATE_DIR = "/var/lib/roslab/network"
PENDING_FILE = "pending.json"  # the plan and backup of a change applied but not confirmed
RECOVERED_FILE = "recovered.json"  # what the boot unit restored, until the next run reports it
# The script's persistent copy (the boot unit runs it; /run is gone after a restart).
SCRIPT_INSTALL_PATH = "/usr/local/lib/roslab/network_apply.py"
BOOT_UNIT = "roslab-network-rollback"
SYSTEMD_DIR = "/etc/systemd/system"
# Inside the run directory: the new files (by their target path), the status, the confirmation.
STAGING_DIR = "staging"
STATUS_FILE = "status.json"
CONFIRMATION_FILE = "confirmed"
# The systemd unit `apply` runs in (journalctl -u roslab-network-apply).
APPLY_UNIT = "roslab-network-apply"

# Linux interface names (dev_valid_name): 1 to 15 characters, no "/", ":" or whitespace.
# Stricter here: no leading "-" or "." (an interface name is an argument to ip, nmcli
# and networkctl, and "." and ".." are refused by the kernel).
INTERFACE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,14}", re.ASCII)

# Status states, in the order a run goes through them.
STATE_APPLYING = "applying"
STATE_WAITING = "waiting-for-confirmation"
STATE_CONFIRMED = "confirmed"
STATE_ROLLED_BACK = "rolled-back"
STATE_ROLLBACK_FAILED = "rollback-failed"
FINAL_STATES = (STATE_CONFIRMED, STATE_ROLLED_BACK, STATE_ROLLBACK_FAILED)

# Neighbour states meaning the gateway answered ARP (ip-neighbour(8)).
NEIGHBOUR_ANSWERED = {"REACHABLE", "STALE", "DELAY", "PROBE", "PERMANENT", "NOARP"}


class ApplyError(Exception):
    """The new configuration did not come up as planned."""


def _absolute_path(path: object) -> bool:
    if not isinstance(path, str) or "\0" in path:
        return False
    pure = PurePosixPath(path)
    return pure.is_absolute() and ".." not in pure.parts


@dataclass(frozen=True)
class Plan:
    """What the controller asks of the host, uploaded as JSON beside this script."""

    token: str  # this run's id: in the status file, and what the controller confirms with
    layout: str  # one of LAYOUTS
    interface: str
    files: tuple[str, ...]  # target paths, installed in this order from the staging directory
    superseded: tuple[str, ...]  # files moved away (into the backup)
    expect_address: str | None  # the address the interface must get, e.g. "10.0.0.11/24"; None: DHCP
    gateway: str | None  # must answer ARP on the interface; None: not checked
    confirm_timeout: int  # seconds to wait for the controller's confirmation
    backups_keep: int = 5  # backup directories kept under backup_root, this run's included
    run_dir: str = RUN_DIR
    backup_root: str = BACKUP_ROOT
    netplan_dir: str = NETPLAN_DIR
    state_dir: str = STATE_DIR
    systemd_dir: str = SYSTEMD_DIR
    script_path: str = SCRIPT_INSTALL_PATH

    def __post_init__(self):
        object.__setattr__(self, "files", tuple(self.files))
        object.__setattr__(self, "superseded", tuple(self.superseded))
        problems = []
        if not isinstance(self.token, str) or not re.fullmatch(r"[0-9A-Za-z_-]{1,64}", self.token):
            problems.append(f"token {self.token!r} is not a token")
        if self.layout not in LAYOUTS:
            problems.append(f"layout {self.layout!r} is not one of {', '.join(LAYOUTS)}")
        if not isinstance(self.interface, str) or not INTERFACE_NAME.fullmatch(self.interface):
            problems.append(f"interface {self.interface!r} is not an interface name")
        for path in (*self.files, *self.superseded, self.run_dir, self.backup_root, self.netplan_dir,
                     self.state_dir, self.systemd_dir, self.script_path):
            if not _absolute_path(path):
                problems.append(f"{path!r} is not an absolute path")
        if isinstance(self.confirm_timeout, bool) or not isinstance(self.confirm_timeout, (int, float)) \
                or self.confirm_timeout <= 0:
            problems.append(f"confirm_timeout {self.confirm_timeout!r} is not a number of seconds")
        if isinstance(self.backups_keep, bool) or not isinstance(self.backups_keep, int) or self.backups_keep < 1:
            problems.append(f"backups_keep {self.backups_keep!r} is not a positive number")
        if problems:
            raise ValueError("bad plan: " + "; ".join(problems))

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "Plan":
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("bad plan: not a JSON object")
        unknown = set(data) - {field.name for field in dataclass_fields(cls)}
        if unknown:
            raise ValueError(f"bad plan: unknown fields {sorted(unknown)}")
        try:
            return cls(**data)
        except TypeError as exc:  # a field missing
            raise ValueError(f"bad plan: {exc}") from None


@dataclass(frozen=True)
class Status:
    """How far a run got, in the run directory's status file (read by the controller)."""

    token: str
    state: str  # one of the STATE_* values
    message: str = ""
    backup: str | None = None  # the backup directory, once there is one

    @property
    def final(self) -> bool:
        return self.state in FINAL_STATES

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str | None, token: str) -> "Status | None":
        """The status in `text` if it is run `token`'s; None if unreadable or another run's."""
        try:
            data = json.loads(text) if text else None
            status = cls(**data) if isinstance(data, dict) else None
        except (ValueError, TypeError):
            return None
        return status if status is not None and status.token == token else None


def load_plan(path: str | Path) -> Plan:
    return Plan.from_json(Path(path).read_text())


def staged_path(plan: Plan, target: str) -> Path:
    """Where the controller uploaded the new content of `target`."""
    return Path(plan.run_dir) / STAGING_DIR / target.lstrip("/")


def write_status(plan: Plan, state: str, message: str = "", backup: str | None = None) -> None:
    path = Path(plan.run_dir) / STATUS_FILE
    temporary = path.with_suffix(".tmp")
    temporary.write_text(Status(plan.token, state, message, backup).to_json())
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


def _write_private(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Write `path` as a new file that is `mode` (0600: nobody else's) from its first byte.

    The file is created beside `path` with O_EXCL (never someone's link or file) and
    renamed over it: a rename replaces a name and never follows a link there.
    """
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=".roslab-")
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
            out.flush()
            os.fsync(out.fileno())
            os.fchmod(out.fileno(), mode)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def remove_staging(plan: Plan) -> None:
    """Remove the staged files (they may hold a WiFi password) and the validation copy."""
    for name in (STAGING_DIR, "validate"):
        shutil.rmtree(Path(plan.run_dir) / name, ignore_errors=True)


def stage(plan: Plan, files: dict) -> None:
    """Write each planned file's new content into the staging directory, 0600 from its first byte."""
    unknown = set(files) - set(plan.files)
    missing = set(plan.files) - set(files)
    if unknown or missing:
        raise ValueError(f"the staged files are not the plan's: unknown {sorted(unknown)}, missing {sorted(missing)}")
    remove_staging(plan)
    umask = os.umask(0o077)  # every directory made here too: nobody else's way in
    try:
        Path(plan.run_dir).mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(plan.run_dir, 0o700)
        for target in plan.files:
            content = files[target]
            if not isinstance(content, str):
                raise ValueError(f"the new content of {target} is not text")
            _write_private(staged_path(plan, target), content.encode())
    finally:
        os.umask(umask)


def launch_command(plan: Plan, plan_path: str) -> list[str]:
    return [
        "systemd-run", f"--unit={APPLY_UNIT}", "--collect", "--quiet",
        "--description=roslab: apply the network change, roll back unless confirmed",
        "python3", plan.script_path, "apply", plan_path,
    ]


def start(plan: Plan, plan_path: str, stdin) -> int:
    """Stage the files read from `stdin` (JSON: target path -> content), validate, launch `apply`.

    Whatever fails, no staged file is left behind.
    """
    try:
        files = json.loads(stdin.read())
        if not isinstance(files, dict):
            raise ValueError("not a JSON object")
    except ValueError as exc:
        print(f"roslab: the new network files did not arrive whole ({exc}); nothing changed", file=sys.stderr)
        return 65
    try:
        stage(plan, files)
        problems = validate(plan)
        if problems:
            for problem in problems:
                print(problem, file=sys.stderr)
            remove_staging(plan)
            return 1
        run(["systemctl", "reset-failed", f"{APPLY_UNIT}.service"])
        result = run(launch_command(plan, plan_path))
        if result.returncode != 0:
            remove_staging(plan)
            print(f"roslab: could not start the network change: {(result.stderr or result.stdout).strip()}",
                  file=sys.stderr)
            return 1
    except BaseException:
        remove_staging(plan)
        raise
    return 0


# Surviving a restart before the confirmation


BOOT_UNIT_TEXT = """\
# managed by roslab: restores the network configuration of a change that was never
# confirmed when the host restarted (a power cut) before the controller could confirm it.
[Unit]
Description=roslab: restore the network configuration of an unconfirmed change
DefaultDependencies=no
After=local-fs.target
Before=sysinit.target network-pre.target systemd-networkd.service NetworkManager.service
Wants=network-pre.target
ConditionPathExists={pending}

[Service]
Type=oneshot
ExecStart=/usr/bin/python3 {script} recover {state_dir}
RemainAfterExit=yes

[Install]
WantedBy=sysinit.target
"""


def boot_unit_text(plan: Plan) -> str:
    return BOOT_UNIT_TEXT.format(pending=str(Path(plan.state_dir) / PENDING_FILE),
                                 script=plan.script_path, state_dir=plan.state_dir)


def arm_boot_rollback(plan: Plan, backup_dir: Path) -> None:
    """Record the change as pending (persistently) and make sure the boot unit would undo it."""
    unit = Path(plan.systemd_dir) / f"{BOOT_UNIT}.service"
    text = boot_unit_text(plan)
    if not unit.is_file() or unit.is_symlink() or unit.read_text() != text:
        _write_private(unit, text.encode(), mode=0o644)
    wants = Path(plan.systemd_dir) / "sysinit.target.wants" / unit.name
    if not (wants.is_symlink() and os.readlink(wants) == str(unit)):
        wants.parent.mkdir(parents=True, exist_ok=True, mode=0o755)
        if wants.is_symlink() or wants.exists():
            wants.unlink()
        wants.symlink_to(unit)
    if not Path(plan.script_path).is_file():
        raise ApplyError(f"the boot-time rollback needs {plan.script_path}, which is missing")
    record = {"plan": json.loads(plan.to_json()), "backup": str(backup_dir), "applied_at": _now()}
    _write_private(Path(plan.state_dir) / PENDING_FILE, json.dumps(record, indent=2).encode())
    os.chmod(plan.state_dir, 0o700)


def disarm_boot_rollback(plan: Plan) -> None:
    pending = Path(plan.state_dir) / PENDING_FILE
    pending.unlink(missing_ok=True)
    fd = os.open(plan.state_dir, os.O_RDONLY)  # the removal itself must survive a power cut
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def recover(state_dir: str) -> int:
    """At boot: undo a change that was never confirmed, and leave a record for the next run."""
    pending = Path(state_dir) / PENDING_FILE
    try:
        record = json.loads(pending.read_text())
        plan = Plan(**record["plan"])
        backup_dir = Path(record["backup"])
    except FileNotFoundError:
        return 0
    except (ValueError, TypeError, KeyError) as exc:
        print(f"roslab: {pending} is unreadable ({exc}); left for a person to look at", file=sys.stderr)
        return 1
    reason = (f"the host restarted before the network change of {record.get('applied_at', '?')} "
              "was confirmed; its previous configuration was restored at boot")
    restore(plan, backup_dir)
    if plan.layout != NM_KEYFILE:
        # netplan's generator ran before this unit, from the new files: generate again
        # from the restored ones, before the renderer starts.
        result = run(["netplan", "generate"])
        if result.returncode != 0:
            reason += f" (netplan generate: {(result.stderr or result.stdout).strip()})"
    recovered = {"token": plan.token, "restored_at": _now(), "backup": str(backup_dir), "reason": reason}
    _write_private(Path(state_dir) / RECOVERED_FILE, json.dumps(recovered).encode(), mode=0o644)
    Path(plan.run_dir).mkdir(parents=True, exist_ok=True, mode=0o700)
    write_status(plan, STATE_ROLLED_BACK, reason, backup=str(backup_dir))  # for a controller still waiting
    disarm_boot_rollback(plan)
    print(f"roslab: {reason}", file=sys.stderr)
    return 0


# Validation


def validation_root(plan: Plan) -> Path:
    """A staging root holding the netplan directory as it will be after the change."""
    root = Path(plan.run_dir) / "validate"
    shutil.rmtree(root, ignore_errors=True)
    netplan_dir = Path(plan.netplan_dir)
    staged_netplan = root / str(netplan_dir).lstrip("/")
    staged_netplan.mkdir(parents=True, mode=0o700)
    replaced = set(plan.superseded) | set(plan.files)
    for existing in sorted(netplan_dir.glob("*.yaml")) if netplan_dir.is_dir() else []:
        if str(existing) not in replaced:
            _copy_private(existing, staged_netplan / existing.name)
    for target in plan.files:
        if Path(target).parent == netplan_dir:
            _copy_private(staged_path(plan, target), staged_netplan / Path(target).name)
    return root


def validate(plan: Plan) -> list[str]:
    """Check the staged files with the tools that will read them; return the problems."""
    problems = []
    if plan.layout != NM_KEYFILE:
        root = validation_root(plan)
        result = run(["netplan", "generate", "--root-dir", str(root)])
        shutil.rmtree(root, ignore_errors=True)
        if result.returncode != 0:
            message = (result.stderr or result.stdout).strip().replace(str(root), "")
            problems.append(f"netplan generate rejected the new configuration: {message}")
    for target in plan.files:
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


def backup(plan: Plan) -> Path:
    """Copy every file the change replaces or creates into a new backup directory."""
    stamp = time.strftime("%Y%m%dT%H%M%S")
    directory = Path(plan.backup_root) / f"{stamp}-{plan.token[:8]}"
    directory.mkdir(parents=True, mode=0o700)
    os.chmod(plan.backup_root, 0o700)
    manifest = {}
    for target in plan.files + plan.superseded:
        source = Path(target)
        manifest[target] = source.exists()
        if source.exists():
            copy = directory / "files" / target.lstrip("/")
            _copy_private(source, copy, mode=source.stat().st_mode & 0o7777)
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return directory


def prune_backups(plan: Plan, current: Path) -> list[Path]:
    """Remove the oldest backup directories beyond `plan.backups_keep`; return what went.

    Only directories named like backup() names them are counted or removed, and never
    `current`: the backup this run restores from if the change is rolled back.
    """
    root = Path(plan.backup_root)
    backups = sorted(
        path for path in root.iterdir()
        if BACKUP_NAME.fullmatch(path.name) and path.is_dir() and not path.is_symlink() and path != current
    )
    removed = backups[: max(0, len(backups) - (plan.backups_keep - 1))]
    for path in removed:
        shutil.rmtree(path)
    return removed


def install(plan: Plan) -> None:
    """Put the staged files in place (root-owned, 0600) and move superseded files away."""
    for target in plan.files:
        _copy_private(staged_path(plan, target), Path(target))
    for superseded in plan.superseded:
        # Already copied into the backup directory by backup().
        Path(superseded).unlink(missing_ok=True)


def restore(plan: Plan, backup_dir: Path) -> None:
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


def apply_commands(plan: Plan) -> list[list[list[str]]]:
    """Ways to make the installed files take effect, best first.

    On Ubuntu `netplan apply` is the right tool. Where it cannot run (containers:
    its `udevadm trigger` fails on a read-only /sys) the same result comes from
    `netplan generate` and asking the renderer to reload and reconfigure the link.
    """
    interface = plan.interface
    # `netplan apply` stops NetworkManager before its udev trigger; when the trigger fails
    # NetworkManager stays stopped, so the fallbacks (re)start it rather than only asking
    # a daemon that may be gone to reload. The rollback takes the same path back.
    restart_networkmanager = [
        ["systemctl", "restart", "NetworkManager"],
        ["nmcli", "--wait", "20", "device", "connect", interface],
    ]
    if plan.layout == NM_KEYFILE:
        return [
            [["nmcli", "connection", "reload"], ["nmcli", "device", "connect", interface]],
            restart_networkmanager,
        ]
    if plan.layout == NETPLAN_NM:
        return [
            [["netplan", "apply"]],
            [["netplan", "generate"], *restart_networkmanager],
        ]
    return [
        [["netplan", "apply"]],
        [["netplan", "generate"], ["networkctl", "reload"], ["networkctl", "reconfigure", interface]],
        [["netplan", "generate"], ["systemctl", "restart", "systemd-networkd"]],
    ]


def apply_files(plan: Plan) -> None:
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


def check_running(plan: Plan, wait: float) -> None:
    """Raise ApplyError unless the interface has the planned address and the gateway answers."""
    if plan.expect_address:
        deadline = time.monotonic() + wait
        while plan.expect_address not in interface_addresses(plan.interface):
            if time.monotonic() > deadline:
                raise ApplyError(f"{plan.interface} did not get {plan.expect_address} within {wait:.0f} s")
            time.sleep(0.5)
    if plan.gateway and not gateway_answers(plan.gateway, plan.interface):
        raise ApplyError(f"gateway {plan.gateway} does not answer on {plan.interface}")


def wait_for_confirmation(plan: Plan, deadline: float) -> bool:
    confirmation = Path(plan.run_dir) / CONFIRMATION_FILE
    while time.monotonic() < deadline:
        try:
            if confirmation.read_text().strip() == plan.token:
                return True
        except FileNotFoundError:
            pass
        time.sleep(0.5)
    return False


def apply(plan: Plan) -> int:
    """Back up, install, apply, and keep the change only if the controller confirms it."""
    deadline = time.monotonic() + plan.confirm_timeout
    Path(plan.run_dir, CONFIRMATION_FILE).unlink(missing_ok=True)
    write_status(plan, STATE_APPLYING)
    try:
        backup_dir = backup(plan)
    except Exception as exc:
        write_status(plan, STATE_ROLLED_BACK, f"nothing changed: could not back up the old files: {exc}")
        return 1
    try:
        prune_backups(plan, backup_dir)
    except OSError:
        pass  # an old backup that cannot go is no reason to stop the change
    try:
        arm_boot_rollback(plan, backup_dir)
        install(plan)
        remove_staging(plan)  # installed: the staged copies (a WiFi password) go at once
        apply_files(plan)
        check_running(plan, wait=min(30.0, plan.confirm_timeout / 2))
        write_status(plan, STATE_WAITING, backup=str(backup_dir))
        if not wait_for_confirmation(plan, deadline):
            raise ApplyError(
                f"the controller did not confirm within {plan.confirm_timeout} s "
                "that it reaches the host at its new address"
            )
    except Exception as exc:  # any failure, even our own bug, must end in a rollback
        reason = str(exc) or type(exc).__name__
        remove_staging(plan)
        try:
            restore(plan, backup_dir)
            apply_files(plan)
        except Exception as rollback_exc:
            # The pending record stays: the boot unit restores the files at the next start.
            write_status(
                plan, STATE_ROLLBACK_FAILED, f"{reason}; rollback failed too: {rollback_exc}",
                backup=str(backup_dir),
            )
            return 2
        disarm_boot_rollback(plan)
        write_status(plan, STATE_ROLLED_BACK, reason, backup=str(backup_dir))
        return 1
    remove_staging(plan)
    disarm_boot_rollback(plan)  # before "confirmed": the controller records the address only then
    write_status(plan, STATE_CONFIRMED, backup=str(backup_dir))
    return 0


def main(argv: list[str]) -> int:
    if len(argv) in (2, 3) and argv[1:2] == ["recover"]:
        return recover(argv[2] if len(argv) == 3 else STATE_DIR)
    if len(argv) != 3 or argv[1] not in ("validate", "apply", "start"):
        print(f"usage: {argv[0]} validate|apply|start PLAN, or recover [STATE_DIR]", file=sys.stderr)
        return 64
    try:
        plan = load_plan(argv[2])
    except (OSError, ValueError) as exc:
        print(f"{argv[2]}: {exc}", file=sys.stderr)
        return 65
    if argv[1] == "validate":
        problems = validate(plan)
        for problem in problems:
            print(problem, file=sys.stderr)
        return 1 if problems else 0
    if argv[1] == "start":
        return start(plan, argv[2], sys.stdin)
    return apply(plan)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
