"""The host's source repositories built in the login user's underlay workspace.

The repositories of the host's .repos files (its robot profile's `sources`, the roster's
`workspace_sources`: host data `roslab_sources`, read and checked by the roster loader) are
fetched by the controller, once per class and pinned (roslab/sources/fetch.py), and copied
here as archives: a Pi never clones. `rosdep install` and `colcon build` run only when the
set of archives changed; a failed build fails this host with the package and its first error
line and leaves the last good install in use (roslab/sources/underlay.py). The student's workspace
(deploy/workspace.py), the ~/.bashrc block (deploy/shell_env.py) and the nodes' unit source the
underlay's install before the workspace's own.
"""

from __future__ import annotations

import posixpath
import threading
from dataclasses import dataclass
from pathlib import Path

from pyinfra import host, logger
from pyinfra.api import deploy
from pyinfra.facts.server import Arch

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
from roslab import class_lock, class_lock_auto, probe, settings
from roslab.sources import fetch as source_fetch
from roslab.sources import groups as underlay_groups
from roslab.sources import ship as underlay_ship
from roslab.sources import underlay as underlay_ops
from roslab.ros import workspace as ws_ops
from roslab.ops.memory import MemoryTotal
from roslab.host_settings import HostSettings, host_settings, peer_settings

DEFAULTS = settings.defaults("sources")
# The controller's warnings about the class's sources, each said once per run (not per host).
_said_lock = threading.Lock()
_said: set[str] = set()


def say_once(note: str) -> None:
    with _said_lock:
        if note in _said:
            return
        _said.add(note)
    logger.warning(f"roslab: sources: {note}")


def class_pins() -> frozenset:
    """Every (url, version) the roster's hosts build, this run's --limit or not: a changed set
    is what makes the controller check the class's tags against upstream again."""
    pins: set[tuple[str, str]] = set()
    for each in host.state.inventory:
        typed = peer_settings(each)
        if typed is not None and typed.sources_enabled:
            pins.update((repo["url"], repo["version"]) for repo in typed.roslab_sources or [])
    return frozenset(pins)


def repositories() -> list[dict]:
    """The host's repositories (the roster loader's `roslab_sources`), none when switched off."""
    typed = host_settings(host)
    if not typed.sources_enabled:
        return []
    return list(typed.roslab_sources or [])


def underlay_dir(home: str) -> str:
    return ws_ops.workspace_path(home, host_settings(host).sources_underlay_dir)


def underlay_setup(home: str) -> str | None:
    """The underlay's setup.bash the student's workspace sources first, or None (no sources)."""
    if not repositories():
        return None
    return posixpath.join(underlay_dir(home), "install", "setup.bash")


def underlay_identity() -> str:
    """What the underlay is built from, as the roster says it (for the workspace's build stamp:
    a changed pin rebuilds the overlay too). A moved tag fails the host before any build."""
    return "\n".join(f"{repo['path']} {repo['url']} {repo['version']}" for repo in repositories())


@dataclass(frozen=True)
class UnderlayInputs:
    """What this host's underlay is built from and where, read before any change."""

    directory: str
    distro: str
    digests: dict[str, str]  # {repository path: its archive's sha256}
    colcon_args: list[str]
    cmake_args: dict[str, list[str]]  # the profile's, per package
    build_dependencies: dict[str, list[str]]  # the profile's build-order edges, per package
    stamp: str  # the build stamp (roslab.sources.underlay.build_stamp)
    digest: str  # the group's input digest (roslab.sources.groups.input_digest)
    machine: str  # the host's architecture
    holds: bool  # the host holds this build already


@deploy("The host's source repositories are built in the login user's underlay workspace",
        data_defaults=DEFAULTS)
def sources():
    """Copy the host's pinned repositories into the underlay, install their dependencies, build it.

    One host of the group that needs the same underlay builds it; the others receive its
    install tree from the controller (roslab/sources/groups.py, roslab/sources/ship.py).

    Reads host_settings(host): sources_enabled, roslab_sources, sources_underlay_dir, sources_cache_dir,
    source_url_rewrites, sources_fetch_timeout, sources_rosdep_install, offline,
    workspace_colcon_args, roslab_profile (cmake_args, build_dependencies,
    skip_packages, underlay_build_memory_mb, name), underlay_builder, login_user, ssh_user,
    ros_distro; of every host in the run with the same underlay inputs: the same, and its
    architecture and memory (facts) when this host needs a build.

    One step per concern, in this order: the repositories fetched by the controller
    (`fetched_sources`), the underlay's inputs (`underlay_inputs`) and builder
    (`underlay_builder`), the archives and dependencies on the host (`underlay_filled`), then
    the build (`underlay_built`) or the builder's install tree (`underlay_received`).
    """
    if not should_run("sources_enabled"):
        return
    wanted = repositories()
    home = existing_login_home()
    if not wanted:
        underlay_emptied(home)
        return
    user = login_user()
    home = login_home()
    if home is None:  # the login user does not exist: login_home() stopped this host
        return
    typed = host_settings(host)
    cache_dir = Path(typed.sources_cache_dir).expanduser()
    fetched = fetched_sources(wanted, typed, cache_dir)
    if fetched is None:  # this host was stopped, saying why
        return
    underlay = underlay_inputs(typed, home, fetched)
    underlay_ship.note_wanted(host.state, underlay.digest)
    builder = underlay_builder(underlay.digest, underlay.machine, cache_dir, underlay.holds, underlay.directory,
                               underlay.stamp)
    if builder is None:
        return
    underlay_filled(underlay, fetched, user=user, home=home)
    if underlay.holds or builder == host.name:
        underlay_built(underlay, user=user)
    # after the build in pyinfra's order: the builder has built when its group receives
    if not underlay.holds and builder != host.name:
        underlay_received(underlay, user=user, cache_dir=cache_dir, builder=builder)


def underlay_emptied(home: str | None) -> None:
    """Repositories roslab put there before are removed (a host whose profile lost its sources);
    no-op where none were recorded or the login user does not exist."""
    if home is not None and host.get_fact(underlay_ops.UnderlaySources,
                                          underlay_dir=underlay_dir(home))["recorded"]:
        underlay_ops.sources(name="Ensure the underlay holds no repositories (none in the .repos files)",
                             underlay_dir=underlay_dir(home), repositories=[], user=login_user())


def fetched_sources(wanted: list[dict], typed: HostSettings, cache_dir: Path) -> list[source_fetch.Fetched] | None:
    """The `wanted` repositories fetched by the controller into `cache_dir` (pinned, once per
    class) and packed for this host: None, with this host stopped, when one cannot be."""
    profile = typed.roslab_profile
    timeout = typed.sources_fetch_timeout
    fetched: list[source_fetch.Fetched] = []
    pins = class_pins()
    # the class lock's commits for the host's group: a tag that moved away from one stops the host
    group = class_lock.host_group(typed.roslab_roster_path, host_distro(), host.get_fact(Arch))
    locked = group.sources if group is not None else {}
    for repo in wanted:
        try:
            item = source_fetch.fetched(
                repo, cache_dir, rewrites=typed.source_url_rewrites, offline=typed.offline, timeout=timeout, pins=pins,
                locked=locked.get(class_lock.source_key(repo["url"], repo["version"])))
            # the packages the profile does not build never reach the host (a ROS 1 leftover)
            fetched.append(source_fetch.for_host(item, cache_dir, profile.skip_packages if profile else (), timeout))
        except source_fetch.SourceError as error:
            stop_host(f"{where()}: sources: {error}; nothing was changed on it")
            return None
        for note in fetched[-1].notes:
            say_once(note)
    if typed.class_lock_auto and typed.roslab_roster_path and group is None:
        # what the run's lock takes for the group, if this host converges (roslab.class_lock_auto)
        class_lock_auto.note_sources(typed.roslab_roster_path, host.name, {
            class_lock.source_key(item.url, item.version): item.commit for item in fetched})
    return fetched


def underlay_inputs(typed: HostSettings, home: str, fetched: list[source_fetch.Fetched]) -> UnderlayInputs:
    """The underlay's directory, build stamp and group digest for the `fetched` archives, and
    whether the host holds that build already (its architecture and stamps are read)."""
    profile = typed.roslab_profile
    distro = host_distro()
    directory = underlay_dir(home)
    digests = {item.path: item.sha256 for item in fetched}
    colcon_args = list(typed.workspace_colcon_args)
    # the profile's CMake settings per package (the micro-ROS agent's superbuild off, say) and
    # the build-order edges the packages' manifests forget
    cmake_args = profile.cmake_args if profile else {}
    build_dependencies = profile.build_dependencies if profile else {}
    stamp = underlay_ops.build_stamp(digests, distro, colcon_args, cmake_args, build_dependencies)
    machine = host.get_fact(Arch) or "unknown"
    digest = underlay_groups.input_digest(stamp, machine, directory)
    stamps = host.get_fact(ws_ops.WorkspaceStamps, workspace_dir=directory)
    holds = bool(stamps.get("build") == stamp and stamps.get("installed"))
    return UnderlayInputs(directory=directory, distro=distro, digests=digests, colcon_args=colcon_args,
                          cmake_args=cmake_args, build_dependencies=build_dependencies, stamp=stamp,
                          digest=digest, machine=machine, holds=holds)


def underlay_filled(underlay: UnderlayInputs, fetched: list[source_fetch.Fetched], *, user: str,
                    home: str) -> None:
    """The underlay's src/ holds the pinned repositories, and (sources_rosdep_install) their
    system dependencies are installed: on a host that receives its build too, the run
    dependencies the shipped tree needs."""
    directory = underlay.directory
    underlay_ops.sources(
        name=f"Ensure {directory}/src holds the pinned repositories ({', '.join(sorted(underlay.digests))})",
        underlay_dir=directory,
        repositories=[{"path": item.path, "sha256": item.sha256, "archive": item.archive} for item in fetched],
        user=user,
    )
    if host_settings(host).sources_rosdep_install:
        ws_ops.dependencies(
            name="Ensure the underlay's system dependencies are installed (rosdep)",
            workspace_dir=directory,
            packages=sorted(underlay.digests),
            distro=underlay.distro,
            packages_hash=underlay.stamp,
            user=user,
            ros_home=posixpath.join(home, ".ros"),
        )


def underlay_built(underlay: UnderlayInputs, *, user: str) -> None:
    """The underlay is built here from its sources (colcon, as the login user); the build is
    noted for the hosts of its group that receive it (roslab/sources/ship.py)."""
    build = underlay_ops.built(
        name=f"Ensure {underlay.directory} is built from these sources (colcon)",
        underlay_dir=underlay.directory,
        distro=underlay.distro,
        colcon_args=underlay.colcon_args,
        stamp=underlay.stamp,
        cmake_args=underlay.cmake_args,
        build_dependencies=underlay.build_dependencies,
        slot=underlay_ops.slot_name(underlay.digest),
        digest=underlay.digest,
        **as_login_user(user),
    )
    underlay_ship.note_build(host.state, underlay.digest, host.name, build,
                             underlay_groups.cache_group(underlay.digests, underlay.distro, underlay.machine,
                                                         underlay.directory))


def underlay_received(underlay: UnderlayInputs, *, user: str, cache_dir: Path, builder: str) -> None:
    """The underlay holds the install tree `builder` built, shipped through the controller's `cache_dir`."""
    underlay_ship.received(
        name=f"Ensure {underlay.directory} holds the underlay built on {builder} "
             f"({underlay_groups.short(underlay.digest)})",
        underlay_dir=underlay.directory,
        digest=underlay.digest,
        stamp=underlay.stamp,
        user=user,
        cache_dir=str(cache_dir),
        builder=builder,
    )


def underlay_builder(digest: str, machine: str, cache_dir: Path, holds: bool, directory: str,
                     stamp: str) -> str | None:
    """Which host builds this host's underlay: this host when it holds the build already, the
    builder the controller's cache records when it has the build, else the group's builder
    (roslab.sources.groups.choose_builder): a host of the group that holds the same build
    (`stamp` in `directory`) before any that would compile it. None when there is none: the
    host is stopped."""
    if holds:
        return host.name
    kept = underlay_ship.cached(cache_dir, digest)
    if kept is not None:
        return kept["builder"]
    mine = underlay_groups.roster_inputs(host_settings(host))
    candidates = [(peer, peer_settings(peer)) for peer in host.state.inventory if peer in host.state.active_hosts]
    typed_peers = [(peer, typed) for peer, typed in candidates
                   if typed is not None and underlay_groups.roster_inputs(typed) == mine]
    peers = [peer for peer, _ in typed_peers]
    named = next((typed.underlay_builder for _, typed in typed_peers if typed.underlay_builder), None)
    members = []
    for peer in peers:
        # the architecture and memory of the others: read only when this host needs a build
        peer_machine = machine if peer.name == host.name else (peer.get_fact(Arch) or "unknown")
        if peer_machine == machine:
            memory = host.get_fact(MemoryTotal) if peer.name == host.name else peer.get_fact(MemoryTotal)
            # a re-imaged builder with the controller's cache gone: a teammate's tree is shipped, not rebuilt
            peer_stamps = {} if peer.name == host.name else peer.get_fact(ws_ops.WorkspaceStamps,
                                                                           workspace_dir=directory)
            peer_holds = bool(peer_stamps.get("build") == stamp and peer_stamps.get("installed"))
            members.append(underlay_groups.Member(peer.name, memory, holds=peer_holds))
    profile = host_settings(host).roslab_profile
    choice = underlay_groups.choose_builder(members, named, profile.underlay_build_memory_mb if profile else None,
                                            profile.name if profile else "")
    if choice.builder is None:
        stop_host(f"{where()}: sources: underlay: {choice.problem}; nothing was changed on it")
    return choice.builder


@probe.reader
def sources_reads() -> list:
    """What the underlay's operations read on a host that needs no change."""
    home = existing_login_home() if should_run("sources_enabled") else None
    if home is None:
        return []
    directory = underlay_dir(home)
    reads = [probe.read(underlay_ops.UnderlaySources, underlay_dir=directory)]
    if repositories():
        reads.append(probe.read(ws_ops.WorkspaceStamps, workspace_dir=directory))
        reads.append(probe.read(Arch))
    return reads
