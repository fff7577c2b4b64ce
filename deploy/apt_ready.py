"""apt ready to install: the dpkg lock free, universe and -updates/-backports enabled, lists fresh."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy

from deploy.common import host_codename, setting, should_run, stop_host, where
from roslab.facts import AptProblem
from roslab.operations import apt_lists_updated, ubuntu_apt_sources

DEFAULTS = {
    # Prepare apt: wait for the dpkg lock, enable universe and the extra suites, refresh the lists.
    "apt_ready_enabled": True,
    # Seconds to wait for the dpkg lock (first-boot unattended-upgrades holds it for minutes).
    "apt_lock_timeout": 600,
    # Enable the universe component (ROS 2 depends on packages there).
    "apt_enable_universe": True,
    # Suites enabled beside the release, as suffixes: noble-updates, noble-backports.
    # Without them ROS 2 on Pi server images fails with unmet dependencies.
    "apt_extra_suites": ["updates", "backports"],
    # Seconds before the apt lists count as stale and `apt-get update` runs again.
    "apt_cache_max_age": 24 * 3600,
}


@deploy(
    "apt is ready: the dpkg lock is free, the sources complete and the lists fresh",
    data_defaults=DEFAULTS,
)
def apt_ready():
    """Wait for apt, enable universe and the extra suites, refresh the lists when needed.

    Reads host.data: apt_ready_enabled, apt_lock_timeout, apt_enable_universe,
    apt_extra_suites, apt_cache_max_age.
    """
    if not should_run("apt_ready_enabled"):
        return
    lock_timeout = host.data.apt_lock_timeout

    problem = host.get_fact(AptProblem, lock_timeout=lock_timeout)
    if problem:
        stop_host(
            f"{where()}: apt is not usable after waiting up to {lock_timeout} s "
            f"(apt_lock_timeout): {problem}"
        )
        return

    sources = ubuntu_apt_sources(
        name="Ensure the Ubuntu apt sources enable universe and the -updates/-backports suites",
        codename=host_codename(),
        components=["universe"] if host.data.apt_enable_universe else [],
        suites=list(host.data.apt_extra_suites),
    )
    apt_lists_updated(
        name="Ensure the apt lists include the changed sources",
        lock_timeout=lock_timeout,
        _if=sources.did_change,
    )
    apt_lists_updated(
        name="Ensure the apt lists are younger than apt_cache_max_age",
        lock_timeout=lock_timeout,
        max_age=setting("apt_cache_max_age"),
    )
