"""What every roslab service unit writes the same way: the user, the folder, the ROS environment,
the bash script it runs and how it restarts (the nodes' unit, a profile's services, the discovery
server or Zenoh router), each value written for systemd (`roslab.quoting`).

Each unit's own template (templates/*.service.j2) adds what is its own: its description, its
header naming the deploy that writes it, its ordering.
"""

from __future__ import annotations

from dataclasses import dataclass

from roslab.quoting import systemd_assignment, systemd_value, systemd_word


@dataclass(frozen=True)
class Restarts:
    """Restart=always after `sec` seconds, giving up after `burst` starts within `interval` s."""

    sec: int
    burst: int
    interval: int


# A launch or a robot's command: a slow start (a lidar, a serial port) gets five tries in 5 minutes.
NODE_RESTARTS = Restarts(sec=5, burst=5, interval=300)
# A discovery server or router starts in a second; three seconds apart, five tries in 2 minutes.
DISCOVERY_RESTARTS = Restarts(sec=3, burst=5, interval=120)


def unit_values(*, user: str, home: str, environment: dict[str, str], script: str,
                restarts: Restarts) -> dict:
    """The template values every roslab service unit shares (keys as the templates name them)."""
    return {
        "service_user": systemd_value(user),
        "working_directory": systemd_value(home),
        "environment": [systemd_assignment(name, value) for name, value in sorted(environment.items())],
        # ExecStart un-escapes \, expands % and $ in every word: the script is one escaped word.
        "exec_start": f"/bin/bash -c {systemd_word(script)}",
        "restart_sec": restarts.sec,
        "start_limit_burst": restarts.burst,
        "start_limit_interval": restarts.interval,
    }
