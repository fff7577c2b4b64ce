"""ROS 2 packages by distro and role, and rosdep for the login user."""

from __future__ import annotations

import pytest
from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.api import DeployError

from deploy.ros_install import DEFAULTS, ros_packages
from deploy.rosdep import rosdep


def settings(**changes):
    return {**DEFAULTS, **changes}


def test_main_hosts_get_desktop_and_robots_ros_base():
    assert ros_packages("jazzy", "main", settings()) == ["ros-jazzy-desktop", "ros-dev-tools"]
    assert ros_packages("humble", "robot", settings()) == ["ros-humble-ros-base", "ros-dev-tools"]


def test_variant_override_dev_tools_switch_and_extras_with_the_distro_filled_in():
    packages = ros_packages(
        "jazzy", "robot",
        settings(ros_variant="desktop", ros_dev_tools=False, ros_extra_packages=["ros-{distro}-turtlesim", "htop"]),
    )
    assert packages == ["ros-jazzy-desktop", "ros-jazzy-turtlesim", "htop"]


def test_an_unknown_variant_is_a_clear_error():
    with pytest.raises(DeployError, match="variant 'desktop-lite' is unknown"):
        ros_packages("jazzy", "main", settings(ros_variant_main="desktop-lite"))


def test_rosdep_is_initialised_and_updated_as_the_login_user(tmp_path):
    host = FakeUbuntu()
    host.commands_on_path.add("rosdep")
    result = plan(rosdep, host.facts(), host_data(tmp_path))
    assert result.operation("rosdep init").text() == ["rosdep init"]
    update = result.operation("younger than rosdep_update_max_age")
    assert update.text() == ["rosdep update"]
    assert update.arguments["_sudo"] and update.arguments["_sudo_user"] == "student"


def test_rosdep_data_from_a_mirror_replaces_rosdep_init(tmp_path):
    sources_list = tmp_path / "20-default.list"
    sources_list.write_text("yaml http://10.11.0.1/rosdep/base.yaml\n")
    host = FakeUbuntu()
    host.commands_on_path.add("rosdep")
    data = host_data(tmp_path, rosdep_sources_list_url=f"file://{sources_list}",
                     rosdistro_index_url="http://10.11.0.1/rosdistro/index-v4.yaml")
    result = plan(rosdep, host.facts(), data)
    assert result.uploads()["/etc/ros/rosdep/sources.list.d/20-default.list"] == sources_list.read_text()
    assert result.operation("follows the changed sources").text() == [
        "env ROSDISTRO_INDEX_URL=http://10.11.0.1/rosdistro/index-v4.yaml rosdep update"
    ]
    host.apply(result)
    again = plan(rosdep, host.facts(), data)
    assert again.changing() == {}
    assert "rosdep cache is 0 s old (max age 604800 s)" in again.noops
