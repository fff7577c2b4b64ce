"""A host that goes silent is dropped by the kernel in SILENT_FOR seconds (roslab.ssh.keepalive)."""

from __future__ import annotations

import socket
from types import SimpleNamespace

import pytest
from pyinfra.connectors.ssh import SSHConnector

from roslab.ssh import keepalive as ssh_keepalive


def options(sock) -> dict[str, int]:
    return {
        "keepalive": sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE),
        "idle": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE),
        "interval": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL),
        "count": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT),
        "user_timeout_ms": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT),
    }


def test_a_silent_peer_is_probed_and_dropped_after_silent_for_seconds():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        ssh_keepalive.keep_alive(sock)
        got = options(sock)
    assert got["keepalive"] == 1
    assert got["user_timeout_ms"] == ssh_keepalive.SILENT_FOR * 1000
    # the probes fit in the same time: the last one is sent before the connection is dropped
    assert got["idle"] + got["interval"] * got["count"] <= ssh_keepalive.SILENT_FOR
    assert got["count"] >= 3


def test_a_connection_that_is_not_tcp_is_left_as_it_is():
    left, right = socket.socketpair()  # a proxy command's pipe is no TCP socket
    with left, right:
        ssh_keepalive.keep_alive(left)


class FakeConnector:
    def __init__(self, sock):
        self.client = SimpleNamespace(get_transport=lambda: SimpleNamespace(sock=sock))


@pytest.fixture
def connect_calls(monkeypatch):
    calls = []
    monkeypatch.setattr(SSHConnector, "connect", lambda self: calls.append(self) or "connected")
    return calls


def test_every_connection_pyinfra_opens_is_kept_alive_once_installed(connect_calls):
    ssh_keepalive.install()
    ssh_keepalive.install()  # idempotent: one wrapper, one connect
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        connector = FakeConnector(sock)
        assert SSHConnector.connect(connector) == "connected"
        assert connect_calls == [connector]
        assert options(sock)["user_timeout_ms"] == ssh_keepalive.SILENT_FOR * 1000


def test_a_failed_connection_is_pyinfras_to_report(monkeypatch):
    def refused(self):
        raise OSError("Connection refused")

    monkeypatch.setattr(SSHConnector, "connect", refused)
    ssh_keepalive.install()
    with pytest.raises(OSError, match="refused"):
        SSHConnector.connect(FakeConnector(None))
