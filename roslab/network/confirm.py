"""The controller's side of a network change: confirm it at the new address, or report the rollback.

Runs on the controller at execution time, as the last command of
`roslab.network.operation.network_in_effect`, after the host started
`network_apply.py apply` detached from SSH. It connects to the host's new
address over a *new* connection and writes the run's token into the
confirmation file once the host waits for it; the host keeps the change only
then. Otherwise it finds the host back at its old address and reports what the
host's status file says happened.
"""

from __future__ import annotations

import time

import gevent
from paramiko import SSHException
from pyinfra import logger
from pyinfra.api import StringCommand
from pyinfra.api.exceptions import ConnectError

from roslab.connections import op_connector_arguments
from roslab.network import state as network_state
from roslab.network.apply import (
    APPLY_UNIT,
    CONFIRMATION_FILE,
    RUN_DIR,
    STATE_CONFIRMED,
    STATE_ROLLED_BACK,
    STATE_WAITING,
    STATUS_FILE,
    Status,
)

# After the host's own deadline: time for its rollback (restore and re-apply) to finish.
ROLLBACK_GRACE = 45
# How often the controller looks at the old address for an early rollback.
OLD_ADDRESS_PROBE_INTERVAL = 5
# Longest wait for one command in the confirmation (s).
COMMAND_TIMEOUT = 10

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


def _read_status(host, arguments: dict, token: str) -> Status | None:
    """This run's status from the host (None: unreadable, or an earlier run's)."""
    return Status.from_json(_run(host, arguments, "cat", f"{RUN_DIR}/{STATUS_FILE}"), token)


def _is_final(status: Status | None) -> bool:
    return status is not None and status.final


def _wait_for_final_status(host, arguments: dict, token: str, wait: float) -> Status | None:
    deadline = time.monotonic() + wait
    status = None
    while time.monotonic() < deadline:
        status = _read_status(host, arguments, token) or status
        if _is_final(status):
            return status
        time.sleep(0.5)
    return status


def _confirm_at_new_address(host, arguments: dict, token: str, new_address: str,
                            old_address: str, deadline: float) -> Status | None:
    """Confirm once the host waits for it; the host's final status, or None at the deadline."""
    connected = False
    next_old_probe = time.monotonic() + OLD_ADDRESS_PROBE_INTERVAL
    while time.monotonic() < deadline:
        connected = connected or _connect_at(host, new_address)
        if connected:
            status = _read_status(host, arguments, token)
            if status is None:
                connected = False  # the connection died, or the file is not there yet
            elif status.state == STATE_WAITING:
                # The confirmation proves the new address works both ways, over a new connection.
                _run(host, arguments, "printf", "%s", token, ">", f"{RUN_DIR}/{CONFIRMATION_FILE}")
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


def change_started(state, host, old_address: str, new_address: str, confirm_timeout: int,
                   roster_path: str | None, token: str | None = None) -> bool:
    """Runs on the controller just before the host is told to apply: the change is pending
    until confirm_network_change sees it end (network_state.record_pending)."""
    if roster_path:
        started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
        network_state.record_pending(roster_path, host.name, old_address, new_address, confirm_timeout, started,
                                     token=token)
    return True


def confirm_pending_change(state, host, token: str, new_address: str, roster_path: str | None) -> bool:
    """Runs on the controller when this run reached a host at the new address of a change an
    earlier (killed) run launched, still waiting for its confirmation: confirm it now, so the
    host keeps the change instead of rolling it back, and remember the address. False (the
    step fails, the host rolls back by itself; the next run makes the change again) when the
    host does not say it kept it."""
    arguments = op_connector_arguments(state, host)
    _run(host, arguments, "printf", "%s", token, ">", f"{RUN_DIR}/{CONFIRMATION_FILE}")
    status = _wait_for_final_status(host, arguments, token, wait=15)
    if status is None or status.state != STATE_CONFIRMED:
        host.log_styled(f"roslab: network: found at {new_address} waiting for the confirmation of a change an "
                        "earlier run started, which did not take it: the host restores its previous settings by "
                        "itself; run again once it has", fg="yellow", log_func=logger.warning)
        return False
    if roster_path:
        network_state.record_address(roster_path, host.name, new_address)
        network_state.clear_pending(roster_path, host.name)
    host.log_styled(f"roslab: network: found at {new_address} waiting for the confirmation of a change an earlier "
                    "run started (its controller stopped during it): confirmed now, the host keeps it",
                    fg="yellow", log_func=logger.warning)
    return True


def change_ended(state, host, roster_path: str | None) -> bool:
    """Runs on the controller when a run finds the host of a change an earlier run left pending
    with nothing more to change: that change is over (the run said what became of it)."""
    if roster_path:
        network_state.clear_pending(roster_path, host.name)
    return True


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
    arguments = op_connector_arguments(state, host)
    old_client = host.connector.client
    deadline = time.monotonic() + confirm_timeout
    status = _confirm_at_new_address(host, arguments, token, new_address, old_address, deadline)

    if status is not None and status.state == STATE_CONFIRMED:
        _settle_confirmed(host, status, old_client, new_address, roster_path)
        return True

    # No confirmation: the host restores its previous configuration by itself.
    status = _final_status_at_old_address(host, arguments, token, old_address, status, deadline)
    if status is not None and roster_path:  # it ended: rolled back or failed, the host says which
        network_state.clear_pending(roster_path, host.name)
    _report_unconfirmed(host, status, new_address, old_address)
    return False


def _settle_confirmed(host, status: Status, old_client, new_address: str, roster_path: str | None) -> None:
    """The host kept the change: stay connected at the new address and remember it beside the roster."""
    if old_client is not None and old_client is not host.connector.client:
        old_client.close()
    if roster_path:
        network_state.record_address(roster_path, host.name, new_address)
        network_state.clear_pending(roster_path, host.name)
    host.log_styled(
        f"Network change confirmed: reachable at {new_address}; "
        f"the previous files are kept in {status.backup}",
        fg="green",
        log_func=logger.info,
    )


def _final_status_at_old_address(host, arguments: dict, token: str, old_address: str,
                                 status: Status | None, deadline: float) -> Status | None:
    """How the unconfirmed change ended, read at the old address once the host answers there again
    (None: it does not answer within the host's own deadline and the rollback's grace)."""
    if status is None:
        wait = max(0.0, deadline - time.monotonic()) + ROLLBACK_GRACE
    else:
        wait = ROLLBACK_GRACE  # the host is re-applying its old files right now
    if _connect_within(host, old_address, wait):
        return _wait_for_final_status(host, arguments, token, wait=ROLLBACK_GRACE)
    return None


def _report_unconfirmed(host, status: Status | None, new_address: str, old_address: str) -> None:
    """One line for the teacher: rolled back, failed on the host, or not heard from at either address."""
    if status is not None and status.state == STATE_ROLLED_BACK:
        host.log_styled(
            f"Network change rolled back: {status.message}. The host is reachable again at "
            f"{old_address} with its previous configuration.",
            fg="red",
            log_func=logger.error,
        )
    elif status is not None:
        host.log_styled(
            f"Network change failed on the host ({status.state}): {status.message}. "
            f"Its previous files are in {status.backup}.",
            fg="red",
            log_func=logger.error,
        )
    else:
        host.log_styled(
            f"Network change not confirmed at {new_address}, and the host does not answer at "
            f"{old_address} either; it restores its previous configuration on its own "
            f"(see `journalctl -u {APPLY_UNIT}` and {RUN_DIR}/{STATUS_FILE} on the host).",
            fg="red",
            log_func=logger.error,
        )
