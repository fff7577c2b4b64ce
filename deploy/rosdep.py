"""rosdep ready for the login user: initialised once, its cache fresh, its data from a setting.

`rosdep init` downloads a sources list from a URL compiled into rosdep (no override), so
when `rosdep_sources_list_url` is set the list is fetched from there by the machine running
pyinfra and written where `rosdep init` would write it: the same end state, from a mirror.
"""

from __future__ import annotations

import functools
import urllib.request
from io import StringIO

from pyinfra.api import DeployError, deploy
from pyinfra.operations import files
from pyinfra.operations.util import any_changed

from deploy.common import login_home, login_user, setting, should_run, where
from roslab.operations import (
    ROSDEP_SOURCES_LIST,
    command_installed,
    rosdep_cache_updated,
    rosdep_initialized,
)

DEFAULTS = {
    # Initialise rosdep and keep the login user's rosdep cache fresh.
    "rosdep_enabled": True,
    # Package that provides rosdep when ros-dev-tools did not (ros_dev_tools: false).
    "rosdep_package": "python3-rosdep",
    # URL of rosdep's sources list (20-default.list); None: `rosdep init` fetches the official one.
    "rosdep_sources_list_url": None,
    # URL of the rosdistro index (ROSDISTRO_INDEX_URL); None: rosdep's built-in default.
    "rosdistro_index_url": None,
    # Seconds before the login user's rosdep cache counts as stale and is updated again.
    "rosdep_update_max_age": 7 * 24 * 3600,
}


@functools.lru_cache(maxsize=None)
def fetched_text(url: str) -> str:
    """The text at `url`, fetched once per run however many hosts need it."""
    try:
        with urllib.request.urlopen(url, timeout=60) as response:
            return response.read().decode()
    except (OSError, UnicodeDecodeError) as error:
        raise DeployError(f"cannot fetch rosdep_sources_list_url {url}: {error}") from None


@deploy("rosdep is initialised and the login user's rosdep cache is fresh", data_defaults=DEFAULTS)
def rosdep():
    """Install rosdep if missing, initialise it, update the login user's cache when stale.

    Reads host.data: rosdep_enabled, rosdep_package, rosdep_sources_list_url,
    rosdistro_index_url, rosdep_update_max_age, login_user, apt_lock_timeout.
    """
    if not should_run("rosdep_enabled"):
        return
    user, home = login_user(), login_home()
    index_url = setting("rosdistro_index_url")
    sources_list_url = setting("rosdep_sources_list_url")

    command_installed(
        name="Ensure rosdep is installed",
        command="rosdep",
        package=setting("rosdep_package"),
        lock_timeout=setting("apt_lock_timeout"),
    )
    if sources_list_url:
        if not str(sources_list_url).startswith(("http://", "https://", "file://")):
            raise DeployError(f"{where()}: rosdep_sources_list_url {sources_list_url!r} is not a URL")
        sources = files.put(
            name=f"Ensure rosdep's sources list comes from {sources_list_url}",
            src=StringIO(fetched_text(sources_list_url)),
            dest=ROSDEP_SOURCES_LIST,
            mode="644",
        )
    else:
        sources = rosdep_initialized(name="Ensure rosdep is initialised (rosdep init)")

    as_login_user = {"_sudo": True, "_sudo_user": user}  # never root: rosdep refuses sudo
    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache follows the changed sources",
        home=home,
        rosdistro_index_url=index_url,
        _if=any_changed(sources),
        **as_login_user,
    )
    rosdep_cache_updated(
        name=f"Ensure {user}'s rosdep cache is younger than rosdep_update_max_age",
        home=home,
        max_age=setting("rosdep_update_max_age"),
        rosdistro_index_url=index_url,
        **as_login_user,
    )
