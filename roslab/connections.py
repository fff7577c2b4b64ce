"""What the controller can tell about a host's SSH connection without asking the host, and how
a controller-side callback reaches the host as its operation would."""

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


def op_connector_arguments(state, host) -> dict:
    """The executing operation's sudo/su settings (its sudo password, if the roster gives one),
    for the commands a FunctionCommand callback runs on `host` itself."""
    from pyinfra.api.arguments import CONNECTOR_ARGUMENT_KEYS

    arguments = state.get_op_data_for_host(host, host.executing_op_hash).global_arguments
    return {key: arguments[key] for key in CONNECTOR_ARGUMENT_KEYS if key in arguments}
