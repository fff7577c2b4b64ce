"""ROSLAB_SANDBOX_ROS_RUNTIME: the sandbox's ROS archive serves real ROS 2 from install trees.

A small tree stands for the real tarball here (the e2e tests use ROSLAB_SANDBOX_ROS_RUNTIME's, ../shared/ros-runtime).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from roslab.sandbox import ros_runtime, upstream
from roslab.sandbox.system import SandboxError

DISTROS = upstream.ROS_DISTROS.values()


def make_tarball(folder: Path, distro: str) -> Path:
    """A tiny install tree as the runtime tarballs hold one (paths relative to /opt/ros/<distro>)."""
    tree = folder / f"tree-{distro}"
    (tree / "bin").mkdir(parents=True)
    (tree / "setup.bash").write_text(f"# real setup of {distro}\n")
    (tree / "bin/ros2").write_text("#!/usr/bin/python3\n")
    (tree / "bin/ros2").chmod(0o755)
    tarball = folder / f"ros-{distro}-core-debian12-amd64.tar.zst"
    subprocess.run(["tar", "--zstd", "-cf", tarball, "-C", tree, "."], check=True)
    return tarball


def fields(deb: Path, *names: str) -> dict[str, str]:
    # All fields, "Name: value" each (with one name asked for, dpkg-deb prints the bare value).
    out = subprocess.run(["dpkg-deb", "--field", deb], capture_output=True, text=True, check=True).stdout
    parsed, name = {}, None
    for line in out.splitlines():
        if line.startswith(" ") and name:
            parsed[name] += "\n" + line
        else:
            name, _, value = line.partition(": ")
            parsed[name] = value
    return parsed


def test_unset_or_empty_means_stand_ins(monkeypatch):
    monkeypatch.delenv(ros_runtime.ENV, raising=False)
    assert ros_runtime.Runtime.from_env(DISTROS).trees == {}
    monkeypatch.setenv(ros_runtime.ENV, "")
    runtime = ros_runtime.Runtime.from_env(DISTROS)
    assert runtime.trees == {} and runtime.debian_packages() == [] and not runtime.is_real("jazzy")


def test_a_missing_folder_is_a_clear_error_naming_the_setting(monkeypatch, tmp_path):
    monkeypatch.setenv(ros_runtime.ENV, str(tmp_path / "nowhere"))
    with pytest.raises(SandboxError, match=rf"{ros_runtime.ENV}=.*nowhere: no such folder"):
        ros_runtime.Runtime.from_env(DISTROS)


def test_a_folder_without_any_runtime_is_refused(monkeypatch, tmp_path):
    monkeypatch.setenv(ros_runtime.ENV, str(tmp_path))
    with pytest.raises(SandboxError, match=r"holds no ros-<distro>-core-\*\.tar\.zst for humble, jazzy"):
        ros_runtime.Runtime.from_env(DISTROS)


def test_two_runtimes_for_one_distro_are_refused(tmp_path):
    (tmp_path / "ros-jazzy-core-a.tar.zst").write_bytes(b"")
    (tmp_path / "ros-jazzy-core-b.tar.zst").write_bytes(b"")
    with pytest.raises(SandboxError, match="more than one runtime for jazzy"):
        ros_runtime.tarballs(tmp_path, DISTROS)


def test_only_the_distros_with_a_tarball_are_real(monkeypatch, tmp_path):
    make_tarball(tmp_path, "jazzy")
    monkeypatch.setenv(ros_runtime.ENV, str(tmp_path))
    runtime = ros_runtime.Runtime.from_env(DISTROS)
    assert runtime.is_real("jazzy") and not runtime.is_real("humble")
    assert runtime.describe()["jazzy"].startswith("real (ros-jazzy-core-debian12-amd64.tar.zst, sha256 ")
    # The Debian runtime libraries go into the Ubuntu-layout archive, Fast DDS's for Jazzy.
    packages = runtime.debian_packages()
    assert {"libfmt9", "libspdlog1.10", "python3-numpy", "libfoonathan-memory0.7.2", "libxml2-utils"} <= set(packages)
    assert set(packages) <= set(upstream.universe_packages({}, packages))


def test_the_archive_serves_the_real_core_and_stand_ins_that_depend_on_it(monkeypatch, tmp_path):
    monkeypatch.setenv("ROSLAB_CACHE_DIR", str(tmp_path / "cache"))  # throwaway keys and archives
    runtime = ros_runtime.Runtime({"jazzy": make_tarball(tmp_path, "jazzy")})
    archive = upstream.ros_archive(set(), runtime)

    core = archive / "pool/main/noble/ros-jazzy-ros-core_0.0.0-1noble_amd64.deb"
    listing = subprocess.run(["dpkg-deb", "--contents", core], capture_output=True, text=True, check=True).stdout
    assert "./opt/ros/jazzy/setup.bash" in listing and "./opt/ros/jazzy/bin/ros2" in listing
    assert "STANDIN" not in listing
    assert all(" root/root " in line for line in listing.splitlines())
    control = fields(core, "Architecture", "Depends", "Description")
    assert control["Architecture"] == "amd64"
    depends = set(control["Depends"].split(", "))
    assert {"libfmt9", "libspdlog1.10", "python3-numpy", "libfoonathan-memory0.7.2", "libtinyxml2-9"} <= depends
    assert "REAL ROS 2" in control["Description"] and runtime.sums["jazzy"] in control["Description"]

    pool = archive / "pool/main/noble"
    base = fields(pool / "ros-jazzy-ros-base_0.0.0-1noble_all.deb", "Depends")
    assert base["Depends"] == "ros-jazzy-ros-core"
    desktop = fields(pool / "ros-jazzy-desktop_0.0.0-1noble_all.deb", "Depends", "Description")
    assert desktop["Depends"] == "ros-jazzy-ros-base" and "stand-in" in desktop["Description"]
    rclpy = fields(pool / "ros-jazzy-rclpy_0.0.0-1noble_all.deb", "Depends")
    assert rclpy["Depends"] == "ros-jazzy-ros-core"
    xmllint = fields(pool / "ros-jazzy-ament-xmllint_0.0.0-1noble_all.deb", "Depends")
    assert xmllint["Depends"] == "ros-jazzy-ros-core, libxml2-utils"
    # turtlesim and every built-in profile's package: stand-ins on the real core (Jazzy's
    # ros_gz also on its simulator's stand-in, which conflicts with Gazebo Classic's).
    for key in ("turtlesim", "turtlebot3_bringup", "turtlebot3_teleop", "ld08_driver", "turtlebot3_gazebo"):
        deb = pool / f"ros-jazzy-{key.replace('_', '-')}_0.0.0-1noble_all.deb"
        assert fields(deb, "Depends")["Depends"] == "ros-jazzy-ros-core", key
    assert fields(pool / "ros-jazzy-ros-gz_0.0.0-1noble_all.deb", "Depends")["Depends"] == (
        "ros-jazzy-ros-core, gz-harmonic")
    # The bringup the robot's service launches is found by the real `ros2 launch`: its launch
    # file, package.xml and ament index entry are in the tree the real setup.bash points at.
    bringup = subprocess.run(["dpkg-deb", "--contents", pool / "ros-jazzy-turtlebot3-bringup_0.0.0-1noble_all.deb"],
                             capture_output=True, text=True, check=True).stdout
    for path in ("share/ament_index/resource_index/packages/turtlebot3_bringup",
                 "share/turtlebot3_bringup/package.xml", "share/turtlebot3_bringup/launch/robot.launch.py"):
        assert f"./opt/ros/jazzy/{path}\n" in bringup, path
    workspace = subprocess.run(["dpkg-deb", "--contents", pool / "ros-jazzy-ros-workspace_0.0.0-1noble_all.deb"],
                               capture_output=True, text=True, check=True).stdout
    assert "setup.bash" not in workspace  # the real tree's own setup scripts, not the stand-in's

    # Humble has no tarball here: today's stand-ins, with their setup scripts and marker.
    humble = subprocess.run(["dpkg-deb", "--contents",
                             archive / "pool/main/jammy/ros-humble-ros-workspace_0.0.0-1jammy_all.deb"],
                            capture_output=True, text=True, check=True).stdout
    assert "./opt/ros/humble/STANDIN" in humble
    packages = (archive / "dists/noble/main/binary-amd64/Packages").read_text()
    assert "Package: ros-jazzy-ros-core\n" in packages

    # Cached by the tarball's sha256: the same runtime is not built again, another one is (its
    # archive's place only: building all stand-ins a second time cost half this test).
    assert upstream.ros_archive(set(), ros_runtime.Runtime({"jazzy": tmp_path / "ros-jazzy-core-debian12-amd64.tar.zst"})) == archive
    builds = []
    monkeypatch.setattr(upstream, "_cached_build", lambda kind, key, build: builds.append(key) or archive.parent / key)
    assert upstream.ros_archive(set(), ros_runtime.Runtime({})) != archive
    assert len(builds) == 1 and not (archive.parent / builds[0]).exists()


def test_a_tarball_that_is_no_install_tree_is_refused(tmp_path):
    (tmp_path / "tree").mkdir()
    (tmp_path / "tree/README").write_text("not ROS\n")
    tarball = tmp_path / "ros-jazzy-core-x.tar.zst"
    subprocess.run(["tar", "--zstd", "-cf", tarball, "-C", tmp_path / "tree", "."], check=True)
    with pytest.raises(SandboxError, match="not a ROS 2 install tree for /opt/ros/jazzy"):
        ros_runtime.build_core_deb(tmp_path / "work", tarball, "jazzy", "ros-jazzy-ros-core", "1", "0" * 64,
                                   tmp_path / "out")


def test_the_bringups_stand_in_launch_needs_the_profiles_variables_and_reports_them(monkeypatch):
    """The launch file the real `ros2 launch` reads, run here with the launch API stubbed (this
    machine has no ROS): a missing variable fails as the real robot.launch.py does, and the one
    process it starts is labelled, says what it got, stays up and ends the launch when it ends."""
    import sys
    import types
    import xml.etree.ElementTree as ElementTree

    assert upstream.profile_launches("jazzy")["turtlebot3_bringup"] == {
        "robot.launch.py": ["LDS_MODEL", "TURTLEBOT3_MODEL"]}
    assert "turtlebot3_bringup" not in upstream.profile_launches("lyrical")  # no TurtleBot3 on Lyrical
    assert upstream.standin_launch_files("jazzy", "turtlesim") == {}
    files = upstream.standin_launch_files("humble", "turtlebot3_bringup")
    share = "/opt/ros/humble/share"
    assert files[f"{share}/ament_index/resource_index/packages/turtlebot3_bringup"] == ""
    manifest = ElementTree.fromstring(files[f"{share}/turtlebot3_bringup/package.xml"])
    assert manifest.findtext("name") == "turtlebot3_bringup"
    source = files[f"{share}/turtlebot3_bringup/launch/robot.launch.py"]
    assert upstream.STANDIN_NOTE in source.splitlines()[0]

    launch = types.ModuleType("launch")
    actions = types.ModuleType("launch.actions")
    launch.LaunchDescription = lambda entities: entities
    actions.ExecuteProcess = lambda **kwargs: kwargs
    actions.Shutdown = lambda reason: ("Shutdown", reason)
    monkeypatch.setitem(sys.modules, "launch", launch)
    monkeypatch.setitem(sys.modules, "launch.actions", actions)
    namespace: dict = {}
    exec(compile(source, "robot.launch.py", "exec"), namespace)

    monkeypatch.delenv("LDS_MODEL", raising=False)
    monkeypatch.setenv("TURTLEBOT3_MODEL", "waffle")
    with pytest.raises(KeyError, match="LDS_MODEL"):
        namespace["generate_launch_description"]()
    monkeypatch.setenv("LDS_MODEL", "LDS-01")
    process, publisher = namespace["generate_launch_description"]()
    # What `roslab verify` expects from a TurtleBot3: LaserScans on /scan, from the real ros2.
    assert publisher["cmd"] == ["ros2", "topic", "pub", "--rate", "2", "--print", "0", "/scan",
                                "sensor_msgs/msg/LaserScan", "{}"]
    assert publisher["on_exit"][0] == "Shutdown"
    assert process["name"] == "roslab-standin-turtlebot3_bringup-robot"
    assert process["on_exit"][0] == "Shutdown"
    # The values are arguments of the shell, never part of its script.
    assert process["cmd"][:2] == ["/bin/bash", "-c"]
    stays_up = 'exec -a "$0" sleep infinity'
    assert process["cmd"][2].endswith(stays_up)
    result = subprocess.run([*process["cmd"][:2], process["cmd"][2].replace(stays_up, "exit 0"),
                             *process["cmd"][3:]], capture_output=True, text=True, check=True)
    assert result.stdout == ("roslab-standin-turtlebot3_bringup-robot: stand-in, no robot code; "
                             "got LDS_MODEL=LDS-01 TURTLEBOT3_MODEL=waffle\n")
    # Under its label: what `ps` shows of the process that stays up.
    labelled = subprocess.run([*process["cmd"][:2], process["cmd"][2].replace("sleep infinity", "ps -o args= -p $$"),
                               *process["cmd"][3:]], capture_output=True, text=True, check=True)
    assert labelled.stdout.splitlines()[-1].startswith("roslab-standin-turtlebot3_bringup-robot -o args= -p ")
