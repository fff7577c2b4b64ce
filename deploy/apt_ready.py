"""apt ready to install: the dpkg lock free, an interrupted install finished, universe and
-updates/-backports enabled, lists fresh."""

from __future__ import annotations

from pyinfra import host, logger
from pyinfra.api import deploy
from pyinfra.operations.util import any_changed

from deploy.common import host_codename, should_run, stop_host, where
from deploy.ros_apt_source import old_method_moved_aside
from roslab import settings
from roslab.facts import AptProblem
from roslab.operations import apt_lists_updated, dpkg_interrupted_install_finished, ubuntu_apt_sources

DEFAULTS = settings.defaults("apt_ready")


@deploy(
    "apt is ready: the dpkg lock is free, the sources complete and the lists fresh",
    data_defaults=DEFAULTS,
)
def apt_ready():
    """Wait for apt, finish an interrupted install, enable universe and the extra suites,
    refresh the lists when needed.

    Reads host.data: apt_ready_enabled, apt_lock_timeout, apt_enable_universe,
    apt_extra_suites, apt_cache_max_age, ros_apt_source_enabled (the old ROS 2 source
    files are moved aside here, before the update they would fail).
    """
    if not should_run("apt_ready_enabled"):
        return
    lock_timeout = host.data.apt_lock_timeout

    problem = host.get_fact(AptProblem, lock_timeout=lock_timeout)
    if problem and problem.get("waited"):
        # Not silent: a first-boot unattended-upgrades can hold the lock for minutes.
        logger.warning(f"{host.print_prefix}roslab: {where()}: waited for the dpkg lock "
                       f"(up to {lock_timeout} s, apt_lock_timeout): {problem['waited'][:200]}")
        problem = None
    if problem and not problem["interrupted"]:
        stop_host(
            f"{where()}: apt is not usable after waiting up to {lock_timeout} s "
            f"(apt_lock_timeout): {problem['message']}"
        )
        return
    if problem:
        # A Pi unplugged (or dpkg killed) mid-install: apt refuses everything until
        # dpkg finishes, so this run does it instead of stopping the host every time.
        logger.warning(
            f"{host.print_prefix}roslab: {where()}: {problem['message']}; "
            "finishing it with dpkg --configure -a and apt-get -f install"
        )
        dpkg_interrupted_install_finished(
            name="Ensure the install dpkg was interrupted in is finished (dpkg --configure -a)",
            lock_timeout=lock_timeout,
        )

    sources = [ubuntu_apt_sources(
        name="Ensure the Ubuntu apt sources enable universe and the -updates/-backports suites",
        codename=host_codename(),
        components=["universe"] if host.data.apt_enable_universe else [],
        suites=list(host.data.apt_extra_suites),
    )]
    if host.data.ros_apt_source_enabled:
        # The pre-2025 ROS source fails every `apt-get update` (expired key, conflicting
        # Signed-By): gone before the update below, not after it.
        sources.append(old_method_moved_aside())
    apt_lists_updated(
        name="Ensure the apt lists include the changed sources",
        lock_timeout=lock_timeout,
        _if=any_changed(*sources),
    )
    apt_lists_updated(
        name="Ensure the apt lists are younger than apt_cache_max_age",
        lock_timeout=lock_timeout,
        max_age=host.data.apt_cache_max_age,
    )
