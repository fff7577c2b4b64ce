"""The ROS 2 environment of a host: the variables its shell, its nodes and `roslab verify` use.

One source for the ~/.bashrc block (deploy/shell_env.py), the roslab-nodes unit
(deploy/workspace.py) and the check `roslab verify` runs on a main host, so a student's
terminal, the service and the check always share the team's domain and discovery settings.
Values arrive checked by the settings schema; each destination quotes them its own way
(`roslab.quoting`).
"""

from __future__ import annotations

from roslab.ros.discovery import host_discovery

# The host.data keys `ros_variables_of` reads (shell_env's, discovery's, the host's identity); `host_environment`
# reads these, the resolved robot profile (roslab_profile) and ros_environment.
SETTING_KEYS = ("ros_domain_id", "ros_automatic_discovery_range", "ros_static_peers", "ros_middleware",
                "ros_discovery_mode", "ros_discovery_server_port", "ros_zenoh_router_port",
                "roslab_team_hosts", "roslab_hostname", "roslab_role")
ENVIRONMENT_KEYS = (*SETTING_KEYS, "roslab_profile", "ros_environment")


def ros_variables_of(data, distro: str, shell: bool = False) -> dict[str, str]:
    """The ROS variables of a host's data (pyinfra's host.data or a roster host's dict: anything
    with .get): domain, middleware and discovery mode (roslab.ros.discovery). `shell`: also what the
    command-line tools of a login shell and `roslab verify` need (the discovery server's super client).
    """
    setup = host_discovery(data, distro)
    return {**setup.variables, **(setup.shell_variables if shell else {})}


def extra_variables(data) -> dict[str, str]:
    """The robot profile's variables (TURTLEBOT3_MODEL...), then the roster's ros_environment.

    Both were checked before connecting (roslab.formats.variable): plain names, never roslab's
    own ROS_* variables, one line each. The roster's value wins over the profile's.
    """
    profile = data.get("roslab_profile") or {}
    return {**(profile.get("environment") or {}), **(data.get("ros_environment") or {})}


def host_environment(data, distro: str, shell: bool = False) -> dict[str, str]:
    """Every variable a host's service (or, `shell`, its login shell and `roslab verify`) sets:
    ROS's, then the extras."""
    return {**ros_variables_of(data, distro, shell), **extra_variables(data)}
