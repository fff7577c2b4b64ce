"""SSH connections without paramiko's tracebacks: a failure is pyinfra's one line naming the host."""

from __future__ import annotations


def quiet_paramiko() -> None:
    """No paramiko traceback on stderr: a Pi whose sshd is still starting accepts the TCP
    connection and hangs up, and paramiko's transport thread logs "Error reading SSH protocol
    banner" with two tracebacks through Python's last-resort handler (paramiko's logger has
    none of its own). pyinfra reports the same failure as one line naming the host."""
    import logging

    paramiko_logger = logging.getLogger("paramiko")
    if not any(isinstance(handler, logging.NullHandler) for handler in paramiko_logger.handlers):
        paramiko_logger.addHandler(logging.NullHandler())
