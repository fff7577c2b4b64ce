"""pyinfra facts and the operation that moves a host's network without locking anyone out.

`network_in_effect` compares the files a host should have with what it has. If
they differ it stages the new files (0600, in a 0700 directory), validates them
on the host, then starts `network_apply.py apply` with systemd-run, detached from
the SSH session, and finally (on the controller, at execution time) connects to
the host's new address, confirms, and moves pyinfra's connection there so the
rest of the deploy runs at the new address. Without a confirmation the host
restores its old files itself; the controller reports that and fails the host.
"""

from __future__ import annotations

import hashlib
import json
import shlex
import time
from io import StringIO
from pathlib import Path
from uuid import uuid4

import gevent
from paramiko import SSHException
from pyinfra import host, logger, state
from pyinfra.api import FactBase, FunctionCommand, OperationError, QuoteString, StringCommand, operation
from pyinfra.api.arguments import CONNECTOR_ARGUMENT_KEYS
from pyinfra.api.command import FileUploadCommand
from pyinfra.api.exceptions import ConnectError
from pyinfra.facts.files import File, Sha256File
from pyinfra.operations.util.files import generate_color_diff

from roslab import netstate, network_apply
from roslab.netcheck import NetworkSettings
from roslab.network_render import (
    SED_MASK_SECRETS,
    RendererFacts,
    choose_layout,
    desired_files,
    mask_secrets,
)

RUN_DIR = "/run/roslab/network"
BACKUP_ROOT = "/var/backups/roslab/network"
NETPLAN_DIR = "/etc/netplan"
APPLY_UNIT = "roslab-network-apply"
APPLY_SCRIPT = Path(network_apply.__file__)
# After the host's own deadline: time for its rollback (restore and re-apply) to finish.
ROLLBACK_GRACE = 45
# How often the controller looks at the old address for an early rollback.
OLD_ADDRESS_PROBE_INTERVAL = 5
# Longest wait for one command in the confirmation (s).
COMMAND_TIMEOUT = 10


class NetworkRenderer(FactBase):
    """Who manages the host's network, and whether cloud-init writes it.

    Returns ``{"renderer": RendererFacts(...), "cloud_init": bool}``.
    """

    def command(self) -> str:
        return (
            "echo networkmanager=$(systemctl is-active NetworkManager 2>/dev/null); "
            "echo networkd=$(systemctl is-active systemd-networkd 2>/dev/null); "
            "if command -v netplan >/dev/null 2>&1; then echo netplan=yes; fi; "
            "if grep -qsiE '^[[:space:]]*renderer:[[:space:]]*NetworkManager' /etc/netplan/*.yaml; "
            "then echo nm_renderer=yes; fi; "
            "if ls /etc/netplan/90-NM-*.yaml >/dev/null 2>&1; then echo nm_profiles=yes; fi; "
            "if [ -d /etc/cloud ] || [ -e /etc/netplan/50-cloud-init.yaml ]; then echo cloud_init=yes; fi; "
            "(. /etc/os-release && echo version=$VERSION_ID)"
        )

    def process(self, output):
        values = dict(line.split("=", 1) for line in output if "=" in line)
        renderer = RendererFacts(
            networkmanager_active=values.get("networkmanager") == "active",
            networkd_active=values.get("networkd") == "active",
            netplan_installed=values.get("netplan") == "yes",
            netplan_nm_renderer=values.get("nm_renderer") == "yes",
            netplan_nm_profiles=values.get("nm_profiles") == "yes",
            ubuntu_version=values.get("version") or None,
        )
        return {"renderer": renderer, "cloud_init": values.get("cloud_init") == "yes"}


class NetplanFilesConfiguring(FactBase):
    """The netplan files in /etc/netplan that configure this interface, as paths.

    netplan merges every file, so another file that sets addresses for the same
    interface (a Desktop's NetworkManager profile, an old hand-written file) would keep
    its address beside ours. Parsed on the host: the files may hold WiFi passwords,
    and only their names leave it.
    """

    default = list

    def command(self, interface: str) -> str:
        script = (
            "import glob, sys, yaml\n"
            "for path in sorted(glob.glob('/etc/netplan/*.yaml')):\n"
            "    try:\n"
            "        network = (yaml.safe_load(open(path)) or {}).get('network') or {}\n"
            "    except Exception:\n"
            "        continue\n"
            "    if any(sys.argv[1] in (network.get(kind) or {}) for kind in ('ethernets', 'wifis')):\n"
            "        print(path)\n"
        )
        return f"python3 -c {shlex.quote(script)} {shlex.quote(interface)} 2>/dev/null || true"

    def process(self, output):
        return [line.strip() for line in output if line.strip()]


class MaskedFileContents(FactBase):
    """A file's content with WiFi passwords masked on the host, for diffs; None if absent.

    Masking happens before the content leaves the host, so not even pyinfra's
    debug output can show the old password.
    """

    def command(self, path: str) -> str:
        quoted = shlex.quote(path)
        return f"if [ -f {quoted} ]; then sed -e {shlex.quote(SED_MASK_SECRETS)} {quoted}; fi"

    def process(self, output):
        return "".join(line + "\n" for line in output)


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _is_private(file_fact) -> bool:
    return bool(file_fact) and file_fact.get("user") == "root" and file_fact.get("mode") == 600


def _print_masked_diff(path: str, new_content: str) -> None:
    old = host.get_fact(MaskedFileContents, path=path)
    new = mask_secrets(new_content)
    host.log(f"Will {'modify' if old else 'create'} {path}", logger.info)
    if old == new:
        logger.info("  (only the WiFi password changes)")
    for line in generate_color_diff((old or "").splitlines(keepends=True), new.splitlines(keepends=True)):
        logger.info("  %s", line)
    logger.info("")


@operation()
def network_in_effect(
    settings: NetworkSettings,
    current_address: str,
    roster_path: str | None = None,
):
    """
    Make the host's network configuration the one from the roster, safely.

    + settings: the host's checked network settings (``roslab.netcheck.network_settings``)
    + current_address: the address pyinfra reaches the host at now
    + roster_path: the roster file; the confirmed address is recorded beside it

    The host keeps the new configuration only if the controller reaches it at its
    new address within ``settings.confirm_timeout`` seconds; otherwise it restores
    the previous files by itself, and this operation fails the host saying so.

    **Example:**

    .. code:: python

        network_in_effect(
            name="Ensure the host has its static address from the roster",
            settings=network_settings(host.data),
            current_address="192.168.50.200",
        )
    """
    found = host.get_fact(NetworkRenderer)
    try:
        layout = choose_layout(settings.backend, found["renderer"])
    except ValueError as exc:
        raise OperationError(f"{host.name}: {exc}") from None
    configuring = host.get_fact(NetplanFilesConfiguring, interface=settings.interface) if layout.uses_netplan else []
    wanted = desired_files(settings, layout, found["cloud_init"], tuple(configuring))

    changed = [path for path, content in wanted.files.items()
               if host.get_fact(Sha256File, path=path) != sha256(content)]
    leftover = [path for path in wanted.superseded if host.get_fact(File, path=path)]
    if not changed and not leftover:
        loose = [path for path in wanted.files if not _is_private(host.get_fact(File, path=path))]
        for path in loose:
            # Same content, wrong owner or mode: fix in place, nothing to apply.
            yield StringCommand("chown", "root:root", path, "&&", "chmod", "0600", path)
        if not loose:
            host.noop(f"network configuration already in place ({layout.reason})")
        return

    if state.config.DIFF:
        for path in changed:
            _print_masked_diff(path, wanted.files[path])
        for path in leftover:
            host.log(f"Will move {path} aside (kept under {BACKUP_ROOT})", logger.info)

    reach_address = str(settings.address.ip) if settings.address else current_address
    token = uuid4().hex
    plan = {
        "token": token,
        "layout": layout.name,
        "interface": settings.interface,
        "netplan_dir": NETPLAN_DIR,
        "files": list(wanted.files),
        "superseded": list(wanted.superseded),
        "expect_address": str(settings.address) if settings.address else None,
        "gateway": str(settings.gateway) if settings.gateway else None,
        "confirm_timeout": settings.confirm_timeout,
        "backup_root": BACKUP_ROOT,
        "run_dir": RUN_DIR,
    }
    plan_path = f"{RUN_DIR}/plan.json"
    script_path = f"{RUN_DIR}/network_apply.py"

    staged_dirs = sorted({str(network_apply.staged_path(plan, path).parent) for path in wanted.files})
    yield StringCommand("rm", "-rf", f"{RUN_DIR}/staging", "&&", "install", "-d", "-m", "0700",
                        RUN_DIR, f"{RUN_DIR}/staging", *staged_dirs)
    # With sudo, pyinfra uploads as the SSH user first and then copies into place:
    # give those temporary copies a directory only that user can read.
    upload_dir = f"/tmp/roslab-network-{token}"
    yield StringCommand("mkdir", "-m", "0700", upload_dir, _sudo=False)
    uploads = [(StringIO(content), network_apply.staged_path(plan, path))
               for path, content in wanted.files.items()]
    uploads.append((StringIO(json.dumps(plan, indent=2)), plan_path))
    uploads.append((str(APPLY_SCRIPT), script_path))
    for number, (source, destination) in enumerate(uploads):
        yield FileUploadCommand(source, str(destination), remote_temp_filename=f"{upload_dir}/{number}")
    yield StringCommand("rm", "-rf", upload_dir, _sudo=False)
    yield StringCommand("chmod", "-R", "go-rwx", RUN_DIR)

    # Validation failure: pyinfra shows the validator's message and stops here, untouched.
    yield StringCommand("python3", script_path, "validate", plan_path)
    yield StringCommand(
        "systemctl", "reset-failed", f"{APPLY_UNIT}.service", "2>/dev/null", ";",
        "systemd-run", f"--unit={APPLY_UNIT}", "--collect", "--quiet",
        QuoteString("--description=roslab: apply the network change, roll back unless confirmed"),
        "python3", script_path, "apply", plan_path,
    )
    yield FunctionCommand(
        confirm_network_change,
        (),
        {
            "token": token,
            "new_address": reach_address,
            "old_address": current_address,
            "confirm_timeout": settings.confirm_timeout,
            "roster_path": roster_path,
        },
    )


# Controller side, at execution time


def _connector_arguments(state, host) -> dict:
    """The op's sudo/su settings, for commands the callback runs itself."""
    op_data = state.get_op_data_for_host(host, host.executing_op_hash)
    arguments = op_data.global_arguments
    return {key: arguments[key] for key in CONNECTOR_ARGUMENT_KEYS if key in arguments}


def _connect_at(host, address: str) -> bool:
    """Point pyinfra's SSH connection for `host` at `address`; True once connected."""
    connector = host.connector
    connector.data["ssh_hostname"] = address
    connector.disconnect()  # forget the file transfer channel of the old connection
    try:
        with gevent.Timeout(COMMAND_TIMEOUT * 2):
            connector.connect()
    except (ConnectError, gevent.Timeout):
        return False
    return True


def _connect_within(host, address: str, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while True:
        if _connect_at(host, address):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(2)


def _run(host, arguments: dict, *bits) -> str | None:
    """Run a command on the current connection; its stdout, or None if it failed.

    Bounded in time: when the host drops the address mid-command (a rollback), a
    command on the dead connection would otherwise wait for TCP to give up.
    """
    try:
        with gevent.Timeout(COMMAND_TIMEOUT):
            ok, output = host.run_shell_command(StringCommand(*bits), **arguments)
    except (gevent.Timeout, OSError, SSHException, EOFError):
        return None
    return output.stdout if ok else None


def _read_status(host, arguments: dict, token: str) -> dict | None:
    """This run's status from the host (None: unreadable, or an earlier run's)."""
    text = _run(host, arguments, "cat", f"{RUN_DIR}/status.json")
    try:
        status = json.loads(text) if text else None
    except ValueError:
        return None
    return status if status and status.get("token") == token else None


def _is_final(status: dict | None) -> bool:
    return bool(status) and status["state"] not in (
        network_apply.STATE_APPLYING, network_apply.STATE_WAITING
    )


def _wait_for_final_status(host, arguments: dict, token: str, wait: float) -> dict | None:
    deadline = time.monotonic() + wait
    status = None
    while time.monotonic() < deadline:
        status = _read_status(host, arguments, token) or status
        if _is_final(status):
            return status
        time.sleep(0.5)
    return status


def _confirm_at_new_address(host, arguments: dict, token: str, new_address: str,
                            old_address: str, deadline: float) -> dict | None:
    """Confirm once the host waits for it; the host's final status, or None at the deadline."""
    connected = False
    next_old_probe = time.monotonic() + OLD_ADDRESS_PROBE_INTERVAL
    while time.monotonic() < deadline:
        connected = connected or _connect_at(host, new_address)
        if connected:
            status = _read_status(host, arguments, token)
            if status is None:
                connected = False  # the connection died, or the file is not there yet
            elif status["state"] == network_apply.STATE_WAITING:
                # The confirmation proves the new address works both ways, over a new connection.
                _run(host, arguments, "printf", "%s", token, ">", f"{RUN_DIR}/confirmed")
                status = _wait_for_final_status(host, arguments, token, wait=10)
                if _is_final(status):
                    return status
            elif _is_final(status):
                return status  # the host gave up by itself, e.g. its gateway did not answer
        elif new_address != old_address and time.monotonic() >= next_old_probe:
            # Back at the old address already? Then the host rolled back early.
            next_old_probe = time.monotonic() + OLD_ADDRESS_PROBE_INTERVAL
            if _connect_at(host, old_address):
                status = _read_status(host, arguments, token)
                if _is_final(status):
                    return status
        time.sleep(1)
    return None


def confirm_network_change(
    state,
    host,
    token: str,
    new_address: str,
    old_address: str,
    confirm_timeout: int,
    roster_path: str | None,
) -> bool:
    """Confirm the change over a new connection to the new address, or report the rollback.

    Runs on the controller. On success pyinfra's connection to the host stays at
    the new address, so the rest of the deploy runs there.
    """
    arguments = _connector_arguments(state, host)
    old_client = host.connector.client
    deadline = time.monotonic() + confirm_timeout
    status = _confirm_at_new_address(host, arguments, token, new_address, old_address, deadline)

    if status and status["state"] == network_apply.STATE_CONFIRMED:
        if old_client is not None and old_client is not host.connector.client:
            old_client.close()
        if roster_path:
            netstate.record_address(roster_path, host.name, new_address)
        host.log_styled(
            f"Network change confirmed: reachable at {new_address}; "
            f"the previous files are kept in {status.get('backup')}",
            fg="green",
            log_func=logger.info,
        )
        return True

    # No confirmation: the host restores its previous configuration by itself.
    if status is None:
        wait = max(0.0, deadline - time.monotonic()) + ROLLBACK_GRACE
    else:
        wait = ROLLBACK_GRACE  # the host is re-applying its old files right now
    status = None
    if _connect_within(host, old_address, wait):
        status = _wait_for_final_status(host, arguments, token, wait=ROLLBACK_GRACE)

    reason = status.get("message") if status else None
    if status and status["state"] == network_apply.STATE_ROLLED_BACK:
        host.log_styled(
            f"Network change rolled back: {reason}. The host is reachable again at "
            f"{old_address} with its previous configuration.",
            fg="red",
            log_func=logger.error,
        )
    elif status:
        host.log_styled(
            f"Network change failed on the host ({status['state']}): {reason}. "
            f"Its previous files are in {status.get('backup')}.",
            fg="red",
            log_func=logger.error,
        )
    else:
        host.log_styled(
            f"Network change not confirmed at {new_address}, and the host does not answer at "
            f"{old_address} either; it restores its previous configuration on its own "
            f"(see `journalctl -u {APPLY_UNIT}` and {RUN_DIR}/status.json on the host).",
            fg="red",
            log_func=logger.error,
        )
    return False
