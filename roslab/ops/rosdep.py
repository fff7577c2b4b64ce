"""rosdep: its system sources list and a user's cache (roslab.ops)."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import QuoteString, StringCommand, operation
from pyinfra.facts.files import File

from roslab.ops.files import FileAge
from roslab.probe import read


ROSDEP_SOURCES_LIST = "/etc/ros/rosdep/sources.list.d/20-default.list"
# rosdep rewrites this index on every `rosdep update`: its age is the cache's age.
ROSDEP_CACHE_INDEX = ".ros/rosdep/sources.cache/index"


@operation()
def rosdep_initialized():
    """
    Ensure rosdep's system sources list exists, running ``rosdep init`` only if it is missing.
    """
    if host.get_fact(File, path=ROSDEP_SOURCES_LIST):
        host.noop(f"{ROSDEP_SOURCES_LIST} already exists")
        return
    yield "rosdep init"


def rosdep_initialized_reads() -> list:
    """What `rosdep_initialized` reads (roslab.probe)."""
    return [read(File, path=ROSDEP_SOURCES_LIST)]


@operation(is_idempotent=False)
def rosdep_cache_updated(home: str, max_age: int | None = None, rosdistro_index_url=None):
    """
    Ensure the user's rosdep cache is fresh (run with ``_sudo_user`` = that user, never root).

    + home: the user's home directory (where ``~/.ros/rosdep`` lives)
    + max_age: update only when the cache is older than this many seconds, or missing;
      ``None`` always updates (gate it with ``_if=`` on a sources change)
    + rosdistro_index_url: where rosdep reads the rosdistro index (``None``: rosdep's own)
    """
    if max_age is not None:
        age = host.get_fact(FileAge, path=f"{home}/{ROSDEP_CACHE_INDEX}")
        if age is not None and age < max_age:
            host.noop(f"rosdep cache is {age} s old (max age {max_age} s)")
            return
    if rosdistro_index_url:
        yield StringCommand(
            "env", QuoteString(f"ROSDISTRO_INDEX_URL={rosdistro_index_url}"), "rosdep update"
        )
    else:
        yield "rosdep update"


def rosdep_cache_updated_reads(home: str) -> list:
    """What `rosdep_cache_updated` reads (roslab.probe)."""
    return [read(FileAge, path=f"{home}/{ROSDEP_CACHE_INDEX}")]
