"""The ROS 2 apt source, the official way (the ros2-apt-source package) or from a local mirror.

Package mode: the machine running pyinfra downloads the pinned ros2-apt-source .deb once
(cached, sha256-checked) and copies it to each host; no Pi fetches it from GitHub, whose
API and downloads rate-limit a classroom behind one address.
Mirror mode: a keyring and a deb822 source with `Signed-By` point at a local mirror.
Either way, leftovers of the pre-2025 method (ros2.list, ros-archive-keyring.gpg) are
moved aside: beside ros2.sources they make apt fail ("Conflicting values set for option
Signed-By"), and their key expired on 2025-06-01.
"""

from __future__ import annotations

import base64
import hashlib
import os
import tempfile
import threading
import urllib.request
from io import BytesIO
from pathlib import Path

from pyinfra import host
from pyinfra.api import DeployError, deploy
from pyinfra.operations import files
from pyinfra.operations.util import any_changed

from deploy.common import controller_path, host_codename, setting, should_run, where
from roslab.operations import (
    apt_lists_updated,
    deb_file_installed,
    deb_purged,
    files_moved_aside,
)

TEMPLATES = Path(__file__).resolve().parent.parent / "templates"

DEFAULTS = {
    # Configure the ROS 2 apt source (and move the old method's files aside).
    "ros_apt_source_enabled": True,
    # "package": install ros2-apt-source (official); "mirror": a local mirror's key and URL.
    "ros_apt_source_mode": "package",
    # The pinned ros2-apt-source release (1.2.0, 2026-04).
    "ros_apt_source_version": "1.2.0",
    # Ubuntu codename -> sha256 of that release's .deb. Copied from public install scripts
    # that pin 1.2.0; not verified from here (GitHub is unreachable): check once online.
    "ros_apt_source_sha256": {
        "noble": "0804d9b13db770eb87019be414cd78378835228ad5fa801fc88758596dd8f7e5",
        "jammy": "767884cf4ed03116b9d64438930a832ed854147ae435279a7924dfdf60f94433",
    },
    # Where the .deb is downloaded from; {version} and {codename} are filled in.
    "ros_apt_source_url": (
        "https://github.com/ros-infrastructure/ros-apt-source/releases/download/"
        "{version}/ros2-apt-source_{version}.{codename}_all.deb"
    ),
    # Download cache on the machine running pyinfra (not on the hosts).
    "ros_apt_source_cache_dir": "~/.cache/roslab/ros-apt-source",
    # Mirror mode: the mirror's URL (serving the ROS 2 archive's dists/ and pool/).
    "ros_apt_mirror_url": None,
    # Mirror mode: path, on the machine running pyinfra, to the mirror's signing key
    # (ASCII-armored or binary).
    "ros_apt_mirror_key_file": None,
}

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

_download_lock = threading.Lock()  # hosts are planned in parallel: download once


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def cached_package(url: str, sha256: str, cache_dir: Path) -> Path:
    """The verified .deb in `cache_dir`, downloaded first if missing.

    A download whose sha256 differs from the pin is discarded and stops the run: every
    host would otherwise trust a package nobody checked.
    """
    path = cache_dir / url.rsplit("/", 1)[-1]
    with _download_lock:
        if path.exists() and sha256_of(path) == sha256:
            return path
        cache_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=cache_dir, suffix=".part", delete=False) as part:
            try:
                with urllib.request.urlopen(url, timeout=60) as response:
                    part.write(response.read())
            except OSError as error:
                os.unlink(part.name)
                raise DeployError(f"cannot download ros2-apt-source from {url}: {error}") from None
        got = sha256_of(Path(part.name))
        if got != sha256:
            os.unlink(part.name)
            raise DeployError(
                f"ros2-apt-source from {url} has sha256 {got}, but ros_apt_source_sha256 "
                f"pins {sha256}: the file was discarded"
            )
        os.replace(part.name, path)
        return path


def dearmored(key: bytes) -> bytes:
    """An OpenPGP key as binary (what apt's Signed-By reads), un-armoring it if needed."""
    text = key.decode("ascii", errors="replace")
    if "-----BEGIN PGP PUBLIC KEY BLOCK-----" not in text:
        return key
    body = text.split("-----BEGIN PGP PUBLIC KEY BLOCK-----", 1)[1]
    body = body.split("-----END PGP PUBLIC KEY BLOCK-----", 1)[0]
    lines = [line.strip() for line in body.strip().splitlines()]
    if "" in lines:  # armor headers ("Version: ...") end at the first blank line
        lines = lines[lines.index("") + 1 :]
    # The "=XXXX" line is the armor's checksum, not key data.
    data = "".join(line for line in lines if line and not line.startswith("="))
    return base64.b64decode(data)


def _package_mode(codename: str) -> list:
    version = host.data.ros_apt_source_version
    pins = host.data.ros_apt_source_sha256 or {}
    if codename not in pins:
        raise DeployError(
            f"{where()}: ros_apt_source_sha256 has no sha256 for Ubuntu {codename} "
            f"(ros2-apt-source {version})"
        )
    url = host.data.ros_apt_source_url.format(version=version, codename=codename)
    cache_dir = Path(os.path.expanduser(host.data.ros_apt_source_cache_dir))
    local_deb = cached_package(url, pins[codename], cache_dir)

    mirror_leftovers = files_moved_aside(
        name="Ensure no mirror-mode ROS 2 source is left (kept in /var/backups/roslab)",
        paths=[SOURCES],
        backup_dir=BACKUP_DIR,
        only_regular_files=True,  # the package's ros2.sources is a symlink
    )
    host_deb = f"{HOST_DEB_DIR}/{local_deb.name}"
    files.put(
        name=f"Ensure {local_deb.name} is on the host",
        src=str(local_deb),
        dest=host_deb,
        mode="644",
    )
    installed = deb_file_installed(
        name=f"Ensure ros2-apt-source {version} is installed", src=host_deb
    )
    return [mirror_leftovers, installed]


def _mirror_mode(codename: str) -> list:
    mirror_url = host.data.ros_apt_mirror_url
    key_file = host.data.ros_apt_mirror_key_file
    for field, value in (("ros_apt_mirror_url", mirror_url), ("ros_apt_mirror_key_file", key_file)):
        if not value:
            raise DeployError(f"{where()}: ros_apt_source_mode is 'mirror' but {field} is not set")
    key_path = controller_path(key_file)
    try:
        key = dearmored(key_path.read_bytes())
    except (OSError, ValueError) as error:
        raise DeployError(f"{where()}: ros_apt_mirror_key_file {key_file}: {error}") from None

    purged = deb_purged(
        name="Ensure the ros2-apt-source package is not installed (the mirror replaces it)",
        package=PACKAGE,
    )
    keyring = files.put(
        name="Ensure the mirror's signing key is in the ROS 2 keyring",
        src=BytesIO(key),
        dest=KEYRING,
        mode="644",
    )
    source = files.template(
        name="Ensure the ROS 2 apt source points at the mirror",
        src=str(TEMPLATES / "ros2.sources.j2"),
        dest=SOURCES,
        mode="644",
        mirror_url=mirror_url,
        codename=codename,
        keyring=KEYRING,
    )
    return [purged, keyring, source]


@deploy("The ROS 2 apt source is configured and apt knows its packages", data_defaults=DEFAULTS)
def ros_apt_source():
    """Install the ROS 2 apt source and move the old method's leftovers aside.

    Reads host.data: ros_apt_source_enabled, ros_apt_source_mode, ros_apt_source_version,
    ros_apt_source_sha256, ros_apt_source_url, ros_apt_source_cache_dir,
    ros_apt_mirror_url, ros_apt_mirror_key_file, apt_lock_timeout.
    """
    if not should_run("ros_apt_source_enabled"):
        return
    codename = host_codename()
    mode = host.data.ros_apt_source_mode

    old_method = files_moved_aside(
        name="Ensure the old ROS 2 apt source files are gone (kept in /var/backups/roslab)",
        paths=OLD_METHOD_FILES,
        backup_dir=BACKUP_DIR,
    )
    if mode == "package":
        changes = _package_mode(codename)
    elif mode == "mirror":
        changes = _mirror_mode(codename)
    else:
        raise DeployError(
            f"{where()}: ros_apt_source_mode is {mode!r}; it must be 'package' or 'mirror'"
        )
    apt_lists_updated(
        name="Ensure the apt lists include the ROS 2 source",
        lock_timeout=setting("apt_lock_timeout"),
        _if=any_changed(old_method, *changes),
    )
