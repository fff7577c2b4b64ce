"""Launch file names as packages write them, and a profile's launch arguments: checked where the
profile is read (and again once its settings are filled), written into the nodes unit's
`ros2 launch` as one shell word each."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from deploy import workspace as deploy_ws
from roslab import formats
from roslab.quoting import systemd_word
from roslab.roster import RosterError, load_roster


@pytest.mark.parametrize("name", ["main.launch.py", "rplidar_c1_launch.py", "osr_launch.py", "robot.launch.xml",
                                  "bringup_launch.xml", "robot.launch.yaml", "lidar_launch.yaml",
                                  "tb4.standard.launch.py", "view-robot.launch.py"])
def test_the_launch_file_forms_packages_use_are_accepted(name):
    assert formats.launch_file_name(name) is None
    assert formats.launch(f"some_pkg {name}") is None


@pytest.mark.parametrize("name", ["launch.py", "main.py", "main.launch", "main.launch.pyc", "mainlaunch.py",
                                  "-x_launch.py", ".hidden.launch.py", "../up.launch.py", "dir/main.launch.py",
                                  "main.launch.py ", "main.launch.py\n", "a b_launch.py", "main_launch.yml",
                                  "m;ls_launch.py", "main.launch.py;reboot", "maïn.launch.py"])
def test_other_names_are_refused(name):
    assert formats.launch_file_name(name) is not None


@pytest.mark.parametrize("value", ["/dev/ttyUSB0", "laser", "115200", "true", "192.168.186.3", "a,b", "user@host",
                                   "x+y", "ns/robot_1", "rplidar:port"])
def test_plain_launch_argument_values_are_accepted(value):
    assert formats.launch_argument_value(value) is None


@pytest.mark.parametrize("value", ["", "a b", "a;reboot", "$(reboot)", "`id`", "a|b", "a&b", "a>b", "'q'", '"q"',
                                   "a\nb", "a\rb", "x:=y", "x serial_port:=/dev/null", "a=b", "$HOME", "~/x",
                                   "%h", "a\\b", "é", "a\tb", "*", "a" * 201])
def test_hostile_launch_argument_values_are_refused(value):
    assert formats.launch_argument_value(value) is not None


@pytest.mark.parametrize("name", ["", "1port", "serial-port", "a:=b", "a b", "port;x", "a" * 65, "pört"])
def test_bad_launch_argument_names_are_refused(name):
    assert formats.launch_argument_name(name) is not None


def script_launch_words(script: str) -> list[str]:
    """The words bash runs for the script's last step (the launch)."""
    return shlex.split(script.split(" && ")[-1])


def test_the_unit_runs_the_launch_with_each_argument_as_one_word():
    arguments = {"serial_port": "/dev/ttyUSB0", "frame_id": "laser", "serial_baudrate": "460800"}
    script = deploy_ws.exec_script(distro="jazzy", workspace_dir="/home/ubuntu/ros2_ws",
                                   launch="rplidar_ros rplidar_c1_launch.py", launch_arguments=arguments)
    assert script_launch_words(script) == ["exec", "ros2", "launch", "rplidar_ros", "rplidar_c1_launch.py",
                                           "serial_port:=/dev/ttyUSB0", "frame_id:=laser", "serial_baudrate:=460800"]
    unit = deploy_ws.unit_text(role="robot", user="ubuntu", home="/home/ubuntu", workspace_dir="/home/ubuntu/ros2_ws",
                               distro="jazzy", launch="rplidar_ros rplidar_c1_launch.py", environment={},
                               launch_arguments=arguments)
    (exec_start,) = [line for line in unit.splitlines() if line.startswith("ExecStart=")]
    assert exec_start == f"ExecStart=/bin/bash -c {systemd_word(script)}"
    # without arguments the launch is as before
    plain = deploy_ws.exec_script(distro="jazzy", workspace_dir="/w", launch="roslab_bringup robot.launch.py")
    assert script_launch_words(plain) == ["exec", "ros2", "launch", "roslab_bringup", "robot.launch.py"]


@pytest.mark.parametrize("name, value", [("port", "a;reboot"), ("port", "x:=y"), ("port", "a\nb"), ("a:=b", "x"),
                                         ("port", "")])
def test_the_unit_refuses_what_the_profile_check_refuses(name, value):
    with pytest.raises(ValueError, match="launch argument"):
        deploy_ws.exec_script(distro="jazzy", workspace_dir="/w", launch="p main.launch.py",
                              launch_arguments={name: value})


ROSTER = """\
classroom:
  ssh_user: ubuntu
profiles:
  lidar:
    extends: demo
    settings:
      lidar_port:
        doc: the lidar's device
        pattern: "{pattern}"
        default: "{default}"
    robot:
      launch: rplidar_ros rplidar_c1_launch.py
      launch_arguments: {arguments}
teams:
  team1:
    ubuntu_release: "24.04"
    hosts:
      team1-robot:
        role: robot
        address: 192.168.50.12
        robot_profile: lidar
"""


def lidar_roster(tmp_path: Path, arguments: str, pattern: str = "[A-Za-z0-9]+", default: str = "ttyUSB0"):
    path = tmp_path / "lab.yaml"
    path.write_text(ROSTER.format(arguments=arguments, pattern=pattern, default=default))
    return path


def robot_profile(classroom) -> dict:
    (host,) = [host for host in classroom.hosts if host.name == "team1-robot"]
    return host.data["roslab_profile"]


def test_a_profile_passes_launch_arguments_with_its_settings_filled(tmp_path):
    classroom = load_roster(lidar_roster(tmp_path, "{serial_port: '/dev/${lidar_port}', frame_id: laser}"))
    profile = robot_profile(classroom)
    assert profile["launch"] == "rplidar_ros rplidar_c1_launch.py"
    assert profile["launch_arguments"] == {"serial_port": "/dev/ttyUSB0", "frame_id": "laser"}


@pytest.mark.parametrize("arguments, words", [
    ("{serial_port: 'a;reboot'}", ["launch_arguments.serial_port", "not a launch argument value"]),
    ("{serial_port: 'x:=y'}", ["launch_arguments.serial_port", "'='"]),
    ("{'a:=b': x}", ["launch_arguments", "launch argument name"]),
    ("{serial_port: 8888}", ["launch_arguments.serial_port", "string"]),
    ("{serial_port: '${lidar_prot}'}", ["lidar_prot", "did you mean 'lidar_port'"]),
    ("[serial_port]", ["launch_arguments", "mapping"]),
])
def test_a_hostile_launch_argument_is_refused_naming_the_field(tmp_path, arguments, words):
    with pytest.raises(RosterError) as error:
        load_roster(lidar_roster(tmp_path, arguments))
    text = str(error.value)
    for word in words:
        assert word in text, text


def test_a_filled_launch_argument_is_checked_again(tmp_path):
    # a setting's value is a word (roslab.profiles.schema), yet filled in it can make the
    # argument longer than a launch argument may be
    path = lidar_roster(tmp_path, "{serial_port: '/dev/${lidar_port}/" + "a" * 80 + "'}", pattern="[a-z]+",
                        default="b" * 128)
    with pytest.raises(RosterError) as error:
        load_roster(path)
    assert "launch argument serial_port" in str(error.value) and "team1-robot" in str(error.value), str(error.value)
