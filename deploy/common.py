"""What every host deploy shares: settings lookup, the login user, the host's distro,
and stopping one host (not the whole run) when it cannot be provisioned.
"""

from __future__ import annotations

import os
from pathlib import Path

from pyinfra import host, logger, state
from pyinfra.api import DeployError, deploy
from pyinfra.context import ctx_host
from pyinfra.facts.server import Home, LinuxDistribution, User

from roslab.distro import DistroError, UBUNTU_CODENAMES, check_distro, codename_for, default_distro

DEFAULTS = {
    # The user who owns the ROS environment (~/.bashrc, ~/ros2_ws, the rosdep cache);
    # None: the SSH user.
    "login_user": None,
}


def setting(key: str):
    """A setting from host data, else its default from the deploy module that owns it.

    A deploy's data_defaults only apply inside that deploy; this lets one deploy read
    another's setting (shell_env reads ros_distro) and still get the documented default.
    """
    from deploy import ALL_DEFAULTS  # late: deploy/__init__ imports this module

    return host.data.get(key, ALL_DEFAULTS[key])


def where() -> str:
    """Names the host for error messages: roster host and team."""
    if not ctx_host.isset():  # rendering outside a deploy (tests, `roslab check`)
        return "roster"
    team = host.data.get("roslab_team")
    return f"host {host.name}" + (f" (team {team})" if team else "")


def stop_host(message: str) -> None:
    """Fail this host before anything changes on it; the other hosts carry on.

    An exception while planning would abort every host, so the host is marked failed
    instead (pyinfra then runs nothing on it and exits 1 at the end).
    """
    logger.error(f"{host.print_prefix}roslab stops this host: {message}")
    state.fail_hosts({host})


def controller_path(value: str) -> Path:
    """A path on the machine running pyinfra; relative paths are relative to the roster."""
    path = Path(os.path.expanduser(str(value)))
    roster = host.data.get("roslab_roster_path")
    if not path.is_absolute():
        path = (Path(roster).parent if roster else Path.cwd()) / path
    return path


def host_is_active() -> bool:
    return host in state.active_hosts


def should_run(enabled_key: str) -> bool:
    """True when the host is still active and the deploy's `<concern>_enabled` is on."""
    return host_is_active() and bool(setting(enabled_key))


def login_user() -> str:
    return setting("login_user") or host.data.get("ssh_user") or host.get_fact(User)


def login_home() -> str:
    """The login user's home directory as the host resolves it (not assumed /home/<user>)."""
    user = login_user()
    home = host.get_fact(Home, user=user)
    if not home or home.startswith("~"):
        raise DeployError(f"{where()}: login_user {user!r} does not exist on the host")
    return home


def host_codename() -> str | None:
    """The host's Ubuntu codename from /etc/os-release, or None if it is not Ubuntu."""
    if "roslab_codename" not in host.data.dict():
        release = host.get_fact(LinuxDistribution)["release_meta"]
        codename = None
        if release.get("ID") == "ubuntu":
            codename = release.get("UBUNTU_CODENAME") or release.get("VERSION_CODENAME")
        host.data.roslab_codename = codename
        host.data.roslab_os_name = release.get("PRETTY_NAME") or release.get("ID") or "unknown"
    return host.data.roslab_codename


def host_distro() -> str:
    """The ROS 2 distro for this host: `ros_distro` if set, else its Ubuntu release's default."""
    codename = host_codename()
    return setting("ros_distro") or default_distro(codename)


def host_problem() -> str | None:
    """Why this host cannot get ROS 2 as the roster asks, or None when it can."""
    codename = host_codename()
    if codename is None:
        return (
            f"it runs {host.data.roslab_os_name}, not Ubuntu "
            f"(roslab supports Ubuntu {', '.join(sorted(UBUNTU_CODENAMES))})"
        )
    if codename not in UBUNTU_CODENAMES.values():
        return f"Ubuntu {codename} is not supported (supported: {', '.join(sorted(UBUNTU_CODENAMES))})"
    expected = setting("ubuntu_release")
    if expected:
        try:
            expected_codename = codename_for(expected)
        except DistroError as error:
            return f"ubuntu_release: {error}"
        if expected_codename != codename:
            return (
                f"ubuntu_release is {expected} ({expected_codename}) in the roster "
                f"but the host runs Ubuntu {codename}"
            )
    try:
        check_distro(host_distro(), codename)
    except DistroError as error:
        return f"ros_distro: {error}"
    if login_user() == "root":
        return "login_user is root: set login_user (or ssh_user) to the student account"
    return None


@deploy(
    "The host runs an Ubuntu release that has packages for its ROS 2 distro",
    data_defaults=DEFAULTS,
)
def supported_host() -> bool:
    """Stop this host (only) when it cannot get the ROS 2 the roster asks for.

    Reads host.data: ubuntu_release, ros_distro, login_user, ssh_user.
    Returns whether the host is still active.
    """
    problem = host_problem()
    if problem:
        stop_host(f"{where()}: {problem}; nothing was changed on it")
    return host_is_active()
