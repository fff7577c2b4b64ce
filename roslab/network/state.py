"""Where each host was last confirmed reachable, kept on the controller beside the roster.

After the network deploy moves a host, the roster's `address` (where SSH reached
it, e.g. its DHCP address) is out of date until the teacher edits it. The
deploy records each confirmed address in `<roster dir>/.roslab-state/addresses.yaml`
so the next run's inventory can find the host there:

    address = last_known_address(roster_path, "team1-main") or roster_address
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import yaml

from roslab.controller_files import UnreadableFile, read_regular_file

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
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=".addresses-")
    with os.fdopen(fd, "w") as out:
        out.write("# managed by roslab: where each host was last confirmed reachable.\n")
        yaml.safe_dump(dict(sorted(addresses.items())), out, default_flow_style=False)
    os.replace(temporary, path)
