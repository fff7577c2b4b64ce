"""How a classroom's ROS hosts find each other: one middleware for the class, a discovery mode per team.

One source for what each host gets, per mode, middleware and distro:

- the variables of its nodes' unit, its login shell and `roslab verify` (`HostDiscovery.variables`),
  plus the ones only the shell and verify's command-line tools need (`shell_variables`: the
  discovery server's super client, which sees the whole graph);
- the files those variables point to (`files`: the middleware's own XML, for Humble, which has
  no ROS_STATIC_PEERS, and for the super client there);
- the service it runs for its team (`service`: the Fast DDS discovery server or the Zenoh router
  on the team's main).

Modes (`ros_discovery_mode`, a classroom setting a team may override):

- `multicast`: DDS's own discovery (today's behaviour; ros_automatic_discovery_range and
  ros_static_peers refine it on Jazzy and later).
- `static`: no multicast; each host's peers are its team's hosts. Jazzy and later:
  ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST with ROS_STATIC_PEERS; Humble: the middleware's own peer
  list (Fast DDS initialPeersList with multicast off, Cyclone DDS Peers with AllowMulticast false).
- `discovery_server`: a Fast DDS discovery server on the team's main (`roslab-discovery-server`),
  ROS_DISCOVERY_SERVER on every host of the team, the super client for the command-line tools.
- `localhost`: nothing leaves the host (a simulation-only host).

With Zenoh (`rmw_zenoh_cpp`) discovery goes through a router: the team's main runs one
(`roslab-zenoh-router`, multicast scouting off so teams' routers never join) and the team's other
hosts connect to it; `multicast` and `static` mean the same there, a `localhost` host runs its own
router on the loopback, and a discovery server is refused.

Everything here is plain data from a host's typed settings (`DiscoverySettings`: what
roslab.host_settings.HostSettings is, built from pyinfra's host.data or a roster host's dict);
the values were checked by the settings schema before, and each destination escapes them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Protocol

from roslab.ros import distro as distros

MODES = ("multicast", "static", "discovery_server", "localhost")
MIDDLEWARES = ("rmw_fastrtps_cpp", "rmw_cyclonedds_cpp", "rmw_zenoh_cpp")
FASTDDS, CYCLONEDDS, ZENOH = MIDDLEWARES

# Defaults, the same as the settings schema's (roslab/settings.py reads them from here).
DEFAULT_MODE = "multicast"
DEFAULT_MIDDLEWARE = FASTDDS
DEFAULT_SERVER_PORT = 11811  # Fast DDS's own default for a discovery server
DEFAULT_ROUTER_PORT = 7447  # rmw_zenoh's router default

# The IDs a team without one is given: 0 is every unset ROS host's, 215-232 are Linux-only.
AUTO_DOMAIN_IDS = tuple(range(1, 102))

CONFIG_DIR = "/etc/roslab/discovery"
FASTDDS_PEERS_XML = f"{CONFIG_DIR}/fastdds-static-peers.xml"
FASTDDS_SUPER_CLIENT_XML = f"{CONFIG_DIR}/fastdds-super-client.xml"
CYCLONEDDS_PEERS_XML = f"{CONFIG_DIR}/cyclonedds-static-peers.xml"
DISCOVERY_SERVER_SERVICE = "roslab-discovery-server"
ZENOH_ROUTER_SERVICE = "roslab-zenoh-router"
SERVICES = (DISCOVERY_SERVER_SERVICE, ZENOH_ROUTER_SERVICE)

# Fast DDS's well-known prefix of discovery server 0 (its CLI's `-i 0`, ROS_DISCOVERY_SERVER's first).
SERVER_0_PREFIX = "44.53.00.5f.45.50.52.4f.53.49.4d.41"
# Cyclone DDS without multicast probes this many participant indexes per peer (its default is 9:
# a main with a launch, the ros2 daemon and a few terminals has more participants than that).
CYCLONE_MAX_PARTICIPANT_INDEX = 32

HEADER = "managed by roslab (roslab/ros/discovery.py): edits here are overwritten; set ros_discovery_mode in the roster"


@dataclass(frozen=True)
class Service:
    """A service the host runs for its team: its unit name, what it is, the command (after
    sourcing the distro's setup.bash) and the variables it runs with."""

    name: str
    description: str
    command: tuple[str, ...]
    environment: dict[str, str] = field(default_factory=dict)


@dataclass
class HostDiscovery:
    mode: str
    middleware: str
    variables: dict[str, str]  # the unit, the shell and verify
    shell_variables: dict[str, str]  # added for the shell and verify's ros2 tools only
    files: dict[str, str]  # path -> content
    service: Service | None


def middleware_package(middleware: str, distro: str) -> str | None:
    """The Debian package a middleware needs beyond ros-<distro>-ros-base (Fast DDS comes with it)."""
    if middleware == FASTDDS:
        return None
    return f"ros-{distro}-{middleware.replace('_', '-')}"


def middleware_ros_package(middleware: str) -> str | None:
    """The ROS package name of `middleware_package`, for the rosdistro check."""
    return None if middleware == FASTDDS else middleware


class DiscoverySettings(Protocol):
    """What discovery reads of a host's settings: roslab.host_settings.HostSettings has these fields
    (named here, not imported: roslab.profiles, which HostSettings holds, builds on roslab.ros)."""

    @property
    def ros_domain_id(self) -> int | None: ...
    @property
    def ros_middleware(self) -> str: ...
    @property
    def ros_discovery_mode(self) -> str: ...
    @property
    def ros_automatic_discovery_range(self) -> str: ...
    @property
    def ros_static_peers(self) -> list[str]: ...
    @property
    def ros_discovery_server_port(self) -> int: ...
    @property
    def ros_zenoh_router_port(self) -> int: ...
    @property
    def roslab_team_hosts(self) -> list[dict[str, str | None]] | None: ...
    @property
    def roslab_hostname(self) -> str | None: ...
    @property
    def roslab_role(self) -> str | None: ...


def team_main(data: DiscoverySettings) -> dict | None:
    """The host's team's main host ({"name", "address", "role"}), or None."""
    for member in data.roslab_team_hosts or ():
        if member.get("role") == "main":
            return member
    return None


def reach(member: dict) -> str:
    """Where another host reaches a team member: its IP, else its name (/etc/hosts has it)."""
    return member.get("address") or member["name"]


def team_peers(data: DiscoverySettings) -> list[str]:
    """The host's team mates (not itself), as other hosts reach them, then the roster's ros_static_peers."""
    me = data.roslab_hostname
    peers = [reach(member) for member in data.roslab_team_hosts or () if member.get("name") != me]
    peers += [peer for peer in data.ros_static_peers or () if peer not in peers]
    return peers


def is_main(data: DiscoverySettings) -> bool:
    return data.roslab_role == "main"


def server_address(data: DiscoverySettings) -> str:
    """The discovery server or router this host talks to: its own loopback on the main."""
    main = team_main(data)
    if is_main(data) or main is None:
        return "127.0.0.1"
    return reach(main)


def host_discovery(data: DiscoverySettings, distro: str) -> HostDiscovery:
    """Everything `data`'s host gets for discovery on `distro` (see the module's docstring)."""
    mode, middleware = data.ros_discovery_mode, data.ros_middleware
    found = HostDiscovery(mode, middleware, {}, {}, {}, None)
    domain = data.ros_domain_id
    if domain is not None:
        found.variables["ROS_DOMAIN_ID"] = str(domain)
    found.variables["RMW_IMPLEMENTATION"] = middleware
    if middleware == ZENOH:
        _zenoh(found, data)
    elif mode == "localhost":
        _range(found, distro, "LOCALHOST", ())
    elif mode == "multicast":
        _range(found, distro, str(data.ros_automatic_discovery_range), list(data.ros_static_peers or ()))
    elif mode == "static":
        _static_peers(found, data, distro)
    elif mode == "discovery_server":  # Fast DDS only (refused otherwise before connecting)
        _discovery_server(found, data, distro)
    return found


def _range(found: HostDiscovery, distro: str, discovery_range: str, peers) -> None:
    """Jazzy and later: ROS_AUTOMATIC_DISCOVERY_RANGE (and ROS_STATIC_PEERS); Humble has only
    ROS_LOCALHOST_ONLY, for LOCALHOST."""
    if distros.record(distro).discovery_range:
        found.variables["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery_range
        if peers:
            found.variables["ROS_STATIC_PEERS"] = ";".join(peers)
    elif discovery_range == "LOCALHOST":
        found.variables["ROS_LOCALHOST_ONLY"] = "1"


def _static_peers(found: HostDiscovery, data: DiscoverySettings, distro: str) -> None:
    """Unicast to the team's hosts only: ROS_STATIC_PEERS where the distro has it, else the
    middleware's own peers file."""
    peers = team_peers(data)
    if distros.record(distro).discovery_range:
        _range(found, distro, "LOCALHOST", peers)
    elif found.middleware == CYCLONEDDS:
        found.variables["CYCLONEDDS_URI"] = f"file://{CYCLONEDDS_PEERS_XML}"
        found.files[CYCLONEDDS_PEERS_XML] = cyclonedds_peers_xml(peers)
    else:
        found.variables[profiles_variable(distro)] = FASTDDS_PEERS_XML
        found.files[FASTDDS_PEERS_XML] = fastdds_peers_xml(peers)


def _discovery_server(found: HostDiscovery, data: DiscoverySettings, distro: str) -> None:
    """Fast DDS's discovery server on the team's main; the shell's tools see the whole graph as
    super clients (ROS_SUPER_CLIENT, or Fast DDS 2.6's XML profile)."""
    port = data.ros_discovery_server_port
    found.variables["ROS_DISCOVERY_SERVER"] = f"{server_address(data)}:{port}"
    if not distros.record(distro).fastdds_super_client_variable:
        found.shell_variables[profiles_variable(distro)] = FASTDDS_SUPER_CLIENT_XML
        found.files[FASTDDS_SUPER_CLIENT_XML] = fastdds_super_client_xml(server_address(data), port)
    else:
        found.shell_variables["ROS_SUPER_CLIENT"] = "TRUE"
    if is_main(data):
        found.service = discovery_server(port)


def _zenoh(found: HostDiscovery, data: DiscoverySettings) -> None:
    """Zenoh: a router on the team's main (or on each host, for localhost); every host's session
    connects to it."""
    port = data.ros_zenoh_router_port
    if found.mode == "localhost":
        found.service = zenoh_router(port, listen="127.0.0.1")
        found.variables["ZENOH_CONFIG_OVERRIDE"] = zenoh_override(connect=f"tcp/127.0.0.1:{port}")
    elif is_main(data):
        found.service = zenoh_router(port, listen="0.0.0.0")
        found.variables["ZENOH_CONFIG_OVERRIDE"] = zenoh_override(connect=f"tcp/127.0.0.1:{port}")
    else:
        found.variables["ZENOH_CONFIG_OVERRIDE"] = zenoh_override(connect=f"tcp/{server_address(data)}:{port}")


def profiles_variable(distro: str) -> str:
    return distros.record(distro).fastdds_profiles_variable


def discovery_server(port: int) -> Service:
    """Fast DDS's discovery server 0 on every interface of the main (its own binary: the `fastdds`
    CLI would start it as a grandchild)."""
    return Service(
        DISCOVERY_SERVER_SERVICE,
        f"roslab: the team's Fast DDS discovery server (UDP {port})",
        ("fast-discovery-server", "-i", "0", "-l", "0.0.0.0", "-p", str(port)),
    )


def zenoh_router(port: int, listen: str) -> Service:
    """rmw_zenoh's router; multicast scouting off, so two teams' routers never connect."""
    return Service(
        ZENOH_ROUTER_SERVICE,
        f"roslab: the team's Zenoh router (TCP {port})",
        ("ros2", "run", "rmw_zenoh_cpp", "rmw_zenohd"),
        {"ZENOH_CONFIG_OVERRIDE": zenoh_override(listen=f"tcp/{listen}:{port}", scouting=False)},
    )


def zenoh_override(connect: str | None = None, listen: str | None = None, scouting: bool | None = None) -> str:
    """ZENOH_CONFIG_OVERRIDE's `key=value;...` (values in JSON5)."""
    parts = []
    if connect:
        parts.append(f'connect/endpoints=["{connect}"]')
    if listen:
        parts.append(f'listen/endpoints=["{listen}"]')
    if scouting is False:
        parts.append("scouting/multicast/enabled=false")
    return ";".join(parts)


def _xml_head() -> str:
    return f'<?xml version="1.0" encoding="UTF-8"?>\n<!-- {HEADER} -->\n'


def fastdds_peers_xml(peers: list[str]) -> str:
    """Fast DDS (2.x) default participant profile: no multicast, the host itself and its peers
    as initial peers (the discovery Fast DDS's docs give for networks without multicast)."""
    from xml.sax.saxutils import escape  # only here: every run imports this module
    locators = "".join(
        f"                    <locator><udpv4><address>{escape(peer)}</address></udpv4></locator>\n"
        for peer in ["127.0.0.1", *peers])
    return (
        _xml_head()
        + '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
        + '    <participant profile_name="roslab_static_peers" is_default_profile="true">\n'
        + "        <rtps>\n"
        + "            <builtin>\n"
        + "                <metatrafficUnicastLocatorList>\n"
        + "                    <locator/>\n"
        + "                </metatrafficUnicastLocatorList>\n"
        + "                <initialPeersList>\n"
        + locators
        + "                </initialPeersList>\n"
        + "            </builtin>\n"
        + "        </rtps>\n"
        + "    </participant>\n"
        + "</profiles>\n"
    )


def fastdds_super_client_xml(server: str, port: int) -> str:
    """Fast DDS (2.x) super client of discovery server 0: what lets `ros2 topic list` see the graph."""
    from xml.sax.saxutils import escape, quoteattr  # only here: every run imports this module
    return (
        _xml_head()
        + "<dds>\n"
        + '    <profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
        + '        <participant profile_name="roslab_super_client" is_default_profile="true">\n'
        + "            <rtps>\n"
        + "                <builtin>\n"
        + "                    <discovery_config>\n"
        + "                        <discoveryProtocol>SUPER_CLIENT</discoveryProtocol>\n"
        + "                        <discoveryServersList>\n"
        + f"                            <RemoteServer prefix={quoteattr(SERVER_0_PREFIX)}>\n"
        + "                                <metatrafficUnicastLocatorList>\n"
        + "                                    <locator>\n"
        + "                                        <udpv4>\n"
        + f"                                            <address>{escape(server)}</address>\n"
        + f"                                            <port>{int(port)}</port>\n"
        + "                                        </udpv4>\n"
        + "                                    </locator>\n"
        + "                                </metatrafficUnicastLocatorList>\n"
        + "                            </RemoteServer>\n"
        + "                        </discoveryServersList>\n"
        + "                    </discovery_config>\n"
        + "                </builtin>\n"
        + "            </rtps>\n"
        + "        </participant>\n"
        + "    </profiles>\n"
        + "</dds>\n"
    )


def cyclonedds_peers_xml(peers: list[str]) -> str:
    """Cyclone DDS configuration: no multicast, the host itself and its peers."""
    from xml.sax.saxutils import quoteattr  # only here: every run imports this module
    entries = "".join(f"            <Peer address={quoteattr(peer)}/>\n" for peer in ["127.0.0.1", *peers])
    return (
        _xml_head()
        + '<CycloneDDS xmlns="https://cdds.io/config">\n'
        + '    <Domain Id="any">\n'
        + "        <General>\n"
        + "            <AllowMulticast>false</AllowMulticast>\n"
        + "        </General>\n"
        + "        <Discovery>\n"
        + "            <ParticipantIndex>auto</ParticipantIndex>\n"
        + f"            <MaxAutoParticipantIndex>{CYCLONE_MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex>\n"
        + "            <Peers>\n"
        + entries
        + "            </Peers>\n"
        + "        </Discovery>\n"
        + "    </Domain>\n"
        + "</CycloneDDS>\n"
    )


# --- domain IDs -------------------------------------------------------------------------


def preferred_domain_id(team: str) -> int:
    """Where a team's automatic ID starts: a hash of its name (never Python's salted hash())."""
    digest = hashlib.sha256(team.encode("utf-8")).digest()
    return AUTO_DOMAIN_IDS[int.from_bytes(digest[:4], "big") % len(AUTO_DOMAIN_IDS)]


def assign_domain_ids(chosen: dict[str, int | None]) -> dict[str, int]:
    """A free ID for each team whose value is None, from its name: stable across runs and however
    the roster orders its teams (teams are taken in name order, each from its preferred ID on to
    the next free one). IDs the roster chose are never given out. Teams beyond the free IDs get none.
    """
    taken = {value for value in chosen.values() if value is not None}
    assigned: dict[str, int] = {}
    for team in sorted(name for name, value in chosen.items() if value is None):
        start = AUTO_DOMAIN_IDS.index(preferred_domain_id(team))
        for step in range(len(AUTO_DOMAIN_IDS)):
            candidate = AUTO_DOMAIN_IDS[(start + step) % len(AUTO_DOMAIN_IDS)]
            if candidate not in taken:
                taken.add(candidate)
                assigned[team] = candidate
                break
    return assigned
