"""The demo nodes: copied into the login user's colcon workspace, built there, run as a service.

Each step runs only when its input changed, so a second run changes nothing:
copy the packages of `nodes/` (only changed files; packages removed from `nodes/`
are removed, a student's own packages in `src/` are not touched), `rosdep install`
when a `package.xml` changed, `colcon build` as the user when a source changed or
the last build did not finish, and restart the role's service when the build or the
unit changed.
"""

from __future__ import annotations

import posixpath
import shlex
from pathlib import Path

from pyinfra import host
from pyinfra.api import DeployError, deploy
from pyinfra.facts.files import File
from pyinfra.operations import files, systemd
from pyinfra.operations.util import any_changed

from deploy.common import host_distro, login_home, login_user, setting, should_run, where
from deploy.shell_env import ros_variables
from roslab import workspace as ws_ops

REPO = Path(__file__).resolve().parent.parent
TEMPLATES = REPO / "templates"
NODES_SERVICE = "roslab-nodes.service"
NODES_UNIT_PATH = f"/etc/systemd/system/{NODES_SERVICE}"
# Templates render without the blank lines a `{% for %}` line would leave.
JINJA_ENV = {"trim_blocks": True, "lstrip_blocks": True}

DEFAULTS = {
    # Copy nodes/ into the login user's workspace, build it and run the role's launch.
    "workspace_enabled": True,
    # The login user's colcon workspace; `~/` is the login user's home.
    "workspace_dir": "~/ros2_ws",
    # Controller directory whose ROS packages are copied into the workspace's src/;
    # None: this checkout's nodes/.
    "workspace_nodes_dir": None,
    # Arguments after `colcon build`; a sequential build is what colcon advises on a Pi.
    "workspace_colcon_args": ["--executor", "sequential"],
    # Run `rosdep install --from-paths src --ignore-src -y` when a package.xml changed.
    "workspace_rosdep_install": True,
    # Run the role's launch as the systemd service roslab-nodes, restarted on failure.
    "nodes_service_enabled": True,
    # What the service runs on main hosts: `ros2 launch <package> <launch file>`.
    "nodes_launch_main": "roslab_bringup main.launch.py",
    # What the service runs on robots: `ros2 launch <package> <launch file>`.
    "nodes_launch_robot": "roslab_bringup robot.launch.py",
    # The topic the verify step expects each team's main host to hear from its robot.
    "nodes_verify_topic": "/chatter",
    # Seconds the verify step waits for a message on that topic.
    "nodes_verify_timeout": 20,
}

# A launch that keeps failing is retried this many times in this many seconds, then left failed.
START_LIMIT_BURST = 5
START_LIMIT_INTERVAL = 300
RESTART_SEC = 5


# Settings, checked (bad input names the host, team and field)
# --------------------------------------------------------------


def workspace_path(home: str) -> str:
    # setting(): the verify step reads this outside the workspace deploy (no data_defaults there).
    value = setting("workspace_dir")
    if not isinstance(value, str) or not value.strip():
        raise DeployError(f"{where()}: workspace_dir must be a path, got {value!r}")
    if value == "~" or value.startswith("~/"):
        value = posixpath.join(home, value[2:])
    if not posixpath.isabs(value):
        raise DeployError(f"{where()}: workspace_dir {value!r} must be absolute or start with ~/")
    return posixpath.normpath(value)


def nodes_dir() -> str:
    value = host.data.workspace_nodes_dir
    path = Path(value) if value else REPO / "nodes"
    if not path.is_dir():
        raise DeployError(f"{where()}: workspace_nodes_dir {str(path)!r} is not a directory")
    return str(path)


def colcon_args() -> list[str]:
    value = host.data.workspace_colcon_args
    if not isinstance(value, (list, tuple)) or not all(isinstance(arg, str) for arg in value):
        raise DeployError(
            f"{where()}: workspace_colcon_args must be a list of strings, got {value!r}"
        )
    return list(value)


def launch_for(role: str) -> tuple[str, str]:
    """(package, launch file) of the role's `nodes_launch_<role>` setting."""
    key = f"nodes_launch_{role}"
    value = host.data.get(key)
    words = value.split() if isinstance(value, str) else []
    if len(words) != 2 or not ws_ops.PACKAGE_NAME.match(words[0]):
        raise DeployError(
            f"{where()}: {key} must be '<package> <launch file>' "
            f"like 'roslab_bringup main.launch.py', got {value!r}"
        )
    return words[0], words[1]


def host_role() -> str:
    role = host.data.get("roslab_role")
    if role not in ("main", "robot"):
        raise DeployError(f"{where()}: roslab_role must be main or robot, got {role!r}")
    return role


# The service's environment: the same variables as the shell block
# ------------------------------------------------------------------


def ros_environment(distro: str) -> dict[str, str]:
    """The ROS variables the nodes need: the same ones the ~/.bashrc block exports."""
    return ros_variables(
        distro,
        setting("ros_domain_id"),
        setting("ros_automatic_discovery_range"),
        setting("ros_static_peers") or [],
    )


def systemd_environment(environment: dict[str, str]) -> list[str]:
    """`Environment=` values, quoted for systemd (quotes, backslashes and % specifiers)."""
    quoted = []
    for name, value in sorted(environment.items()):
        text = f"{name}={value}".replace("\\", "\\\\").replace('"', '\\"').replace("%", "%%")
        quoted.append(f'"{text}"')
    return quoted


def unit_variables(
    *, role: str, user: str, home: str, workspace_dir: str, distro: str,
    launch: tuple[str, str], environment: dict[str, str],
) -> dict:
    """Everything templates/roslab-nodes.service.j2 needs."""
    package, launch_file = launch
    script = " && ".join(
        [
            f"source /opt/ros/{distro}/setup.bash",
            f"source {shlex.quote(posixpath.join(workspace_dir, 'install', 'setup.bash'))}",
            f"exec ros2 launch {package} {shlex.quote(launch_file)}",
        ]
    )
    # Not "user": files.template takes that as the owner of the unit file itself.
    return {
        "role": role,
        "service_user": user,
        "home": home,
        "workspace_dir": workspace_dir,
        "launch": f"{package} {launch_file}",
        "service": NODES_SERVICE,
        "environment": systemd_environment(environment),
        "exec_script": shlex.quote(script).replace("%", "%%"),
        "restart_sec": RESTART_SEC,
        "start_limit_burst": START_LIMIT_BURST,
        "start_limit_interval": START_LIMIT_INTERVAL,
    }


def as_login_user(user: str) -> dict:
    """pyinfra arguments that run an operation as the workspace's owner."""
    return {"_sudo": True, "_sudo_user": user}


@deploy("The demo nodes are built in the login user's workspace and run as the role's service",
        data_defaults=DEFAULTS)
def workspace():
    """Copy nodes/ into the workspace, install its dependencies, build it, run the role's launch.

    Reads host.data: workspace_enabled, workspace_dir, workspace_nodes_dir,
    workspace_colcon_args, workspace_rosdep_install, nodes_service_enabled,
    nodes_launch_main, nodes_launch_robot, login_user, ssh_user, ros_distro,
    ros_domain_id, ros_automatic_discovery_range, ros_static_peers, roslab_role.
    """
    if not should_run("workspace_enabled"):
        return
    user = login_user()
    home = login_home()
    distro = host_distro()
    role = host_role()
    workspace_dir = workspace_path(home)
    src_dir = posixpath.join(workspace_dir, "src")
    source_dir = nodes_dir()
    launch = launch_for(role)
    packages = ws_ops.local_packages(source_dir)

    for path in (workspace_dir, src_dir):
        files.directory(
            name=f"Ensure {path} exists, owned by {user}", path=path, user=user,
        )
    ws_ops.packages(
        name=f"Ensure {src_dir} holds the packages of {source_dir}",
        nodes_dir=source_dir,
        src_dir=src_dir,
        user=user,
    )
    if host.data.workspace_rosdep_install:
        ws_ops.dependencies(
            name="Ensure the packages' system dependencies are installed (rosdep)",
            workspace_dir=workspace_dir,
            packages=sorted(packages),
            distro=distro,
            packages_hash=ws_ops.tree_hash(packages, only="package.xml"),
            user=user,
            ros_home=posixpath.join(home, ".ros"),
        )
    build = ws_ops.built(
        name=f"Ensure {workspace_dir} is built from these sources (colcon)",
        workspace_dir=workspace_dir,
        distro=distro,
        # Only roslab's packages: a student's broken package in src/ must not fail the
        # classroom's deploy. (`--paths` is colcon-core's; `--packages-up-to` needs an
        # extension that not every colcon install has.)
        colcon_args=[*colcon_args(), "--paths", *(f"src/{name}" for name in sorted(packages))],
        sources_hash=ws_ops.tree_hash(packages),
        **as_login_user(user),
    )

    if not host.data.nodes_service_enabled:
        if host.get_fact(File, path=NODES_UNIT_PATH):
            systemd.service(
                name=f"Ensure {NODES_SERVICE} is stopped and disabled (nodes_service_enabled is off)",
                service=NODES_SERVICE, running=False, enabled=False,
            )
        return

    unit = files.template(
        name=f"Ensure {NODES_SERVICE} runs the {role}'s launch as {user}",
        src=str(TEMPLATES / "roslab-nodes.service.j2"),
        dest=NODES_UNIT_PATH,
        mode="644",
        jinja_env_kwargs=JINJA_ENV,
        **unit_variables(
            role=role, user=user, home=home, workspace_dir=workspace_dir, distro=distro,
            launch=launch, environment=ros_environment(distro),
        ),
    )
    systemd.daemon_reload(name="Ensure systemd has read the changed unit", _if=unit.did_change)
    # running=None: starting belongs to the restart below (only after a change), so a
    # node that keeps failing does not make every re-run report a start.
    systemd.service(
        name=f"Ensure {NODES_SERVICE} starts at boot", service=NODES_SERVICE,
        enabled=True, running=None,
    )
    ws_ops.restarted(
        name=f"Ensure {NODES_SERVICE} runs the new build and unit",
        service=NODES_SERVICE,
        _if=any_changed(unit, build),
    )
