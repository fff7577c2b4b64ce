"""ROS 2 packages by distro and role, and rosdep for the login user."""

from __future__ import annotations

import hashlib
import signal
import subprocess

import pytest
from fixtures.classroom import host_data, typed
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy.ros_install import DEFAULTS, ros_install, ros_packages
from deploy.rosdep import rosdep
from roslab import settings as schema
from roslab.ops.class_lock import AptVersionsNow
from roslab.ops.apt import reporting_a_signal


def settings(**changes):
    return typed({**DEFAULTS, **changes})


def test_main_hosts_get_desktop_and_robots_ros_base():
    assert ros_packages("jazzy", "main", settings()) == ["ros-jazzy-desktop", "ros-dev-tools"]
    assert ros_packages("humble", "robot", settings()) == ["ros-humble-ros-base", "ros-dev-tools"]


def test_variant_override_dev_tools_switch_and_extras_with_the_distro_filled_in():
    packages = ros_packages(
        "jazzy", "robot",
        settings(ros_variant="desktop", ros_dev_tools=False, ros_extra_packages=["ros-{distro}-turtlesim", "htop"]),
    )
    assert packages == ["ros-jazzy-desktop", "ros-jazzy-turtlesim", "htop"]


def test_an_unknown_variant_is_refused_by_the_schema():
    assert "is not one of" in schema.check_value(schema.SETTINGS["ros_variant_main"], "desktop-lite")


@pytest.mark.parametrize("name", ["-oAPT::Get::AllowUnauthenticated=1", "--allow-downgrades", "htop vim",
                                  "ros-{distro}-x\n-y", "ros-{ros_distro}-turtlesim", "Htop"])
def test_an_extra_package_that_is_not_a_package_name_is_refused_by_the_schema(name):
    assert schema.check_value(schema.SETTINGS["ros_extra_packages"], [name])


def test_package_names_can_never_reach_apt_get_as_options():
    with pytest.raises(ValueError, match="starts with '-'"):
        ros_packages("jazzy", "main", settings(ros_extra_packages=["-oAPT::Get::AllowUnauthenticated=1"]))


def test_packages_go_after_the_lock_wait_and_an_end_of_options(tmp_path):
    data = host_data(tmp_path, ros_extra_packages=["ros-{distro}-turtlesim", "g++"])
    assert schema.check_value(schema.SETTINGS["ros_extra_packages"], data["ros_extra_packages"]) is None
    result = plan(ros_install, FakeUbuntu().facts(), data)
    (command,) = result.operation("Ensure ROS 2 jazzy is installed").text()
    assert "apt-get -y -o DPkg::Lock::Timeout=600 " in command
    assert " install -- ros-jazzy-desktop ros-dev-tools ros-jazzy-turtlesim g++; status=$?;" in command


def test_only_missing_packages_are_installed_and_none_is_a_noop(tmp_path):
    host = FakeUbuntu()
    host.packages["ros-jazzy-desktop"] = {"0.11.0"}
    result = plan(ros_install, host.facts(), host_data(tmp_path))
    (command,) = result.operation("Ensure ROS 2 jazzy is installed").text()
    assert " install -- ros-dev-tools; status=$?;" in command
    host.packages["ros-dev-tools"] = {"1.0.0"}
    result = plan(ros_install, host.facts(), host_data(tmp_path))
    assert result.operation("Ensure ROS 2 jazzy is installed").text() == []


@pytest.mark.parametrize("signal_name", ["KILL", "TERM", "INT"])
def test_a_killed_install_says_which_signal_and_keeps_its_exit_status(signal_name):
    command = reporting_a_signal(f"sh -c 'kill -{signal_name} $$'", "apt-get install")
    number = getattr(signal, f"SIG{signal_name}")
    # a shell keeps a signal ignored at its start ignored (a test run started in the background
    # has SIGINT ignored): the command gets the signal's default, as an apt-get on a host has it
    done = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=10,
                          preexec_fn=None if number == signal.SIGKILL else
                          lambda: signal.signal(number, signal.SIG_DFL))
    assert done.returncode == 128 + number
    assert done.stderr.strip().splitlines()[-1] == (  # the shell may say "Killed" before it
        f"roslab: apt-get install was killed by signal SIG{signal_name} (exit status {128 + number})")


def test_an_install_that_fails_on_its_own_keeps_its_words_and_status():
    command = reporting_a_signal("echo 'E: Unable to locate package x' >&2; exit 100", "apt-get install")
    done = subprocess.run(["sh", "-c", command], capture_output=True, text=True, timeout=10)
    assert (done.returncode, done.stderr.strip()) == (100, "E: Unable to locate package x")


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


def test_a_sources_list_the_controller_cannot_fetch_stops_only_the_hosts_that_need_it(tmp_path):
    host = FakeUbuntu()
    host.commands_on_path.add("rosdep")
    url = f"file://{tmp_path}/no-such/20-default.list"
    result = plan(rosdep, host.facts(), host_data(tmp_path, rosdep_sources_list_url=url))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1): rosdep_sources_list_url: cannot download" in error and url in error
    assert not plan(rosdep, host.facts(), host_data(tmp_path)).failed  # hosts using rosdep init


def test_rosdep_for_a_login_user_the_host_lacks_stops_that_host(tmp_path):
    host = FakeUbuntu()
    result = plan(rosdep, host.facts(), host_data(tmp_path, login_user="ghost"))
    assert result.failed and result.operations == []
    assert "login_user 'ghost' does not exist on the host" in result.errors[0]


# --- the class lock (roslab.class_lock): facts in, commands out ------------------------------

LOCK = """groups:
  'jazzy/arm64':
    taken: '2026-11-28T22:00:00Z'
    taken_from: 'team1-main'
    packages:
      'ros-dev-tools': '1.0.1'
      'ros-jazzy-desktop': '0.11.0-1noble.20250101.000000'
"""


def locked(tmp_path, host: FakeUbuntu, available: dict | None = None):
    (tmp_path / "classroom.lock").write_text(LOCK)
    data = host_data(tmp_path, roslab_roster_path=str(tmp_path / "classroom.yaml"),
                     class_lock_debs_dir=str(tmp_path / "class-debs"))
    facts = {**host.facts(), AptVersionsNow: lambda packages: {name: available.get(name, []) for name in packages}}
    return plan(ros_install, facts, data)


def test_a_locked_host_is_pinned_and_installs_the_locked_versions(tmp_path):
    result = locked(tmp_path, FakeUbuntu(), {"ros-jazzy-desktop": ["0.11.1", "0.11.0-1noble.20250101.000000"],
                                               "ros-dev-tools": ["1.0.1"]})
    pins = result.uploads()["/etc/apt/preferences.d/roslab-lock"]
    assert "Package: ros-jazzy-desktop\nPin: version 0.11.0-1noble.20250101.000000\nPin-Priority: 1001" in pins
    (command,) = result.operation("Ensure ROS 2 jazzy is installed").text()
    assert " install -- ros-jazzy-desktop=0.11.0-1noble.20250101.000000 ros-dev-tools=1.0.1;" in command


def test_a_fresh_host_whose_lists_do_not_know_the_locked_packages_asks_apt_for_the_locked_versions(tmp_path):
    """A re-imaged Pi has no ROS source while the run is planned (it comes with the run): its
    lists know no ros-* package. It is not stopped for that; the install names the locked
    versions, so apt installs them or refuses, naming package and version (found end to end)."""
    result = locked(tmp_path, FakeUbuntu(), {})
    assert not result.failed
    (command,) = result.operation("Ensure ROS 2 jazzy is installed").text()
    assert " install -- ros-jazzy-desktop=0.11.0-1noble.20250101.000000 ros-dev-tools=1.0.1;" in command


def test_a_host_on_other_versions_is_moved_to_the_lock_and_a_host_on_them_is_a_noop(tmp_path):
    host = FakeUbuntu()
    host.packages.update({"ros-jazzy-desktop": {"0.11.1"}, "ros-dev-tools": {"1.0.1"}})
    available = {"ros-jazzy-desktop": ["0.11.0-1noble.20250101.000000"]}
    (command,) = locked(tmp_path, host, available).operation("at the class lock's versions").text()
    assert "--allow-downgrades install -- ros-jazzy-desktop=0.11.0-1noble.20250101.000000;" in command
    host.packages["ros-jazzy-desktop"] = {"0.11.0-1noble.20250101.000000"}
    host.files["/etc/apt/preferences.d/roslab-lock"] = locked(tmp_path, host).uploads()[
        "/etc/apt/preferences.d/roslab-lock"].splitlines()
    assert locked(tmp_path, host).changing() == {}


def test_a_locked_version_nobody_serves_stops_the_host_before_anything_is_installed(tmp_path):
    result = locked(tmp_path, FakeUbuntu(), {"ros-jazzy-desktop": ["0.11.1"], "ros-dev-tools": ["1.0.1"]})
    assert result.failed and result.changing() == {}  # nothing pinned, nothing installed
    (error,) = result.errors
    assert "ros-jazzy-desktop=0.11.0-1noble.20250101.000000 is locked but no apt source of the host lists it any more" in error


def test_a_move_to_a_locked_version_nobody_serves_stops_the_host_too(tmp_path):
    host = FakeUbuntu()
    host.packages.update({"ros-jazzy-desktop": {"0.11.0-1noble.20250101.000000"}, "ros-dev-tools": {"1.0.2"}})
    result = locked(tmp_path, host, {"ros-dev-tools": ["1.0.2"]})
    assert result.failed and result.changing() == {}
    assert "ros-dev-tools=1.0.1 is locked but" in result.errors[0]


def test_a_locked_version_the_controller_kept_is_served_instead_of_stopping_the_host(tmp_path):
    """After a sync the archive lists only a newer desktop; the controller kept the locked one
    (roslab lock, class_lock_debs_dir): the host is not stopped, the kept .debs its sources
    dropped are served before the install (which ones is read when it runs), then installed."""
    from roslab import class_debs

    body = b"the locked desktop"
    desktop = ("ros-jazzy-desktop", "0.11.0-1noble.20250101.000000")
    deb = class_debs.KeptDeb(*desktop, "arm64", "ros-jazzy-desktop_0.11.0-1noble.20250101.000000_arm64.deb",
                             hashlib.sha256(body).hexdigest(), len(body), (("Package", desktop[0]),))
    root = class_debs.class_root(tmp_path / "class-debs", tmp_path / "classroom.yaml")
    folder = class_debs.folder(root, "jazzy/arm64")
    folder.mkdir(parents=True)
    (folder / deb.file).write_bytes(body)
    class_debs.write_kept(root, "jazzy/arm64", {desktop: deb})
    result = locked(tmp_path, FakeUbuntu(), {"ros-jazzy-desktop": ["0.11.1"], "ros-dev-tools": ["1.0.1"]})
    assert not result.failed
    names = [op.name.split(" | ")[-1] for op in result.operations if op.commands]
    assert names == ["Ensure apt installs the class lock's versions (2 packages)",
                     "Ensure apt can install the locked versions its sources dropped (the class's kept .debs)",
                     "Ensure ROS 2 jazzy is installed (ros-jazzy-desktop, ros-dev-tools)"]
    assert result.operation("its sources dropped").text() == ["call serve_dropped"]
    (command,) = result.operation("Ensure ROS 2 jazzy is installed").text()
    assert " install -- ros-jazzy-desktop=0.11.0-1noble.20250101.000000 ros-dev-tools=1.0.1;" in command
