"""The systemd services a host runs by its roster and robot profile, for `roslab verify` and
`roslab status` to judge it by.

One source, the host's typed settings (roslab.host_settings.HostSettings), as the deploys read them:

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

from roslab.host_settings import HostSettings
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


def runs_a_launch(typed: HostSettings) -> bool:
    """Whether the host's roslab-nodes service has a launch to run: its nodes_launch (or a
    deprecated nodes_launch_<role>), as the roster loader resolved it from the robot profile; a
    host without a resolved profile (a hand-made inventory) runs the demo's."""
    if typed.roslab_profile is None:
        return True
    side = {"main": typed.nodes_launch_main, "robot": typed.nodes_launch_robot}.get(typed.roslab_role or "")
    return bool(typed.nodes_launch or side)


def runs_nodes(typed: HostSettings) -> bool:
    """Whether the deploys install and run roslab-nodes.service on the host."""
    return typed.workspace_enabled and typed.nodes_service_enabled and runs_a_launch(typed)


def profile_name(typed: HostSettings) -> str:
    return (typed.roslab_profile.name if typed.roslab_profile is not None else None) or "demo"


def services_not_started(typed: HostSettings) -> list[tuple[str, str]]:
    """(service, why) of the robot profile's services that the roster's settings leave off here
    (the rover's osr_startup until osr_calibrated: true): the reason a robot runs nothing yet."""
    if not typed.profile_services_enabled or typed.roslab_profile is None:
        return []
    return [(service.name, service.disabled_because or "not enabled by the roster")
            for service in typed.roslab_profile.services if not service.enabled]


def host_services(typed: HostSettings) -> list[HostService]:
    """Every service the host runs by its roster, the team's discovery service first (when it is
    down, nothing else can be heard), then the profile's, then the nodes."""
    services: list[HostService] = []
    if typed.discovery_enabled:
        distro = typed.ros_distro or typed.roslab_expected_distro or "jazzy"
        service = discovery.host_discovery(typed, distro).service
        if service is not None:
            what = ("the team's Zenoh router" if service.name == discovery.ZENOH_ROUTER_SERVICE
                    else "the team's Fast DDS discovery server")
            services.append(HostService(f"{service.name}.service", what, "discovery"))
    if typed.profile_services_enabled and typed.roslab_profile is not None:
        for own in typed.roslab_profile.services:
            if own.enabled:
                services.append(HostService(f"{own.name}.service",
                                            f"robot profile {profile_name(typed)}'s {own.name}", "profile",
                                            launch=str(own.command or "").startswith("ros2 launch ")))
    if runs_nodes(typed):
        services.append(HostService(NODES_SERVICE, "the nodes", "nodes"))
    return services
