"""Where each host was last confirmed reachable, kept on the controller beside the roster.

After the network deploy moves a host, the roster's `address` (where SSH reached
it, e.g. its DHCP address) is out of date until the teacher edits it. The
deploy records each confirmed address in `<roster dir>/.roslab-state/addresses.yaml`
so the next run's inventory can find the host there:

    address = last_known_address(roster_path, "team1-main") or roster_address
"""

from __future__ import annotations

import os
import socket
import threading
from pathlib import Path

import yaml

from roslab.controller_files import UnreadableFile, read_regular_file, replace_file

STATE_DIR = ".roslab-state"
ADDRESSES_FILE = "addresses.yaml"


def addresses_path(roster_path: str | os.PathLike) -> Path:
    return Path(roster_path).resolve().parent / STATE_DIR / ADDRESSES_FILE


def _load(path: Path) -> dict[str, str]:
    if not os.path.lexists(path):
        return {}
    try:
        # Bounded and never waiting (a FIFO or a device here must not hang the inventory).
        data = yaml.safe_load(read_regular_file(path, 1024 * 1024).decode("utf-8")) or {}
    except (UnreadableFile, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: {error}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of host name to address")
    return {str(name): str(address) for name, address in data.items()}


def last_known_addresses(roster_path: str | os.PathLike) -> dict[str, str]:
    """Every recorded host's last confirmed address (one read for the whole classroom)."""
    return _load(addresses_path(roster_path))


def last_known_address(roster_path: str | os.PathLike, host: str) -> str | None:
    """The address `host` was last confirmed at by the network deploy, or None."""
    return last_known_addresses(roster_path).get(host)


def record_address(roster_path: str | os.PathLike, host: str, address: str) -> None:
    """Remember that `host` answers at `address` (an atomic rewrite of the state file)."""
    path = addresses_path(roster_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    addresses = _load(path)
    if addresses.get(host) == address:
        return
    addresses[host] = address
    replace_file(path, "# managed by roslab: where each host was last confirmed reachable.\n"
                 + yaml.safe_dump(dict(sorted(addresses.items())), default_flow_style=False), mode=0o600)


# A change the controller started and has not seen end (confirmed, rolled back or failed):
# written before the host is told to apply it, so a controller killed during the change
# leaves a record the next run names when the host does not answer.
PENDING_FILE = "pending-network.yaml"
_pending_lock = threading.Lock()  # hosts' changes run in threads: one rewrite at a time


def pending_path(roster_path: str | os.PathLike) -> Path:
    return Path(roster_path).resolve().parent / STATE_DIR / PENDING_FILE


def pending_changes(roster_path: str | os.PathLike) -> dict[str, dict]:
    """host -> {"from", "to", "started", "confirm_timeout"}; {} when none or unreadable (this
    record only makes a failure's message truer: it never stops a run)."""
    path = pending_path(roster_path)
    if not os.path.lexists(path):
        return {}
    try:
        data = yaml.safe_load(read_regular_file(path, 1024 * 1024).decode("utf-8")) or {}
    except (UnreadableFile, UnicodeDecodeError, yaml.YAMLError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {str(name): entry for name, entry in data.items() if isinstance(entry, dict)}


def _write_pending(path: Path, pending: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, "# managed by roslab: network changes started and not yet seen to end.\n"
                 + yaml.safe_dump(dict(sorted(pending.items())), default_flow_style=False), mode=0o600)


def record_pending(roster_path: str | os.PathLike, host: str, old_address: str, new_address: str,
                   confirm_timeout: int, started: str, token: str | None = None) -> None:
    """Note that `host` is being moved from `old_address` to `new_address` (until it ends);
    `token`: the change's, as the host's status file names it (what became of it, later)."""
    with _pending_lock:
        pending = pending_changes(roster_path)
        pending[host] = {"from": old_address, "to": new_address, "started": started,
                         "confirm_timeout": int(confirm_timeout)}
        if token:
            pending[host]["token"] = token
        _write_pending(pending_path(roster_path), pending)


def clear_pending(roster_path: str | os.PathLike, host: str) -> None:
    """The change on `host` ended (confirmed, rolled back, failed): nothing pending."""
    with _pending_lock:
        pending = pending_changes(roster_path)
        if host in pending:
            del pending[host]
            _write_pending(pending_path(roster_path), pending)


def pending_description(entry: dict) -> str:
    """One clause for a failure line: what was pending, where the host may answer."""
    return (f"a network change started {entry.get('started', '?')} (from {entry.get('from', '?')} to "
            f"{entry.get('to', '?')}) was not seen to end: the controller stopped during it; the host "
            f"restores its previous settings by itself within {entry.get('confirm_timeout', '?')} s unless "
            f"it was confirmed, so it answers at {entry.get('from', '?')} or at {entry.get('to', '?')}")


# How long the inventory waits for a host's SSH port while it looks where a host in the middle
# of a change answers (s).
ANSWER_WAIT = 3


def answers(address: str, port: int, wait: float = ANSWER_WAIT) -> bool:
    """Whether something accepts a TCP connection at `address`:`port` within `wait` seconds."""
    try:
        with socket.create_connection((address, port), timeout=wait):
            return True
    except OSError:
        return False


def address_during_change(address: str, pending: dict | None, port: int, answering=answers) -> str:
    """Where to reach a host whose network change an earlier run left pending (its controller was
    killed): `address` (where it was last confirmed) if it answers there, else the change's new
    address if it answers there (the host waits there for a confirmation this run can give),
    else `address`. Without a pending change: `address`, nothing tried."""
    new = pending.get("to") if pending else None
    if not isinstance(new, str) or not new or new == address or answering(address, port):
        return address
    return new if answering(new, port) else address
