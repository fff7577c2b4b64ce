"""reporting.summary.closed_by_the_host: whether a failed step's connection ended because its host
went away (the summary then says "lost the connection", not pyinfra's words)."""

from __future__ import annotations

import gevent
import pytest

from roslab.reporting import summary


class Connection:
    """A paramiko Transport as closed_by_the_host reads it: active or not, the exception that
    ended it, and what a keepalive request meets."""

    def __init__(self, active: bool, saved=None, keepalive=None):
        self.active, self.saved_exception, self.keepalive = active, saved, keepalive

    def is_active(self) -> bool:
        return self.active

    def global_request(self, kind, wait):
        if isinstance(self.keepalive, BaseException):
            raise self.keepalive
        if self.keepalive == "silent":
            gevent.sleep(10)


@pytest.mark.parametrize("connection, lost", [
    (None, False),
    (Connection(False, EOFError()), True),  # ended by the host's end of file
    (Connection(False, ConnectionResetError()), True),
    (Connection(False), False),  # the controller closed it
    (Connection(True), False),  # it answers
    (Connection(True, keepalive=EOFError()), True),  # the keepalive met the end the reader had not seen yet
    (Connection(True, keepalive=BrokenPipeError()), True),
    (Connection(True, keepalive=ValueError("unexpected")), False),
])
def test_a_connection_ended_by_its_host_is_lost_and_one_the_controller_ended_is_not(connection, lost):
    assert summary.closed_by_the_host(connection) is lost


def test_a_connection_that_stays_silent_past_the_wait_is_lost(monkeypatch):
    monkeypatch.setattr(summary, "ANSWER_WITHIN", 0.05)
    assert summary.closed_by_the_host(Connection(True, keepalive="silent")) is True
