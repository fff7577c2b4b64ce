"""`roslab esp32-firmware [ROSTER] [--limit NAME]`: how to flash each ESP32 team's board.

firmware/esp32_microros takes the team's ROS domain, its node name, and (UDP) the agent's
address and port at build time, from environment variables its platformio.ini turns into build
flags (it refuses to compile without them). This command prints, for each ESP32 team `--limit`
selects, the exact `pio` command line with those values, read from the roster as the agent's
host gets them: the domain is the agent host's ROS_DOMAIN_ID, the agent's address its roster
address, the port `esp32_udp_port`, the firmware's micro-ROS distro the host's ROS distro.

The sandbox's emulated board (roslab/sandbox/esp32_board.py) takes the same values from
`board_values`, so the two cannot drift; tests/unit/test_esp32_board.py holds both to the
firmware's source. The WiFi name and password are never printed: the teacher exports them.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from roslab.quoting import shell_word

PROFILE = "esp32_microros"
# The environment variables platformio.ini reads (${sysenv.NAME}): one place for their names.
DOMAIN_ENV = "ROSLAB_ROS_DOMAIN_ID"
NODE_ENV = "ROSLAB_NODE_NAME"
AGENT_IP_ENV = "ROSLAB_AGENT_IP"
AGENT_PORT_ENV = "ROSLAB_AGENT_PORT"
WIFI_ENVS = ("ROSLAB_WIFI_SSID", "ROSLAB_WIFI_PASSWORD")


def node_name(team: str) -> str:
    """The board's ROS node name, which says whose board it is: the profile's verify_publisher
    (`esp32_board_${team}`, which `roslab verify` expects), the team's name as a ROS name."""
    from roslab.profiles.library import builtin_profiles
    from roslab.roster.reader import ros_name

    return builtin_profiles()[PROFILE].verify_publisher.replace("${team}", ros_name(team))


@dataclass(frozen=True)
class BoardValues:
    """What one team's board is flashed with (and what the sandbox's emulated board runs with)."""

    team: str
    agent_host: str  # the roster host the board is attached to (it runs the agent)
    domain_id: int
    node_name: str
    transport: str  # serial or udp
    agent_address: str  # the agent host's roster address (the board's target on udp)
    agent_port: int
    distro: str

    def environment(self) -> dict[str, str]:
        """The build's environment variables (without the WiFi secrets)."""
        values = {DOMAIN_ENV: str(self.domain_id), NODE_ENV: self.node_name}
        if self.transport == "udp":
            values.update({AGENT_IP_ENV: self.agent_address, AGENT_PORT_ENV: str(self.agent_port)})
        return values

    def pio_command(self) -> str:
        """The command that builds and flashes the board (firmware/esp32_microros)."""
        assignments = " ".join(f"{name}={shell_word(value)}" for name, value in self.environment().items())
        return f"{assignments} pio run -e {self.transport}_{self.distro} -t upload"


def profile_settings(host) -> dict[str, str] | None:
    """The host's esp32_microros settings (a roster Host's resolved profile's), or None (another
    profile, or none)."""
    profile = host.settings.roslab_profile
    return profile.settings if profile is not None and profile.name == PROFILE else None


def board_values(classroom, team: str) -> BoardValues | None:
    """The values team `team`'s board is flashed with, from the roster (None: no ESP32 team)."""
    for host in classroom.hosts:
        settings = profile_settings(host)
        if host.team != team or settings is None or host.role != settings.get("esp32_attached_to", "robot"):
            continue
        return BoardValues(team=team, agent_host=host.name, domain_id=int(host.ros_domain_id or 0),
                           node_name=node_name(team), transport=settings.get("esp32_transport", "serial"),
                           agent_address=host.address, agent_port=int(settings.get("esp32_udp_port", 8888)),
                           distro=host.distro)
    return None


def run(args: argparse.Namespace) -> int:
    """Print each selected ESP32 team's flash command; 1 when the selection holds none (or the
    roster has errors), 2 when a --limit pattern selects no host."""
    from roslab.reach import RosterProblem, limited_hosts, load_classroom

    try:
        classroom = load_classroom(args.roster, "esp32-firmware")
    except RosterProblem as error:
        print(error, file=sys.stderr)
        return 1
    hosts, problem = limited_hosts(classroom, args.limit, "roslab esp32-firmware")
    if problem:  # a pattern that selects no host: bad usage, as for every command
        print(problem, file=sys.stderr)
        return 2
    teams = list(dict.fromkeys(host.team for host in hosts if profile_settings(host) is not None))
    boards = [values for values in (board_values(classroom, team) for team in teams) if values]
    if not boards:
        print(f"roslab esp32-firmware: no {PROFILE} team among the selected hosts", file=sys.stderr)
        return 1
    print("In firmware/esp32_microros, with the board on USB:")
    for values in boards:
        print(f"\n{values.team}: node {values.node_name}, domain {values.domain_id}, agent on "
              f"{values.agent_host} ({values.transport}"
              + (f" {values.agent_address}:{values.agent_port})" if values.transport == "udp" else ")"))
        if values.transport == "udp":
            print(f"  export {' '.join(WIFI_ENVS)} first (the classroom WiFi's; never written to a file)")
        print(f"  {values.pio_command()}")
    return 0


def register(commands) -> None:
    """Add `roslab esp32-firmware`."""
    from roslab.reach import add_roster_argument

    parser = commands.add_parser(
        "esp32-firmware",
        help="print the command that flashes each ESP32 team's board with its domain and node name",
        description="From the roster alone (no host is reached): for each esp32_microros team --limit "
        "selects, the PlatformIO command that builds and flashes firmware/esp32_microros with the "
        "team's ROS domain, its board's node name and, over UDP, the agent's address and port.",
    )
    add_roster_argument(parser)
    parser.set_defaults(run=run)
