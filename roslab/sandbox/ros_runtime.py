"""Real ROS 2 for the sandbox's ROS archive, from prebuilt install trees (opt-in).

`ROSLAB_SANDBOX_ROS_RUNTIME=DIR` (a setting any user of the sandbox may set) names a folder
of `ros-<distro>-core-*.tar.zst` files: real ROS 2 install trees built for hosts with a
Debian 12 userland and Python 3.11, whose files are relative to `/opt/ros/<distro>` and
already name that prefix (as the shared folder `../shared/ros-runtime` beside the clone holds
them: see its README).
For each distro with such a file, `roslab sandbox up` serves in its ROS archive:

  ros-<distro>-ros-core   REAL: the whole install tree in /opt/ros/<distro> (rclpy, rcl,
                          Cyclone DDS, launch, launch_ros, ros2cli, the messages, the ament
                          linters, the setup scripts), Depends: on the Debian runtime
                          libraries the tree needs (RUNTIME_DEPENDS), from the sandbox's
                          Ubuntu-layout archive.
  ros-<distro>-ros-base   a metapackage on ros-core (whose tree holds ros-base's messages).
  everything else         stand-ins as before (`-desktop`, `-rclpy`, `-ament-flake8`, the
                          profile packages...), now with no files of their own: each depends
                          on ros-core (the tree holds the code, where it exists at all), and
                          the linters also on the Debian tools the real ones need.

A distro without a tarball in DIR keeps today's stand-ins. Without the setting, every distro
has stand-ins. The .deb built from a tarball is cached under the sandbox cache, keyed by the
tarball's sha256, so a second `up` (or a second CI run) does not rebuild it.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from .system import SandboxError, announced, file_sha256, folder_setting, run, write_file

ENV = "ROSLAB_SANDBOX_ROS_RUNTIME"

# Bump when the runtime .debs' layout or control fields change: part of the archive's cache key.
RUNTIME_DEB_VERSION = 1

# The Debian 12 packages the runtime trees need at run time (the runtime README's list, and
# the Python modules ros2cli, launch and rosidl import), by distro; "" applies to every one.
RUNTIME_DEPENDS = {
    "": ("libfmt9", "libspdlog1.10", "python3-numpy", "python3-psutil", "python3-lark",
         "python3-argcomplete", "libpython3.11", "python3-yaml", "python3-netifaces",
         "python3-packaging", "python3-pkg-resources"),
    "jazzy": ("libfoonathan-memory0.7.2", "libtinyxml2-9"),  # Fast DDS
}

# The Debian tools the real ament linter packages depend on (their package.xml exec_depends),
# so `colcon test` of an ament_python package finds them as on a real install.
LINTER_DEPENDS = {
    "ament_flake8": ("python3-flake8",),
    "ament_pep257": ("python3-pydocstyle",),
    "ament_xmllint": ("libxml2-utils",),
    "ament_lint_common": ("python3-flake8", "python3-pydocstyle", "libxml2-utils"),
}

REAL_NOTE = "roslab sandbox: REAL ROS 2"


def runtime_dir() -> Path | None:
    """The folder `ROSLAB_SANDBOX_ROS_RUNTIME` names, or None when it is unset or empty."""
    return folder_setting(ENV, "ros-<distro>-core-*.tar.zst")


def tarballs(folder: Path, distros) -> dict[str, Path]:
    """distro -> its `ros-<distro>-core-*.tar.zst` in `folder` (one each at most)."""
    found = {}
    for distro in sorted(set(distros)):
        matches = sorted(folder.glob(f"ros-{distro}-core-*.tar.zst"))
        if len(matches) > 1:
            raise SandboxError(f"{ENV}={folder}: more than one runtime for {distro}: "
                               f"{', '.join(path.name for path in matches)}")
        if matches:
            found[distro] = matches[0]
    if not found:
        raise SandboxError(f"{ENV}={folder}: holds no ros-<distro>-core-*.tar.zst for "
                           f"{', '.join(sorted(set(distros)))}")
    return found


sha256 = file_sha256


class Runtime:
    """The real ROS 2 trees the sandbox serves: distro -> tarball (and its sha256)."""

    def __init__(self, trees: dict[str, Path]):
        self.trees = dict(trees)
        self.sums = {distro: sha256(path) for distro, path in self.trees.items()}

    @classmethod
    def from_env(cls, distros) -> "Runtime":
        folder = runtime_dir()
        return cls(tarballs(folder, distros) if folder else {})

    def is_real(self, distro: str) -> bool:
        return distro in self.trees

    def debian_packages(self) -> list[str]:
        """The Debian packages the real trees and linters need (for the Ubuntu-layout archive)."""
        if not self.trees:
            return []
        packages = set(RUNTIME_DEPENDS[""])
        for distro in self.trees:
            packages |= set(RUNTIME_DEPENDS.get(distro, ()))
        for tools in LINTER_DEPENDS.values():
            packages |= set(tools)
        return sorted(packages)

    def describe(self) -> dict[str, str]:
        """distro -> "real (<tarball>, sha256 <12 hex>)" for the log and the instance's state."""
        return {distro: f"real ({path.name}, sha256 {self.sums[distro][:12]})"
                for distro, path in sorted(self.trees.items())}

    def cache_key(self) -> list:
        return [RUNTIME_DEB_VERSION, sorted(self.sums.items()), RUNTIME_DEPENDS, LINTER_DEPENDS]


def depends_of(distro: str) -> list[str]:
    return sorted(set(RUNTIME_DEPENDS[""]) | set(RUNTIME_DEPENDS.get(distro, ())))


def build_core_deb(workdir: Path, tarball: str | os.PathLike, distro: str, package: str, version: str,
                   tarball_sha256: str, out_dir: Path) -> Path:
    """Build `package` (ros-<distro>-ros-core) holding the tree of `tarball` in /opt/ros/<distro>."""
    with announced(f"building the sandbox's REAL {package} from {Path(tarball).name} (once per tarball)"):
        return _build_core_deb(workdir, tarball, distro, package, version, tarball_sha256, out_dir)


def _build_core_deb(workdir: Path, tarball: str | os.PathLike, distro: str, package: str, version: str,
                    tarball_sha256: str, out_dir: Path) -> Path:
    root = workdir / package
    shutil.rmtree(root, ignore_errors=True)
    prefix = root / "opt/ros" / distro
    prefix.mkdir(parents=True)
    run("tar", "--zstd", "-xf", tarball, "-C", prefix, "--no-same-owner")
    # A tree made by colcon: nothing of it may be a stand-in's (the stand-in marker, its ros2).
    if (prefix / "STANDIN").exists() or not (prefix / "setup.bash").is_file():
        raise SandboxError(f"{tarball}: not a ROS 2 install tree for /opt/ros/{distro} (no setup.bash)")
    size_kib = sum(path.stat().st_size for path in prefix.rglob("*") if path.is_file()) // 1024
    control = (
        f"Package: {package}\nVersion: {version}\nArchitecture: amd64\n"
        "Maintainer: roslab sandbox <roslab-sandbox@invalid>\n"
        "Section: misc\nPriority: optional\n"
        f"Installed-Size: {size_kib}\n"
        f"Depends: {', '.join(depends_of(distro))}\n"
        f"Description: {REAL_NOTE} {distro} core, built from the official sources for Debian 12\n"
        f" The install tree of {Path(tarball).name} (sha256 {tarball_sha256}) in /opt/ros/{distro}:\n"
        " rclpy, rcl, Cyclone DDS, launch, launch_ros, ros2cli, the common interfaces and the\n"
        " ament linters. Not Ubuntu's packages: made for the roslab sandbox's Debian 12 hosts.\n"
    )
    write_file(root / "DEBIAN/control", control)
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"{package}_{version}_amd64.deb"
    run("dpkg-deb", "--root-owner-group", "-Zgzip", "-z6", "--build", root, out)
    shutil.rmtree(root)
    return out
