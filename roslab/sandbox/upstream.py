"""The sandbox's local "upstream": what stands in for the internet.

Served over HTTP on the instance's bridge address (hosts reach nothing else):

  /ubuntu/          an apt archive in Ubuntu's layout, signed with a sandbox key
                    standing in for Ubuntu's. Its `universe` component holds the
                    REAL Debian packages the deploys install (rosdep, colcon, ...)
                    and what they need beyond the base image.
  /ros2/ubuntu/     an apt archive in packages.ros.org's layout, signed with a
                    sandbox "ROS" key, holding STAND-IN ROS packages: they install
                    /opt/ros/<distro>/setup.bash and depend on the real rosdep and
                    colcon, but carry no ROS code (`import rclpy` fails honestly).
                    With ROSLAB_SANDBOX_ROS_RUNTIME (roslab.sandbox.ros_runtime),
                    ros-<distro>-ros-core is REAL ROS 2 instead, and the stand-ins
                    depend on it.
  /ros-snapshots/<distro>/<date>/ubuntu/
                    a STAND-IN of snapshots.ros.org: the ROS archive as `up` served
                    it, named by the day it was built; `publish` moves /ros2/ubuntu
                    only, so the snapshot keeps its versions (snapshot mode).
  /ros-apt-source/  stand-ins for ros2-apt-source's .deb (key + deb822 source).
  /rosdep/          rosdep's sources list and rules for the keys the demo nodes use.
  /rosdistro/       a rosdistro index listing the stand-in ROS packages.
  /keys/            the public keys, for the mirror mode (key file + mirror URL).
  /pypi/            a STAND-IN Python package index (roslab/sandbox/pypi.py) for the
                    profiles' python_packages.

The two archives do not depend on the instance and are cached under the cache
directory; everything that embeds the instance's URL is rebuilt per instance.
"""

from __future__ import annotations

import datetime
import gzip
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ElementTree
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from roslab.controller_files import file_lock
from roslab.ros.distro import DEFAULT_DISTRO, PLATFORMS
from roslab.ros.distro import ROS_APT_SOURCE_VERSION as ROS_APT_SOURCE_PIN

from . import git_standins, image, pypi, real_sources, ros_runtime
from .system import SandboxError, announced, pid_alive, run, terminate, write_file

# Bump when the archives' layout or the stand-ins change: part of the cache keys.
ARCHIVE_VERSION = 6

ROS_APT_SOURCE_VERSION = ROS_APT_SOURCE_PIN  # the version roslab pins (roslab.ros.distro)

# Ubuntu codename -> the ROS distro whose stand-ins its ROS archive suite holds
# (roslab.ros.distro's one record per Ubuntu/ROS pair).
# codename -> distro: the release records' live index (a record added later is served too).
ROS_DISTROS = DEFAULT_DISTRO
SNAPSHOTS_PATH = "ros-snapshots"  # the stand-in of snapshots.ros.org: <distro>/<snapshot>/ubuntu
UBUNTU_SUITE_POCKETS = ("", "-updates", "-backports", "-security")
UBUNTU_COMPONENTS = ("main", "restricted", "universe", "multiverse")

# The real Debian tools ros-dev-tools brings (Debian's names for them).
ROS_DEV_TOOLS_DEPENDS = (
    "python3-rosdep2", "colcon", "python3-colcon-ros", "python3-colcon-python-setup-py",
    "python3-colcon-bash", "python3-colcon-package-selection", "python3-colcon-parallel-executor",
    "python3-colcon-output", "python3-colcon-test-result", "python3-colcon-recursive-crawl",
    "python3-colcon-library-path", "python3-colcon-metadata", "python3-colcon-defaults",
    "python3-catkin-pkg", "python3-rosdistro", "python3-setuptools", "vcstool", "git",
)

# rosdep system keys the sandbox's rosdep data resolves, key -> Debian/Ubuntu package.
# Keys named python3-* in a node's package.xml are added with the same package name.
SYSTEM_ROSDEP_KEYS = {
    "python3-pytest": "python3-pytest",
    "python3-yaml": "python3-yaml",
    "python3-setuptools": "python3-setuptools",
    "python3-numpy": "python3-numpy",
    "git": "git",
}

# Real Debian packages the universe component offers besides ros-dev-tools' and the
# rosdep keys' packages (udev: the jammy install docs upgrade systemd and udev first;
# apt-cacher-ng: the classroom's apt cache, which Ubuntu has in universe).
EXTRA_UNIVERSE_PACKAGES = ("udev", "apt-cacher-ng",
                           # a profile's Python venv (deploy/python_env.py), and building an sdist in it
                           "python3-venv", "python3-dev", "gcc")

# ROS packages every distro gets a stand-in for (rosdep keys, underscores);
# those the demo nodes' package.xml files declare are added.
STANDIN_ROS_KEYS = (
    "rclpy", "std_msgs", "sensor_msgs", "geometry_msgs", "diagnostic_msgs", "launch",
    "launch_ros", "ros2launch", "ros2cli", "ament_index_python", "ament_copyright",
    "ament_flake8", "ament_pep257", "ament_xmllint", "ament_lint_auto", "ament_lint_common",
    # ros_extra_packages' documented example (ros-{distro}-turtlesim): the roster's package check
    # reads the sandbox's rosdistro, so a name the sandbox does not serve is refused as a typo.
    "turtlesim",
    # The class's middleware (ros_middleware): STAND-INS here, no code. With a real runtime
    # (ros_runtime.py) rmw_cyclonedds_cpp's code is in the real ros-core tree (both cores have
    # Cyclone DDS), so its package is a name on ros-core; rmw_zenoh_cpp stays a stand-in
    # everywhere: no Zenoh router runs in the sandbox.
    "rmw_cyclonedds_cpp", "rmw_zenoh_cpp",
)

# The stand-ins carrying the setup scripts, and the variant metapackages.
ROS_WORKSPACE_KEY = "ros_workspace"
VARIANT_DEPENDS = {
    "ros_core": ["ros_workspace", "rclpy", "std_msgs", "launch", "launch_ros", "ros2launch", "ros2cli",
                 "ament_index_python"],
    "ros_base": ["ros_core", "sensor_msgs", "geometry_msgs", "diagnostic_msgs"],
    "desktop": ["ros_base"],
}

STANDIN_NOTE = "roslab sandbox stand-in"

# The simulators the robot profiles' ROS packages bring (each release record's Gazebo), as
# stand-ins that conflict the way the real ones do: Gazebo Classic 11 (Humble's turtlebot3_gazebo,
# through gazebo_ros_pkgs) cannot be installed beside Gazebo Harmonic (Jazzy's, through ros_gz).
# The stand-ins' versions: gazebo11's, and gz-sim's of each Gazebo release.
SIMULATOR_VERSIONS = {"gazebo11": "11.10.2", "gz-harmonic": "8.9.0"}


def simulator_standins() -> dict[str, tuple[str, str, list[str]]]:
    """Debian package -> (stand-in version, title, the packages it conflicts with), from the records."""
    return {p.gazebo.debian_package: (SIMULATOR_VERSIONS.get(p.gazebo.debian_package, "0.0.0"),
                                      f"Gazebo {p.gazebo.name}", list(p.gazebo.conflicts_with))
            for p in PLATFORMS if p.gazebo.debian_package}


def simulator_of(distro: str, key: str) -> str | None:
    """The simulator stand-in a ROS package key depends on, on `distro` (its release's Gazebo)."""
    for platform in PLATFORMS:
        if platform.distro == distro and platform.gazebo.ros_package == key and platform.gazebo.debian_package:
            return platform.gazebo.debian_package
    return None


def profile_keys(distro: str) -> set[str]:
    """Every ROS package roslab's built-in robot profiles install on `distro` (stand-ins for each)."""
    from roslab.profiles.library import builtin_ros_packages

    return builtin_ros_packages(distro)


def profile_launches(distro: str) -> dict[str, dict[str, list[str]]]:
    """ROS package -> {launch file -> the variables its profile sets on that side} for every launch
    a built-in profile's service runs from a stand-in package on `distro`.

    roslab_bringup is not among them: the demo's workspace builds it from source.
    """
    from roslab.profiles.library import builtin_profiles

    stand_ins = profile_keys(distro)
    launches: dict[str, dict[str, list[str]]] = {}
    for profile in builtin_profiles().values():
        if distro not in profile.distros:
            continue
        for side in profile.sides.values():
            names = set(side.environment)
            for block in side.when:
                names |= set(block["side"].environment)
            for launch in side.launches():
                package, launch_file = launch.split()
                if package in stand_ins:
                    files = launches.setdefault(package, {})
                    files[launch_file] = sorted(set(files.get(launch_file, [])) | names)
    return launches


def profile_verify_topics(distro: str) -> dict[tuple[str, str], tuple[str, str]]:
    """(ROS package, launch file) -> (topic, message type) that `roslab verify` expects from a
    robot running it, for every robot-side launch of a built-in profile on `distro` whose
    package is a stand-in (TurtleBot3's bringup: /scan, a LaserScan)."""
    from roslab.profiles.library import builtin_profiles

    stand_ins = profile_keys(distro)
    topics = {}
    for profile in builtin_profiles().values():
        robot = profile.sides.get("robot")
        if distro not in profile.distros or robot is None or not profile.verify_topic:
            continue
        for launch in robot.launches():
            package, launch_file = launch.split()
            if package in stand_ins:
                topics[(package, launch_file)] = (profile.verify_topic, profile.verify_type)
    return topics


def standin_launch(distro: str, package: str, launch_file: str, variables: list[str],
                   publishes: tuple[str, str] | None = None) -> str:
    """A stand-in launch file: read by the REAL `ros2 launch` where the sandbox has a real runtime
    (the stand-in `ros2` never reads it).

    Like the real one, it needs the profile's variables (the real turtlebot3_bringup's
    robot.launch.py ends in a KeyError without TURTLEBOT3_MODEL or LDS_MODEL), then runs one
    labelled process that says which values it got and stays up (`sleep` under the label as its
    argv[0], so `pgrep -f` and `ps` name it); the launch ends when it ends, so the service's
    restart is what a real node's end would cause.

    `publishes` (topic, type): what `roslab verify` expects from the robot; the real
    `ros2 topic pub` sends default-valued messages of that type (the real bringup's lidar would
    send scans), twice a second, printing none.
    """
    label = f"roslab-standin-{package}-{launch_file.removesuffix('.launch.py')}"
    publisher = ""
    if publishes:
        topic, message_type = publishes
        publisher = (
            "        ExecuteProcess(\n"
            f"            name=LABEL + '-publisher',\n"
            f"            cmd=['ros2', 'topic', 'pub', '--rate', '2', '--print', '0', {topic!r}, {message_type!r}, '{{}}'],\n"
            "            output='screen',\n"
            "            on_exit=Shutdown(reason=f'{LABEL} publisher ended'),\n"
            "        ),\n"
        )
    return (
        f"# {STANDIN_NOTE} for {package}'s {launch_file} (ROS 2 {distro}): no robot code behind it.\n"
        "# It needs the variables the real launch file needs, and runs one process that reports them.\n"
        "import os\n\n"
        "from launch import LaunchDescription\n"
        "from launch.actions import ExecuteProcess, Shutdown\n\n"
        f"LABEL = {label!r}\n"
        f"VARIABLES = {variables!r}\n\n\n"
        "def generate_launch_description():\n"
        "    values = [f'{name}={os.environ[name]}' for name in VARIABLES]  # KeyError, as the real one\n"
        "    return LaunchDescription([\n"
        "        ExecuteProcess(\n"
        "            name=LABEL,\n"
        "            cmd=['/bin/bash', '-c',\n"
        "                 'printf \"%s: stand-in, no robot code; got %s\\\\n\" \"$0\" \"$*\"; exec -a \"$0\" sleep infinity',\n"
        "                 LABEL, *values],\n"
        "            output='screen',\n"
        "            on_exit=Shutdown(reason=f'{LABEL} ended'),\n"
        "        ),\n"
        f"{publisher}"
        "    ])\n"
    )


def standin_launch_files(distro: str, key: str) -> dict[str, str]:
    """The files a stand-in package whose launch a profile runs carries: its launch files, its
    package.xml and its ament index entry, where the real `ros2 launch` looks for them."""
    launches = profile_launches(distro).get(key)
    if not launches:
        return {}
    share = f"/opt/ros/{distro}/share"
    files = {
        f"{share}/ament_index/resource_index/packages/{key}": "",
        f"{share}/{key}/package.xml": (
            '<?xml version="1.0"?>\n<package format="3">\n'
            f"  <name>{key}</name>\n  <version>0.0.0</version>\n"
            f"  <description>{STANDIN_NOTE} for {key}: its launch files only</description>\n"
            "  <maintainer email=\"roslab-sandbox@invalid\">roslab sandbox</maintainer>\n"
            "  <license>Apache-2.0</license>\n"
            "  <exec_depend>launch</exec_depend>\n"
            "  <export><build_type>ament_python</build_type></export>\n</package>\n"
        ),
    }
    publishes = profile_verify_topics(distro)
    for launch_file, variables in sorted(launches.items()):
        files[f"{share}/{key}/launch/{launch_file}"] = standin_launch(distro, key, launch_file, variables,
                                                                      publishes.get((key, launch_file)))
    return files


def debian_name(distro: str, key: str) -> str:
    """The apt package name of ROS package `key` for `distro` (ros-jazzy-launch-ros)."""
    return f"ros-{distro}-{key.replace('_', '-')}"


# -- what the demo nodes need ---------------------------------------------------------

def node_dependencies(nodes_dir: Path) -> tuple[set[str], dict[str, str]]:
    """(ROS keys, system keys -> package) declared by every nodes/*/package.xml.

    The workspace's own packages are built from source, so they get no stand-in.
    """
    return manifest_dependencies(sorted(nodes_dir.glob("*/package.xml")))


def manifest_dependencies(paths) -> tuple[set[str], dict[str, str]]:
    """(ROS keys, system keys -> package) the package.xml files at `paths` declare, less the
    packages they are themselves (built from source, they get no stand-in)."""
    manifests = [ElementTree.parse(path).getroot() for path in paths]
    own_packages = {manifest.findtext("name") for manifest in manifests}
    ros_keys: set[str] = set()
    system: dict[str, str] = {}
    for manifest in manifests:
        for element in manifest:
            if not element.tag.endswith("depend") or not element.text:
                continue
            key = element.text.strip()
            if key in SYSTEM_ROSDEP_KEYS or key.startswith("python3-"):
                system[key] = SYSTEM_ROSDEP_KEYS.get(key, key)
            elif key not in own_packages:
                ros_keys.add(key)
    return ros_keys, system


def default_nodes_dir() -> Path:
    from roslab.packaged import nodes_dir  # the checkout's nodes/, or the installed package's

    return nodes_dir()


# -- signing keys ---------------------------------------------------------------------

@dataclass(frozen=True)
class SigningKey:
    """A throwaway OpenPGP key standing in for an archive's signing key."""

    home: Path  # gnupg home (root-only), holding the secret key

    @property
    def keyring(self) -> Path:
        """Binary public keyring, for Signed-By."""
        return self.home / "public.gpg"

    @property
    def armored(self) -> Path:
        return self.home / "public.asc"

    @property
    def fingerprint(self) -> str:
        return (self.home / "fingerprint").read_text().strip()

    def gpg(self, *args: str | os.PathLike) -> None:
        # gpg's agent listens on a socket in the home, and a socket's path has at most 107 bytes:
        # a cache folder deep enough (ROSLAB_CACHE_DIR, a test's temporary folder) fails with "No
        # agent running" where no /run/user/<uid> takes the socket. A short link to the home is
        # the home gpg is given.
        with tempfile.TemporaryDirectory(prefix="roslab-gpg-") as short:
            home = Path(short) / "h"
            home.symlink_to(self.home.resolve())
            try:
                run("gpg", "--homedir", home, "--batch", "--yes", "--quiet", *args)
            finally:
                # gpg starts an agent per home; it is ours to stop.
                run("gpgconf", "--homedir", home, "--kill", "gpg-agent", check=False)

    def sign_release(self, release: Path) -> None:
        self.gpg("--clearsign", "--output", release.with_name("InRelease"), release)
        self.gpg("--armor", "--detach-sign", "--output", release.with_name("Release.gpg"), release)


def signing_key(role: str, description: str) -> SigningKey:
    """The cached sandbox key for `role` ("ubuntu", "ros"), generated once."""
    key = SigningKey(image.cache_dir() / "keys" / role)
    if key.keyring.exists():
        return key
    with file_lock(image.cache_dir() / "lock.keys"):
        if key.keyring.exists():
            return key
        shutil.rmtree(key.home, ignore_errors=True)
        key.home.mkdir(parents=True, mode=0o700)
        key.gpg("--passphrase", "", "--quick-generate-key",
                f"roslab sandbox stand-in for the {description} <roslab-sandbox@invalid>", "ed25519", "sign", "never")
        listing = subprocess.run(["gpg", "--homedir", str(key.home), "--with-colons", "--list-keys"],
                                 capture_output=True, text=True, check=True).stdout
        fingerprint = next(line.split(":")[9] for line in listing.splitlines() if line.startswith("fpr:"))
        write_file(key.home / "fingerprint", fingerprint + "\n")
        key.gpg("--export", "--armor", "--output", key.armored, fingerprint)
        key.gpg("--export", "--output", key.home / "public.gpg.tmp", fingerprint)
        os.chmod(key.home / "public.gpg.tmp", 0o644)
        (key.home / "public.gpg.tmp").rename(key.keyring)
    return key


def ubuntu_key() -> SigningKey:
    return signing_key("ubuntu", "Ubuntu archive signing key")


def ros_key() -> SigningKey:
    return signing_key("ros", "ROS 2 archive signing key")


# -- apt archive plumbing -------------------------------------------------------------

def write_indexes(archive: Path, dist_dir: Path, component: str, pool: str | None) -> None:
    """Write Packages(.gz) for one component from the debs under `pool` (relative to `archive`;
    None: empty)."""
    binary = dist_dir / component / "binary-amd64"
    binary.mkdir(parents=True, exist_ok=True)
    packages = ""
    if pool:
        packages = run("apt-ftparchive", "packages", pool, cwd=archive).stdout
    (binary / "Packages").write_text(packages)
    with gzip.open(binary / "Packages.gz", "wt") as handle:
        handle.write(packages)


def _write_release(dist_dir: Path, key: SigningKey, **fields: str) -> None:
    options = []
    for name, value in fields.items():
        options += ["-o", f"APT::FTPArchive::Release::{name}={value}"]
    release = run("apt-ftparchive", *options, "release", ".", cwd=dist_dir).stdout
    (dist_dir / "Release").write_text(release)
    key.sign_release(dist_dir / "Release")


def _build_deb(workdir: Path, package: str, version: str, description: str,
               files: Mapping[str, str | bytes] | None = None, depends: list[str] | None = None,
               links: dict[str, str] | None = None, out_dir: Path | None = None,
               conflicts: list[str] | None = None) -> Path:
    """Build an Architecture: all .deb of plain files with dpkg-deb."""
    root = workdir / package
    shutil.rmtree(root, ignore_errors=True)
    for path, content in (files or {}).items():
        write_file(root / path.lstrip("/"), content)
        if "/bin/" in path or (isinstance(content, str) and content.startswith("#!")):
            (root / path.lstrip("/")).chmod(0o755)
    for path, target in (links or {}).items():
        link = root / path.lstrip("/")
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(target)
    control = (
        f"Package: {package}\nVersion: {version}\nArchitecture: all\n"
        "Maintainer: roslab sandbox <roslab-sandbox@invalid>\n"
        "Section: misc\nPriority: optional\n"
    )
    if depends:
        control += f"Depends: {', '.join(depends)}\n"
    if conflicts:
        control += f"Conflicts: {', '.join(conflicts)}\n"
    control += f"Description: {description}\n"
    write_file(root / "DEBIAN/control", control)
    out = (out_dir or workdir) / f"{package}_{version}_all.deb"
    out.parent.mkdir(parents=True, exist_ok=True)
    run("dpkg-deb", "--root-owner-group", "-Zgzip", "--build", root, out)
    shutil.rmtree(root)
    return out


def _cache_key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _cached_build(kind: str, key: str, build) -> Path:
    """Return cache_dir/kind/key, running build(tmp_dir) under the cache lock if missing."""
    final = image.cache_dir() / kind / key
    if final.is_dir():
        return final
    with file_lock(image.cache_dir() / "lock"):
        if final.is_dir():
            return final
        building = final.with_name(final.name + ".building")
        shutil.rmtree(building, ignore_errors=True)
        building.mkdir(parents=True)
        build(building)
        building.rename(final)
    return final


# -- the Ubuntu-layout archive of real Debian packages -----------------------------------

def universe_packages(system_keys: dict[str, str], runtime_packages=()) -> list[str]:
    from roslab.profiles.library import builtin_debian_packages  # the robot profiles' own debs

    return sorted(set(ROS_DEV_TOOLS_DEPENDS) | set(system_keys.values()) | set(EXTRA_UNIVERSE_PACKAGES)
                  | set(runtime_packages) | builtin_debian_packages())


def _download_closure(rootfs: Path, packages: list[str], workdir: Path, debs: Path) -> None:
    """Download `packages` and every dependency the base image lacks, with this machine's apt.

    apt resolves against the base image's dpkg status, so the result is exactly
    what a fresh host needs from the archive (recommends included, as Ubuntu's
    apt installs them by default).
    """
    apt = workdir / "apt"
    for sub in ("sources.list.d", "preferences.d", "lists/partial", "cache", "archives/partial"):
        (apt / sub).mkdir(parents=True, exist_ok=True)
    write_file(apt / "sources.list.d/debian.sources", image.debian_sources())
    write_file(apt / "empty", "")
    options = [
        f"Dir::Etc::SourceList={apt / 'empty'}", f"Dir::Etc::SourceParts={apt / 'sources.list.d'}",
        f"Dir::Etc::Preferences={apt / 'empty'}", f"Dir::Etc::PreferencesParts={apt / 'preferences.d'}",
        f"Dir::State::Lists={apt / 'lists'}", f"Dir::Cache={apt / 'cache'}",
        f"Dir::Cache::Archives={apt / 'archives'}", f"Dir::State::status={image.dpkg_status(rootfs)}",
        f"Dir::State::extended_states={apt / 'extended_states'}", "Debug::NoLocking=1",
        "APT::Install-Recommends=true", "APT::Get::Download-Only=true",
    ]
    argv = ["apt-get", "-q", "-y"] + [arg for option in options for arg in ("-o", option)]
    run(*argv, "update")
    run(*argv, "install", *packages)
    debs.mkdir(parents=True, exist_ok=True)
    for deb in (apt / "archives").glob("*.deb"):
        shutil.move(deb, debs / deb.name)
    shutil.rmtree(apt)


def ubuntu_archive(rootfs: Path, system_keys: dict[str, str], runtime_packages=()) -> Path:
    """The cached Ubuntu-layout archive (real Debian packages in universe).

    `runtime_packages`: the Debian libraries and tools a real ROS runtime needs (ros_runtime).
    """
    packages = universe_packages(system_keys, runtime_packages)
    key = ubuntu_key()

    def build(out: Path) -> None:
        with announced("building the sandbox's Ubuntu-layout archive (once, then cached; downloads from Debian)"):
            fill(out)

    def fill(out: Path) -> None:
        _download_closure(rootfs, packages, out / "work", out / "pool/universe")
        shutil.rmtree(out / "work")
        for codename, version in ((p.codename, p.release) for p in PLATFORMS):
            for pocket in UBUNTU_SUITE_POCKETS:
                suite = codename + pocket
                dist_dir = out / "dists" / suite
                for component in UBUNTU_COMPONENTS:
                    has_debs = component == "universe" and pocket == ""
                    write_indexes(out, dist_dir, component, "pool/universe" if has_debs else None)
                write_ubuntu_release(dist_dir, suite, codename, version)

    return _cached_build("ubuntu-archive", _cache_key(ARCHIVE_VERSION, rootfs.parent.name, packages,
                                                      key.fingerprint), build)


def write_ubuntu_release(dist_dir: Path, suite: str, codename: str, version: str) -> None:
    """The signed Release of one suite of the Ubuntu-layout archive (of the Packages under it)."""
    _write_release(dist_dir, ubuntu_key(), Origin="Ubuntu", Label="Ubuntu (roslab sandbox stand-in)",
                   Suite=suite, Codename=codename, Version=version, Architectures="amd64",
                   Components=" ".join(UBUNTU_COMPONENTS),
                   Description=f"{STANDIN_NOTE} for Ubuntu {version}: real Debian packages")


def write_ros_release(dist_dir: Path, codename: str, distro: str) -> None:
    """The signed Release of one codename of the ROS archive (of the Packages under it)."""
    _write_release(dist_dir, ros_key(), Origin="ROS", Label="ROS 2 (roslab sandbox stand-in)",
                   Suite=codename, Codename=codename, Architectures="amd64", Components="main",
                   Description=f"{STANDIN_NOTE} for packages.ros.org/ros2: ROS 2 {distro}")


# -- the ROS archive of stand-ins ---------------------------------------------------------

def setup_script(distro: str) -> str:
    return (
        f"# {STANDIN_NOTE} for ROS 2 {distro}'s setup script: it sets the variables a real\n"
        "# install sets and nothing else (there is no ROS code behind it).\n"
        f"export ROS_DISTRO={distro}\n"
        "export ROS_VERSION=2\n"
        "export ROS_PYTHON_VERSION=3\n"
        'case ":${AMENT_PREFIX_PATH:-}:" in\n'
        f'  *":/opt/ros/{distro}:"*) ;;\n'
        f'  *) export AMENT_PREFIX_PATH="/opt/ros/{distro}${{AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}}" ;;\n'
        "esac\n"
        'case ":${PATH}:" in\n'
        f'  *":/opt/ros/{distro}/bin:"*) ;;\n'
        f'  *) export PATH="/opt/ros/{distro}/bin:$PATH" ;;\n'
        "esac\n"
    )


def standin_ros2(distro: str) -> str:
    """A stand-in `ros2`: only `ros2 launch` works, and it only stays up like a healthy launch.

    That is what the deploy needs (the nodes' service runs, so a re-run is a no-op); every
    other command says there is no ROS runtime and exits 127, as a missing command would.
    """
    return (
        "#!/bin/sh\n"
        f"# {STANDIN_NOTE} for ROS 2 {distro}'s ros2: there is no ROS code behind it.\n"
        'if [ "$1" = launch ]; then\n'
        f'  echo "{STANDIN_NOTE}: no ROS runtime; \\`ros2 $*\\` only stays up like a healthy launch" >&2\n'
        "  exec sleep infinity\n"
        "fi\n"
        f'echo "{STANDIN_NOTE}: ros2 $* needs a ROS 2 runtime, which the sandbox does not have" >&2\n'
        "exit 127\n"
    )


def standin_marker(distro: str) -> str:
    return (
        f"This /opt/ros/{distro} comes from the roslab sandbox's STAND-IN ROS packages.\n"
        "They install these setup scripts and depend on the real Debian rosdep and colcon,\n"
        "but hold no ROS code: `import rclpy` fails; `ros2` is a stand-in whose `launch` only\n"
        "stays up (so the nodes' service runs) and whose other commands fail with exit 127.\n"
        "A real classroom installs the real packages from packages.ros.org.\n"
    )


def ros_keys_for(extra_keys: set[str]) -> list[str]:
    keys = set(STANDIN_ROS_KEYS) | set(extra_keys) | set(VARIANT_DEPENDS) | {ROS_WORKSPACE_KEY}
    return sorted(keys)


def ros_archive(extra_keys: set[str], runtime: ros_runtime.Runtime | None = None,
                bundles: real_sources.Bundles | None = None) -> Path:
    """The cached ROS archive (stand-ins for jazzy on noble, humble on jammy, ros-dev-tools on both).

    A distro `runtime` holds a real tree for gets the real ros-core instead (ros_runtime), and
    with the robots' real `bundles` (real_sources) the released packages built from them.
    """
    keys = ros_keys_for(extra_keys)
    signer = ros_key()
    runtime = runtime or ros_runtime.Runtime({})
    bundles = bundles or real_sources.Bundles(None)

    def build(out: Path) -> None:
        work = out / "work"
        common = out / "pool/main/common"
        _build_deb(work, "ros-dev-tools", "1.0.1", f"{STANDIN_NOTE}: ROS development tools (real Debian "
                   "rosdep, colcon and vcstool)", depends=list(ROS_DEV_TOOLS_DEPENDS), out_dir=common)
        for simulator_package, (version, title, conflicts) in simulator_standins().items():
            _build_deb(work, simulator_package, version, f"{STANDIN_NOTE}: {title} (no simulator; conflicts with "
                       f"{', '.join(conflicts)} as the real packages do)", conflicts=conflicts, out_dir=common)
        for codename, distro in ROS_DISTROS.items():
            pool = out / "pool/main" / codename
            distro_keys = sorted(set(keys) | profile_keys(distro))
            if runtime.is_real(distro):
                _real_ros_packages(work, codename, distro, distro_keys, runtime, pool, bundles)
                keys_to_stand_in = []
            else:
                keys_to_stand_in = distro_keys
            for key in keys_to_stand_in:
                package = debian_name(distro, key)
                files, depends = standin_launch_files(distro, key), [
                    debian_name(distro, dep) for dep in VARIANT_DEPENDS.get(key, [])]
                if simulator := simulator_of(distro, key):
                    depends.append(simulator)
                if key == ROS_WORKSPACE_KEY:
                    prefix = f"/opt/ros/{distro}"
                    files = {f"{prefix}/{name}": setup_script(distro)
                             for name in ("setup.bash", "setup.sh", "local_setup.bash", "local_setup.sh")}
                    files[f"{prefix}/STANDIN"] = standin_marker(distro)
                    files[f"{prefix}/bin/ros2"] = standin_ros2(distro)
                elif key not in VARIANT_DEPENDS:
                    depends = [debian_name(distro, ROS_WORKSPACE_KEY), *depends]
                _build_deb(work, package, f"0.0.0-1{codename}", f"{STANDIN_NOTE}: {key} for ROS 2 {distro} "
                           "(no code)", files=files, depends=depends, out_dir=pool)
            dist_dir = out / "dists" / codename
            shutil.copytree(common, pool, dirs_exist_ok=True)
            write_indexes(out, dist_dir, "main", f"pool/main/{codename}")
            write_ros_release(dist_dir, codename, distro)
        shutil.rmtree(work)
        shutil.rmtree(common)

    profiles = {distro: sorted(profile_keys(distro)) for distro in ROS_DISTROS.values()}
    launches = {distro: (profile_launches(distro), sorted(profile_verify_topics(distro).items()))
                for distro in ROS_DISTROS.values()}
    return _cached_build("ros-archive", _cache_key(ARCHIVE_VERSION, keys, ROS_DEV_TOOLS_DEPENDS, profiles,
                                                   launches, simulator_standins(), signer.fingerprint,
                                                   runtime.cache_key(), bundles.cache_key(),
                                                   real_sources.BUILD_DEPENDS), build)


def _real_ros_packages(work: Path, codename: str, distro: str, keys: list[str],
                       runtime: ros_runtime.Runtime, pool: Path, bundles: real_sources.Bundles) -> None:
    """A distro on real ROS: the real ros-core from its tree, ros-base on it, stand-ins on them.

    A stand-in whose launch a profile's service runs (turtlebot3_bringup robot.launch.py)
    carries a real launch file in the ament index (standin_launch_files), so the real
    `ros2 launch` finds it and runs its labelled stand-in process.
    """
    version = f"0.0.0-1{codename}"
    core = debian_name(distro, "ros_core")
    ros_runtime.build_core_deb(work, runtime.trees[distro], distro, core, version, runtime.sums[distro], pool)
    built_from_source = _released_from_bundles(work, distro, keys, runtime, bundles, version, pool)
    for key in keys:
        package = debian_name(distro, key)
        if key == "ros_core" or key in built_from_source:
            continue
        if key == "ros_base":
            _build_deb(work, package, version, f"{ros_runtime.REAL_NOTE} {distro} ros-base: a metapackage on "
                       "ros-core, whose real tree holds ros-base's packages", depends=[core], out_dir=pool)
            continue
        depends = [debian_name(distro, dep) for dep in VARIANT_DEPENDS.get(key, [])] or [core]
        depends += ros_runtime.LINTER_DEPENDS.get(key, ())
        depends += real_sources.BUILD_DEPENDS.get(key, ())  # what Ubuntu's deb brings along
        if simulator := simulator_of(distro, key):
            depends.append(simulator)
        files = {**standin_launch_files(distro, key), **real_sources.standin_executable_files(distro, key)}
        what = "stand-in launch files or executables" if files else "no files of its own"
        _build_deb(work, package, version, f"{STANDIN_NOTE}: {key} for ROS 2 {distro} ({what}; "
                   "the real code, where the runtime has it, is in ros-core)", files=files, depends=depends,
                   out_dir=pool)


def _released_from_bundles(work: Path, distro: str, keys: list[str], runtime: ros_runtime.Runtime,
                           bundles: real_sources.Bundles, version: str, pool: Path) -> set[str]:
    """The released packages (real_sources.RELEASED_FROM_SOURCE) a profile installs on `distro`
    that the bundles hold: built for real against the runtime's tree. Returns their keys."""
    wanted = [key for key in keys if key in real_sources.RELEASED_FROM_SOURCE
              and real_sources.RELEASED_FROM_SOURCE[key][0] in bundles.paths]
    if not wanted:
        return set()
    tree = work / f"runtime-{distro}"
    shutil.rmtree(tree, ignore_errors=True)
    tree.mkdir(parents=True)
    run("tar", "--zstd", "-xf", runtime.trees[distro], "-C", tree, "--no-same-owner")
    for key in wanted:
        real_sources.build_released_deb(bundles, key, distro, tree, version, pool, debian_name(distro, key))
    shutil.rmtree(tree)
    return set(wanted)


def source_keys(bundles: real_sources.Bundles) -> tuple[set[str], dict[str, str]]:
    """(ROS keys, system keys -> Debian package) the real trees of the built-in .repos files
    declare at their pins: the sandbox's rosdep and archive resolve them as a real host's do."""
    ros_keys: set[str] = set()
    system: dict[str, str] = {}
    for _, url, version in git_standins.repositories(builtin_repos_files()):
        bundle = bundles.bundle_for(url)
        if bundle is None or not version:
            continue
        with tempfile.TemporaryDirectory(prefix="roslab-keys-") as work:
            tree = bundles.tree(bundle.name.removesuffix(".bundle"), version, Path(work) / "tree")
            repo_keys, repo_system = manifest_dependencies(real_sources.built_manifests(tree))
        ros_keys |= repo_keys
        system.update(repo_system)
    return ros_keys, system


# -- per-instance content ----------------------------------------------------------------

def ros2_sources(url: str, codename: str, armored_key: str | None = None) -> str:
    """ros2.sources as the real ros2-apt-source writes it: deb822, its signing key inline in
    `Signed-By:` (the armored block, each line indented, an empty line as " ."), so apt needs no
    keyring file. `armored_key`: the sandbox ROS archive's key (default: its own)."""
    armored = armored_key if armored_key is not None else ros_key().armored.read_text()
    key_lines = [line if line.strip() else "." for line in armored.strip().splitlines()]
    return (
        f"# {STANDIN_NOTE} for ros2-apt-source's ros2.sources\n"
        "Types: deb\n"
        f"URIs: {url}/ros2/ubuntu\n"
        f"Suites: {codename}\n"
        "Components: main\n"
        f"Signed-By: {key_lines[0]}\n" + "".join(f" {line}\n" for line in key_lines[1:])
    )


def build_ros_apt_source(out: Path, url: str) -> dict[str, str]:
    """Build the stand-in ros2-apt-source debs, laid out like its GitHub releases; return codename -> sha256."""
    sums = {}
    keyring = ros_key().keyring.read_bytes()
    version_dir = out / "ros-apt-source" / ROS_APT_SOURCE_VERSION
    for codename in ROS_DISTROS:
        deb = _build_deb(
            out / "work", "ros2-apt-source", ROS_APT_SOURCE_VERSION,
            f"{STANDIN_NOTE}: ROS 2 apt source and archive key (sandbox upstream)",
            files={"/usr/share/ros-apt-source/ros2.sources": ros2_sources(url, codename),
                   "/usr/share/keyrings/ros2-archive-keyring.gpg": keyring},
            links={"/etc/apt/sources.list.d/ros2.sources": "/usr/share/ros-apt-source/ros2.sources"},
            out_dir=version_dir,
        )
        target = deb.with_name(f"ros2-apt-source_{ROS_APT_SOURCE_VERSION}.{codename}_all.deb")
        deb.rename(target)
        sums[codename] = hashlib.sha256(target.read_bytes()).hexdigest()
    shutil.rmtree(out / "work")
    return sums


def rosdep_files(url: str, system_keys: dict[str, str]) -> dict[str, str]:
    header = f"# {STANDIN_NOTE} for rosdep's data (served by the sandbox upstream)\n"
    rules = {key: {"debian": [package], "ubuntu": [package]} for key, package in sorted(system_keys.items())}
    python_rules = {k: v for k, v in rules.items() if k.startswith("python3-")}
    base_rules = {k: v for k, v in rules.items() if not k.startswith("python3-")}
    return {
        "rosdep/20-default.list": header + f"yaml {url}/rosdep/base.yaml\nyaml {url}/rosdep/python.yaml\n",
        "rosdep/base.yaml": header + yaml.safe_dump(base_rules, sort_keys=True),
        "rosdep/python.yaml": header + yaml.safe_dump(python_rules, sort_keys=True),
    }


def rosdistro_files(url: str, ros_keys: list[str]) -> dict[str, str]:
    header = f"%YAML 1.1\n# {STANDIN_NOTE} for the rosdistro index\n---\n"
    index: dict[str, Any] = {"type": "index", "version": 4, "distributions": {}}
    files = {}
    for codename, distro in sorted(ROS_DISTROS.items()):
        index["distributions"][distro] = {
            "distribution": [f"{distro}/distribution.yaml"],
            "distribution_status": "active",
            "distribution_type": "ros2",
            "python_version": 3,
        }
        repositories = {
            key: {"release": {"packages": [key], "tags": {"release": f"release/{distro}/{{package}}/{{version}}"},
                              "url": f"{url}/release/{key}.git", "version": "0.0.0-1"},
                  "status": "maintained"}
            for key in sorted(set(ros_keys) | profile_keys(distro))
        }
        distribution = {"type": "distribution", "version": 2, "release_platforms": {"ubuntu": [codename]},
                        "repositories": repositories}
        files[f"rosdistro/{distro}/distribution.yaml"] = header + yaml.safe_dump(distribution, sort_keys=True)
    files["rosdistro/index-v4.yaml"] = header + yaml.safe_dump(index, sort_keys=True)
    return files


@dataclass(frozen=True)
class Upstream:
    """What `up` publishes about the upstream: URLs and checksums for the roster."""

    url: str
    ros_apt_source_sha256: dict[str, str]
    # distro -> "stand-in", or "real (<tarball>, sha256 <12 hex>)" (ros_runtime.Runtime.describe)
    ros: dict[str, str] | None = None
    # the built-in .repos repositories served from real bundles (real_sources), by URL
    real_repositories: tuple[str, ...] = ()
    snapshot: str = ""  # the stand-in snapshot's name (snapshot_name), under SNAPSHOTS_PATH/<distro>/

    def roster_settings(self) -> dict:
        return {
            "ros_apt_source_url": (f"{self.url}/ros-apt-source/{{version}}/"
                                   "ros2-apt-source_{version}.{codename}_all.deb"),
            "ros_apt_source_version": ROS_APT_SOURCE_VERSION,
            "ros_apt_source_sha256": dict(sorted(self.ros_apt_source_sha256.items())),
            "rosdep_sources_list_url": f"{self.url}/rosdep/20-default.list",
            "rosdistro_index_url": f"{self.url}/rosdistro/index-v4.yaml",
            # An apt cache (apt_cache_host) may fetch from the upstream's port, as from a
            # classroom's local mirror on a port other than 80.
            "apt_cache_upstream_ports": [int(self.url.rsplit(":", 1)[1])],
            # The stand-in git server (git_standins.py): the class fetches .repos repositories here.
            "source_url_rewrites": git_standins.rewrites(self.url),
            # The built-in profiles' commit pins cannot be stood in: their stand-ins' tag instead.
            "source_pins": git_standins.commit_pins(builtin_repos_files(), real=self.real_repositories),
            "python_index_url": f"{self.url}/pypi/simple",  # the stand-in index (sandbox/pypi.py)
            "sources_cache_dir": self.sources_cache_dir(),
            **self.middleware_settings(),
        }

    def sources_cache_dir(self) -> str:
        """The controller's mirrors and lock for what this upstream serves under the real URLs:
        one cache for stand-ins only, one per set of real repositories. The shared default
        would take one for the other: a real micro-ROS-Agent an earlier sandbox fetched (with
        ROSLAB_SANDBOX_SOURCES), whose rosdep keys a stand-in sandbox does not serve."""
        # The stand-ins' own content too: a changed stand-in is another commit under the same tag.
        served = [*sorted(self.real_repositories), git_standins.content_key()]
        digest = hashlib.sha256("\n".join(served).encode()).hexdigest()[:12]
        return f"~/.cache/roslab/sandbox-sources/{'real' if self.real_repositories else 'stand-ins'}-{digest}"

    def middleware_settings(self) -> dict:
        """The class's middleware where a distro is served from a real runtime: Cyclone DDS,
        the one both runtimes have (Humble's has no Fast DDS, which Ubuntu's ros-base brings;
        ROSLAB_SANDBOX_ROS_RUNTIME's README). With stand-ins only: roslab's default."""
        if any(not served.startswith("stand-in") for served in (self.ros or {}).values()):
            return {"ros_middleware": "rmw_cyclonedds_cpp"}
        return {}

    def mirror_settings(self, key_file: Path) -> dict:
        return {"ros_apt_mirror_url": f"{self.url}/ros2/ubuntu", "ros_apt_mirror_key_file": str(key_file)}

    def snapshot_settings(self, key_file: Path) -> dict:
        """Snapshot mode from the stand-in snapshot server (signed with the stand-in ROS key)."""
        return {"ros_apt_snapshot": self.snapshot, "ros_apt_snapshot_url": f"{self.url}/{SNAPSHOTS_PATH}",
                "ros_apt_snapshot_key_file": str(key_file)}


def builtin_repos_files() -> list[Path]:
    """The built-in robot profiles' .repos files (roslab/profiles/data)."""
    return sorted(Path(__file__).resolve().parent.parent.joinpath("profiles", "data").glob("*.repos"))


def served_keys(nodes_dir: Path, bundles: real_sources.Bundles) -> tuple[set[str], dict[str, str]]:
    """(ROS keys, system keys -> Debian package) the sandbox's rosdep data resolves, besides the
    ROS keys every distro gets (`ros_keys_for`): the demo nodes' and the real repositories'."""
    ros_keys, system_keys = node_dependencies(nodes_dir)
    source_ros_keys, source_system_keys = source_keys(bundles)
    return ros_keys | source_ros_keys, {**SYSTEM_ROSDEP_KEYS, **system_keys, **source_system_keys}


def build(serve_dir: Path, url: str, rootfs: Path, nodes_dir: Path | None = None,
          runtime: ros_runtime.Runtime | None = None) -> Upstream:
    """Assemble the served tree for one instance (archives from the cache, the rest fresh).

    `runtime`: the real ROS trees to serve (default: those ROSLAB_SANDBOX_ROS_RUNTIME names).
    """
    runtime = runtime if runtime is not None else ros_runtime.Runtime.from_env(ROS_DISTROS.values())
    bundles = real_sources.Bundles.from_env() if runtime.trees else real_sources.Bundles(None)
    ros_keys, system_keys = served_keys(nodes_dir or default_nodes_dir(), bundles)
    # the real ros-core's stand-ins depend on them as Ubuntu's debs do (real_sources.BUILD_DEPENDS)
    build_tools = sorted({package for packages in real_sources.BUILD_DEPENDS.values() for package in packages}
                         ) if runtime.trees else []
    ubuntu = ubuntu_archive(rootfs, system_keys, [*runtime.debian_packages(), *build_tools])
    ros = ros_archive(ros_keys, runtime, bundles)
    shutil.rmtree(serve_dir, ignore_errors=True)
    (serve_dir / "ros2").mkdir(parents=True)
    (serve_dir / "ubuntu").symlink_to(ubuntu)
    (serve_dir / "ros2/ubuntu").symlink_to(ros)
    # A stand-in of snapshots.ros.org: the archive as `up` built it, named by the day it was built
    # (a sync's date); `publish` moves ros2/ubuntu only, so the snapshot keeps these versions.
    snapshot = snapshot_name(ros)
    for distro in sorted(set(ROS_DISTROS.values())):
        (serve_dir / SNAPSHOTS_PATH / distro / snapshot).mkdir(parents=True)
        (serve_dir / SNAPSHOTS_PATH / distro / snapshot / "ubuntu").symlink_to(ros)
    sums = build_ros_apt_source(serve_dir, url)
    for path, content in {**rosdep_files(url, system_keys), **rosdistro_files(url, ros_keys_for(ros_keys))}.items():
        write_file(serve_dir / path, content)
    write_file(serve_dir / "keys/ros.asc", ros_key().armored.read_bytes())
    write_file(serve_dir / "keys/ubuntu.asc", ubuntu_key().armored.read_bytes())
    # The built-in profiles' .repos repositories: the real ones where a bundle holds them
    # (real_sources.py), stand-ins for the rest (git_standins.py).
    real = []
    for _, repository_url, _ in git_standins.repositories(builtin_repos_files()):
        if bundles.bundle_for(repository_url) is not None and repository_url not in real:
            bundles.serve(serve_dir / git_standins.served_path(repository_url), repository_url)
            real.append(repository_url)
    git_standins.from_repos_files(serve_dir, builtin_repos_files(), skip=real)
    # ROBOTIS's real OpenCR archive where ROSLAB_SANDBOX_SOURCES has it (roslab opencr-update --url).
    opencr = real_sources.opencr_archive(real_sources.Bundles.from_env(), serve_dir.parent)
    if opencr is not None:
        write_file(serve_dir / real_sources.OPENCR_SERVED, opencr)
    pypi.build_index(serve_dir)  # the stand-in Python index, for the profiles' python_packages
    served = {distro: "stand-in" for distro in ROS_DISTROS.values()} | runtime.describe()
    return Upstream(url=url, ros_apt_source_sha256=sums, ros=served, real_repositories=tuple(real),
                    snapshot=snapshot)


def snapshot_name(archive: Path) -> str:
    """The stand-in snapshot's name: the UTC day the served ROS archive was built."""
    return datetime.datetime.fromtimestamp(archive.stat().st_mtime, datetime.timezone.utc).date().isoformat()


# -- the HTTP server ------------------------------------------------------------------------

# Beside the server's log: one line per request, `time client method path status bytes`
# (tab-separated), so tests and the benchmark can count what the class fetched upstream.
REQUEST_LOG = "upstream-requests.log"
SERVER_MODULE = "roslab.sandbox.upstream"


@dataclass(frozen=True)
class Request:
    """One line of the upstream's request log."""

    time: float
    client: str
    method: str
    path: str
    status: int
    bytes: int


def read_requests(log_file: Path) -> list[Request]:
    """The requests logged in `log_file` (none if it does not exist yet)."""
    try:
        lines = Path(log_file).read_text().splitlines()
    except FileNotFoundError:
        return []
    requests = []
    for line in lines:
        fields = line.split("\t")
        if len(fields) == 6:
            requests.append(Request(float(fields[0]), fields[1], fields[2], fields[3], int(fields[4]),
                                    int(fields[5])))
    return requests


def serve(serve_dir: Path, address: str, port: int, request_log: Path) -> None:
    """Serve `serve_dir` (a thread per request) and log every request with its status and size."""
    import threading
    from functools import partial
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    lock = threading.Lock()

    class LoggingHandler(SimpleHTTPRequestHandler):
        # Keep-alive, like a real archive: apt-cacher-ng pipelines its requests on one
        # connection, and an HTTP/1.0 server's close after each answer fails them (503).
        protocol_version = "HTTP/1.1"
        status = 0
        sent = 0

        def send_response(self, code, message=None):
            self.status = code
            super().send_response(code, message)

        def copyfile(self, source, outputfile):
            while chunk := source.read(64 * 1024):
                outputfile.write(chunk)
                self.sent += len(chunk)

        def handle_one_request(self):
            self.status, self.sent, self.requestline = 0, 0, ""
            super().handle_one_request()
            if self.requestline:
                path = getattr(self, "path", "").replace("\t", " ").replace("\n", " ")
                with lock, open(request_log, "a") as log_handle:  # reopened: a test may remove it
                    log_handle.write(f"{time.time():.3f}\t{self.client_address[0]}\t{self.command}\t"
                                     f"{path}\t{self.status}\t{self.sent}\n")

        def log_message(self, format, *args):  # the request log above replaces stderr's
            pass

    handler = partial(LoggingHandler, directory=str(serve_dir))
    with ThreadingHTTPServer((address, port), handler) as server:
        server.serve_forever()


def start_server(serve_dir: Path, address: str, port: int, pid_file: Path, log_file: Path) -> None:
    """Serve `serve_dir` on address:port in a background process; wait until it answers.

    Requests are logged in REQUEST_LOG beside `log_file` (kept across restarts of the server).
    """
    request_log = log_file.with_name(REQUEST_LOG)
    with open(log_file, "ab") as log_handle:
        process = subprocess.Popen(
            [sys.executable, "-m", SERVER_MODULE, str(serve_dir), address, str(port), str(request_log)],
            stdin=subprocess.DEVNULL, stdout=log_handle, stderr=log_handle, start_new_session=True,
        )
    write_file(pid_file, f"{process.pid}\n")
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise SandboxError(f"the sandbox upstream server exited at once (see {log_file})")
        try:
            with socket.create_connection((address, port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise SandboxError(f"the sandbox upstream server did not answer on {address}:{port} (see {log_file})")


def stop_server(pid_file: Path) -> None:
    """Stop the server named by `pid_file`, if it is still ours and running."""
    try:
        pid = int(pid_file.read_text())
    except (OSError, ValueError):
        return
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        cmdline = []
    # http.server: a server started before the request log existed.
    if (SERVER_MODULE.encode() in cmdline or b"http.server" in cmdline) and pid_alive(pid):
        terminate(pid)
    pid_file.unlink(missing_ok=True)


if __name__ == "__main__":  # the server process start_server runs
    serve(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), Path(sys.argv[4]))
