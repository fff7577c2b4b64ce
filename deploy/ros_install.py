"""ROS 2 installed: the distro's desktop (main hosts) or ros-base (robots), dev tools, extras."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.server import Arch

from deploy.common import host_codename, host_distro, should_run, stop_host, where
from roslab import class_debs, class_lock, probe, settings
from roslab.ops import class_debs as debs_ops
from roslab.ops import class_lock as lock_ops
from roslab.ros.discovery import middleware_package
from roslab.ros.distro import default_distro
from roslab.ops.apt import packages_installed
from roslab.quoting import apt_arguments
from roslab.host_settings import HostSettings, host_settings

DEFAULTS = settings.defaults("ros_install")


def ros_packages(distro: str, role: str | None, settings: HostSettings) -> list[str]:
    """The apt packages a host of this role gets, from its typed settings: what this step
    declares it installs (the class cache, deploy/apt_cache.py, fills itself from it).

    The class's middleware (ros_middleware) and the robot profile's packages for the host's side
    (roslab_profile, resolved from the roster) come after the variant, the dev tools and
    ros_extra_packages.

    The variants and extra package names were checked by the schema (roslab.settings);
    `apt_arguments` refuses anything apt-get would read as an option all the same.
    """
    # The roster loader resolved ros_variant (host's, deprecated role key, profile side); a
    # hand-made inventory without it gets the role's default.
    variant = settings.ros_variant or (settings.ros_variant_robot if role == "robot" else settings.ros_variant_main)
    packages = [f"ros-{distro}-{variant}"]
    if settings.ros_dev_tools:
        packages.append("ros-dev-tools")
    packages += [name.replace("{distro}", distro) for name in settings.ros_extra_packages or []]
    middleware = middleware_package(settings.ros_middleware, distro)  # Fast DDS comes with every variant
    if middleware and middleware not in packages:
        packages.append(middleware)
    profile = settings.roslab_profile
    if profile is not None and profile.distro == distro:  # resolved for the distro the roster expects, which this host runs
        packages += [name for name in profile.packages or [] if name not in packages]
    return apt_arguments(packages)


@probe.installs
def ros_install_packages(settings: HostSettings, codename: str | None, python_sdist: bool = False) -> list[str]:
    """What this step installs on a host of this codename (roslab.probe.installs)."""
    if not settings.ros_install_enabled:
        return []
    return ros_packages(settings.ros_distro or default_distro(codename), settings.roslab_role, settings)


@deploy("ROS 2 is installed for the host's distro and role", data_defaults=DEFAULTS)
def ros_install():
    """Install ros-<distro>-<variant>, ros-dev-tools and the classroom's extra packages.

    Reads host_settings(host): ros_install_enabled, ros_distro, ros_variant, ros_variant_main,
    ros_variant_robot, ros_dev_tools, ros_extra_packages, ros_middleware, roslab_role, roslab_profile,
    apt_lock_timeout, class_lock_debs_dir.
    (ubuntu_release is checked by deploy.common.supported_host.)
    """
    typed = host_settings(host)
    if not should_run("ros_install_enabled"):
        return
    distro = host_distro()
    packages = ros_install_packages(typed, host_codename())  # as declared for the class cache
    # The title names the first two packages and counts the rest: a robot's list (ten packages
    # for a TurtleBot3) would make a 290-character step name; the no-op line lists them all.
    shown = ", ".join(packages[:2]) + (f" and {len(packages) - 2} more" if len(packages) > 2 else "")
    specs = locked_versions_met(typed, distro, packages)
    if specs is None:
        return
    packages_installed(
        name=f"Ensure ROS 2 {distro} is installed ({shown})",
        packages=specs,
        lock_timeout=typed.apt_lock_timeout,
    )


def locked_versions_met(typed: HostSettings, distro: str, packages: list[str]) -> list[str] | None:
    """Pin apt to the class lock's versions of this host's group (classroom.lock beside the
    roster), serve it the group's kept .debs its sources dropped (class_lock_debs_dir), and stop
    the host before anything is installed if a package it lacks is locked at a version its apt
    sources list without it and the controller did not keep. The packages to install (a locked
    one as `name=version`, so that apt itself refuses a version no source has), or None: stopped.

    Without a lock, or without this group in it, nothing is pinned (the group's first converge).
    """
    roster_path, lock_timeout = typed.roslab_roster_path, typed.apt_lock_timeout
    if class_lock.lock_beside(roster_path) is None:  # no lock: no architecture read either
        return packages
    machine = host.get_fact(Arch)
    group = class_lock.host_group(roster_path, distro, machine)
    if group is None:
        return packages
    installed = host.get_fact(DebPackages) or {}
    # what this run would install or move: each must be at its locked version in some source
    needed = [name for name in packages if name in group.packages and name not in installed]
    needed += [name for name in lock_ops.off_lock(group, installed) if name not in needed]
    # read from fresh lists (apt-get update first): after `roslab lock --update` the host's own
    # lists may predate the versions it is to move to; read only when there is something to do.
    # A package the lists do not know (a fresh host: its ROS source comes with this run) is
    # judged by apt at install time, asked for at its locked version.
    available = (host.get_fact(lock_ops.AptVersionsNow, packages=needed) or {}) if needed else {}
    # the controller's kept .debs of the group: read only when there is something to install or move
    key, root, kept = class_lock.host_group_key(distro, machine) or "", None, {}
    if needed and typed.class_lock_debs_dir:
        root = class_debs.class_root(typed.class_lock_debs_dir, str(roster_path))
        kept = class_debs.read_kept(root, key)
    problems = lock_ops.unmet(group, [name for name in needed if available.get(name)
                                      and (name, group.packages[name]) not in kept], available)
    if problems:
        stop_host(f"{where()}: {problems[0]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
        return None
    lock_ops.locked_versions_pinned(
        name=f"Ensure apt installs the class lock's versions ({len(group.packages)} packages)", group=group)
    if kept:
        debs_ops.dropped_versions_served(
            name="Ensure apt can install the locked versions its sources dropped (the class's kept .debs)",
            root=str(root), key=key, date=group.taken, lock_timeout=lock_timeout)
    lock_ops.packages_at_locked_versions(
        name="Ensure the installed packages are at the class lock's versions", group=group, lock_timeout=lock_timeout)
    return [f"{name}={group.packages[name]}" if name in group.packages else name for name in packages]


@probe.reader
def ros_install_reads() -> list:
    """What ros_install's operation reads on a host that needs no change (with a class lock: the
    architecture and the pin file, in the same one read)."""
    if not should_run("ros_install_enabled"):
        return []
    reads = probe.packages_reads()
    if class_lock.lock_beside(host_settings(host).roslab_roster_path) is not None:
        reads += [probe.read(Arch), *lock_ops.locked_versions_pinned_reads()]
    return reads
