"""The team's discovery on its hosts: the middleware's files, the discovery server or Zenoh router.

What a host gets is `roslab.ros.discovery.host_discovery` (the same source as its variables in
~/.bashrc, the nodes' unit and `roslab verify`):

- the files the variables point to, under /etc/roslab/discovery (Humble's static peers as Fast
  DDS or Cyclone DDS XML, Humble's discovery-server super client); a file a changed mode no longer
  needs is removed, so a switched team keeps nothing stale;
- on the team's main, `roslab-discovery-server` (Fast DDS, ros_discovery_mode discovery_server) or
  `roslab-zenoh-router` (ros_middleware rmw_zenoh_cpp) as a systemd service: enabled, restarted
  only when its unit changed (or it is not running), stopped, disabled and removed where the
  roster no longer asks for it.

The nodes' unit carries a digest of these files (deploy/workspace.py), so a changed file restarts
the nodes that read it and nothing else.
"""

from __future__ import annotations

from io import StringIO

from pyinfra import host, logger
from pyinfra.api import deploy
from pyinfra.facts.files import File
from pyinfra.operations import files, systemd

from deploy.common import existing_login_home, host_distro, login_home, login_user, should_run, stop_host, where
from roslab.host_settings import host_settings
from roslab import probe, settings
from roslab.ros import discovery
from roslab.ros import workspace as ws_ops
from roslab.quoting import shell_word, systemd_value
from roslab.service_units import DISCOVERY_RESTARTS, unit_values
from roslab.templating import render
from roslab.ros.workspace import NODES_SERVICE

DEFAULTS = settings.defaults("discovery")

UNIT_DIR = "/etc/systemd/system"
MANAGED_FILES = (discovery.FASTDDS_PEERS_XML, discovery.FASTDDS_SUPER_CLIENT_XML, discovery.CYCLONEDDS_PEERS_XML)


def unit_path(service: str) -> str:
    return f"{UNIT_DIR}/{service}.service"


def service_unit_text(service: discovery.Service, *, distro: str, user: str, home: str) -> str:
    """templates/roslab-discovery.service.j2 for `service`, every value written for systemd."""
    script = " && ".join([
        f"source {shell_word(f'/opt/ros/{distro}/setup.bash')}",
        "exec " + " ".join(shell_word(word) for word in service.command),
    ])
    return render(
        "roslab-discovery.service.j2",
        description=systemd_value(service.description),
        nodes_service=NODES_SERVICE,
        **unit_values(user=user, home=home, environment=service.environment, script=script,
                      restarts=DISCOVERY_RESTARTS),
    )


def host_setup() -> discovery.HostDiscovery:
    return discovery.host_discovery(host_settings(host), host_distro())


@deploy("The team's discovery: the middleware's files, the discovery server or Zenoh router on its main",
        data_defaults=DEFAULTS)
def discovery_in_place():
    """Write the host's discovery files and run (or retire) its team's discovery service.

    Reads host_settings(host): discovery_enabled, ros_middleware, ros_discovery_mode, ros_discovery_server_port,
    ros_zenoh_router_port, ros_domain_id, ros_automatic_discovery_range, ros_static_peers,
    roslab_team_hosts, roslab_hostname, roslab_role, ros_distro, login_user, ssh_user.
    """
    if not should_run("discovery_enabled"):
        return
    setup = host_setup()
    distro = host_distro()
    unit_text = None
    if setup.service is not None:
        user = login_user()
        home = login_home()
        if home is None:  # login_home() stopped this host
            return
        try:  # before any change: a value the unit cannot carry stops this host only
            unit_text = service_unit_text(setup.service, distro=distro, user=user, home=home)
        except ValueError as error:
            stop_host(f"{where()}: discovery: {error}; nothing was changed by this step")
            return

    for path, content in sorted(setup.files.items()):
        files.put(
            name=f"Ensure {path} holds the team's {setup.mode} discovery for {setup.middleware}",
            src=StringIO(content), dest=path, user="root", group="root", mode="644",
            create_remote_dir=True,
        )
    for path in MANAGED_FILES:
        if path not in setup.files and host.get_fact(File, path=path):
            files.file(name=f"Ensure {path} is gone (ros_discovery_mode {setup.mode} does not use it)",
                       path=path, present=False)

    wanted = setup.service.name if setup.service else None
    for service in discovery.SERVICES:
        if service != wanted and host.get_fact(File, path=unit_path(service)):
            systemd.service(name=f"Ensure {service} is stopped and disabled (the roster no longer runs it here)",
                            service=f"{service}.service", running=False, enabled=False)
            retired = files.file(name=f"Ensure {unit_path(service)} is gone", path=unit_path(service),
                                 present=False)
            systemd.daemon_reload(name="Ensure systemd has forgotten the removed unit", _if=retired.did_change)
    if setup.service is None:
        return

    unit_name = f"{setup.service.name}.service"
    unit_state = host.get_fact(ws_ops.NodesUnitState, service=unit_name)
    unit = files.put(
        name=f"Ensure {setup.service.name} runs {setup.service.description.removeprefix('roslab: ')}",
        src=StringIO(unit_text), dest=unit_path(setup.service.name), user="root", group="root", mode="644",
    )
    stopped = ws_ops.stopped_reason(unit_state)
    if stopped:
        host.log(f"discovery: {unit_name} is {stopped}: starting it again", logger.warning)
    systemd.daemon_reload(name="Ensure systemd has read the changed unit", _if=unit.did_change)
    systemd.service(name=f"Ensure {setup.service.name} starts at boot", service=unit_name,
                    enabled=True, running=None)
    ws_ops.restarted(name=f"Ensure {setup.service.name} runs its current unit", service=unit_name,
                     _if=lambda: bool(stopped) or unit.did_change())


@probe.reader
def discovery_reads() -> list:
    """What discovery_in_place's operations read on a host that needs no change."""
    if not should_run("discovery_enabled"):
        return []
    setup = host_setup()
    reads = []
    for path in sorted(setup.files):
        reads += probe.put_reads(path)
    reads += [probe.read(File, path=path) for path in MANAGED_FILES if path not in setup.files]
    wanted = setup.service.name if setup.service else None
    reads += [probe.read(File, path=unit_path(service)) for service in discovery.SERVICES if service != wanted]
    if setup.service is not None and existing_login_home():
        unit_name = f"{setup.service.name}.service"
        reads += [*probe.put_reads(unit_path(setup.service.name)),
                  probe.read(ws_ops.NodesUnitState, service=unit_name), *probe.service_reads(unit_name)]
    return reads
