"""A host that goes silent (its power cut, its cable pulled) is found lost in seconds, not never.

pyinfra's SSH connections have no keepalive of their own (only an ssh_config's
ServerAliveInterval, and paramiko's keepalive asks for no answer). A Pi that loses its power
sends nothing, not even the end of its connection: while a step waits for its command's output
the controller sends nothing either, so TCP never notices, and the step, and with it the whole
class's run (pyinfra runs each step on every host before the next), waits forever.

`install()` makes every SSH connection pyinfra opens ask the kernel to probe an idle peer
(TCP keepalive) and to drop the connection once the peer has answered nothing, neither a probe
nor data, for `SILENT_FOR` seconds (TCP_USER_TIMEOUT). The kernel acknowledges for a host
whatever its load, so only a host that is gone (or off the network) is dropped; its step then
fails as "lost the connection to the host during this step" (roslab.reporting.summary), and the other
hosts carry on.
"""

from __future__ import annotations

import socket

# A host silent this long is gone: a loaded Pi's kernel still answers within milliseconds.
SILENT_FOR = 45
# Probes start after this much quiet, then one every PROBE_EVERY seconds.
IDLE_BEFORE_PROBES = 15
PROBE_EVERY = 5


def keep_alive(sock) -> None:
    """Ask the kernel to probe `sock`'s peer and drop it after SILENT_FOR seconds of silence
    (the options a platform lacks are left out: the connection works as before there)."""
    options = [(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)]
    for name, value in (("TCP_KEEPIDLE", IDLE_BEFORE_PROBES), ("TCP_KEEPINTVL", PROBE_EVERY),
                        ("TCP_KEEPCNT", (SILENT_FOR - IDLE_BEFORE_PROBES) // PROBE_EVERY),
                        ("TCP_USER_TIMEOUT", SILENT_FOR * 1000)):
        if hasattr(socket, name):
            options.append((socket.IPPROTO_TCP, getattr(socket, name), value))
    for level, option, value in options:
        try:
            sock.setsockopt(level, option, value)
        except (OSError, AttributeError):
            return  # not a TCP socket (a proxy command's pipe): nothing to probe


def _transport_socket(connector):
    client = getattr(connector, "client", None)
    transport = client.get_transport() if client is not None else None
    return getattr(transport, "sock", None)


def install() -> None:
    """Make every SSH connection pyinfra opens from now on keep_alive. Idempotent."""
    from pyinfra.connectors.ssh import SSHConnector

    if getattr(SSHConnector.connect, "roslab_keeps_alive", False):
        return
    connect = SSHConnector.connect

    def connect_kept_alive(self, *args, **kwargs):
        result = connect(self, *args, **kwargs)
        sock = _transport_socket(self)
        if sock is not None:
            keep_alive(sock)
        return result

    connect_kept_alive.roslab_keeps_alive = True  # type: ignore[attr-defined]  # the patch's marker (getattr above)
    SSHConnector.connect = connect_kept_alive  # type: ignore[method-assign]  # roslab patches pyinfra here on purpose

