"""What the controller can tell about a host's SSH connection without asking the host."""

from __future__ import annotations


def connection_lost(host) -> bool:
    """Whether pyinfra's SSH connection to `host` was made and is closed now (the host lost
    power, rebooted or left the network). False where it cannot tell (not SSH, never connected)."""
    client = getattr(getattr(host, "connector", None), "client", None)
    get_transport = getattr(client, "get_transport", None)
    if get_transport is None:
        return False
    try:
        transport = get_transport()
        return transport is None or not transport.is_active()
    except Exception:  # noqa: BLE001 - a half-closed client: nothing more to learn
        return False
