"""The demo nodes: copied into the login user's colcon workspace, built there, run as a service.

Each step runs only when its input changed, so a second run changes nothing:
copy the packages of `nodes/` (only changed files; packages removed from `nodes/`
are removed, a student's own packages in `src/` are not touched), `rosdep install`
when a `package.xml` changed, `colcon build` as the user when a source changed or
the last build did not finish, and restart the role's service when the build or the
unit changed.

Classroom accidents heal on the next run, each named in one line for its host:
- a workspace (or part of it) a student gave to root is given back to the login user;
- a Python file of roslab's packages that does not compile fails this host's build with
  file and line, before colcon runs (the service keeps its last good build, no restart);
- a nodes unit that gave up (failed after its start limit) or was stopped is started again.
"""

from __future__ import annotations

import hashlib
import posixpath
from dataclasses import dataclass
from io import StringIO
from pathlib import Path

from pyinfra import host, logger
from pyinfra.api import OperationError, deploy
from pyinfra.api.operation import OperationMeta
from pyinfra.facts.files import File
from pyinfra.operations import files, server, systemd

from deploy.common import (
    as_login_user,
    existing_login_home,
    host_distro,
    login_home,
    login_user,
    should_run,
    stop_host,
    where,
)
from deploy.python_env import filled_venv
from deploy.sources import underlay_identity, underlay_setup
from roslab import formats, packaged, probe, settings
from roslab.ros import workspace as ws_ops
from roslab.python_env.venv import venv_on_pythonpath
from roslab.quoting import shell_word, systemd_value
from roslab.service_units import NODE_RESTARTS, unit_values
from roslab.profiles.library import DEFAULT_PROFILE, builtin_profiles
from roslab.ros.discovery import host_discovery
from roslab.ros.environment import host_environment
from roslab.templating import render
from roslab.ros.workspace import NODES_SERVICE, NODES_UNIT_PATH
from roslab.host_settings import HostSettings, host_settings

REPO = Path(__file__).resolve().parent.parent


DEFAULTS = settings.defaults("workspace")

# A launch that keeps failing is retried this many times in this many seconds, then left failed.


def nodes_dir() -> str:
    """The controller directory whose packages are copied (absolute: the roster made it so)."""
    value = host_settings(host).workspace_nodes_dir
    return str(Path(value) if value else packaged.nodes_dir())  # the checkout's or the installed nodes/


def exec_script(*, distro: str, workspace_dir: str, launch: str, underlay_setup: str | None = None,
                venv_dir: str | None = None, launch_arguments: dict[str, str] | None = None) -> str:
    """The bash script the unit runs: the distro's, the underlay's (deploy/sources.py) and the
    workspace's setup, the profile's venv on PYTHONPATH (`venv_dir`, absolute, or None), then
    the launch with its `launch_arguments` ({name: value}: one shell word `name:=value` each;
    ValueError for a name or value roslab.formats refuses, checked where they were read too)."""
    package, launch_file = launch.split(" ")
    words = []
    for name, value in (launch_arguments or {}).items():
        problem = formats.launch_argument_name(name) or formats.launch_argument_value(value)
        if problem:
            raise ValueError(f"launch argument {name!r}: {problem}")
        words.append(" " + shell_word(f"{name}:={value}"))
    return " && ".join(
        [
            f"source {shell_word(f'/opt/ros/{distro}/setup.bash')}",
            *([f"source {shell_word(underlay_setup)}"] if underlay_setup else []),
            f"source {shell_word(posixpath.join(workspace_dir, 'install', 'setup.bash'))}",
            *([venv_on_pythonpath(shell_word(venv_dir))] if venv_dir else []),
            f"exec ros2 launch {shell_word(package)} {shell_word(launch_file)}" + "".join(words),
        ]
    )


def unit_text(
    *, role: str, user: str, home: str, workspace_dir: str, distro: str, launch: str,
    environment: dict[str, str], discovery_files: dict[str, str] | None = None,
    underlay_setup: str | None = None, venv_dir: str | None = None,
    launch_arguments: dict[str, str] | None = None,
) -> str:
    """templates/roslab-nodes.service.j2 with every value written for systemd.

    `launch` is the host's `role_launch()` ("<package> <launch file>"). `discovery_files`: the
    middleware files its variables point to (deploy/discovery.py writes them); their digest is in
    the unit, so a changed file restarts the nodes, as a changed variable does.
    """
    script = exec_script(distro=distro, workspace_dir=workspace_dir, launch=launch,
                         underlay_setup=underlay_setup, venv_dir=venv_dir, launch_arguments=launch_arguments)
    return render(
        "roslab-nodes.service.j2",
        role=systemd_value(role),
        launch=systemd_value(launch),
        workspace_dir=systemd_value(workspace_dir),
        description=systemd_value(f"roslab {role} nodes (ros2 launch {launch})"),
        service=NODES_SERVICE,
        **unit_values(user=user, home=home, environment=environment, script=script, restarts=NODE_RESTARTS),
        discovery_digest=files_digest(discovery_files) if discovery_files else None,
    )


def files_digest(contents: dict[str, str]) -> str:
    """One sha256 over paths and contents."""
    digest = hashlib.sha256()
    for path, text in sorted(contents.items()):
        digest.update(path.encode() + b"\0" + text.encode() + b"\0")
    return digest.hexdigest()


def discovery_files(distro: str) -> dict[str, str]:
    """The discovery files this host's nodes read (none when the discovery deploy is switched off)."""
    typed = host_settings(host)
    if not typed.discovery_enabled:
        return {}
    return host_discovery(typed, distro).files


def role_launch() -> str | None:
    """What this host's service runs ("<package> <launch file>"), or None for no service:
    nodes_launch, which the roster loader resolved (the host's own, a deprecated
    nodes_launch_<role>, else its robot profile's launch for its side)."""
    if not host_settings(host).nodes_service_enabled:
        return None
    typed = host_settings(host)
    role = typed.roslab_role
    launch = typed.nodes_launch or getattr(typed, f"nodes_launch_{role}", None)
    if launch is None and typed.roslab_profile is None:
        # A hand-made inventory (no roster, so no resolved profile): the default profile's launch.
        side = builtin_profiles()[DEFAULT_PROFILE].sides.get(role) if role else None
        launch = side.launch if side else None
    return launch


def role_launch_arguments(launch: str | None) -> dict[str, str]:
    """The robot profile's launch arguments, where the host runs its profile's launch (a
    roster's own nodes_launch gets none: they were written for the profile's file)."""
    profile = host_settings(host).roslab_profile
    if launch is None or profile is None or profile.launch != launch:
        return {}
    return dict(profile.launch_arguments)


def profile_name() -> str:
    profile = host_settings(host).roslab_profile
    return profile.name if profile is not None else "demo"


@dataclass(frozen=True)
class NodesWorkspace:
    """What the workspace's steps act on, read before any of them changes the host."""

    user: str
    home: str
    distro: str
    role: str | None
    workspace_dir: str
    src_dir: str
    source_dir: str
    packages: dict[str, dict[str, ws_ops.LocalFile]]  # nodes/'s packages (ws_ops.local_packages)
    underlay: str | None  # the underlay's setup.bash (deploy/sources.py), or None
    unit_file: str | None  # the nodes unit's text, or None where the host runs no nodes


@deploy("The demo nodes are built in the login user's workspace and run as the role's service",
        data_defaults=DEFAULTS)
def workspace():
    """Copy nodes/ into the workspace, install its dependencies, build it, run the role's launch.

    Reads host_settings(host): workspace_enabled, workspace_dir, workspace_nodes_dir,
    workspace_colcon_args, workspace_rosdep_install, nodes_service_enabled,
    nodes_launch (nodes_launch_<role> in hand-made inventories), login_user, ssh_user, ros_distro,
    ros_domain_id, ros_automatic_discovery_range, ros_static_peers, ros_middleware,
    ros_discovery_mode, ros_discovery_server_port, ros_zenoh_router_port, roslab_team_hosts,
    roslab_hostname, roslab_role, roslab_profile (its environment and name), ros_environment,
    roslab_sources and sources_underlay_dir (the underlay it overlays, deploy/sources.py),
    python_env_enabled and roslab_profile's python venv (first on the nodes' PYTHONPATH).

    One step per concern, in this order: the tree given back to the login user
    (`workspace_owned`), nodes/ copied and its dependencies installed (`workspace_synced`),
    the build (`workspace_built`), the role's service (`nodes_service_running`, or
    `nodes_service_stopped` where the host runs no nodes).
    """
    typed = host_settings(host)
    if not should_run("workspace_enabled"):
        return
    nodes = nodes_workspace(typed)
    if nodes is None:  # this host was stopped, saying why
        return
    workspace_owned(nodes)
    workspace_synced(nodes, rosdep_install=typed.workspace_rosdep_install)
    build = workspace_built(nodes, colcon_args=typed.workspace_colcon_args)
    if nodes.unit_file is None:
        nodes_service_stopped(nodes)
        return
    nodes_service_running(nodes, build)


def nodes_workspace(typed: HostSettings) -> NodesWorkspace | None:
    """The workspace's paths, nodes/'s packages and the nodes unit, read before any change:
    None, with this host stopped, when the login user is missing, nodes/ cannot be read or
    a value cannot go into the unit (a home directory whose name holds a newline, say)."""
    user = login_user()
    home = login_home()
    if home is None:  # the login user does not exist: login_home() stopped this host
        return None
    distro = host_distro()
    role = typed.roslab_role
    workspace_dir = ws_ops.workspace_path(home, typed.workspace_dir)
    src_dir = posixpath.join(workspace_dir, "src")
    source_dir = nodes_dir()
    try:
        packages = ws_ops.local_packages(source_dir)
    except OperationError as error:
        stop_host(f"{where()}: workspace: {error}; nothing was changed by this step")
        return None

    launch = role_launch()
    underlay = underlay_setup(home)
    try:  # before any change: a value the unit cannot carry stops this host only
        unit_file = unit_text(
            role=str(role), user=user, home=home, workspace_dir=workspace_dir, distro=distro,
            launch=launch, environment=host_environment(typed, distro),
            discovery_files=discovery_files(distro), underlay_setup=underlay,
            venv_dir=filled_venv(home), launch_arguments=role_launch_arguments(launch),
        ) if launch else None
    except ValueError as error:  # e.g. a home directory whose name holds a newline
        stop_host(f"{where()}: workspace: {error}; nothing was changed by this step")
        return None
    return NodesWorkspace(user=user, home=home, distro=distro, role=role, workspace_dir=workspace_dir,
                          src_dir=src_dir, source_dir=source_dir, packages=packages, underlay=underlay,
                          unit_file=unit_file)


def workspace_owned(nodes: NodesWorkspace) -> None:
    """The workspace and its src/ exist and everything in them belongs to the login user.

    Before anything runs as the user: a tree a student gave to root would fail the build.
    (First: a repair is said once, and the folders below then need nothing.)
    """
    user, workspace_dir = nodes.user, nodes.workspace_dir
    ws_ops.owned(
        name=f"Ensure everything in {workspace_dir} belongs to {user}",
        workspace_dir=workspace_dir,
        user=user,
    )
    # With the user's primary group (read ahead with the ownership fact, no command of its
    # own): a folder left in root's group would be "given back" by the next run, a warning
    # about nothing a student did.
    group = host.get_fact(ws_ops.WorkspaceForeign, workspace_dir=workspace_dir, user=user).get("group")
    for path in (workspace_dir, nodes.src_dir):
        files.directory(
            name=f"Ensure {path} exists, owned by {user}", path=path, user=user, group=group,
        )


def workspace_synced(nodes: NodesWorkspace, *, rosdep_install: bool) -> None:
    """src/ holds nodes/'s packages, and (`rosdep_install`) their system dependencies are installed."""
    ws_ops.packages(
        name=f"Ensure {nodes.src_dir} holds the packages of {nodes.source_dir}",
        nodes_dir=nodes.source_dir,
        src_dir=nodes.src_dir,
        user=nodes.user,
    )
    if rosdep_install:
        ws_ops.dependencies(
            name="Ensure the packages' system dependencies are installed (rosdep)",
            workspace_dir=nodes.workspace_dir,
            packages=sorted(nodes.packages),
            distro=nodes.distro,
            packages_hash=ws_ops.tree_hash(nodes.packages, only="package.xml"),
            user=nodes.user,
            ros_home=posixpath.join(nodes.home, ".ros"),
        )


def workspace_built(nodes: NodesWorkspace, *, colcon_args: list[str]) -> OperationMeta:
    """The workspace is built from these sources (colcon, as the login user, with `colcon_args`
    first); the build operation, whose change restarts the nodes."""
    managed = [f"src/{name}" for name in sorted(nodes.packages)]
    underlay = nodes.underlay
    return ws_ops.built(
        name=f"Ensure {nodes.workspace_dir} is built from these sources (colcon)",
        workspace_dir=nodes.workspace_dir,
        distro=nodes.distro,
        # Only roslab's packages: a student's broken package in src/ must not fail the
        # classroom's deploy. (`--paths` is colcon-core's; `--packages-up-to` needs an
        # extension that not every colcon install has.)
        colcon_args=[*colcon_args, "--paths", *managed],
        # a changed underlay (a new pin) rebuilds the overlay too
        sources_hash=ws_ops.tree_hash(nodes.packages) + (f"\n{underlay_identity()}" if underlay else ""),
        python_paths=managed,
        underlays=[underlay] if underlay else [],
        **as_login_user(nodes.user),
    )


def nodes_service_stopped(nodes: NodesWorkspace) -> None:
    """The nodes service is stopped and disabled where the host runs no nodes; no-op when no
    unit was ever written (nothing to stop)."""
    if host.get_fact(File, path=NODES_UNIT_PATH):
        why = "nodes_service_enabled is off" if not host_settings(host).nodes_service_enabled else \
            f"robot profile {profile_name()!r} runs nothing on a {nodes.role}"
        systemd.service(
            name=f"Ensure {NODES_SERVICE} is stopped and disabled ({why})",
            service=NODES_SERVICE, running=False, enabled=False,
        )


def nodes_service_running(nodes: NodesWorkspace, build: OperationMeta) -> None:
    """The role's launch runs as the login user from the unit, restarted when the `build`, the
    unit changed or the unit was found failed or stopped (a healthy re-run reports nothing)."""
    unit_state = host.get_fact(ws_ops.NodesUnitState, service=NODES_SERVICE)
    if unit_state.get("LoadState") == "masked":
        # Someone on the host masked it (`systemctl mask`: a link to /dev/null, which no
        # upload writes through). The roster says the nodes run, so the deploy heals it,
        # saying so; `nodes_service_enabled: false` is how a teacher turns them off.
        host.log(f"workspace: {NODES_SERVICE} was masked on this host (systemctl mask): unmasking it, "
                 "as the roster runs the nodes (nodes_service_enabled)", logger.warning)
        server.shell(
            name=f"Ensure {NODES_SERVICE} is not masked",
            commands=[f"systemctl unmask -- {NODES_SERVICE}"],
        )
    unit = files.put(
        name=f"Ensure {NODES_SERVICE} runs the {nodes.role}'s launch as {nodes.user}",
        src=StringIO(nodes.unit_file),
        dest=NODES_UNIT_PATH,
        user="root",
        group="root",
        mode="644",
    )
    # Read when planning: a unit that gave up (or was stopped) is started again below.
    stopped = ws_ops.stopped_reason(unit_state)
    if stopped:
        host.log(f"workspace: {NODES_SERVICE} is {stopped}: starting it again", logger.warning)
    systemd.daemon_reload(name="Ensure systemd has read the changed unit", _if=unit.did_change)
    # running=None: starting belongs to the restart below (after a change, or when the unit
    # is failed or stopped), so a healthy re-run reports nothing.
    systemd.service(
        name=f"Ensure {NODES_SERVICE} starts at boot", service=NODES_SERVICE,
        enabled=True, running=None,
    )
    ws_ops.restarted(
        name=f"Ensure {NODES_SERVICE} runs the current build and unit",
        service=NODES_SERVICE,
        _if=lambda: bool(stopped) or unit.did_change() or build.did_change(),
    )


@probe.reader
def workspace_reads() -> list:
    """What the workspace's operations read on a host that needs no change."""
    home = existing_login_home() if should_run("workspace_enabled") else None
    if home is None:
        return []
    user = login_user()
    workspace_dir = ws_ops.workspace_path(home, host_settings(host).workspace_dir)
    src_dir = posixpath.join(workspace_dir, "src")
    try:
        packages = ws_ops.local_packages(nodes_dir())
    except OperationError:
        return []
    reads = [
        *probe.directory_reads(workspace_dir),
        *probe.directory_reads(src_dir),
        probe.read(ws_ops.WorkspaceForeign, workspace_dir=workspace_dir, user=user),
        probe.read(ws_ops.WorkspacePackages, src_dir=src_dir, packages=sorted(packages), user=user),
        probe.read(ws_ops.WorkspaceStamps, workspace_dir=workspace_dir),
        *probe.service_reads(NODES_SERVICE),
    ]
    if role_launch():
        reads += [*probe.put_reads(NODES_UNIT_PATH), probe.read(ws_ops.NodesUnitState, service=NODES_SERVICE)]
    else:
        reads.append(probe.read(File, path=NODES_UNIT_PATH))
    return reads
