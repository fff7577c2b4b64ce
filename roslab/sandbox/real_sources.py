"""The robots' REAL source repositories for the sandbox's git upstream (opt-in).

`ROSLAB_SANDBOX_SOURCES=DIR` (a setting any user of the sandbox may set) names a folder of
git bundles of the public repositories the built-in robot profiles build from source
(`micro-ROS-Agent.bundle`, `osr-rover-code.bundle`, ...; the shared `../shared/sources` beside the clone holds them,
see its README). A repository of a built-in .repos file whose name has a bundle there is served
as that real repository, under the URL the profile names (`<upstream>/git/github.com/owner/
name.git`, where the sandbox roster's `source_url_rewrites` points), the way a lab's git
mirror serves it: every tag and branch of the bundle, real commits, real code. The hosts then
build the real micro-ROS agent and the real rover packages. A repository with no bundle keeps
its stand-in (git_standins.py), and the log says which is which.

What the real trees need that the shared ROS runtime lacks is served in the sandbox's ROS
archive (upstream.py):
- the rosdep keys their package.xml files name (rmw_fastrtps_shared_cpp, teleop_twist_joy,
  python3-serial...), as names: stand-ins on the real ros-core, or Debian packages;
- `micro_ros_msgs`, which Humble and Jazzy release (1.0.0): built here from its bundle against
  the real runtime, installed into /opt/ros/<distro> as a real .deb (`released_debs`), cached by
  the digests of both;
- the CMake packages Ubuntu's ROS debs bring as dependencies (foonathan_memory's, spdlog's,
  tinyxml2's) and the build tools: Debian's packages, as Depends of the stand-ins that bring
  them on Ubuntu (BUILD_DEPENDS).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from .system import SandboxError, announced, file_sha256, folder_setting, log, run

ENV = "ROSLAB_SANDBOX_SOURCES"
REAL_NOTE = "roslab sandbox: REAL source"

# Bump when the served repositories' layout or the built debs change: part of the cache keys.
REAL_SOURCES_VERSION = 1

# Released ROS packages a profile installs from the distro's archive (its ros_packages) whose
# code no runtime tree has: built from their bundle at the version the distro releases
# (ros/rosdistro's jazzy and humble distribution files: micro_ros_msgs 1.0.0-5 and 1.0.0-3).
RELEASED_FROM_SOURCE = {"micro_ros_msgs": ("micro_ros_msgs", "1.0.0")}

# What Ubuntu's ROS debs of these keys bring as Depends, in Debian's names: the build tools and
# the CMake packages of system libraries (ros-<distro>-ament-cmake needs cmake and a compiler
# through ros-dev-tools' build-essential; -fastrtps needs foonathan_memory_vendor, tinyxml2 and
# OpenSSL's development files; -spdlog-vendor needs libspdlog-dev; rosidl's generators need
# empy, numpy and the Python headers). A stand-in of the key depends on them, so a host whose
# rosdep installs the key can build what a real Ubuntu host builds.
BUILD_DEPENDS = {
    "ament_cmake": ("cmake", "g++", "make"),
    "rosidl_default_generators": ("cmake", "g++", "make", "python3-empy", "python3-dev", "python3-numpy",
                                  "python3-lark"),
    "foonathan_memory_vendor": ("libfoonathan-memory-dev",),
    "fastrtps": ("libfoonathan-memory-dev", "libtinyxml2-dev", "libssl-dev"),
    "rmw_fastrtps_shared_cpp": ("libfoonathan-memory-dev", "libtinyxml2-dev", "libssl-dev"),
    "spdlog_vendor": ("libspdlog-dev",),
}

# Executables the real osr_launch.py (osr-rover-code v4.1.0) runs from packages no runtime tree
# has: STAND-INS that say so and stay up, so the launch starts and the rover's own nodes run
# (and fail where this machine lacks the hardware or a package, each in its own line).
STANDIN_EXECUTABLES = {"joy": ("joy_node",), "teleop_twist_joy": ("teleop_node",)}


def standin_executable_files(distro: str, key: str) -> dict[str, str]:
    """The ament index entry and the stand-in executables of `key` (STANDIN_EXECUTABLES)."""
    executables = STANDIN_EXECUTABLES.get(key)
    if not executables:
        return {}
    prefix = f"/opt/ros/{distro}"
    files = {f"{prefix}/share/ament_index/resource_index/packages/{key}": ""}
    for name in executables:
        files[f"{prefix}/lib/{key}/{name}"] = (
            "#!/bin/sh\n"
            f"# roslab sandbox stand-in for {key}'s {name} (ROS 2 {distro}): no code behind it.\n"
            f"echo 'roslab sandbox stand-in: {key} {name} (the shared runtime has no {key}); staying up' >&2\n"
            "exec sleep infinity\n")
    return files


_GIT_ENV = {"GIT_CONFIG_NOSYSTEM": "1", "GIT_CONFIG_GLOBAL": os.devnull, "LC_ALL": "C"}


def sources_dir() -> Path | None:
    """The folder `ROSLAB_SANDBOX_SOURCES` names, or None when it is unset or empty."""
    return folder_setting(ENV, "<repository>.bundle files")


def _git(*args, cwd: Path | None = None) -> str:
    done = subprocess.run(["git", *map(str, args)], cwd=cwd, env={**os.environ, **_GIT_ENV},
                          capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if done.returncode:
        raise SandboxError(f"git {' '.join(map(str, args))}: {done.stderr.strip()}")
    return done.stdout


def repository_name(url: str) -> str:
    """`https://github.com/owner/Name.git` -> `Name` (a bundle's file name without .bundle)."""
    return url.rstrip("/").rsplit("/", 1)[-1].removesuffix(".git")


class Bundles:
    """The bundles of a folder: repository name -> bundle (and its sha256)."""

    def __init__(self, folder: Path | None):
        self.folder = folder
        self.paths = {path.name.removesuffix(".bundle"): path
                      for path in sorted(folder.glob("*.bundle"))} if folder else {}
        self.sums = {name: file_sha256(path) for name, path in self.paths.items()}

    @classmethod
    def from_env(cls) -> "Bundles":
        return cls(sources_dir())

    def __bool__(self) -> bool:
        return bool(self.paths)

    def bundle_for(self, url: str) -> Path | None:
        return self.paths.get(repository_name(url))

    def cache_key(self) -> list:
        return [REAL_SOURCES_VERSION, sorted(self.sums.items())]

    def serve(self, bare: Path, url: str) -> None:
        """Serve the bundle of `url` as the bare repository `bare` (git's dumb HTTP)."""
        bundle = self.bundle_for(url)
        if bundle is None:  # callers serve only what bundle_for found
            raise SandboxError(f"no bundle of {url} in {self.folder}")
        shutil.rmtree(bare, ignore_errors=True)
        bare.parent.mkdir(parents=True, exist_ok=True)
        _git("clone", "--quiet", "--bare", bundle, bare)
        # A bundle's HEAD may name a branch it does not carry: point it at one it has.
        heads = _git("for-each-ref", "--format=%(refname)", "refs/heads", cwd=bare).split()
        if heads and f"refs/heads/{_git('symbolic-ref', 'HEAD', cwd=bare).strip().rsplit('/', 1)[-1]}" not in heads:
            _git("symbolic-ref", "HEAD", heads[0], cwd=bare)
        _git("update-server-info", cwd=bare)
        log.warning(f"sandbox upstream: {url} is the REAL repository from {bundle.name}")

    def tree(self, name: str, ref: str, into: Path) -> Path:
        """Extract `ref` of bundle `name` into `into` (a fresh folder); returns it."""
        bare = into.with_name(into.name + ".git")
        shutil.rmtree(bare, ignore_errors=True)
        _git("clone", "--quiet", "--bare", self.paths[name], bare)
        into.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "--git-dir", str(bare), "archive", "--format=tar", ref],
                                 capture_output=True, check=True, env={**os.environ, **_GIT_ENV}).stdout
        subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
        shutil.rmtree(bare)
        return into


# ROBOTIS's OpenCR firmware archive (roslab opencr-update), as OpenCR-Binaries holds it: the
# sandbox's upstream serves it under the path of ROBOTIS's URL, the tests unpack and run it.
OPENCR_BUNDLE = "OpenCR-Binaries"
OPENCR_ARCHIVE = "turtlebot3/ROS2/latest/opencr_update.tar.bz2"
OPENCR_SERVED = f"github.com/ROBOTIS-GIT/{OPENCR_BUNDLE}/raw/master/{OPENCR_ARCHIVE}"


def opencr_archive(bundles: Bundles, work: Path) -> bytes | None:
    """The bytes of ROBOTIS's `opencr_update.tar.bz2` at the OpenCR-Binaries bundle's HEAD (None
    without that bundle); `work` is a scratch folder."""
    bundle = bundles.paths.get(OPENCR_BUNDLE)
    if bundle is None:
        return None
    bare = work / f"{OPENCR_BUNDLE}.git"
    shutil.rmtree(bare, ignore_errors=True)
    _git("clone", "--quiet", "--bare", bundle, bare)
    try:
        return subprocess.run(["git", "--git-dir", str(bare), "cat-file", "blob", f"HEAD:{OPENCR_ARCHIVE}"],
                              capture_output=True, check=True, env={**os.environ, **_GIT_ENV}).stdout
    finally:
        shutil.rmtree(bare, ignore_errors=True)


def built_manifests(tree: Path) -> list[Path]:
    """The package.xml files in `tree` that colcon builds (none below an ignore marker)."""
    return sorted(manifest for manifest in tree.rglob("package.xml")
                  if not any((parent / marker).exists() for parent in manifest.parents
                             for marker in ("COLCON_IGNORE", "AMENT_IGNORE", "CATKIN_IGNORE")))


def build_released_deb(bundles: Bundles, key: str, distro: str, tree: Path, version: str,
                       out_dir: Path, package: str) -> Path:
    """Build `key` (RELEASED_FROM_SOURCE) from its bundle against the real runtime `tree` (the
    install tree of /opt/ros/<distro>, unpacked), as a .deb that installs into /opt/ros/<distro>.

    CMake runs in a private mount namespace where /opt/ros/<distro> is that tree, so the files
    name the prefix a host installs them to; `make install` stages them with DESTDIR (as a
    Debian package build does).
    """
    name, ref = RELEASED_FROM_SOURCE[key]
    with announced(f"building the sandbox's REAL {package} from {name}.bundle at {ref} against the {distro} "
                   "runtime (once per bundle and runtime)"):
        return _build_released_deb(bundles, key, distro, tree, version, out_dir, package)


def _build_released_deb(bundles: Bundles, key: str, distro: str, tree: Path, version: str,
                        out_dir: Path, package: str) -> Path:
    name, ref = RELEASED_FROM_SOURCE[key]
    with tempfile.TemporaryDirectory(prefix=f"roslab-{key}-") as work_dir:
        work = Path(work_dir)
        source = bundles.tree(name, ref, work / "src")
        stage = work / "stage"
        script = "\n".join([
            "set -e",
            "mount -t tmpfs roslab-sandbox-build /opt",
            f"mkdir -p /opt/ros/{distro}",
            f"mount --bind {tree} /opt/ros/{distro}",
            # the runtime is built for Debian's python3 (3.11), not another python on PATH
            "export PATH=/usr/bin:/bin:/usr/sbin:/sbin",
            f". /opt/ros/{distro}/setup.sh",
            f"cmake -S {source} -B {work}/build -DCMAKE_INSTALL_PREFIX=/opt/ros/{distro} -DBUILD_TESTING=OFF "
            "-DCMAKE_BUILD_TYPE=Release > /dev/null",
            f"cmake --build {work}/build -j 2 > /dev/null",
            f"DESTDIR={stage} cmake --install {work}/build > /dev/null",
        ])
        done = subprocess.run(["unshare", "--mount", "--propagation", "private", "bash", "-c", script],
                              capture_output=True, text=True)
        if done.returncode:
            raise SandboxError(f"building {key} from {name}.bundle against the {distro} runtime failed: "
                               f"{done.stderr.strip()[-2000:]}")
        size_kib = sum(path.stat().st_size for path in stage.rglob("*") if path.is_file()) // 1024
        control = (
            f"Package: {package}\nVersion: {version}\nArchitecture: amd64\n"
            "Maintainer: roslab sandbox <roslab-sandbox@invalid>\nSection: misc\nPriority: optional\n"
            f"Installed-Size: {size_kib}\n"
            f"Depends: ros-{distro}-ros-core\n"
            f"Description: {REAL_NOTE} {key} {ref} for ROS 2 {distro}\n"
            f" Built from {name}.bundle (sha256 {bundles.sums[name]}) at {ref} against the real\n"
            f" {distro} runtime, for the roslab sandbox's Debian 12 hosts.\n")
        (stage / "DEBIAN").mkdir(parents=True)
        (stage / "DEBIAN/control").write_text(control)
        out_dir.mkdir(parents=True, exist_ok=True)
        out = out_dir / f"{package}_{version}_amd64.deb"
        run("dpkg-deb", "--root-owner-group", "-Zgzip", "--build", stage, out)
        return out
