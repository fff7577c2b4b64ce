"""The ~/.bashrc block: what a student's shell gets on each distro."""

from __future__ import annotations

import subprocess

import pytest
from pyinfra.api import DeployError

from deploy.shell_env import render_ros_environment


def test_jazzy_block_sources_ros_and_the_workspace_and_sets_discovery():
    text = render_ros_environment("jazzy", 11, "SUBNET", ["10.11.0.2", "team1-robot"])
    assert text.startswith("# managed by roslab")
    assert "source /opt/ros/jazzy/setup.bash" in text
    assert 'source "$HOME/ros2_ws/install/setup.bash"' in text
    assert "export ROS_DOMAIN_ID=11\n" in text
    assert "export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET\n" in text
    assert "export ROS_STATIC_PEERS='10.11.0.2;team1-robot'\n" in text


def test_humble_block_has_no_jazzy_only_variables():
    text = render_ros_environment("humble", 12, "SUBNET", ["10.11.0.2"])
    assert "source /opt/ros/humble/setup.bash" in text
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in text and "ROS_STATIC_PEERS" not in text
    assert "ROS_LOCALHOST_ONLY" not in text
    assert "export ROS_LOCALHOST_ONLY=1" in render_ros_environment("humble", 12, "LOCALHOST")


def test_the_rosdistro_index_is_exported_only_when_set():
    assert "ROSDISTRO_INDEX_URL" not in render_ros_environment("jazzy", 1)
    text = render_ros_environment("jazzy", 1, rosdistro_index_url="http://10.11.0.1/index-v4.yaml")
    assert "export ROSDISTRO_INDEX_URL=http://10.11.0.1/index-v4.yaml" in text


def test_the_block_runs_in_bash_and_exports_what_it_says(tmp_path):
    block = render_ros_environment("jazzy", 30, "LOCALHOST", ["a", "b"], workspace_dir=str(tmp_path))
    shown = subprocess.run(
        ["bash", "-c", block + "\necho $ROS_DOMAIN_ID $ROS_AUTOMATIC_DISCOVERY_RANGE $ROS_STATIC_PEERS"],
        capture_output=True, text=True, check=True,
    ).stdout
    assert shown == "30 LOCALHOST a;b\n"


@pytest.mark.parametrize(
    ("arguments", "field"),
    [
        ({"domain_id": 102}, "ros_domain_id"),
        ({"domain_id": "11"}, "ros_domain_id"),
        ({"discovery_range": "LAN"}, "ros_automatic_discovery_range"),
        ({"static_peers": "10.0.0.1"}, "ros_static_peers"),
    ],
)
def test_bad_settings_name_their_field(arguments, field):
    values = {"distro": "jazzy", "domain_id": 11, **arguments}
    with pytest.raises(DeployError, match=field):
        render_ros_environment(**values)
