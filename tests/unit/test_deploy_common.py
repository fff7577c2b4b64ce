"""Distro selection on the host's real release, and stopping one host before it changes."""

from __future__ import annotations

import pytest
from fixtures.classroom import host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu


def installs(result) -> str:
    return next(" ".join(cmds) for name, cmds in result.changing().items() if "Ensure ROS 2" in name)


@pytest.mark.parametrize(("codename", "distro"), [("noble", "jazzy"), ("jammy", "humble")])
def test_the_distro_follows_the_hosts_release(tmp_path, codename, distro):
    host = with_stand_in_deb(FakeUbuntu(codename), codename)
    assert f"ros-{distro}-desktop" in installs(plan(run_deploy_py, host.facts(), host_data(tmp_path, codename)))


def test_a_team_override_with_packages_for_the_release_is_used(tmp_path):
    host = with_stand_in_deb(FakeUbuntu("noble"))
    result = plan(run_deploy_py, host.facts(), host_data(tmp_path, ros_distro="kilted"))
    assert "ros-kilted-desktop" in installs(result)


@pytest.mark.parametrize(
    ("fake_host", "settings", "reason"),
    [
        (FakeUbuntu("jammy"), {"ros_distro": "jazzy", "ubuntu_release": "22.04"},
         "ros_distro: ROS 2 jazzy has no packages for Ubuntu jammy"),
        (FakeUbuntu("noble"), {"ubuntu_release": "22.04"},
         "ubuntu_release is 22.04 (jammy) in the roster but the host runs Ubuntu noble"),
        (FakeUbuntu("noble"), {"ubuntu_release": "23.10"}, "ubuntu_release: Ubuntu 23.10 is not supported"),
        (FakeUbuntu("bookworm", os_id="debian"), {}, "it runs Debian GNU/Linux 12, not Ubuntu"),
        (FakeUbuntu("noble", user="root"), {"ssh_user": "root"}, "login_user is root"),
    ],
)
def test_a_host_that_cannot_get_its_ros_is_stopped_before_any_change(tmp_path, fake_host, settings, reason):
    data = host_data(tmp_path, fake_host.codename if fake_host.os_id == "ubuntu" else "noble", **settings)
    result = plan(run_deploy_py, fake_host.facts(), data)
    assert result.failed
    assert result.operations == []
    (error,) = result.errors
    # named by the deploy's own check, or (a value no roster takes) by the hand-made inventory rules
    assert ("host pi (team team1)" in error or "host pi: " in error) and reason in error
    assert "nothing was changed" in error


def test_a_login_user_the_host_lacks_stops_that_host_in_one_line_without_raising(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    result = plan(run_deploy_py, host.facts(), host_data(tmp_path, login_user="ghost"))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1): login_user 'ghost' does not exist on the host" in error
    assert "\n" not in error


def test_a_dpkg_interrupted_on_an_earlier_run_is_healed_and_the_run_converges(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.apt_problem = {"interrupted": True, "message": "dpkg was interrupted"}
    result = plan(run_deploy_py, host.facts(), host_data(tmp_path))
    assert not result.failed, result.errors
    names = [op.name for op in result.operations]
    assert "install dpkg was interrupted in is finished" in names[0]
    assert any("Ensure ROS 2 jazzy is installed" in name for name in result.changing())


def test_a_wrong_typed_data_value_stops_that_host_in_one_line_naming_the_key(tmp_path):
    """A hand-made inventory or --data bypasses the roster's checks: the typed settings refuse
    the value for this host only, before anything is read or changed on it."""
    host = with_stand_in_deb(FakeUbuntu())
    result = plan(run_deploy_py, host.facts(), host_data(tmp_path, apt_lock_timeout="600"),
                  hosts_after=(("pi2", host_data(tmp_path)),))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi: apt_lock_timeout must be an integer, not '600' (remove the quotes)" in error
    assert "nothing was changed on it" in error and "\n" not in error
    assert result.facts_asked == []  # refused before the host is read
