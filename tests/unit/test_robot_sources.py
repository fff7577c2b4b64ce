"""The robot profiles' pins against the REAL upstream repositories (git bundles).

The bundles are the public repositories the built-in profiles build from source
(`ROSLAB_SANDBOX_SOURCES`, else `../shared/sources` beside the checkout; see
roslab/sandbox/real_sources.py). Without them these tests skip, saying so. They read what the
pins hold with git and colcon's own package discovery and topological order, as a host's build
would:

- the micro-ROS agent's underlay builds micro_ros_agent after the XRCE-DDS agent only with the
  profile's build-order edge (its package.xml does not declare it);
- the rover's pin is its ROS 2 code, and the ROS 1 leftover is skipped, while a pin holding a
  catkin package is refused before any host is touched, naming the repository and the package;
- each pin (tag or commit) exists upstream and is the version the profile says it is.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from roslab.sources import fetch as source_fetch
from roslab.sources import underlay
from roslab.profiles import library
from roslab.profiles.resolve import resolve_host
from tests import upstream_bundles

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "roslab/profiles/data"
COLCON = Path(sys.executable).parent / "colcon"


def bundles_dir() -> Path | None:
    return upstream_bundles.all_present("micro-ROS-Agent")


pytestmark = pytest.mark.skipif(bundles_dir() is None, reason=(
    "no git bundles of the robots' real repositories (set ROSLAB_SANDBOX_SOURCES, or ../shared/sources): "
    "the pins are checked against the real code only where the bundles are"))


def repos(name: str) -> dict:
    return yaml.safe_load((DATA / name).read_text())["repositories"]


@pytest.fixture(scope="module")
def mirrors(tmp_path_factory) -> Path:
    """A controller cache whose bare mirrors are the bundles (what roslab fetched)."""
    cache = tmp_path_factory.mktemp("sources-cache")
    for name, spec in {**repos("esp32_microros_jazzy.repos"), **repos("esp32_microros_humble.repos"),
                       **repos("osr.repos")}.items():
        mirror = source_fetch.mirror_path(cache, spec["url"])
        if not mirror.exists():
            subprocess.run(["git", "clone", "--quiet", "--bare", str(bundles_dir() / f"{name}.bundle"), str(mirror)],
                           check=True, capture_output=True)
    return cache


def commit_of(mirror: Path, version: str) -> str:
    return subprocess.run(["git", "rev-parse", f"{version}^{{commit}}"], cwd=mirror, capture_output=True,
                          text=True, check=True).stdout.strip()


def show(mirror: Path, version: str, path: str) -> str:
    return subprocess.run(["git", "show", f"{version}:{path}"], cwd=mirror, capture_output=True, text=True,
                          check=True).stdout


def fetched(cache: Path, name: str, spec: dict) -> source_fetch.Fetched:
    mirror = source_fetch.mirror_path(cache, spec["url"])
    commit = commit_of(mirror, spec["version"])
    archive = subprocess.run(["git", "archive", "--format=tar", commit], cwd=mirror, capture_output=True,
                             check=True).stdout
    return source_fetch.Fetched(name, spec["url"], spec["version"], commit, "sha", archive)


def extract(cache: Path, files: list[str], into: Path, skip=()) -> Path:
    """The underlay's src/ as a host gets it (the archives roslab ships)."""
    for file in files:
        for name, spec in repos(file).items():
            item = source_fetch.for_host(fetched(cache, name, spec), cache, skip)
            (into / "src" / name).mkdir(parents=True)
            subprocess.run(["tar", "-x", "-C", str(into / "src" / name)], input=item.archive, check=True)
    return into


def colcon(workspace: Path, *args: str) -> str:
    done = subprocess.run([str(COLCON), "--log-base", os.devnull, *args, "--base-paths", "src"], cwd=workspace,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_the_agent_is_built_after_the_xrce_agent_only_with_the_profiles_edge(mirrors, tmp_path, distro):
    profile = library.builtin_profiles()["esp32_microros"]
    host, _ = resolve_host(profile, {"esp32_usb_serial": "A1"}, distro=distro, role="robot")
    workspace = extract(mirrors, [f"esp32_microros_{distro}.repos"], tmp_path)
    # as a host has it: the profile's colcon.meta, given with --metas
    meta = tmp_path / underlay.COLCON_META  # roslab's folder: a colcon.meta beside src/ is read unasked
    meta.parent.mkdir()
    meta.write_text(underlay.colcon_meta(host["cmake_args"], host["build_dependencies"]))

    def build_dependencies(*metas: str) -> set[str]:
        info = colcon(workspace, "info", "micro_ros_agent", *metas)
        return set(re.search(r"^\s+build: (.*)$", info, re.M).group(1).split())

    # the defect: without the edge colcon may start the agent first (its find_package fails)
    assert "microxrcedds_agent" not in build_dependencies()
    assert "microxrcedds_agent" in build_dependencies("--metas", str(meta))
    order = [line.split("\t")[0] for line in colcon(workspace, "list", "--topological-order", "--metas",
                                                    str(meta)).splitlines()]
    assert order.index("microxrcedds_agent") < order.index("micro_ros_agent"), order
    # the XRCE-DDS agent is a plain CMake package: the profile's settings reach it by its colcon.pkg name
    assert json.loads(show(source_fetch.mirror_path(mirrors, repos(f"esp32_microros_{distro}.repos")[
        "Micro-XRCE-DDS-Agent"]["url"]), repos(f"esp32_microros_{distro}.repos")["Micro-XRCE-DDS-Agent"]["version"],
        "colcon.pkg"))["name"] == "microxrcedds_agent"


@pytest.mark.parametrize("distro, agent, xrce, fast_cdr", [("jazzy", "5.0.2", "v2.4.3", "2"),
                                                          ("humble", "3.0.6", "v2.4.2", "1")])
def test_the_agent_pins_are_the_distros_releases(mirrors, distro, agent, xrce, fast_cdr):
    pins = repos(f"esp32_microros_{distro}.repos")
    agent_mirror = source_fetch.mirror_path(mirrors, pins["micro-ROS-Agent"]["url"])
    manifest = show(agent_mirror, pins["micro-ROS-Agent"]["version"], "micro_ros_agent/package.xml")
    assert f"<version>{agent}</version>" in manifest
    # the agent's tip of its distro's branch (later commits move to Fast DDS 3, which neither has)
    assert commit_of(agent_mirror, pins["micro-ROS-Agent"]["version"]) == commit_of(agent_mirror, distro)
    xrce_mirror = source_fetch.mirror_path(mirrors, pins["Micro-XRCE-DDS-Agent"]["url"])
    assert commit_of(xrce_mirror, pins["Micro-XRCE-DDS-Agent"]["version"]) == commit_of(xrce_mirror, xrce)
    cmake = show(xrce_mirror, xrce, "CMakeLists.txt")
    assert re.search(rf"set\(_fastcdr_version {fast_cdr}\.", cmake), "Fast CDR major of the distro"


def test_the_rovers_pin_is_its_ros2_code_without_the_ros1_leftover(mirrors, tmp_path):
    spec = repos("osr.repos")["osr-rover-code"]
    mirror = source_fetch.mirror_path(mirrors, spec["url"])
    packages = {package.name: (package.build_type, package.ignored) for package in
                source_fetch.packages_in(mirror, commit_of(mirror, spec["version"]))}
    # ROS/led_screen, the ROS 1 leftover, carries a COLCON_IGNORE upstream: colcon and rosdep skip it
    assert packages == {"led_screen": ("catkin", True), "osr_bringup": ("ament_cmake", False),
                        "osr_control": ("ament_python", False), "osr_gazebo": ("ament_cmake", False),
                        "osr_interfaces": ("ament_cmake", False)}
    robot, _ = resolve_host(library.builtin_profiles()["osr"], {}, distro="jazzy", role="robot")
    workspace = extract(mirrors, ["osr.repos"], tmp_path, robot["skip_packages"])
    built = [line.split("\t")[0] for line in colcon(workspace, "list", "--topological-order").splitlines()]
    assert sorted(built) == ["osr_bringup", "osr_control", "osr_interfaces"], built
    assert built.index("osr_interfaces") < built.index("osr_control"), built  # osr_control's exec_depend
    assert not (workspace / "src/osr-rover-code/ROS/led_screen").exists()
    assert "osr_launch.py" in show(mirror, spec["version"], "ROS/osr_bringup/CMakeLists.txt") or \
        show(mirror, spec["version"], "ROS/osr_bringup/launch/osr_launch.py")


def test_a_pin_holding_a_catkin_package_is_refused_naming_the_repository_and_the_package(mirrors, tmp_path):
    """A pin of the rover's ROS 1 days (its 2020 commits: catkin packages only), made here from
    v4.1.0 by taking led_screen's COLCON_IGNORE away: its catkin package would be built."""
    spec = repos("osr.repos")["osr-rover-code"]
    mirror = source_fetch.mirror_path(mirrors, spec["url"])
    work = tmp_path / "work"
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@roslab.invalid"]
    subprocess.run([*git, "clone", "--quiet", str(mirror), str(work)], check=True, capture_output=True)
    for step in (["checkout", "--quiet", spec["version"]], ["rm", "--quiet", "ROS/led_screen/COLCON_IGNORE"],
                 ["commit", "--quiet", "-m", "a ROS 1 pin"], ["push", "--quiet", "origin", "HEAD:refs/tags/ros1"]):
        subprocess.run([*git, *step], cwd=work, check=True, capture_output=True)
    item = fetched(mirrors, "osr-rover-code", {**spec, "version": "ros1"})
    with pytest.raises(source_fetch.SourceError) as refused:
        source_fetch.for_host(item, mirrors, skip_packages=["osr_gazebo"])
    message = str(refused.value)
    assert message.startswith("repository 'osr-rover-code' (https://github.com/nasa-jpl/osr-rover-code.git ros1)")
    assert "package led_screen (ROS/led_screen/package.xml) is a ROS 1 (catkin) package" in message
    assert "skip the package (skip_packages)" in message
    # skipped, the same pin is shipped without it
    shipped = source_fetch.for_host(item, mirrors, skip_packages=["led_screen", "osr_gazebo"])
    names = subprocess.run(["tar", "-t"], input=shipped.archive, capture_output=True, check=True).stdout.decode()
    assert "ROS/osr_control/package.xml" in names and "led_screen" not in names and "osr_gazebo" not in names


def test_the_firmware_builds_the_distros_the_agent_runs(tmp_path):
    ini = (REPO / "firmware/esp32_microros/platformio.ini").read_text()
    pin = re.search(r"micro_ros_platformio#([0-9a-f]{40})", ini).group(1)
    mirror = tmp_path / "platformio.git"
    subprocess.run(["git", "clone", "--quiet", "--bare", str(bundles_dir() / "micro_ros_platformio.bundle"),
                    str(mirror)], check=True, capture_output=True)
    readme = show(mirror, pin, "README.md")
    distros = set(re.findall(r"^\s+- `([a-z]+)`", readme, re.M))
    firmware = set(re.findall(r"^board_microros_distro = ([a-z]+)$", ini, re.M))
    assert firmware == set(library.builtin_profiles()["esp32_microros"].distros) == {"humble", "jazzy"}
    assert firmware <= distros, (firmware, distros)
