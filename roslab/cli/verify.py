"""Verify each team's main host hears its robot: a table per team, non-zero exit unless all do.

    roslab verify [ROSTER] [--limit team1 ...]      (or: python -m roslab.cli.verify ...)

Read-only and bounded. On every host it asks systemd for the state of the services the
host runs by its roster and robot profile (`roslab.cli.host_services`: roslab-nodes.service
where the profile has a launch there, the team's discovery server or Zenoh router, the
profile's own services), one unit at a time. On each main host whose profile names a
topic, as the login user and with the team's ROS environment (the same as the service's,
`roslab.ros.environment`), it lists the topics and waits up to `nodes_verify_timeout` seconds for
one message on `nodes_verify_topic`, with `--no-daemon` so no ros2 daemon is left behind
(and one the check started anyway is stopped). Every ros2 call runs under `timeout
--kill-after`, and the whole check under one more bound: a node that ignores SIGTERM cannot
hang the check.

A team passes only when every one of those services is active (running) (a stopped discovery
server or Zenoh router is named as the cause), no node of a profile service that runs `ros2
launch` died in the last minute (with `respawn` the launch restarts a crashing node while
systemd sees it running: roslab.cli.launch_journal), and the message itself is a robot's greeting
(`Hello from <robot> #<n>`, the demo talker's `chatter_text`) naming one of the team's
robots: a greeting from another team's robot (domain IDs crossed) or any other text is not a
pass. A host without a ROS 2 runtime (no `ros2` command, as in the sandbox's stand-in ROS) is
reported as such. A team whose main's profile names no topic (sim: no robot; a rover not yet
calibrated) is NOT CHECKED, never a PASS: its services are still judged (a stopped one is a
FAIL), and the line says why there was nothing to hear (a profile service not started, and the
setting that starts it).

Exit code: 0 when every team passed (its main heard its robot), 1 when a team failed, 2 for a
bad `--limit`, 3 when none failed but some were not checked.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from dataclasses import dataclass, field
from typing import Any

from pyinfra.api import FactBase, State
from pyinfra.api.connect import disconnect_all
from pyinfra.context import ctx_host
from pyinfra.facts.server import LinuxDistribution

from roslab.ros.distro import default_distro
# runs_a_launch: verify's own name for it before host_services held it.
from roslab.cli.host_services import (host_services, profile_name, runs_a_launch, runs_nodes,  # noqa: F401
                                      services_not_started)
from roslab.cli import launch_journal
from roslab.reporting import waiting
from roslab.ops.users import as_user
from roslab.quoting import shell_home_path, shell_word
from roslab.host_settings import HostSettings, host_settings
from roslab.ros.environment import host_environment
from roslab.ros.workspace import NODES_SERVICE, NodesUnitState

# The demo talker's message: nodes/roslab_demo/roslab_demo/logic.py, CHATTER_FORMAT
# 'Hello from {robot_name} #{count}' (nodes/README.md documents it). Parsed here the same
# way as logic.robot_name_from_chatter, without importing the nodes (a unit test checks
# this against chatter_text's own output).
CHATTER_PATTERN = re.compile(r"Hello from (?P<robot_name>.+) #(?P<count>[0-9]+)", re.DOTALL)
# The message type the talker publishes on the verify topic.
CHATTER_TYPE = "std_msgs/msg/String"

# What service_state says of a nodes service that runs; any other state fails the team.
SERVICE_RUNNING = "active (running)"

# Bounds, in seconds. Each ros2 call gets SIGTERM at its bound and SIGKILL KILL_AFTER later.
KILL_AFTER = 5
LIST_TIMEOUT = 15  # `ros2 topic list`
LIST_SPIN_TIME = 3  # discovery time `ros2 topic list --no-daemon` waits
DAEMON_TIMEOUT = 15  # `ros2 daemon status|stop`
# How long the publishers' node names are read again while one is still unnamed: a
# participant's node name comes in its ros_discovery_info, which can arrive seconds after its
# topic; until then ROS names it UNNAMED_PUBLISHER.
PUBLISHERS_WAIT = 20
UNNAMED_PUBLISHER = "_CREATED_BY_BARE_DDS_APP_"
MESSAGE_LIMIT = 4096  # bytes of the message kept


def robot_name_from_chatter(text: str) -> str | None:
    """The robot name in a whole chatter message, or None if it is not a greeting."""
    match = CHATTER_PATTERN.fullmatch(text)
    return match["robot_name"] if match else None


def check_bound(timeout: int, kill_after: int = KILL_AFTER) -> int:
    """Seconds after which the whole check is killed: every step's bound, plus slack."""
    steps = [LIST_TIMEOUT, int(timeout), PUBLISHERS_WAIT + LIST_TIMEOUT] + [DAEMON_TIMEOUT] * 3
    return sum(steps) + kill_after * (len(steps) + 1) + 10


class LaunchDeaths(FactBase):
    """The deaths (and error lines) in the last minute of a service that runs `ros2 launch`
    (roslab.cli.launch_journal): with `respawn`, its nodes die and start again while systemd
    sees the launch running. Returns the journal lines (process_lines)."""

    def command(self, unit: str) -> str:
        return launch_journal.command(shlex.quote(unit))

    def process(self, output):
        return list(output)


class NodesHeard(FactBase):
    """
    What a main host hears on its ROS domain, as its login user.

    ``{"ros": bool, "topics": [...], "message": str | None, "robot": str | None,
    "echo_status": int | None, "daemon_stopped": bool, "finished": bool}``: ``ros`` is
    False when there is no ``ros2`` command after sourcing the distro; ``message`` is the
    first message on ``topic`` within ``timeout`` seconds and ``robot`` the robot name in
    it; ``finished`` is False when the whole check hit its bound.
    """

    @staticmethod
    def default():
        return parse_check_output([])

    def command(self, distro: str, environment: dict, workspace_dir: str, topic: str,
                timeout: int, kill_after: int = KILL_AFTER, message_type: str = CHATTER_TYPE,
                publisher: str = "") -> str:
        script = check_script(distro, environment, workspace_dir, topic, timeout, kill_after, message_type,
                              publisher)
        bound = check_bound(timeout, kill_after)
        # The check always "succeeds" as a command; what happened is in its sections.
        return (f"timeout --kill-after={int(kill_after)} {bound} bash -c {shlex.quote(script)}; "
                "echo \"## exit $?\"")

    def process(self, output):
        return parse_check_output(output)


def check_script(distro: str, environment: dict, workspace_dir: str, topic: str, timeout: int,
                 kill_after: int = KILL_AFTER, message_type: str = CHATTER_TYPE, publisher: str = "") -> str:
    """The bash script the fact runs (as the login user): it reports in `## ` sections.

    A greeting (CHATTER_TYPE) is echoed as its text (`--field data`); any other message type
    as ros2 prints it (YAML), to show that one came. With a `publisher` to check (the profile's
    verify_publisher), the node names of the topic's publishers follow (`ros2 topic info -v`).
    """
    timeout, kill_after = int(timeout), int(kill_after)

    def bounded(seconds: int) -> str:
        return f"timeout --kill-after={kill_after} {int(seconds)}"

    ros_setup = shell_word(f"/opt/ros/{distro}/setup.bash")
    workspace_setup = shell_home_path(workspace_dir.rstrip("/") + "/install/setup.bash")
    exports = [f"export {name}={shell_word(value)}" for name, value in sorted(environment.items())]
    daemon_status = f"{bounded(DAEMON_TIMEOUT)} ros2 daemon status 2>/dev/null | grep -q 'is running'"
    return "\n".join(
        [
            f"[ -f {ros_setup} ] && source {ros_setup}",
            f"[ -f {workspace_setup} ] && source {workspace_setup}",
            *exports,
            # No ros2, or one that cannot even list its own commands: no ROS runtime.
            f"if ! command -v ros2 >/dev/null 2>&1 || ! {bounded(LIST_TIMEOUT)} ros2 --help"
            " >/dev/null 2>&1; then echo '## ros missing'; exit 0; fi",
            f"if {daemon_status}; then daemon_before=1; else daemon_before=0; fi",
            "echo '## topics'",
            f"{bounded(LIST_TIMEOUT)} ros2 topic list --no-daemon --spin-time {LIST_SPIN_TIME} 2>/dev/null",
            "echo '## message'",
            f"{bounded(timeout)} ros2 topic echo --no-daemon --once"
            f"{' --field data' if message_type == CHATTER_TYPE else ''} --full-length"
            f" {shell_word(topic)} {shell_word(message_type)} 2>/dev/null | head -c {MESSAGE_LIMIT}",
            "echo_status=${PIPESTATUS[0]}",
            "echo \"## echo status $echo_status\"",
            *([
                "echo '## publishers'",
                # Read again, up to PUBLISHERS_WAIT s, while one is still unnamed, or none is
                # seen although a message came.
                f"publishers_until=$((SECONDS + {PUBLISHERS_WAIT}))",
                "while :; do",
                f"  publishers=$({bounded(LIST_TIMEOUT)} ros2 topic info --no-daemon --spin-time {LIST_SPIN_TIME}"
                f" --verbose {shell_word(topic)} 2>/dev/null"
                " | awk '/^Subscription count/ {exit} /^Node name: / {print $3}')",
                f"  if [ -z \"$publishers\" ] && [ \"$echo_status\" != 0 ]; then break; fi",
                f"  if [ -n \"$publishers\" ] && ! grep -qx {shell_word(UNNAMED_PUBLISHER)} <<<\"$publishers\"; then"
                " break; fi",
                "  if [ $SECONDS -ge $publishers_until ]; then break; fi",
                "  sleep 1",
                "done",
                "[ -n \"$publishers\" ] && printf '%s\\n' \"$publishers\"",
            ] if publisher else []),
            # --no-daemon starts none; should one have been started anyway, stop it.
            f"if [ $daemon_before = 0 ] && {daemon_status}; then",
            f"  {bounded(DAEMON_TIMEOUT)} ros2 daemon stop >/dev/null 2>&1",
            "  echo '## daemon stopped'",
            "fi",
            "exit 0",
        ]
    )


def parse_check_output(lines) -> dict:
    result: dict[str, Any] = {"ros": True, "topics": [], "message": None, "robot": None, "echo_status": None,
              "daemon_stopped": False, "finished": False, "publishers": []}
    section = None
    message: list[str] = []
    seen = False
    for line in lines:
        if line.startswith("## "):
            seen = True
            section = line[3:].strip()
            if section == "ros missing":
                result["ros"] = False
            elif section == "daemon stopped":
                result["daemon_stopped"] = True
            elif section.startswith("echo status "):
                status = section.removeprefix("echo status ").strip()
                result["echo_status"] = int(status) if status.isdigit() else None
            elif section.startswith("exit "):
                result["finished"] = section == "exit 0"
            continue
        if section == "topics" and line.strip():
            result["topics"].append(line.strip())
        elif section == "publishers" and line.strip():
            result["publishers"].append(line.strip())
        elif section == "message":
            message.append(line)
    if not seen:
        result["ros"] = None  # nothing came back: the check could not run
    # `--field data` prints the text, then a `---` line.
    while message and not message[-1].strip():
        message.pop()
    if message and message[-1].strip() == "---":
        message.pop()
    if message:
        # Lines ros2 printed before the message (QoS notes) are not part of it.
        for start in range(len(message)):
            text = "\n".join(message[start:])
            robot = robot_name_from_chatter(text)
            if robot is not None:
                result["message"], result["robot"] = text, robot
                break
        else:
            result["message"] = "\n".join(message).strip() or None
    return result


@dataclass
class TeamResult:
    team: str
    main: str | None = None
    robots: list[str] = field(default_factory=list)
    topic: str = "/chatter"
    timeout: int = 20
    # CHATTER_TYPE: the message must be a robot's greeting; any other type: one message passes
    # (a LaserScan does not say which robot sent it).
    message_type: str = CHATTER_TYPE
    services: dict = field(default_factory=dict)  # host name -> "active (running)", "failed (...)", ...
    heard: dict | None = None  # NodesHeard of the main host
    error: str | None = None
    # Hosts whose roster gives them no launch (a TurtleBot3's main: its profile runs nothing there),
    # so no roslab-nodes service is theirs to run.
    without_service: set = field(default_factory=set)
    # what publishes the topic (the profile's verify_source), named when nothing was heard
    source: str = ""
    # The other services the team's hosts run by their roster (roslab.cli.host_services: the discovery
    # server or Zenoh router, the profile's own): (host, HostService, state).
    other_services: list = field(default_factory=list)
    # False when the main's robot profile names no topic to hear (sim: no robot; an ESP32 not
    # yet present): the team is judged by the services it runs.
    listens: bool = True
    profile: str = "demo"  # the main's robot profile, for the verdict
    # (host, service, why) of the profile's services that are not started by the roster's settings
    # (the rover's osr_startup until osr_calibrated: true): why a team has nothing to hear.
    not_started: list = field(default_factory=list)
    # (host, unit, node, deaths, why) of nodes of the team's launch services that died in the
    # last minute (a respawning node): a running unit is not a working robot.
    node_deaths: list = field(default_factory=list)
    # the node that must publish the topic (the profile's verify_publisher: the ESP32 board's
    # flashed name), "" for any
    publisher: str = ""

    def services_down(self) -> list[tuple[str, str]]:
        """(host, state) of the team's hosts whose nodes service is not active (running).

        A message heard beside a stopped, failed or restarting service is not a pass: right
        after a reboot the main may hear a robot whose service is still starting, or has
        just failed; the classroom is verified only once every service really runs.
        """
        hosts = ([self.main] if self.main else []) + list(self.robots)
        return [(host, self.services.get(host, "?")) for host in hosts
                if self.services.get(host) != SERVICE_RUNNING and host not in self.without_service]

    def stopped_services(self) -> list[tuple]:
        """(host, HostService, state) of the team's other services that do not run: a stopped
        discovery server or Zenoh router is why a main hears nothing, so it comes first."""
        return [(host, service, state) for host, service, state in self.other_services
                if state != SERVICE_RUNNING]

    @property
    def greeting(self) -> bool:
        """Whether the topic carries roslab's greeting, which names the robot that sent it."""
        return self.message_type == CHATTER_TYPE

    def heard_robots(self) -> list[str]:
        """The team's robots the main heard: the one its greeting names, or, on a topic whose
        messages name no sender, every robot once a message came."""
        heard = self.heard or {}
        if not heard.get("ros"):
            return []
        if self.greeting:
            return [heard["robot"]] if heard.get("robot") in self.robots else []
        if self.publisher and self.publisher not in heard.get("publishers", []):
            return []  # a message, but not from the team's own board
        return list(self.robots) if heard.get("message") else []

    @property
    def passed(self) -> bool:
        """Heard: the main host heard the team's robot, beside services that all run."""
        if self.error or self.services_down() or self.stopped_services() or self.node_deaths or not self.listens:
            return False
        return bool(self.heard_robots())

    @property
    def unchecked(self) -> bool:
        """Nothing to hear (no topic named for the main), and nothing found wrong: not a PASS,
        since nothing was heard, and not a FAIL, since nothing failed."""
        return (not self.listens and bool(self.main) and not self.error and not self.services_down()
                and not self.stopped_services() and not self.node_deaths)

    @property
    def outcome(self) -> str:
        """PASS, NOT CHECKED or FAIL: the table's word for the team."""
        return "PASS" if self.passed else "NOT CHECKED" if self.unchecked else "FAIL"

    def publisher_verdict(self, publishers: list[str]) -> str:
        """A message came: from the team's own board (`publisher`), another's, or one whose
        node name had not arrived (ROS's UNNAMED_PUBLISHER, never called another team's)."""
        if self.publisher in publishers:
            return f"heard a {self.message_type} on {self.topic} from {self.publisher}"
        named = [name for name in publishers if name != UNNAMED_PUBLISHER]
        if not named and publishers:
            return (f"heard a {self.message_type} on {self.topic}, but its publisher's node name was still "
                    f"unknown after {PUBLISHERS_WAIT} s (ROS shows {UNNAMED_PUBLISHER}): not shown to be "
                    f"{self.publisher}; run verify again")
        return (f"heard a {self.message_type} on {self.topic}, but not from {self.publisher} (its publishers: "
                f"{', '.join(named) or 'none seen'}): another team's board, or one "
                "flashed for another team (roslab esp32-firmware prints this team's values)")

    def verdict(self) -> str:
        if self.error:
            return self.error
        if not self.main:
            return "no main host in the team"
        stopped = self.stopped_services()
        if stopped:
            return "; ".join(stopped_service_line(host, service, state) for host, service, state in stopped)
        if self.node_deaths:
            return "; ".join(f"{unit} on {host} runs, but its node {node} died "
                             f"{'once' if count == 1 else f'{count} times'} in the last minute: {why}"
                             for host, unit, node, count, why in self.node_deaths)
        if not self.listens:
            down = self.services_down()
            if down:
                return "; ".join(f"{NODES_SERVICE} on {host} is {state}" for host, state in down)
            running = sorted({service.unit for _, service, _ in self.other_services}
                             | {NODES_SERVICE for host in self.services if host not in self.without_service})
            runs = f"; running: {', '.join(running)}" if running else "; roslab runs no service there"
            robots = "no robot" if not self.robots else f"no topic for {', '.join(self.robots)}"
            why = "".join(f"; {service} on {host} not started: {because}"
                          for host, service, because in self.not_started)
            return f"not checked, nothing to hear: robot profile {self.profile} names {robots} on {self.main}{why}{runs}"
        heard = self.heard or parse_check_output([])
        if heard["ros"] is None:
            return f"the check on {self.main} returned nothing"
        if not heard["ros"]:
            return f"no ROS runtime on {self.main}: not verified"
        if not self.robots:
            return "no robot in the team: nothing to hear"
        down = self.services_down()
        if down:
            return "; ".join(f"{NODES_SERVICE} on {host} is {state}" for host, state in down)
        if not self.greeting and heard["message"] and self.publisher:
            return self.publisher_verdict(heard.get("publishers") or [])
        if not self.greeting and heard["message"]:
            return f"heard a {self.message_type} on {self.topic}"
        if heard["robot"] is not None:
            if heard["robot"] in self.robots:
                return f"heard {heard['robot']}"
            return (f"heard {heard['robot']!r}, which is not a robot of team {self.team} "
                    f"({', '.join(self.robots)}): are two teams on one ROS_DOMAIN_ID?")
        if heard["message"]:
            return f"{self.topic} carries a message that is not a robot's greeting"
        if not heard["finished"]:
            return f"the check on {self.main} did not finish in time"
        because = f": {self.source} publishes nothing" if self.source else ""
        if self.publisher:  # the topic is listed by the team's own subscriber (the servo node) anyway
            return f"no message from {self.publisher} on {self.topic} within {self.timeout} s{because}"
        if self.topic in heard["topics"]:
            return f"{self.topic} listed but no message within {self.timeout} s{because}"
        return f"{self.main} does not see {self.topic}{because}"


def stopped_service_line(host: str, service, state: str) -> str:
    """One host's service that does not run, and what that means when it is the team's discovery."""
    line = f"{service.unit} on {host} is {state}"
    if service.kind == "discovery":
        line += f" ({service.what}: without it the team's hosts do not find each other)"
    return line


def _service_cell(result: TeamResult, name: str | None) -> str:
    """The host's nodes service as systemd has it, or, where its roster and profile give it
    none (a TurtleBot3's or a sim main), that it runs none: "not installed" there is no fault."""
    if not name:
        return "-"
    state = result.services.get(name, "?")
    if name in result.without_service and state != "?":
        return f"none ({result.profile} main)" if name == result.main else "none"
    return state


# The result's word in a terminal: green heard, yellow not checked, red failed.
OUTCOME_COLOURS = {"PASS": "\033[32m", "NOT CHECKED": "\033[33m", "FAIL": "\033[31m"}


def format_table(results: list[TeamResult], colour: bool = False) -> str:
    header = ("team", "main", "robot", "main service", "robot service", "topics seen", "message heard", "result")
    rows = [header]
    for result in sorted(results, key=lambda r: r.team):
        heard = result.heard or parse_check_output([])
        topics = ", ".join(t for t in heard["topics"] if not t.startswith(("/rosout", "/parameter_events")))
        message = " ".join((heard["message"] or "-").split())
        if len(message) > 40:
            message = message[:37] + "..."
        rows.append(
            (
                result.team,
                result.main or "-",
                ", ".join(result.robots) or "-",
                _service_cell(result, result.main),
                ", ".join(_service_cell(result, robot) for robot in result.robots) or "-",
                topics or "-",
                message,
                f"{result.outcome} {result.verdict()}",
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows]
    if colour:  # the last column starts with the outcome's word
        start = sum(widths[:-1]) + 2 * (len(widths) - 1)
        for index, result in enumerate(sorted(results, key=lambda r: r.team), start=1):
            word = result.outcome
            lines[index] = f"{lines[index][:start]}{OUTCOME_COLOURS[word]}{word}\033[0m{lines[index][start + len(word):]}"
    lines.insert(1, "  ".join("-" * width for width in widths))
    return "\n".join(lines)


# Running it against an inventory
# -------------------------------


def service_state(unit_state: dict) -> str:
    """A unit's state for the table: 'active (running)', 'failed (start-limit-hit)', ..."""
    if not unit_state or unit_state.get("LoadState") == "not-found":
        return "not installed"
    active, sub = unit_state.get("ActiveState", "?"), unit_state.get("SubState", "")
    if active == "failed" and unit_state.get("Result") not in (None, "", "success"):
        return f"failed ({unit_state['Result']})"
    return f"{active} ({sub})" if sub and sub != active else active


def host_distro(host) -> str:
    """The host's ROS 2 distro: ros_distro, else its Ubuntu release's default."""
    if host_settings(host).ros_distro:
        return str(host_settings(host).ros_distro)
    release = host.get_fact(LinuxDistribution)["release_meta"]
    return default_distro(release.get("UBUNTU_CODENAME") or release.get("VERSION_CODENAME"))


def hear(host, distro: str | None = None, timeout: int | None = None) -> dict:
    """NodesHeard on a main host: the topics it lists and the first message on
    `nodes_verify_topic`, as its login user with the team's ROS environment, bounded.

    `distro`: the host's ROS 2 distro if the caller knows it (else `host_distro` reads
    the host's release); `timeout`: seconds to wait for a message (else
    `nodes_verify_timeout`). As the SSH user itself, the check runs without sudo.
    """
    typed = host_settings(host)
    timeout = int(typed.nodes_verify_timeout if timeout is None else timeout)
    distro = distro or host_distro(host)
    login_user = typed.login_user or typed.ssh_user
    user = {"_sudo": False} if login_user is None or login_user == typed.ssh_user else as_user(login_user)
    return host.get_fact(
        NodesHeard,
        distro=distro,
        environment=host_environment(typed, distro, shell=True),
        workspace_dir=typed.workspace_dir,
        topic=typed.nodes_verify_topic,
        timeout=timeout,
        message_type=typed.nodes_verify_type or CHATTER_TYPE,
        publisher=typed.roslab_verify_publisher or "",
        **user,
        # The connection's own bound, beyond the check's.
        _timeout=check_bound(timeout) + 30,
    )


def _check_host(state: State, host) -> tuple[str, dict, dict | None, str | None, list]:
    """(nodes service state, {unit: state} of its other services, NodesHeard on main hosts,
    error, deaths of its launch services' nodes in the last minute) for one host."""
    with ctx_host.use(host):
        try:
            service = service_state(host.get_fact(NodesUnitState, service=NODES_SERVICE))
            typed = host_settings(host)
            services = [item for item in host_services(typed) if item.kind != "nodes"]
            others = {item.unit: service_state(host.get_fact(NodesUnitState, service=item.unit)) for item in services}
            deaths = [(host.name, item.unit.removesuffix(".service"), node, count, why)
                      for item in services if item.launch and others.get(item.unit) == SERVICE_RUNNING
                      for node, (count, why) in launch_journal.died_nodes(
                          host.get_fact(LaunchDeaths, unit=item.unit)).items()]
            if typed.roslab_role != "main" or not typed.nodes_verify_topic:
                return service, others, None, None, deaths  # a robot, or a main with nothing to hear (sim)
            return service, others, hear(host), None, deaths
        except Exception as error:  # one host's trouble is its team's row, not a crash
            return "?", {}, None, f"{host.name}: {one_line(error)}", []


def one_line(error) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def verify(state: State) -> list[TeamResult]:
    """Check every active host in parallel and group the results by team."""
    hosts = [host for host in state.inventory.iter_activated_hosts() if host in state.active_hosts]
    greenlets = {host: state.pool.spawn(_check_host, state, host) for host in hosts}
    # never silent: a line every few seconds names the hosts still being checked
    waiting.joined({greenlet: host.name for host, greenlet in greenlets.items()}, "roslab verify: still checking")
    teams: dict[str, TeamResult] = {}

    def team_of(typed: HostSettings, name: str) -> TeamResult:
        name = typed.roslab_team or name
        if name not in teams:
            teams[name] = TeamResult(
                name, topic=typed.nodes_verify_topic or "/chatter",
                timeout=typed.nodes_verify_timeout or 0,
                message_type=typed.nodes_verify_type or CHATTER_TYPE,
            )
        return teams[name]

    for host, greenlet in greenlets.items():
        service, others, heard, error, deaths = greenlet.get()
        typed = host_settings(host)
        team = team_of(typed, host.name)
        team.node_deaths += deaths
        team.services[host.name] = service
        if not runs_nodes(typed):
            team.without_service.add(host.name)
        team.other_services += [(host.name, item, others.get(item.unit, "?"))
                                for item in host_services(typed) if item.kind != "nodes" and not error]
        if typed.roslab_role == "main":
            team.main, team.heard = host.name, heard
            _main_says(team, typed)
        else:
            team.robots.append(host.name)
        team.not_started += [(host.name, name, why) for name, why in services_not_started(typed)]
        team.error = team.error or error
    for host in state.inventory:  # unreachable ones too: never activated, or failed since
        if state.is_host_in_limit(host) and host not in state.active_hosts:
            team = team_of(host_settings(host), host.name)
            if host_settings(host).roslab_role == "main":
                team.main = host.name
            else:
                team.robots.append(host.name)
            team.services[host.name] = "unreachable"
            team.error = team.error or f"{host.name} is unreachable"
    for team in teams.values():
        team.robots.sort()
    return list(teams.values())


def _main_says(team: TeamResult, typed: HostSettings) -> None:
    """What a team's main host's settings say of the check: its topic, bound, profile, publisher."""
    team.listens = bool(typed.nodes_verify_topic)
    team.profile = profile_name(typed)
    team.topic = typed.nodes_verify_topic or team.topic
    team.timeout = typed.nodes_verify_timeout or team.timeout
    team.message_type = typed.nodes_verify_type or team.message_type
    team.source = typed.roslab_verify_source or ""
    team.publisher = typed.roslab_verify_publisher or ""


def listening_line(state: State) -> str:
    """What the check is about to do, before its silent wait: which main host listens for which
    topic, and for how long at most (all at once)."""
    mains = [(host.name, host_settings(host)) for host in state.inventory.iter_activated_hosts()
             if host in state.active_hosts and host_settings(host).roslab_role == "main"]
    listening = [f"{name} for {typed.nodes_verify_topic}" for name, typed in mains if typed.nodes_verify_topic]
    if not listening:
        return "roslab verify: reading the services' states (no main host has a topic to hear)"
    longest = max(int(typed.nodes_verify_timeout or 0) for _, typed in mains)
    return (f"roslab verify: listening on {', '.join(listening)} (all at once, each up to {longest} s "
            "for a message, after the ROS tools start)")


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    from roslab.reach import add_roster_argument

    parser = parser or argparse.ArgumentParser(prog="roslab verify", description=__doc__.splitlines()[0])
    add_roster_argument(parser)
    return parser


def run(args: argparse.Namespace) -> int:
    """`roslab verify [ROSTER] [--limit NAME ...]`: the roster's hosts, reached as deploy.py
    reaches them (roslab.reach)."""
    from roslab.reach import RosterProblem, connected_state, limit_problem, load_classroom_groups, names_of

    try:
        classroom, groups = load_classroom_groups(args.roster, "verify")
    except RosterProblem as error:
        print(error, file=sys.stderr)
        return 1
    problem = limit_problem(names_of(groups), args.limit, "roslab verify")
    if problem:
        print(problem, file=sys.stderr)
        return 2
    from gevent import monkey

    # As pyinfra's CLI and `roslab status` do: without it each host's SSH blocks the others, so the
    # hosts were checked one after another and no "still checking" line could come in between.
    monkey.patch_all()
    print("roslab verify: connecting to the hosts ...", file=sys.stderr, flush=True)
    state = connected_state(groups, args.limit)
    print(listening_line(state), file=sys.stderr, flush=True)
    try:
        results = verify(state)
    finally:
        disconnect_all(state)
    print(format_table(results, colour=sys.stdout.isatty()))
    return summarize(results)


def summarize(results: list[TeamResult]) -> int:
    """The summary line after the table, and the exit code: how many teams were really
    verified (heard), which failed and which were not checked."""
    failed = sorted(r.team for r in results if r.outcome == "FAIL")
    unchecked = sorted(r.team for r in results if r.outcome == "NOT CHECKED")
    heard = len(results) - len(failed) - len(unchecked)
    if not failed and not unchecked:
        print(f"\nevery team's main host hears its robot ({len(results)} teams)")
        return 0
    print(f"\n{heard} of {len(results)} teams verified (their main host heard their robot)")
    if unchecked:
        print(f"not checked (nothing to hear, see the table): {', '.join(unchecked)}", file=sys.stderr)
    if failed:
        print(f"not verified: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 3


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
