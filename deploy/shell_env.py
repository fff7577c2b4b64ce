"""The login user's shell sources ROS 2 and exports the team's domain and discovery settings.

One marked block in ~/.bashrc: re-runs never duplicate it, a changed setting rewrites it
(shown under --diff), and the rest of the user's .bashrc is left as it is.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import jinja2
from pyinfra.api import DeployError, deploy

from deploy.common import host_distro, login_home, login_user, setting, should_run, where
from roslab.distro import DISCOVERY_RANGE_DISTROS
from roslab.operations import managed_block

TEMPLATES = Path(__file__).resolve().parent.parent / "templates"
BLOCK_LABEL = "ROS 2 environment"
# deploy/workspace.py owns workspace_dir; the deploy passes its setting, this default
# only serves callers outside a deploy (tests).
WORKSPACE_DIR_FALLBACK = "~/ros2_ws"

DEFAULTS = {
    # Write the ROS 2 environment block into the login user's ~/.bashrc.
    "shell_env_enabled": True,
    # ROS_DOMAIN_ID: give each team its own (0-101, or 215-232), so teams on one
    # network do not see each other's topics.
    "ros_domain_id": 0,
    # Jazzy and later: ROS_AUTOMATIC_DISCOVERY_RANGE (SUBNET, LOCALHOST, OFF, SYSTEM_DEFAULT).
    # On Humble, LOCALHOST becomes ROS_LOCALHOST_ONLY=1 and the others export nothing.
    "ros_automatic_discovery_range": "SUBNET",
    # Jazzy and later: ROS_STATIC_PEERS, hosts to discover without multicast (unreliable on WiFi).
    "ros_static_peers": [],
}

DISCOVERY_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")


def _valid_domain_id(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and (
        0 <= value <= 101 or 215 <= value <= 232
    )


def _shell_path(path: str) -> str:
    """A path for the shell, with a leading ~ as $HOME (quoted, ~ would not expand)."""
    if path == "~" or path.startswith("~/"):
        return '"$HOME' + path[1:].replace('"', '\\"') + '"'
    return shlex.quote(path)


def ros_variables(
    distro: str, domain_id: int, discovery_range: str = "SUBNET", static_peers=(),
) -> dict[str, str]:
    """The ROS variables a shell or a service of this host needs, in export order.

    The one source for both the ~/.bashrc block and the nodes' systemd unit.
    """
    variables = {"ROS_DOMAIN_ID": str(domain_id)}
    if distro in DISCOVERY_RANGE_DISTROS:
        variables["ROS_AUTOMATIC_DISCOVERY_RANGE"] = str(discovery_range)
        if static_peers:
            variables["ROS_STATIC_PEERS"] = ";".join(static_peers)
    elif discovery_range == "LOCALHOST":
        # Humble has no discovery range; LOCALHOST is its ROS_LOCALHOST_ONLY.
        variables["ROS_LOCALHOST_ONLY"] = "1"
    return variables


def render_ros_environment(
    distro: str,
    domain_id: int,
    discovery_range: str = "SUBNET",
    static_peers: list[str] | tuple = (),
    workspace_dir: str = WORKSPACE_DIR_FALLBACK,
    rosdistro_index_url: str | None = None,
) -> str:
    """The text of the ~/.bashrc block for these settings."""
    if not _valid_domain_id(domain_id):
        raise DeployError(f"{where()}: ros_domain_id {domain_id!r} must be 0-101 or 215-232")
    if discovery_range not in DISCOVERY_RANGES:
        raise DeployError(
            f"{where()}: ros_automatic_discovery_range {discovery_range!r} must be one of "
            + ", ".join(DISCOVERY_RANGES)
        )
    if isinstance(static_peers, str) or not all(isinstance(p, str) for p in static_peers or []):
        raise DeployError(f"{where()}: ros_static_peers must be a list of host names or addresses")
    environment = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    return environment.get_template("bashrc-ros-environment.sh.j2").render(
        distro=distro,
        workspace_setup=_shell_path(workspace_dir.rstrip("/") + "/install/setup.bash"),
        ros_variables={
            name: shlex.quote(value)
            for name, value in ros_variables(distro, domain_id, discovery_range, static_peers).items()
        },
        rosdistro_index_url=shlex.quote(rosdistro_index_url) if rosdistro_index_url else None,
    )


@deploy(
    "The login user's shell sources ROS 2 with the team's domain and discovery settings",
    data_defaults=DEFAULTS,
)
def shell_env():
    """Write the ROS 2 environment block into the login user's ~/.bashrc.

    Reads host.data: shell_env_enabled, ros_domain_id, ros_automatic_discovery_range,
    ros_static_peers, ros_distro, workspace_dir, rosdistro_index_url, login_user.
    """
    if not should_run("shell_env_enabled"):
        return
    user = login_user()
    managed_block(
        name=f"Ensure {user}'s ~/.bashrc sets up the ROS 2 environment",
        path=f"{login_home()}/.bashrc",
        content=render_ros_environment(
            distro=host_distro(),
            domain_id=setting("ros_domain_id"),
            discovery_range=setting("ros_automatic_discovery_range"),
            static_peers=setting("ros_static_peers") or [],
            workspace_dir=setting("workspace_dir"),
            rosdistro_index_url=setting("rosdistro_index_url"),
        ),
        label=BLOCK_LABEL,
        user=user,
        group=user,
        mode="644",
    )
