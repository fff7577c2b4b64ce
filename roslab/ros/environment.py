"""The ROS 2 environment of a host: the variables its shell, its nodes and `roslab verify` use.

One source for the ~/.bashrc block (deploy/shell_env.py), the roslab-nodes unit
(deploy/workspace.py) and the check `roslab verify` runs on a main host, so a student's
terminal, the service and the check always share the team's domain and discovery settings.
Values arrive checked by the settings schema (a host's roslab.host_settings.HostSettings);
each destination quotes them its own way (`roslab.quoting`).
"""

from __future__ import annotations

from typing import Protocol

from roslab.ros.discovery import DiscoverySettings, host_discovery


class ProfileEnvironment(Protocol):
    """The part of a resolved robot profile (roslab.profiles.resolve.ResolvedProfile) read here."""

    @property
    def environment(self) -> dict[str, str]: ...


class EnvironmentSettings(DiscoverySettings, Protocol):
    """What a host's environment reads of its settings: discovery's, the roster's ros_environment
    and the resolved robot profile (roslab.host_settings.HostSettings has these fields; named here,
    not imported: roslab.profiles builds on roslab.ros)."""

    @property
    def ros_environment(self) -> dict[str, str]: ...
    @property
    def roslab_profile(self) -> ProfileEnvironment | None: ...


def ros_variables_of(settings: DiscoverySettings, distro: str, shell: bool = False) -> dict[str, str]:
    """The ROS variables of a host's settings: domain, middleware and discovery mode
    (roslab.ros.discovery). `shell`: also what the command-line tools of a login shell and
    `roslab verify` need (the discovery server's super client).
    """
    setup = host_discovery(settings, distro)
    return {**setup.variables, **(setup.shell_variables if shell else {})}


def extra_variables(settings: EnvironmentSettings) -> dict[str, str]:
    """The robot profile's variables (TURTLEBOT3_MODEL...), then the roster's ros_environment.

    Both were checked before connecting (roslab.formats.variable): plain names, never roslab's
    own ROS_* variables, one line each. The roster's value wins over the profile's.
    """
    profile = settings.roslab_profile
    return {**(profile.environment if profile is not None else {}), **(settings.ros_environment or {})}


def host_environment(settings: EnvironmentSettings, distro: str, shell: bool = False) -> dict[str, str]:
    """Every variable a host's service (or, `shell`, its login shell and `roslab verify`) sets:
    ROS's, then the extras."""
    return {**ros_variables_of(settings, distro, shell), **extra_variables(settings)}
