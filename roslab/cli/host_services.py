"""The systemd services a host runs by its roster and robot profile, for `roslab verify` and
`roslab status` to judge it by.

One source, from the same host data the deploys read:

- `roslab-nodes.service` when the host has a launch to run (its nodes_launch, else its
  profile side's; a hand-made inventory without a resolved profile runs the demo's) and
  `workspace_enabled` and `nodes_service_enabled` are on. A TurtleBot3's or a sim main has none.
- the team's discovery service (`roslab-discovery-server` on a discovery-server team's main,
  `roslab-zenoh-router` on a Zenoh team's main or a Zenoh localhost host), from
  `roslab.ros.discovery`, when `discovery_enabled` is on.
- the robot profile's own services whose `enabled_if` holds (the rover's `osr_startup`, the
  ESP32's `micro_ros_agent`), when `profile_services_enabled` is on.

A service on this list that does not run is the team's fault to name: a stopped discovery
server leaves both nodes services active and the main hearing nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

from roslab import settings
from roslab.host_settings import settings_of
from roslab.ros import discovery
from roslab.ros.workspace import NODES_SERVICE


@dataclass(frozen=True)
class HostService:
    unit: str  # "roslab-discovery-server.service"
    what: str  # what it is for, said where it is the cause: "the team's Fast DDS discovery server"
    kind: str  # "nodes", "discovery" or "profile"
    # a profile's service that runs `ros2 launch` (the rover's osr_startup): its nodes can die
    # and start again while systemd sees the launch running (roslab.cli.launch_journal)
    launch: bool = False


def _on(data, key: str) -> bool:
    value = data.get(key)
    return True if value is None else bool(value)


def runs_a_launch(data) -> bool:
    """Whether the host's roslab-nodes service has a launch to run: its nodes_launch (or a
    deprecated nodes_launch_<role>), as the roster loader resolved it from the robot profile; a
    host without a resolved profile (a hand-made inventory) runs the demo's."""
    if data.get("roslab_profile") is None:
        return True
    return bool(data.get("nodes_launch") or data.get(f"nodes_launch_{data.get('roslab_role')}"))


def runs_nodes(data) -> bool:
    """Whether the deploys install and run roslab-nodes.service on the host."""
    return _on(data, "workspace_enabled") and _on(data, "nodes_service_enabled") and runs_a_launch(data)


def profile_name(data) -> str:
    return (data.get("roslab_profile") or {}).get("name") or "demo"


def services_not_started(data) -> list[tuple[str, str]]:
    """(service, why) of the robot profile's services that the roster's settings leave off here
    (the rover's osr_startup until osr_calibrated: true): the reason a robot runs nothing yet."""
    if not _on(data, "profile_services_enabled"):
        return []
    return [(service["name"], service.get("disabled_because") or "not enabled by the roster")
            for service in (data.get("roslab_profile") or {}).get("services") or () if not service.get("enabled")]


def host_services(data) -> list[HostService]:
    """Every service the host runs by its roster, the team's discovery service first (when it is
    down, nothing else can be heard), then the profile's, then the nodes."""
    services: list[HostService] = []
    if _on(data, "discovery_enabled"):
        distro = data.get("ros_distro") or data.get("roslab_expected_distro") or "jazzy"
        given = data.dict() if hasattr(data, "dict") else dict(data)  # pyinfra's HostData, or a dict
        merged = {**settings.defaults("discovery"), **{k: v for k, v in given.items() if v is not None}}
        typed = settings_of(str(merged.get("roslab_hostname") or ""), merged)  # the boundary: a mapping to typed
        service = discovery.host_discovery(typed, distro).service
        if service is not None:
            what = ("the team's Zenoh router" if service.name == discovery.ZENOH_ROUTER_SERVICE
                    else "the team's Fast DDS discovery server")
            services.append(HostService(f"{service.name}.service", what, "discovery"))
    if _on(data, "profile_services_enabled"):
        for service in (data.get("roslab_profile") or {}).get("services") or ():
            if service.get("enabled"):
                services.append(HostService(f"{service['name']}.service",
                                            f"robot profile {profile_name(data)}'s {service['name']}", "profile",
                                            launch=str(service.get("command") or "").startswith("ros2 launch ")))
    if runs_nodes(data):
        services.append(HostService(NODES_SERVICE, "the nodes", "nodes"))
    return services
