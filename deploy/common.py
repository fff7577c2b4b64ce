"""What every host deploy shares: the login user, the host's distro, running as the login
user, and stopping one host (not the whole run) when it cannot be provisioned.

Settings are typed: `host_settings(host)` (roslab/host_settings.py), built once per host from
its data; the roster loader checked every value against `roslab.settings` and merged in every
default before pyinfra connected. Only this run's own notes (`_roslab_*`, the host's codename)
live in `host.data`.
"""

from __future__ import annotations

from pyinfra import host, logger, state
from pyinfra.api import deploy
from pyinfra.context import ctx_host
from pyinfra.facts.server import Home, LinuxDistribution, User

from roslab import settings
from roslab.reporting import summary
from roslab.ssh import run_lock
from roslab.ops.users import as_user
from roslab.ops.systemd import BOOT_WAIT, BootFinished
from roslab.probe import read, read_ahead, registered_reads
from roslab.ros.distro import DistroError, UBUNTU_CODENAMES, check_distro, codename_for, default_distro
from roslab.host_settings import HostSettingsError, host_settings

DEFAULTS = settings.defaults("common")


def where() -> str:
    """Names the host for error messages: roster host and team."""
    if not ctx_host.isset():  # rendering outside a deploy (tests, `roslab check`)
        return "roster"
    try:
        team = host_settings(host).roslab_team
    except HostSettingsError:  # the host is being stopped for that very error
        team = None
    return f"host {host.name}" + (f" (team {team})" if team else "")


def stop_host(message: str) -> None:
    """Fail this host before anything changes on it; the other hosts carry on.

    An exception while planning would abort every host, so the host is marked failed
    instead (pyinfra then runs nothing on it and exits 1 at the end).
    """
    logger.error(f"{host.print_prefix}roslab stops this host: {message}")
    summary.record_stop(host, message)
    # The real Host, not the context proxy: pyinfra reads failed_hosts after the run,
    # when the proxy points at no host any more (its --json output crashed on it).
    state.fail_hosts({ctx_host.get()})


def host_is_active() -> bool:
    return host in state.active_hosts


def should_run(enabled_key: str) -> bool:
    """True when the host is still active and the deploy's `<concern>_enabled` is on."""
    return host_is_active() and bool(getattr(host_settings(host), enabled_key))


def apt_sources_written(*operations) -> list:
    """Note operations that write apt sources; all noted so far.

    deploy.apt_ready.apt_lists runs one `apt-get update` after them when any changed.
    """
    noted = [*(host.data.get("_roslab_apt_sources") or []), *operations]
    host.data._roslab_apt_sources = noted
    return noted


def login_user() -> str:
    typed = host_settings(host)
    return typed.login_user or typed.ssh_user or host.get_fact(User)


def as_login_user(user: str) -> dict:
    """pyinfra arguments that run an operation as the login user (rosdep and colcon refuse root)."""
    return as_user(user)


def login_home() -> str | None:
    """The login user's home directory as the host resolves it (not assumed /home/<user>).

    None, with this host stopped, when the user does not exist there.
    """
    home = existing_login_home()
    if home is None:
        stop_host(f"{where()}: login_user {login_user()!r} does not exist on the host; "
                  "nothing was changed by this step")
    return home


def existing_login_home() -> str | None:
    """The login user's home directory, or None when the user does not exist (nothing stopped)."""
    home = host.get_fact(Home, user=login_user())
    return None if not home or home.startswith("~") else home


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


def ubuntu_codename() -> str:
    """The codename of a host the deploy runs on: supported_host() let only Ubuntu through."""
    codename = host_codename()
    if codename is None:
        raise RuntimeError(f"{where()}: a deploy step ran on a host that is not Ubuntu "
                           "(supported_host() stops those before any step)")
    return codename


def host_distro() -> str:
    """The ROS 2 distro for this host: `ros_distro` if set, else its Ubuntu release's default."""
    codename = ubuntu_codename()
    return host_settings(host).ros_distro or default_distro(codename)


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
    expected = host_settings(host).ubuntu_release
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


def said_boot_wait() -> None:
    """Say that this run waited for the host to finish booting (read ahead in supported_host),
    or that it is still booting after BOOT_WAIT seconds: what it reads of units may change."""
    boot = host.get_fact(BootFinished, timeout=BOOT_WAIT)
    if not boot or not boot["waited"]:
        return
    if boot["timed_out"]:
        logger.warning(f"{host.print_prefix}roslab: {where()}: still booting after {BOOT_WAIT} s "
                       "(systemctl is-system-running: starting); carrying on: a unit still starting "
                       "may be started by this run")
    elif boot["seconds"] > 0:
        logger.warning(f"{host.print_prefix}roslab: {where()}: waited {boot['seconds']} s for the host to "
                       f"finish booting (systemd: {boot['state'] or 'unknown'})")


@deploy(
    "The host runs an Ubuntu release that has packages for its ROS 2 distro",
    data_defaults=DEFAULTS,
)
def supported_host() -> bool:
    """Stop this host (only) when it cannot get the ROS 2 the roster asks for.

    Reads host_settings(host): ubuntu_release, ros_distro, login_user, ssh_user; a value of the
    wrong type (a hand-made inventory, --data) stops this host with the error naming the key.
    Returns whether the host is still active.

    Reads the host in two remote commands (roslab.probe): its release and the login
    user's home (no sudo needed; first waiting for a host still booting: BootFinished), then,
    for a host that can be provisioned, everything the deploys' operations read when nothing
    needs changing (under sudo: apt's lock, root's files).
    """
    try:
        host_settings(host)
    except HostSettingsError as error:
        stop_host(f"{error}; nothing was changed on it")
        return False
    busy = run_lock.run_lock_problem(host, host_settings(host).run_lock_wait)  # before anything is read: one run at a time per host
    if busy:
        stop_host(f"{where()}: {busy}")
        return False
    read_ahead([read(BootFinished, timeout=BOOT_WAIT), read(LinuxDistribution), read(Home, user=login_user())],
               _sudo=False)
    said_boot_wait()
    problem = host_problem()
    if problem:
        stop_host(f"{where()}: {problem}; nothing was changed on it")
    else:
        read_ahead(registered_reads())
    return host_is_active()
