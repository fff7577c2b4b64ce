"""apt ready to install: the dpkg lock free, an interrupted install finished, universe and
-updates/-backports enabled (`apt_ready`), then, once every source is written (the ROS 2
source by deploy.ros_apt_source too), the lists fresh with one `apt-get update` (`apt_lists`)."""

from __future__ import annotations

from typing import Any

from pyinfra import host, logger
from pyinfra.api import deploy

from deploy.common import (
    apt_sources_written,
    ubuntu_codename,
    host_is_active,
    should_run,
    stop_host,
    where,
)
from deploy.apt_cache import fills_the_class_cache, updates_through_the_class_cache
from deploy.ros_apt_source import OLD_METHOD_FILES, old_method_moved_aside
from roslab.host_settings import host_settings
from roslab import probe, settings
from roslab.ops.apt import (
    AptProblem,
    apt_lists_updated,
    apt_lists_updated_reads,
    dpkg_interrupted_install_finished,
    ubuntu_apt_sources,
    ubuntu_apt_sources_reads,
)
from roslab.ops.files import files_moved_aside_reads

DEFAULTS = settings.defaults("apt_ready")


@deploy(
    "apt is ready: the dpkg lock is free, the sources complete and the lists fresh",
    data_defaults=DEFAULTS,
)
def apt_ready():
    """Wait for apt, finish an interrupted install, enable universe and the extra suites.

    First it waits for cloud-init to finish a freshly seeded Pi's first boot (bounded by
    apt_lock_timeout, in the same probe command: free on a host where cloud-init is done).

    Reads host_settings(host): apt_ready_enabled, apt_lock_timeout, apt_enable_universe,
    apt_extra_suites, ros_apt_source_enabled (the old ROS 2 source files are moved aside
    here, before the update they would fail). The update itself is `apt_lists`, after
    every source is written.
    """
    typed = host_settings(host)
    if not should_run("apt_ready_enabled"):
        return
    if not dpkg_usable(typed.apt_lock_timeout):  # this host was stopped, saying why
        return

    sources = [ubuntu_apt_sources(
        name="Ensure the Ubuntu apt sources enable universe and the -updates/-backports suites",
        codename=ubuntu_codename(),
        components=["universe"] if typed.apt_enable_universe else [],
        suites=list(typed.apt_extra_suites),
    )]
    if typed.ros_apt_source_enabled:
        # The pre-2025 ROS source fails every `apt-get update` (expired key, conflicting
        # Signed-By): gone before the update in apt_lists, not after it.
        sources.append(old_method_moved_aside())
    apt_sources_written(*sources)


def dpkg_usable(lock_timeout: int) -> bool:
    """cloud-init's first boot done, the dpkg lock free (waited for up to `lock_timeout` s) and
    an install dpkg was interrupted in finished; False, with this host stopped, when apt
    cannot be used. Waits and repairs are said in one line for the host."""
    problem = host.get_fact(AptProblem, lock_timeout=lock_timeout)
    cloud_init = (problem or {}).get("cloud_init")
    if cloud_init:
        problem = {key: value for key, value in problem.items() if key != "cloud_init"}
        if not problem.get("message") and not problem.get("interrupted") and not problem.get("waited"):
            problem = None
        if not cloud_init_finished(cloud_init, lock_timeout):
            return False
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
        return False
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
    return True


def cloud_init_finished(cloud_init: dict, lock_timeout: int) -> bool:
    """cloud-init's first boot is over (AptProblem's `cloud_init`: status, seconds, output);
    a wait for it or its own errors are said; False, with this host stopped, while it still
    runs after `lock_timeout` s."""
    said = f": {cloud_init['output']}" if cloud_init["output"] else ""
    if cloud_init["status"] == 124:
        stop_host(f"{where()}: cloud-init's first boot is still running after {lock_timeout} s "
                  f"(apt_lock_timeout){said}; run again once it is done (cloud-init status)")
        return False
    if cloud_init["status"] == 0 and cloud_init["seconds"] > 0:
        logger.warning(f"{host.print_prefix}roslab: {where()}: waited {cloud_init['seconds']} s for "
                       f"cloud-init to finish its first boot (cloud-init status --wait){said}")
    elif cloud_init["status"] not in (0, 124):
        # Its own errors are the seed's business; apt can still be used.
        logger.warning(f"{host.print_prefix}roslab: {where()}: cloud-init finished its first boot "
                       f"with errors (exit status {cloud_init['status']}, see cloud-init status "
                       f"--long){said}; carrying on")
    return True


@deploy(
    "The apt lists are fresh: one apt-get update after every source is written",
    data_defaults=DEFAULTS,
)
def apt_lists():
    """Update the apt lists once: when an earlier step changed a source (apt_ready's, the
    ROS 2 source), or when they are older than apt_cache_max_age.

    Runs after every step that writes apt sources (deploy.py) and before any install. With
    a class apt cache, the first host of each release (deploy.apt_cache.fills_the_class_cache)
    updates before the others, one release at a time, and then the others one at a time.
    Reads host_settings(host): apt_ready_enabled, apt_lock_timeout, apt_cache_max_age,
    apt_cache_enabled, apt_cache_host, ubuntu_release, ros_apt_source_enabled (without apt_ready, the lists are updated only after the ROS 2
    source changed).
    """
    typed = host_settings(host)
    ready = typed.apt_ready_enabled
    if not host_is_active() or not (ready or typed.ros_apt_source_enabled):
        return
    arguments: dict[str, Any] = dict(
        lock_timeout=typed.apt_lock_timeout,
        max_age=typed.apt_cache_max_age if ready else None,
        sources=apt_sources_written(),
    )
    if fills_the_class_cache():
        # With a class apt cache, the first host of each release updates first, alone: the
        # cache then holds fresh index files and answers the class's updates from them.
        apt_lists_updated(
            name="Ensure the apt lists are fresh, updated through the class cache before the other hosts",
            _serial=True,
            **arguments,
        )
        return
    if updates_through_the_class_cache():
        # Then the others, one host at a time too. Hosts refreshing the same index through
        # apt-cacher-ng in the same second made it fail one ("Failure to move file ... out of
        # the way ... File exists" in apt-cacher.err), and that host's apt-get update then
        # waited forever for the item it lost; FreshIndexMaxAge did not stop the refreshes.
        # An update answered from the cache takes seconds, so a class of 30 waits a minute or two.
        apt_lists_updated(
            name="Ensure the apt lists are fresh, updated through the class cache one host at a time",
            _serial=True,
            **arguments,
        )
        return
    apt_lists_updated(
        name=("Ensure the apt lists are updated after a source change"
              + (" or apt_cache_max_age" if ready else "")),
        **arguments,
    )


@probe.reader
def apt_reads() -> list:
    """What apt_ready and apt_lists read on a host that needs no change."""
    typed = host_settings(host)
    if not host_is_active():
        return []
    reads = []
    if typed.apt_ready_enabled:
        reads += [probe.read(AptProblem, lock_timeout=typed.apt_lock_timeout),
                  *ubuntu_apt_sources_reads(), *apt_lists_updated_reads()]
    if typed.ros_apt_source_enabled:
        reads += files_moved_aside_reads(OLD_METHOD_FILES)
    return reads
