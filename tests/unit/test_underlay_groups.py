"""A class compiles once (issue 31): which hosts share an underlay, its digest, which host
builds it, and the roster's refusals of a builder that cannot build for the host naming it."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from roslab.sources import underlay
from roslab.profiles import library
from roslab.roster import RosterError, load_roster
from fixtures.classroom import typed
from roslab.sources.groups import Member, choose_builder, input_digest, roster_inputs


@pytest.fixture(autouse=True)
def _here(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)


# Two ESP32 teams on Ubuntu 24.04 (jazzy), a third on 22.04 (humble): the agent is built on
# the robot (esp32_attached_to: robot), from the profile's pinned .repos of the host's distro.
ROSTER = """\
    classroom:
      name: esp32-lab
      ssh_user: ubuntu
      ubuntu_release: "24.04"
      ros_packages_check: false
      robot_profile: esp32_microros
      esp32_usb_serial: A1
    {classroom}
    teams:
      team1:
        hosts:
          team1-main: {{role: main, address: 192.0.2.11}}
          team1-robot:
            role: robot
            address: 192.0.2.12
    {robot1}
      team2:
        hosts:
          team2-main: {{role: main, address: 192.0.2.21}}
          team2-robot:
            role: robot
            address: 192.0.2.22
    {robot2}
      team3:
        ubuntu_release: "22.04"
        hosts:
          team3-robot: {{role: robot, address: 192.0.2.32}}
    """


def roster(tmp_path: Path, classroom: str = "", robot1: str = "", robot2: str = "") -> Path:
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent(ROSTER).format(classroom=textwrap.indent(classroom, "  "),
                                                   robot1=textwrap.indent(robot1, "        "),
                                                   robot2=textwrap.indent(robot2, "        ")))
    return path


def hosts_of(path: Path) -> dict:
    return {host.name: host for host in load_roster(path).hosts}


def errors_of(path: Path) -> list[str]:
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    return [str(problem) for problem in raised.value.problems]


def test_the_esp32_robots_of_one_distro_form_one_group_and_the_mains_build_nothing(tmp_path):
    hosts = hosts_of(roster(tmp_path))
    inputs = {name: roster_inputs(host.settings) for name, host in hosts.items()}
    assert inputs["team1-robot"] is not None
    assert inputs["team1-robot"] == inputs["team2-robot"]
    # another distro pins other agent branches: another group
    assert inputs["team3-robot"] not in (None, inputs["team1-robot"])
    assert inputs["team1-main"] is None and inputs["team2-main"] is None


def test_the_esp32_profile_declares_the_memory_a_builder_needs(tmp_path):
    profile = library.builtin_profiles()["esp32_microros"]
    assert profile.underlay_build_memory_mb == 1536
    data = hosts_of(roster(tmp_path))["team1-robot"].data
    assert data["roslab_profile"]["underlay_build_memory_mb"] == 1536


def test_a_changed_pin_or_build_setting_makes_another_group(tmp_path):
    base = hosts_of(roster(tmp_path))["team1-robot"].data
    pin = {**base, "source_pins": {}, "roslab_sources": [
        {**repo, "version": "v9"} if i == 0 else repo for i, repo in enumerate(base["roslab_sources"])]}
    assert roster_inputs(typed(pin)) != roster_inputs(typed(base))
    assert roster_inputs(typed({**base, "workspace_colcon_args": ["--parallel-workers", "1"]})) != roster_inputs(typed(base))
    assert roster_inputs(typed({**base, "sources_underlay_dir": "~/other"})) != roster_inputs(typed(base))
    assert roster_inputs(typed({**base, "sources_enabled": False})) is None


def test_the_input_digest_changes_with_every_input_and_only_with_them():
    stamp = underlay.build_stamp({"agent": "a" * 64}, "jazzy", ["--executor", "sequential"])
    digest = input_digest(stamp, "aarch64", "/home/student/roslab_underlay")
    assert digest == input_digest(stamp, "aarch64", "/home/student/roslab_underlay")
    assert len({
        digest,
        input_digest(underlay.build_stamp({"agent": "b" * 64}, "jazzy", ["--executor", "sequential"]),
                     "aarch64", "/home/student/roslab_underlay"),
        input_digest(underlay.build_stamp({"agent": "a" * 64}, "humble", ["--executor", "sequential"]),
                     "aarch64", "/home/student/roslab_underlay"),
        input_digest(underlay.build_stamp({"agent": "a" * 64}, "jazzy", []), "aarch64",
                     "/home/student/roslab_underlay"),
        input_digest(underlay.build_stamp({"agent": "a" * 64}, "jazzy", ["--executor", "sequential"],
                                          {"agent": ["-DX=1"]}), "aarch64", "/home/student/roslab_underlay"),
        input_digest(stamp, "x86_64", "/home/student/roslab_underlay"),
        input_digest(stamp, "aarch64", "/home/teacher/roslab_underlay"),
    }) == 7


def test_the_first_host_with_enough_memory_builds_and_a_small_one_never_does():
    group = [Member("team1-robot", 906), Member("team2-robot", 3792), Member("team3-robot", 7810)]
    assert choose_builder(group, min_memory_mb=1536).builder == "team2-robot"
    assert choose_builder(group).builder == "team1-robot"
    # memory the host could not tell: it may build
    assert choose_builder([Member("a"), Member("b", 4000)], min_memory_mb=1536).builder == "a"


def test_a_named_builder_builds_unless_it_is_too_small_or_not_in_the_group():
    group = [Member("team1-robot", 3792), Member("teacher", 15800)]
    assert choose_builder(group, named="teacher", min_memory_mb=1536).builder == "teacher"
    small = choose_builder([Member("team1-robot", 3792), Member("pi3", 906)], named="pi3", min_memory_mb=1536,
                           profile="esp32_microros")
    assert small.builder is None
    assert "'pi3' has 906 MiB" in small.problem and "1536 MiB profile 'esp32_microros'" in small.problem
    assert "name a host with more memory" in small.problem
    absent = choose_builder(group, named="elsewhere")
    assert absent.builder is None and "'elsewhere' is not a host of this group" in absent.problem


def test_a_group_of_small_hosts_fails_saying_what_to_do():
    choice = choose_builder([Member("a", 900), Member("b", 1000)], min_memory_mb=1536)
    assert choice.builder is None
    assert "no host of this group has the 1536 MiB" in choice.problem
    assert "underlay_builder" in choice.problem


def test_a_named_builder_of_the_same_group_is_accepted(tmp_path):
    hosts = hosts_of(roster(tmp_path, robot1="underlay_builder: team2-robot",
                            robot2="underlay_builder: team2-robot"))
    assert hosts["team1-robot"].data["underlay_builder"] == "team2-robot"
    # classroom-wide: the hosts without an underlay (the mains) and those of another group that
    # do not need it are not refused for it... but team3-robot needs another underlay: refused
    errors = errors_of(roster(tmp_path, classroom="underlay_builder: team1-robot"))
    assert len(errors) == 1, errors
    assert "host 'team3-robot', field 'underlay_builder'" in errors[0]


@pytest.mark.parametrize("robot1, words", [
    ("underlay_builder: team9-robot", "'team9-robot' is not a host of this roster (did you mean"),
    ("underlay_builder: team1-main", "'team1-main' builds no underlay"),
    ("underlay_builder: team3-robot", "'team3-robot' needs another underlay than 'team1-robot' (distro: "),
    ("underlay_builder: Team_2", "is not a valid hostname"),
    ("underlay_builder: [team2-robot]", "underlay_builder"),
])
def test_a_builder_that_cannot_build_for_the_host_is_one_error_naming_file_line_team_host_and_field(
        tmp_path, robot1, words):
    errors = errors_of(roster(tmp_path, robot1=robot1))
    assert len(errors) == 1, errors
    assert errors[0].startswith("lab.yaml:16: team 'team1', host 'team1-robot', field 'underlay_builder'"), errors
    assert words in errors[0], errors


def test_two_hosts_of_one_group_naming_different_builders_are_refused(tmp_path):
    errors = errors_of(roster(tmp_path, robot1="underlay_builder: team1-robot",
                              robot2="underlay_builder: team2-robot"))
    assert len(errors) == 1, errors
    assert "host 'team2-robot', field 'underlay_builder'" in errors[0]
    assert "'team1-robot' of the same group names 'team1-robot': a group has one builder" in errors[0]


@pytest.mark.parametrize("value", ["lots", True, 10, 10**9, 1.5, [1536], None])
def test_a_profiles_build_memory_is_a_number_of_mib_in_range(value):
    from roslab.profiles.schema import read_profile
    from roslab.checked.problems import Report

    mapping = {"profile": "bot", "distros": ["jazzy"], "robot": {"variant": "ros-base"},
               "underlay_build_memory_mb": value}
    report = Report("lab.yaml")
    profile = read_profile(mapping, report, "profiles.bot", "the roster")
    if value is None:  # absent: any host may build
        assert profile is not None and profile.underlay_build_memory_mb is None
        return
    assert profile is None
    (problem,) = [str(p) for p in report.errors]
    assert "field 'profiles.bot.underlay_build_memory_mb'" in problem and "256 to 65536" in problem, problem


def test_a_member_holding_the_build_is_its_source_before_any_that_would_compile_it():
    group = [Member("team1-robot", 3792), Member("pi3", 906, holds=True), Member("teacher", 16000)]
    assert choose_builder(group, min_memory_mb=1536).builder == "pi3"  # shipped, not built: memory is no matter
    assert choose_builder(group, named="teacher", min_memory_mb=1536).builder == "pi3"
    assert choose_builder([Member("a"), Member("b", holds=True), Member("c", holds=True)]).builder == "b"
