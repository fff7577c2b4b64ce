"""Verify each team's main host hears its robot: a table per team, non-zero exit unless all do.

    python -m deploy.verify inventories/lab.py [--limit team1 ...]

Read-only: on every host it asks systemd whether roslab-nodes.service is active, and on
each main host, with the team's ROS environment (the same as the service's), it lists the
topics and waits up to `nodes_verify_timeout` seconds for one message on
`nodes_verify_topic` (`ros2 topic echo --once`). A host without a ROS 2 runtime
(no `ros2` command, as in the sandbox's stand-in ROS) is reported as such and does
not pass. The settings come from the roster like every other setting (deploy/workspace.py).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from dataclasses import dataclass, field

from pyinfra.api import Config, FactBase, State
from pyinfra.api.connect import connect_all, disconnect_all
from pyinfra.context import ctx_config, ctx_host, ctx_inventory, ctx_state
from pyinfra.facts.systemd import SystemdStatus

from deploy.common import host_distro, login_home, login_user, setting
from deploy.workspace import NODES_SERVICE, ros_environment, workspace_path


class NodesHeard(FactBase):
    """
    What a host hears on its ROS domain: ``{"ros": bool, "topics": [...], "message": str | None}``.

    ``ros`` is False when the host has no ``ros2`` command after sourcing the distro.
    ``message`` is the first message on ``topic`` within ``timeout`` seconds, or None.
    """

    def command(self, distro: str, environment: dict, workspace_dir: str, topic: str, timeout: int):
        return "bash -c " + shlex.quote(check_script(distro, environment, workspace_dir, topic, timeout))

    def process(self, output):
        return parse_check_output(output)


def check_script(distro: str, environment: dict, workspace_dir: str, topic: str, timeout: int) -> str:
    """The bash script the fact runs: it always exits 0 and reports in sections."""
    timeout = int(timeout)
    exports = [f"export {name}={shlex.quote(value)}" for name, value in sorted(environment.items())]
    workspace_setup = shlex.quote(f"{workspace_dir}/install/setup.bash")
    return "\n".join(
        [
            f"[ -f /opt/ros/{shlex.quote(distro)}/setup.bash ] && source /opt/ros/{shlex.quote(distro)}/setup.bash",
            f"[ -f {workspace_setup} ] && source {workspace_setup}",
            *exports,
            "if ! command -v ros2 >/dev/null 2>&1; then echo '## ros missing'; exit 0; fi",
            "echo '## topics'",
            f"timeout {timeout} ros2 topic list 2>/dev/null",
            "echo '## message'",
            f"timeout {timeout} ros2 topic echo --once {shlex.quote(topic)} 2>/dev/null | head -n 20",
            "exit 0",
        ]
    )


def parse_check_output(lines) -> dict:
    result = {"ros": True, "topics": [], "message": None}
    section = None
    message = []
    for line in lines:
        if line.startswith("## "):
            section = line[3:].strip()
            if section == "ros missing":
                result["ros"] = False
            continue
        if section == "topics" and line.strip():
            result["topics"].append(line.strip())
        elif section == "message" and line.strip() and line.strip() != "---":
            message.append(line.strip())
    if message:
        result["message"] = " ".join(message)
    return result


@dataclass
class TeamResult:
    team: str
    main: str | None = None
    robot: str | None = None
    topic: str = "/chatter"
    services: dict = field(default_factory=dict)  # host name -> "active", "failed", ...
    heard: dict | None = None  # NodesHeard of the main host
    error: str | None = None

    @property
    def passed(self) -> bool:
        return bool(self.heard and self.heard["ros"] and self.heard["message"] and not self.error)

    def verdict(self) -> str:
        if self.error:
            return self.error
        if not self.main:
            return "no main host in the team"
        if not self.heard["ros"]:
            return f"no ROS runtime on {self.main}: not verified"
        if self.heard["message"]:
            return f"heard {self.robot or 'the robot'}"
        if self.topic in self.heard["topics"]:
            return f"{self.topic} listed but no message within the timeout"
        return f"{self.main} does not see {self.topic}"


def _service_cell(result: TeamResult, name: str | None) -> str:
    return result.services.get(name, "?") if name else "-"


def format_table(results: list[TeamResult]) -> str:
    header = ("team", "main", "robot", "main service", "robot service", "topics seen", "message heard", "result")
    rows = [header]
    for result in sorted(results, key=lambda r: r.team):
        heard = result.heard or {"ros": False, "topics": [], "message": None}
        topics = ", ".join(t for t in heard["topics"] if not t.startswith(("/rosout", "/parameter_events")))
        message = heard["message"] or "-"
        if len(message) > 40:
            message = message[:37] + "..."
        rows.append(
            (
                result.team,
                result.main or "-",
                result.robot or "-",
                _service_cell(result, result.main),
                _service_cell(result, result.robot),
                topics or "-",
                message,
                ("PASS " if result.passed else "FAIL ") + result.verdict(),
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    lines.insert(1, "  ".join("-" * width for width in widths))
    return "\n".join(lines)


# Running it against an inventory
# -------------------------------


def _check_host(state: State, host) -> tuple[str, dict | None, str | None]:
    """(service state, NodesHeard on main hosts, error) for one host."""
    with ctx_host.use(host):
        try:
            statuses = host.get_fact(SystemdStatus, services=[NODES_SERVICE])
            running = statuses.get(NODES_SERVICE)
            service = "active" if running else "not running" if running is False else "not installed"
            if host.data.get("roslab_role") != "main":
                return service, None, None
            distro = host_distro()
            heard = host.get_fact(
                NodesHeard,
                distro=distro,
                environment=ros_environment(distro),
                workspace_dir=workspace_path(login_home()),
                topic=setting("nodes_verify_topic"),
                timeout=setting("nodes_verify_timeout"),
                _sudo=True,
                _sudo_user=login_user(),
            )
            return service, heard, None
        except Exception as error:  # one host's trouble is its team's row, not a crash
            return "?", None, f"{host.name}: {error}"


def verify(state: State) -> list[TeamResult]:
    """Check every active host in parallel and group the results by team."""
    hosts = [host for host in state.inventory.iter_activated_hosts() if host in state.active_hosts]
    greenlets = {host: state.pool.spawn(_check_host, state, host) for host in hosts}
    teams: dict[str, TeamResult] = {}
    for host, greenlet in greenlets.items():
        service, heard, error = greenlet.get()
        with ctx_host.use(host):
            team_name = host.data.get("roslab_team") or host.name
            topic = setting("nodes_verify_topic")
        team = teams.setdefault(team_name, TeamResult(team_name, topic=topic))
        team.services[host.name] = service
        if host.data.get("roslab_role") == "main":
            team.main, team.heard = host.name, heard
        else:
            team.robot = host.name
        team.error = team.error or error
    for host in state.inventory.iter_activated_hosts():
        if host not in state.active_hosts:
            team_name = host.data.get("roslab_team") or host.name
            team = teams.setdefault(team_name, TeamResult(team_name))
            team.error = team.error or f"{host.name} is unreachable"
    return list(teams.values())


def connect(inventory_path: str, limit: list[str] | None = None) -> State:
    """A pyinfra state connected to the inventory's hosts (as `pyinfra INVENTORY ...` would)."""
    from pyinfra_cli.cli import _apply_inventory_limit
    from pyinfra_cli.inventory import make_inventory

    state = State(check_for_changes=False)
    state.cwd = os.getcwd()
    config = Config()
    ctx_state.set(state)
    ctx_config.set(config)
    inventory = make_inventory(inventory_path, cwd=state.cwd)
    ctx_inventory.set(inventory)
    # The same --limit patterns as pyinfra's (group or host names, globs).
    state.init(inventory, config, initial_limit=_apply_inventory_limit(inventory, limit))
    connect_all(state)
    return state


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("inventory", nargs="?", default="inventories/lab.py",
                        help="pyinfra inventory (default: inventories/lab.py)")
    parser.add_argument("--limit", action="append", help="a group or host name (repeatable)")
    args = parser.parse_args(argv)
    state = connect(args.inventory, args.limit)
    try:
        results = verify(state)
    finally:
        disconnect_all(state)
    print(format_table(results))
    failed = [r.team for r in results if not r.passed]
    if failed:
        print(f"\nnot verified: {', '.join(sorted(failed))}", file=sys.stderr)
        return 1
    print(f"\nevery team's main host hears its robot ({len(results)} teams)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
