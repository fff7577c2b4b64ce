"""rosdep ready for the login user: initialised once, its cache fresh, its data from a setting.

By default (`rosdep_data_from_controller`) the machine running pyinfra downloads rosdep's
sources list, the files it lists and the rosdistro index with the host's distro once per
run (roslab/ros/rosdep_data.py) and copies them to each host: no Pi downloads rosdep's data
itself, and `offline: true` uses the controller's kept copies. Otherwise `rosdep init`
downloads a sources list from a URL compiled into rosdep (no override), so when
`rosdep_sources_list_url` is set the list is fetched from there by the controller and
written where `rosdep init` would write it: the same end state, from a mirror.
"""

from __future__ import annotations

from io import BytesIO
from pathlib import Path

from pyinfra import host, logger
from pyinfra.api import deploy
from pyinfra.operations import files, server
from pyinfra.operations.util import any_changed

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
from roslab.host_settings import host_settings
from roslab import downloads, probe, settings
from roslab.ros import rosdep_data
from roslab.ops.apt import command_installed, command_installed_reads
from roslab.ops.rosdep import (
    ROSDEP_SOURCES_LIST,
    rosdep_cache_updated,
    rosdep_cache_updated_reads,
    rosdep_initialized,
    rosdep_initialized_reads,
)

DEFAULTS = settings.defaults("rosdep")


@deploy("rosdep is initialised and the login user's rosdep cache is fresh", data_defaults=DEFAULTS)
def rosdep():
    """Install rosdep if missing, initialise it, update the login user's cache when stale.

    Reads host_settings(host): rosdep_enabled, rosdep_package, rosdep_sources_list_url,
    rosdistro_index_url, rosdep_data_from_controller, rosdep_cache_dir, offline,
    rosdep_update_max_age, login_user, apt_lock_timeout.
    """
    typed = host_settings(host)
    if not should_run("rosdep_enabled"):
        return
    user, home = login_user(), login_home()
    if home is None:  # the login user does not exist there: the host is stopped
        return
    if typed.rosdep_data_from_controller or typed.offline:
        _rosdep_from_controller(user, home)
        return
    index_url = typed.rosdistro_index_url
    sources_list_url = typed.rosdep_sources_list_url
    sources_list = None
    if sources_list_url:
        # Fetched by the controller once per run; a failure stops the hosts that need it.
        try:
            sources_list = downloads.fetch(sources_list_url)
        except downloads.DownloadError as error:
            stop_host(f"{where()}: rosdep_sources_list_url: {error}; nothing was changed on it")
            return

    _rosdep_installed()
    if sources_list is not None:
        sources = files.put(
            name=f"Ensure rosdep's sources list comes from {sources_list_url}",
            src=BytesIO(sources_list),
            dest=ROSDEP_SOURCES_LIST,
            mode="644",
        )
    else:
        sources = rosdep_initialized(name="Ensure rosdep is initialised (rosdep init)")

    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache follows the changed sources",
        home=home,
        rosdistro_index_url=index_url,
        _if=any_changed(sources),
        **as_login_user(user),  # never root: rosdep refuses sudo
    )
    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache is younger than rosdep_update_max_age",
        home=home,
        max_age=typed.rosdep_update_max_age,
        rosdistro_index_url=index_url,
        **as_login_user(user),
    )


def _rosdep_installed() -> None:
    """Both ways of getting rosdep's data install it the same way, once their data is in hand."""
    typed = host_settings(host)
    command_installed(
        name="Ensure rosdep is installed",
        command="rosdep",
        package=typed.rosdep_package,
        lock_timeout=typed.apt_lock_timeout,
    )


ARCHIVE = f"{rosdep_data.HOST_DIR}.tar"
UNPACK = (f"set -e; rm -rf {rosdep_data.HOST_DIR}.new; mkdir -p {rosdep_data.HOST_DIR}.new; "
          f"tar -xf {ARCHIVE} --no-same-owner -C {rosdep_data.HOST_DIR}.new; "
          f"rm -rf {rosdep_data.HOST_DIR}; mv {rosdep_data.HOST_DIR}.new {rosdep_data.HOST_DIR}")


def _rosdep_from_controller(user: str, home: str) -> None:
    """rosdep's data downloaded once by the controller, copied here, and rosdep pointed at it."""
    typed = host_settings(host)
    try:
        data = rosdep_data.for_distro(
            typed.rosdep_sources_list_url, typed.rosdistro_index_url, host_distro(),
            Path(typed.rosdep_cache_dir).expanduser(), offline=typed.offline,
            max_age=typed.rosdep_update_max_age,
        )
    except rosdep_data.RosdepDataError as error:
        stop_host(f"{where()}: rosdep's data: {error}; nothing was changed on it")
        return
    for line in data.stale:
        # Upstream is down: the kept copy stands in, and a host that needs nothing new carries on.
        logger.warning(f"{host.print_prefix}roslab: {where()}: rosdep's data: {line}")

    _rosdep_installed()
    archive = files.put(
        name="Ensure rosdep's data (downloaded once by the controller) is on the host",
        src=BytesIO(data.archive),
        dest=ARCHIVE,
        mode="644",
    )
    server.shell(
        name=f"Ensure rosdep's data is unpacked in {rosdep_data.HOST_DIR}",
        commands=[UNPACK],
        _if=archive.did_change,
    )
    sources = files.put(
        name="Ensure rosdep's sources list points at the copied data",
        src=BytesIO(data.sources_list),
        dest=ROSDEP_SOURCES_LIST,
        mode="644",
    )
    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache follows the changed data",
        home=home,
        rosdistro_index_url=data.index_url,
        _if=any_changed(sources, archive),
        **as_login_user(user),  # never root: rosdep refuses sudo
    )
    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache is younger than rosdep_update_max_age",
        home=home,
        max_age=typed.rosdep_update_max_age,
        rosdistro_index_url=data.index_url,
        **as_login_user(user),
    )


@probe.reader
def rosdep_reads() -> list:
    """What rosdep's operations read on a host that needs no change."""
    typed = host_settings(host)
    home = existing_login_home() if should_run("rosdep_enabled") else None
    if home is None:
        return []
    if typed.rosdep_data_from_controller or typed.offline:
        sources = [*probe.put_reads(ARCHIVE), *probe.put_reads(ROSDEP_SOURCES_LIST)]
    elif typed.rosdep_sources_list_url:
        sources = probe.put_reads(ROSDEP_SOURCES_LIST)
    else:
        sources = rosdep_initialized_reads()
    return [*command_installed_reads("rosdep"), *sources, *rosdep_cache_updated_reads(home)]
