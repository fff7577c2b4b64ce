"""The ROS 2 apt source, the official way (the ros2-apt-source package) or from a local mirror.

Package mode: the machine running pyinfra downloads the pinned ros2-apt-source .deb once
(cached by its sha256, checked) and copies exactly those bytes to each host; no Pi fetches
it from GitHub, whose API and downloads rate-limit a classroom behind one address.
Mirror mode: a keyring and a deb822 source with `Signed-By` point at a local mirror.
Snapshot mode: the same, pointing at the ROS archive as it was at one sync
(snapshots.ros.org/<distro>/<snapshot>/ubuntu, signed with a key of its own whose
fingerprint the ROS 2 documentation publishes: a key file with another is refused).
Either way, leftovers of the pre-2025 method (ros2.list, ros-archive-keyring.gpg) are
moved aside: beside ros2.sources they make apt fail ("Conflicting values set for option
Signed-By"), and their key expired on 2025-06-01.
"""

from __future__ import annotations

from io import BytesIO, StringIO
from pathlib import Path

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.operations import apt, files

from deploy.common import apt_sources_written, host_distro, ubuntu_codename, should_run, stop_host, where
from roslab import downloads, openpgp, probe, settings
from roslab.ops.apt import apt_install_options
from roslab.ops.files import files_moved_aside, files_moved_aside_reads
from roslab.quoting import deb822_value
from roslab.ros import distro as distros
from roslab.ros import snapshots
from roslab.templating import render
from roslab.host_settings import host_settings

DEFAULTS = settings.defaults("ros_apt_source")

KEYRING = "/usr/share/keyrings/ros2-archive-keyring.gpg"
SOURCES = "/etc/apt/sources.list.d/ros2.sources"
PACKAGE = "ros2-apt-source"
HOST_DEB_DIR = "/var/cache/roslab"
BACKUP_DIR = "/var/backups/roslab"
# The manual method's files (ROS 2 docs before 2025, and their older ros2-latest name).
OLD_METHOD_FILES = [
    "/etc/apt/sources.list.d/ros2.list",
    "/etc/apt/sources.list.d/ros2-latest.list",
    "/usr/share/keyrings/ros-archive-keyring.gpg",
]


def old_method_moved_aside():
    """Move the pre-2025 method's files aside, planned once per host: the result of the
    operation, whichever deploy asks first.

    apt_ready asks before its `apt-get update`, which they would fail (an expired key,
    "Conflicting values set for option Signed-By"); ros_apt_source asks again when
    apt_ready is switched off.
    """
    planned = host.data.get("_roslab_old_ros_method_moved")
    if planned is None:
        planned = files_moved_aside(
            name="Ensure the old ROS 2 apt source files are gone (kept in /var/backups/roslab)",
            paths=OLD_METHOD_FILES,
            backup_dir=BACKUP_DIR,
        )
        host.data._roslab_old_ros_method_moved = planned
    return planned


def deb_name(version: str, codename: str) -> str:
    return f"{PACKAGE}_{version}.{codename}_all.deb"


def _package_mode(codename: str) -> list | None:
    typed = host_settings(host)
    version = typed.ros_apt_source_version
    pins = typed.ros_apt_source_sha256
    if codename not in pins:
        stop_host(f"{where()}: ros_apt_source_sha256 has no sha256 for Ubuntu {codename} "
                  f"(ros2-apt-source {version}); nothing was changed on it")
        return None
    url = typed.ros_apt_source_url.format(version=version, codename=codename)
    name = deb_name(version, codename)
    try:
        deb = downloads.pinned(url, pins[codename], Path(typed.ros_apt_source_cache_dir), name,
                               "ros_apt_source_sha256", offline=typed.offline)
    except downloads.DownloadError as error:
        stop_host(f"{where()}: ros2-apt-source: {error}; nothing was changed on it")
        return None

    mirror_leftovers = files_moved_aside(
        name="Ensure no mirror-mode ROS 2 source is left (kept in /var/backups/roslab)",
        paths=[SOURCES],
        backup_dir=BACKUP_DIR,
        only_regular_files=True,  # the package's ros2.sources is a symlink
    )
    host_deb = f"{HOST_DEB_DIR}/{name}"
    copied = files.put(
        name=f"Ensure {name} is on the host",
        src=BytesIO(deb),  # the very bytes whose sha256 was checked above
        dest=host_deb,
        mode="644",
    )
    installed = apt.deb(name=f"Ensure ros2-apt-source {version} is installed", src=host_deb)
    return [mirror_leftovers, copied, installed]


def _mode_lacks(mode: str, **needed) -> bool:
    """Stop this host when a setting its ROS source mode needs is not set (True then)."""
    for field, value in needed.items():
        if not value:
            stop_host(f"{where()}: ros_apt_source_mode is '{mode}' but {field} is not set; nothing was changed on it")
            return True
    return False


def _mirror_mode(codename: str) -> list | None:
    typed = host_settings(host)
    if _mode_lacks("mirror", ros_apt_mirror_url=typed.ros_apt_mirror_url,
                   ros_apt_mirror_key_file=typed.ros_apt_mirror_key_file):
        return None
    return _signed_source(str(typed.ros_apt_mirror_url), str(typed.ros_apt_mirror_key_file),
                          "ros_apt_mirror_key_file", codename, "the mirror")


def _snapshot_mode(codename: str) -> list | None:
    typed = host_settings(host)
    if _mode_lacks("snapshot", ros_apt_snapshot=typed.ros_apt_snapshot,
                   ros_apt_snapshot_key_file=typed.ros_apt_snapshot_key_file):
        return None
    distro = host_distro()
    if not distros.record(distro).lts:
        stop_host(f"{where()}: ros_apt_source_mode is 'snapshot' but ROS {distro} is not an LTS distro: "
                  "snapshots.ros.org keeps LTS distros only; nothing was changed on it")
        return None
    server, snapshot = typed.ros_apt_snapshot_url, str(typed.ros_apt_snapshot)
    return _signed_source(snapshots.snapshot_url(server, distro, snapshot), str(typed.ros_apt_snapshot_key_file),
                          "ros_apt_snapshot_key_file", codename, f"the ROS {distro} snapshot {snapshot}",
                          key_problem=lambda key: snapshots.key_problem(server, key))


def _signed_source(url: str, key_file: str, key_field: str, codename: str, what: str,
                   key_problem=None) -> list | None:
    """The ROS 2 apt source at `url`, signed by the key in `key_file`: the keyring and a deb822
    source with Signed-By, and no ros2-apt-source package (whose source it replaces)."""
    typed = host_settings(host)
    try:
        key = openpgp.dearmored(Path(key_file).read_bytes())
    except (OSError, ValueError) as error:
        stop_host(f"{where()}: {key_field} {key_file}: {error}; nothing was changed on it")
        return None
    problem = key_problem(key) if key_problem else None
    if problem:
        stop_host(f"{where()}: {key_field} {key_file} {problem}; nothing was changed on it")
        return None

    purged = apt.packages(
        name=f"Ensure the ros2-apt-source package is not installed ({what} replaces it)",
        packages=[PACKAGE],
        present=False,
        purge=True,
        extra_uninstall_args=apt_install_options(typed.apt_lock_timeout),
    )
    keyring = files.put(
        name=f"Ensure {what}'s signing key is in the ROS 2 keyring",
        src=BytesIO(key),
        dest=KEYRING,
        mode="644",
    )
    # deb822: a value holding a newline would add a field of its own (`Trusted: yes`).
    text = render(
        "ros2.sources.j2",
        mirror_url=deb822_value(url),
        codename=deb822_value(codename),
        keyring=deb822_value(KEYRING),
    )
    source = files.put(
        name=f"Ensure the ROS 2 apt source points at {what}",
        src=StringIO(text),
        dest=SOURCES,
        mode="644",
    )
    return [purged, keyring, source]


@deploy("The ROS 2 apt source is configured", data_defaults=DEFAULTS)
def ros_apt_source():
    """Install the ROS 2 apt source and move the old method's leftovers aside.

    Reads host_settings(host): ros_apt_source_enabled, ros_apt_source_mode, ros_apt_source_version,
    ros_apt_source_sha256, ros_apt_source_url, ros_apt_source_cache_dir,
    ros_apt_mirror_url, ros_apt_mirror_key_file, ros_apt_snapshot, ros_apt_snapshot_url,
    ros_apt_snapshot_key_file, apt_lock_timeout, offline (the .deb only
    from the controller's cache).
    """
    if not should_run("ros_apt_source_enabled"):
        return
    codename = ubuntu_codename()

    # First, as apt refuses to work beside them (the package mode's apt-get reads the
    # sources); apt_ready, when it runs, did it already.
    moved_here = host.data.get("_roslab_old_ros_method_moved") is None
    old_method = old_method_moved_aside()
    # A file the controller cannot get stops this host here: pyinfra then runs none of its
    # operations, so nothing changes on it.
    mode = host_settings(host).ros_apt_source_mode
    if mode == "mirror":
        changes = _mirror_mode(codename)
    elif mode == "snapshot":
        changes = _snapshot_mode(codename)
    else:
        changes = _package_mode(codename)
    if changes is None:
        return
    # The one `apt-get update` follows every source (deploy.apt_ready.apt_lists).
    apt_sources_written(*([old_method] if moved_here else []), *changes)


@probe.reader
def ros_apt_source_reads() -> list:
    """What ros_apt_source's operations read on a host that needs no change."""
    typed = host_settings(host)
    if not should_run("ros_apt_source_enabled"):
        return []
    reads = files_moved_aside_reads(OLD_METHOD_FILES)
    if typed.ros_apt_source_mode in ("mirror", "snapshot"):
        return [*reads, *probe.packages_reads(), *probe.put_reads(KEYRING), *probe.put_reads(SOURCES)]
    codename = ubuntu_codename()
    host_deb = f"{HOST_DEB_DIR}/{deb_name(typed.ros_apt_source_version, codename)}"
    return [*reads, *files_moved_aside_reads([SOURCES]), *probe.put_reads(host_deb),
            *probe.deb_reads(host_deb)]
