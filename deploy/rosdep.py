"""rosdep ready for the login user: initialised once, its cache fresh, its data from a setting.

`rosdep init` downloads a sources list from a URL compiled into rosdep (no override), so
when `rosdep_sources_list_url` is set the list is fetched from there by the machine running
pyinfra and written where `rosdep init` would write it: the same end state, from a mirror.
"""

from __future__ import annotations

from io import BytesIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.operations import files
from pyinfra.operations.util import any_changed

from deploy.common import as_login_user, login_home, login_user, should_run, stop_host, where
from roslab import downloads, settings
from roslab.operations import (
    ROSDEP_SOURCES_LIST,
    command_installed,
    rosdep_cache_updated,
    rosdep_initialized,
)

DEFAULTS = settings.defaults("rosdep")


@deploy("rosdep is initialised and the login user's rosdep cache is fresh", data_defaults=DEFAULTS)
def rosdep():
    """Install rosdep if missing, initialise it, update the login user's cache when stale.

    Reads host.data: rosdep_enabled, rosdep_package, rosdep_sources_list_url,
    rosdistro_index_url, rosdep_update_max_age, login_user, apt_lock_timeout.
    """
    if not should_run("rosdep_enabled"):
        return
    user, home = login_user(), login_home()
    if home is None:  # the login user does not exist there: the host is stopped
        return
    index_url = host.data.rosdistro_index_url
    sources_list_url = host.data.rosdep_sources_list_url
    sources_list = None
    if sources_list_url:
        # Fetched by the controller once per run; a failure stops the hosts that need it.
        try:
            sources_list = downloads.fetch(sources_list_url)
        except downloads.DownloadError as error:
            stop_host(f"{where()}: rosdep_sources_list_url: {error}; nothing was changed on it")
            return

    command_installed(
        name="Ensure rosdep is installed",
        command="rosdep",
        package=host.data.rosdep_package,
        lock_timeout=host.data.apt_lock_timeout,
    )
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
        max_age=host.data.rosdep_update_max_age,
        rosdistro_index_url=index_url,
        **as_login_user(user),
    )
