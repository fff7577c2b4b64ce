"""The class lock taken by a run itself (class_lock_auto, issue 39): the last step a host of an
unlocked group gets, what the controller writes at the run's end, and what it never rewrites."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from fixtures.fake_host import plan
from pyinfra.facts.server import Arch, LinuxDistribution

from deploy import class_lock_taken as step
from roslab import class_lock, class_lock_auto, settings
from roslab.ops import class_lock as lock_ops
from roslab.python_env.wheelhouse import File
from roslab.reporting.summary import RunSummary

TAKEN = "2026-11-28T22:00:00Z"
INSTALLED = {"ros-jazzy-ros-base": "0.11.0-1noble.20250101.000000", "libc6": "2.39-0ubuntu8.4"}
SHA = "ab" * 32
FACTS = {LinuxDistribution: {"release_meta": {"ID": "ubuntu", "UBUNTU_CODENAME": "noble"}}, Arch: "aarch64"}


@pytest.fixture(autouse=True)
def _fresh_run():
    class_lock_auto.forget()
    yield
    class_lock_auto.forget()


def data(roster, auto=True) -> dict:
    return {**settings.defaults("ros_install"), "class_lock_auto": auto, "roslab_roster_path": str(roster)}


def locked(roster, key="jazzy/arm64") -> None:
    group = class_lock.LockedGroup(TAKEN, "robot1", {"libc6": "2.39-0ubuntu8.3"})
    (roster.parent / class_lock.LOCK_FILE).write_text(class_lock.render_lock(class_lock.ClassLock({key: group})))


def test_a_host_whose_group_the_lock_lacks_reads_its_versions_last_at_run_time(tmp_path):
    roster = tmp_path / "classroom.yaml"
    result = plan(step.class_lock_taken, FACTS, data(roster))
    (op,) = result.operations
    assert op.text() == ["call installed_noted"]  # executed on the controller after the host's other steps
    assert result.facts_asked == ["LinuxDistribution"]  # no lock file: the architecture is not read


def test_a_locked_group_or_the_setting_off_plans_nothing(tmp_path):
    roster = tmp_path / "classroom.yaml"
    off = plan(step.class_lock_taken, FACTS, data(roster, auto=False))
    assert off.operations == [] and off.facts_asked == []
    locked(roster)
    result = plan(step.class_lock_taken, FACTS, data(roster))
    assert result.operations == []  # a run never rewrites a locked group
    other = plan(step.class_lock_taken, {**FACTS, Arch: "x86_64"}, data(roster))
    assert [op.text() for op in other.operations] == [["call installed_noted"]]  # jazzy/amd64: not locked


def test_the_reading_is_noted_under_the_hosts_group(tmp_path, monkeypatch):
    roster = tmp_path / "classroom.yaml"
    reading = lock_ops.parse_installed(["arm64", "ii \tlibc6\tarm64\t2.39-0ubuntu8.4"])
    monkeypatch.setattr(step, "get_fact", lambda state, host, cls: reading)
    step.installed_noted(None, SimpleNamespace(name="robot1"), str(roster), "jazzy")
    assert class_lock_auto.write_taken(["robot1"]) == [
        "classroom.lock now locks jazzy/arm64 from robot1 (1 packages, 0 wheels) (`roslab lock` keeps its .debs "
        "while the archives list them): commit it; `roslab lock --update` moves it on purpose"]
    lock, report = class_lock.read_lock(tmp_path / class_lock.LOCK_FILE)
    assert report.errors == [] and lock.groups["jazzy/arm64"].packages == {"libc6": "2.39-0ubuntu8.4"}


def test_the_run_end_takes_each_missing_group_from_its_first_converged_host_with_the_groups_wheels(tmp_path):
    """... and the commits of the repositories the group's converged hosts build (not a failed host's)."""
    roster = tmp_path / "classroom.yaml"
    locked(roster, "humble/arm64")
    before = (tmp_path / class_lock.LOCK_FILE).read_text()
    path = str(roster)
    class_lock_auto.note_installed(path, "team1-main", "jazzy/arm64", {**INSTALLED, "ros2-apt-source": "1.1.0"})
    class_lock_auto.note_installed(path, "team1-robot", "jazzy/arm64", {"libc6": "9"})
    class_lock_auto.note_installed(path, "team2-main", "humble/arm64", {"libc6": "9"})
    class_lock_auto.note_wheels(path, "team1-robot", [File("RPi.GPIO-0.7.1.tar.gz", SHA, True),
                                                      File("ina260-0.0.3-py3-none-any.whl", SHA, False)])
    class_lock_auto.note_wheels(path, "team2-robot", [File("numpy-2.0.0-cp312-cp312-linux_aarch64.whl", SHA, False)])
    agent, lidar = "https://github.com/micro-ROS/micro-ROS-Agent.git@5.0.2", "https://example.org/lidar.git@v1"
    class_lock_auto.note_sources(path, "team1-robot", {agent: "a" * 40})
    class_lock_auto.note_sources(path, "team1-main", {lidar: "b" * 40})
    class_lock_auto.note_sources(path, "team3-robot", {"https://example.org/failed.git@v1": "c" * 40})

    lines = class_lock_auto.write_taken(["team1-robot", "team1-main", "team2-main"])  # roster order, converged

    assert lines == ["classroom.lock now locks jazzy/arm64 from team1-robot (1 packages, 2 wheels, 2 sources) "
                     "(`roslab lock` keeps its .debs while the archives list them): commit it; "
                     "`roslab lock --update` moves it on purpose"]
    lock, _ = class_lock.read_lock(tmp_path / class_lock.LOCK_FILE)
    jazzy = lock.groups["jazzy/arm64"]
    assert (jazzy.taken_from, jazzy.packages) == ("team1-robot", {"libc6": "9"})
    assert jazzy.wheels == {"rpi-gpio": class_lock.LockedWheel("0.7.1", SHA),
                            "ina260": class_lock.LockedWheel("0.0.3", SHA)}
    assert jazzy.sources == {agent: "a" * 40, lidar: "b" * 40}
    assert lock.groups["humble/arm64"].packages == {"libc6": "2.39-0ubuntu8.3"}  # locked: never rewritten
    assert (tmp_path / class_lock.LOCK_FILE).read_text().startswith(before.split("groups:")[0])


def test_a_host_that_failed_is_not_taken_and_nothing_new_writes_nothing(tmp_path):
    roster = tmp_path / "classroom.yaml"
    class_lock_auto.note_installed(str(roster), "team1-main", "jazzy/arm64", INSTALLED)
    assert class_lock_auto.write_taken(["team1-robot"]) == []  # team1-main failed: its group waits
    assert not (tmp_path / class_lock.LOCK_FILE).exists()
    locked(roster, "jazzy/arm64")
    text = (tmp_path / class_lock.LOCK_FILE).read_text()
    class_lock_auto.note_installed(str(roster), "team1-main", "jazzy/arm64", INSTALLED)
    assert class_lock_auto.write_taken(["team1-main"]) == []
    assert (tmp_path / class_lock.LOCK_FILE).read_text() == text


def test_a_dry_run_writes_no_lock(tmp_path):
    roster = tmp_path / "classroom.yaml"
    class_lock_auto.note_installed(str(roster), "team1-main", "jazzy/arm64", INSTALLED)
    assert RunSummary().lock_taken(SimpleNamespace(is_executing=False)) == []
    assert class_lock_auto.write_taken(["team1-main"]) == []  # and what was noted is gone
    assert not (tmp_path / class_lock.LOCK_FILE).exists()


def test_a_lock_broken_since_the_run_began_is_left_alone_in_one_line(tmp_path):
    roster = tmp_path / "classroom.yaml"
    (tmp_path / class_lock.LOCK_FILE).write_text("groups: [\n")
    class_lock_auto.note_installed(str(roster), "team1-main", "jazzy/arm64", INSTALLED)
    (line,) = class_lock_auto.write_taken(["team1-main"])
    assert "classroom.lock was not written: it is no valid class lock now" in line
    assert (tmp_path / class_lock.LOCK_FILE).read_text() == "groups: [\n"
