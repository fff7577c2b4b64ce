"""The login user's shell sources ROS 2 and exports the team's domain and discovery settings.

One marked block in ~/.bashrc: re-runs never duplicate it, a changed setting rewrites it
(shown under --diff), and the rest of the user's .bashrc is left as it is. Every value in
it is one single-quoted shell word: a student's shell never runs what a setting holds.
"""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy

from deploy.common import (
    existing_login_home,
    host_distro,
    login_home,
    login_user,
    should_run,
    stop_host,
    where,
)
from roslab import probe, settings
from roslab.ops.files import managed_block, managed_block_reads
from roslab.quoting import shell_home_path, shell_word
from deploy.python_env import filled_venv
from deploy.sources import repositories
from roslab.python_env.venv import venv_on_pythonpath
from roslab.ros.environment import host_environment
from roslab.templating import render
from roslab.host_settings import host_settings

BLOCK_LABEL = "ROS 2 environment"

DEFAULTS = settings.defaults("shell_env")


def render_ros_environment(
    distro: str,
    variables: dict[str, str],
    workspace_dir: str = settings.SETTINGS["workspace_dir"].default,
    rosdistro_index_url: str | None = None,
    underlay_dir: str | None = None,
    venv_dir: str | None = None,
) -> str:
    """The text of the ~/.bashrc block for these (schema-checked) settings.

    `variables`: every variable, as `roslab.ros.environment.host_environment(settings, distro, shell=True)` gives
    them (domain, middleware, discovery mode, the profile's and the roster's extras).
    `underlay_dir`: the underlay workspace (deploy/sources.py) sourced before the workspace, or None.
    `venv_dir`: the robot profile's venv (`~/...`), whose site-packages go first on PYTHONPATH, or None.
    """
    return render(
        "bashrc-ros-environment.sh.j2",
        ros_setup=shell_word(f"/opt/ros/{distro}/setup.bash"),
        # "$HOME"/'rest': ~ would not expand inside quotes, and double quotes would run
        # a $(...) in the rest in every student shell.
        workspace_setup=shell_home_path(workspace_dir.rstrip("/") + "/install/setup.bash"),
        underlay_setup=shell_home_path(underlay_dir.rstrip("/") + "/install/setup.bash") if underlay_dir else None,
        ros_variables={name: shell_word(value) for name, value in variables.items()},
        rosdistro_index_url=shell_word(rosdistro_index_url) if rosdistro_index_url else None,
        venv_pythonpath=venv_on_pythonpath(shell_home_path(venv_dir.rstrip("/"))) if venv_dir else None,
    )


@deploy(
    "The login user's shell sources ROS 2 with the team's domain and discovery settings",
    data_defaults=DEFAULTS,
)
def shell_env():
    """Write the ROS 2 environment block into the login user's ~/.bashrc.

    Reads host_settings(host): shell_env_enabled, ros_domain_id, ros_automatic_discovery_range,
    ros_static_peers, ros_middleware, ros_discovery_mode, ros_discovery_server_port,
    ros_zenoh_router_port, roslab_team_hosts, roslab_hostname, roslab_role, ros_distro,
    workspace_dir, rosdistro_index_url, login_user, ssh_user, roslab_profile (its environment),
    ros_environment, roslab_sources and sources_underlay_dir (the underlay, sourced before the workspace),
    python_env_enabled and roslab_profile's python venv (first on PYTHONPATH).
    """
    typed = host_settings(host)
    if not should_run("shell_env_enabled"):
        return
    user = login_user()
    home = login_home()
    if home is None:  # the login user does not exist: login_home() stopped this host
        return
    try:
        distro = host_distro()
        block = render_ros_environment(
            distro=distro,
            workspace_dir=typed.workspace_dir,
            rosdistro_index_url=typed.rosdistro_index_url,
            variables=host_environment(typed, distro, shell=True),
            underlay_dir=typed.sources_underlay_dir if repositories() else None,
            venv_dir=filled_venv("~"),
        )
    except ValueError as error:  # a value no shell word can carry (only `--data` skips the schema)
        stop_host(f"{where()}: shell_env: {error}; nothing was changed by this step")
        return
    managed_block(
        name=f"Ensure {user}'s ~/.bashrc sets up the ROS 2 environment",
        path=f"{home}/.bashrc",
        content=block,
        label=BLOCK_LABEL,
        user=user,
        group=user,
        mode="644",
    )


@probe.reader
def shell_env_reads() -> list:
    """What shell_env's operation reads on a host that needs no change."""
    if not should_run("shell_env_enabled"):
        return []
    home = existing_login_home()
    return managed_block_reads(f"{home}/.bashrc") if home else []
