"""Step titles a teacher reads: each step's own name, distinct and at most 80 characters
(the compact change lists cut the deploy's title, which every step of a deploy shares), and a
"Starting operation" line that names the step once, not seven deploy titles joined."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import pytest
from fixtures.classroom import host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from test_deploy_converge import turtlebot3_robot_data

from roslab.reporting import summary


def first_run_names(data) -> list[str]:
    codename = {"22.04": "jammy"}.get(data["ubuntu_release"], "noble")
    host = with_stand_in_deb(FakeUbuntu(codename), codename)
    first = plan(run_deploy_py, host.facts(), data)
    assert not first.failed, first.errors
    return [summary.own_name(op.name) for op in first.operations]


@pytest.mark.parametrize("which", ["noble main", "jammy robot", "turtlebot3 robot"])
def test_every_step_of_a_first_run_has_a_distinct_own_name_of_at_most_80_characters(tmp_path, which):
    codename, role = which.split()
    data = (turtlebot3_robot_data(tmp_path) if codename == "turtlebot3"
            else host_data(tmp_path, codename, role))
    names = first_run_names(data)
    assert len(names) > 15
    assert [name for name, count in Counter(names).items() if count > 1] == []
    assert [name for name in names if len(name) > summary.MAX_STEP_NAME] == []


def test_a_steps_title_drops_its_deploys_title_and_is_clipped():
    assert summary.own_name("The demo nodes are built in the login user's workspace | Ensure x") == "Ensure x"
    assert summary.own_name("Ensure y") == "Ensure y"
    assert summary.clipped("a" * 100) == "a" * 77 + "..."
    assert len(summary.clipped("a" * 100)) == summary.MAX_STEP_NAME


def test_a_start_line_names_each_step_without_the_deploys_title():
    deploy = "ROS 2 is installed for the host's distro and role | "
    names = [f"{deploy}Ensure ROS 2 jazzy is installed (ros-jazzy-desktop, ros-dev-tools, many more)",
             f"{deploy}Ensure ROS 2 humble is installed (ros-humble-ros-base, ros-dev-tools)"]
    state = SimpleNamespace(op_meta={"h": SimpleNamespace(names=set(names))})
    line = summary.short_start_line(f"--> Starting operation: {', '.join(names)}", state)
    assert line.startswith("--> Starting operation: Ensure ROS 2 jazzy is installed")
    assert deploy not in line and len(line) <= summary.MAX_START_LINE
    assert summary.short_start_line("--> Starting operation: Ensure z", state) == "--> Starting operation: Ensure z"
    # One name is kept whole, however long: it may end in the path a teacher looks for.
    long_one = f"{deploy}Ensure /home/ubuntu/ros2_ws/src holds the packages of /{'x' * 300}/nodes"
    state = SimpleNamespace(op_meta={"h": SimpleNamespace(names={long_one})})
    assert summary.short_start_line(f"--> Starting operation: {long_one}", state) == (
        f"--> Starting operation: {summary.own_name(long_one)}")
