"""Every way a host's settings come in is checked by the same rules (issue 37).

Each hostile value of tests/unit/fixtures/hostile_values.py goes in through a roster (its
file:line named), pyinfra's `--data key=value` (the option named, not the roster), and a
hand-made inventory's host data (one line naming host and key), and is refused before any
host is contacted (`no_connections` fails the test on any connection).
"""

from __future__ import annotations

import json

import pytest

from roslab import formats, host_rules, settings
from roslab.host_settings import HostSettingsError, settings_of
from roslab.profiles.resolve import dependency_cycle
from roslab.roster import RosterError, load_roster
from roslab.roster.overrides import command_line_data
from fixtures.classroom import host_data, run_deploy_py
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from fixtures.hostile_values import COMMAND_LINE_ONLY, HOSTILE

ROSTER = """\
classroom:
  ssh_user: ubuntu
teams:
  team1:
    ros_domain_id: 11
    hosts:
      team1-main:
        role: main
        address: 127.0.0.10{host}
"""
HOST_LINE = 9  # the host's last line (its address); a value goes under it
IDS = [f"{key}={json.dumps(value)[:30]}" for key, value, _ in HOSTILE]


@pytest.fixture(autouse=True)
def _here(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)


def roster(tmp_path, host: str = "", extra: str = ""):
    path = tmp_path / "lab.yaml"
    path.write_text(ROSTER.format(host=host) + extra)
    return path


def problems_of(path, argv=()) -> list:
    with pytest.raises(RosterError) as raised:
        load_roster(path, command_line=command_line_data(["pyinfra", *argv]))
    return raised.value.problems


@pytest.mark.parametrize("key, value, words", HOSTILE, ids=IDS)
def test_a_hostile_value_in_a_roster_is_refused_naming_file_line_and_field(key, value, words, tmp_path,
                                                                          no_connections):
    if "host" in settings.SETTINGS[key].levels:
        path = roster(tmp_path, host=f"\n        {key}: {json.dumps(value)}")
        line = HOST_LINE + 1
    else:  # a classroom setting
        path = roster(tmp_path)
        path.write_text(path.read_text().replace("  ssh_user: ubuntu\n", f"  ssh_user: ubuntu\n  {key}: {json.dumps(value)}\n"))
        line = 3
    problems = [problem for problem in problems_of(path) if problem.field == key]
    assert len(problems) >= 1 and all(problem.line == line and problem.path == "lab.yaml" for problem in problems)
    assert words in problems[0].message, problems
    assert no_connections == []


@pytest.mark.parametrize("key, value, words", HOSTILE + COMMAND_LINE_ONLY,
                         ids=IDS + [f"{key}=null" for key, _, _ in COMMAND_LINE_ONLY])
def test_a_hostile_value_from_pyinfras_data_option_is_refused_naming_the_option(key, value, words, tmp_path,
                                                                                no_connections):
    text = value if isinstance(value, str) else json.dumps(value)
    problems = [problem for problem in problems_of(roster(tmp_path), ["--data", f"{key}={text}"])
                if problem.field == key]
    assert problems, key
    for problem in problems:  # the option named, never the roster file
        assert problem.path == "pyinfra's command line" and f"--data {key}=" in problem.message
    assert words in problems[0].message
    assert no_connections == []


@pytest.mark.parametrize("key, value, words", HOSTILE, ids=IDS)
def test_a_hostile_value_in_a_hand_made_inventory_is_one_line_naming_host_and_key(key, value, words):
    with pytest.raises(HostSettingsError) as raised:
        settings_of("pi", {key: value, "ros_domain_id": 5} if key != "ros_domain_id" else {key: value})
    message = str(raised.value)
    assert "\n" not in message and message.startswith("host pi: ") and f"{key}: " in message, message
    assert words in message, message
    assert formats.home_path("~/" + "u" * 5000)[:200] not in message or "bytes long" in message


@pytest.mark.parametrize("key, value, words", [HOSTILE[2], HOSTILE[4], HOSTILE[5], HOSTILE[10]],
                         ids=[IDS[2], IDS[4], IDS[5], IDS[10]])
def test_a_hand_made_inventorys_bad_value_stops_its_host_before_any_change(key, value, words, tmp_path):
    """Through deploy.py as pyinfra runs it on a host of a hand-made inventory."""
    result = plan(run_deploy_py, FakeUbuntu().facts(), host_data(tmp_path, **{key: value}))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi: " in error and f"{key}: " in error and words in error and "nothing was changed" in error
    assert "\n" not in error and "Traceback" not in error


def test_a_hand_made_inventorys_null_domain_id_is_refused_not_left_unexported():
    # A roster derives null from the team's name; a hand-made inventory has no team to.
    with pytest.raises(HostSettingsError) as raised:
        settings_of("pi", {"ros_domain_id": None})
    assert str(raised.value).startswith("host pi: ros_domain_id: must not be null here: give a number "
                                        "(0 to 101, 215 to 232)")
    assert settings_of("pi", {}).ros_domain_id is None  # left out: ROS's own default, 0


def test_a_hand_made_inventory_with_values_a_roster_takes_passes():
    typed = settings_of("pi", {"ros_domain_id": 5, "ros_environment": {"LAB_ROBOT_NAME": "r1"},
                               "sources_underlay_dir": "~/underlay", "workspace_colcon_args":
                               ["--executor", "sequential", "--parallel-workers", "2", "--cmake-args",
                                "-DBUILD_TESTING=OFF"], "network_gateway": "192.168.50.1"})
    assert typed.ros_domain_id == 5 and typed.sources_underlay_dir == "~/underlay"


def test_the_roster_and_a_hand_made_inventory_share_one_set_of_rules():
    """Each rule across a host's values lives in roslab.host_rules, which both ways call."""
    data = {**settings.defaults(), "sources_underlay_dir": "~/ros2_ws", "ssh_port": 7447}
    given = {"sources_underlay_dir", "ssh_port"}
    assert {key for key, _ in host_rules.across_problems(data, given)} == given
    assert {key for key, _ in host_rules.hand_made_problems({key: data[key] for key in given}, data)} == given


ESP32_ROSTER = """\
classroom:
  ssh_user: ubuntu
  ubuntu_release: "24.04"
  ros_packages_check: false
  robot_profile: esp32_microros
  esp32_usb_serial: A1
teams:
  team1:
    hosts:
      team1-main: {role: main, address: 192.0.2.11}
      team1-robot: {role: robot, address: 192.0.2.12}
"""


def test_underlay_builder_from_the_command_line_is_blamed_on_the_option(tmp_path, no_connections):
    (tmp_path / "lab.yaml").write_text(ESP32_ROSTER)
    problems = problems_of(tmp_path / "lab.yaml", ["--data", "underlay_builder=nosuch"])
    mine = [problem for problem in problems if problem.field == "underlay_builder"]
    assert mine and all(problem.path == "pyinfra's command line" for problem in mine), problems
    assert "--data underlay_builder=nosuch: 'nosuch' is not a host of this roster" in mine[0].message


@pytest.mark.parametrize("argv, text", [((), ESP32_ROSTER.replace("esp32_usb_serial: A1", "esp32_usb_serial: A1\n  esp32_udp_port: '5'")),
                                        (("--data", "esp32_udp_port=5"), ESP32_ROSTER)])
def test_a_bad_profile_setting_is_answered_in_words_never_with_its_pattern(argv, text, tmp_path, no_connections):
    (tmp_path / "lab.yaml").write_text(text)
    problems = [str(problem) for problem in problems_of(tmp_path / "lab.yaml", argv)]
    mine = [line for line in problems if "esp32_udp_port" in line]
    assert mine and all("'5' is not a port from 1024 to 65535" in line for line in mine), problems
    assert not any("[0-9]" in line or "6553[0-5]" in line for line in problems)


@pytest.mark.parametrize("written", ["0x7f.0.0.11", "127.11", "2130706443", "0177.0.0.11"])
def test_an_address_in_another_ipv4_form_is_refused_naming_the_address_it_means(written, tmp_path):
    path = roster(tmp_path, extra=f"      team1-robot:\n        role: robot\n        address: {json.dumps(written)}\n")
    problems = [problem for problem in problems_of(path) if problem.field == "address"]
    assert len(problems) == 1 and problems[0].line == 12, problems
    assert "four decimal numbers" in problems[0].message and "'127.0.0.11'" in problems[0].message


def test_an_ipv4_mapped_ipv6_address_is_refused_naming_the_ipv4_address(tmp_path):
    path = roster(tmp_path, extra="      team1-robot:\n        role: robot\n        address: '::ffff:127.0.0.10'\n")
    problems = [problem for problem in problems_of(path) if problem.field == "address"]
    assert len(problems) == 1 and "write '127.0.0.10'" in problems[0].message


@pytest.mark.parametrize("graph, cycle", [
    ({"a": ["b"], "b": ["a"]}, ["a", "b", "a"]),
    ({"a": ["b"], "b": ["c"], "c": ["d"], "d": ["b"]}, ["b", "c", "d", "b"]),
    ({"a": ["b", "c"], "b": ["c"], "c": []}, None),
    ({f"p{i}": [f"p{i + 1}"] for i in range(5000)}, None),  # a long chain: no recursion limit
])
def test_a_build_dependencies_cycle_of_any_length_is_found(graph, cycle):
    assert dependency_cycle(graph) == cycle


def test_colcon_options_come_from_an_allow_list():
    assert formats.colcon_arguments(["--executor", "parallel", "--parallel-workers", "4", "--event-handlers",
                                     "console_direct+", "status-", "--cmake-args", "-DBUILD_TESTING=OFF"]) is None
    assert "takes no value" in formats.colcon_arguments(["--symlink-install=yes"])
    assert "1 to 64" in formats.colcon_arguments(["--parallel-workers=0"])
    assert "roslab decides" in formats.colcon_arguments(["--cmake-args", "-DCMAKE_INSTALL_LIBDIR=/usr/lib"])


# --- a bad file in the profile folder -------------------------------------------------------

SECRET_LINE = "root:$6$PLANTED-secret-hash:19000:0:99999:7:::"


@pytest.fixture
def profile_folder(tmp_path, monkeypatch):
    """A copy of roslab's profile folder to spoil: the real files, then a broken one and a
    symlink out of the folder to a file of secret-looking lines."""
    from roslab.profiles import library

    folder = tmp_path / "profiles"
    folder.mkdir()
    for path in library.data_folder().iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    (folder / "broken.yaml").write_text("profile: broken\nrobot:\n  launch: [\n")
    (tmp_path / "shadow").write_text(f"{SECRET_LINE}\nsecond line: PLANTED-too\n")
    (folder / "leak.yaml").symlink_to(tmp_path / "shadow")
    monkeypatch.setattr(library, "data_folder", lambda: folder)
    library._builtin.cache_clear()
    yield folder
    library._builtin.cache_clear()


def test_a_bad_profile_file_never_stops_an_unrelated_command(profile_folder, tmp_path, capsys, no_connections):
    from roslab.cli.main import main

    with pytest.raises(SystemExit) as exited:
        main(["--help"])
    assert exited.value.code == 0 and "usage: roslab" in capsys.readouterr().out
    assert main(["check", str(roster(tmp_path))]) == 0  # a roster that does not use it
    err = capsys.readouterr().err
    assert "profiles/broken.yaml:4: not valid YAML" in err  # file:line, like a roster's problem
    assert f"{profile_folder / 'leak.yaml'}: a symlink that leads out of the profile folder" in err
    assert "PLANTED" not in err and "root:" not in err  # the file behind the link is never read
    assert "Traceback" not in err and no_connections == []


def test_a_roster_naming_a_broken_profile_is_refused_pointing_at_its_file(profile_folder, tmp_path, capsys):
    from roslab.cli.main import main

    assert main(["check", str(roster(tmp_path, host="\n        robot_profile: broken"))]) == 1
    err = capsys.readouterr().err
    assert "field 'robot_profile': 'broken' is not a robot profile" in err and "its file in roslab's profile" in err
    assert "PLANTED" not in err and "Traceback" not in err


def test_the_home_as_a_cache_is_refused_whatever_home_is(tmp_path, monkeypatch):
    """A HOME inside the temporary directory (a private one, as CI's) is still the whole home."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    assert "not a folder of its own" in formats.cache_dir("~", formats.Context(tmp_path / "roster"))
    assert formats.cache_dir("~/.cache/roslab/rosdep", formats.Context(tmp_path / "roster")) is None


# --- a roster's own profile ------------------------------------------------------------------

PROFILE = """\
profiles:
  mine:
    extends: demo
    robot:
{side}
"""


def profile_problems(tmp_path, side: str) -> list:
    text = ROSTER.format(host="\n      team1-robot:\n        role: robot\n        robot_profile: mine")
    path = tmp_path / "lab.yaml"
    path.write_text(PROFILE.format(side=side) + text)
    return [str(problem) for problem in problems_of(path)]


@pytest.mark.parametrize("graph", ["{a_pkg: [b_pkg], b_pkg: [a_pkg]}",
                                   "{a_pkg: [b_pkg], b_pkg: [c_pkg], c_pkg: [a_pkg]}"])
def test_a_build_dependencies_cycle_in_a_profile_is_refused(graph, tmp_path, no_connections):
    problems = profile_problems(tmp_path, f"      build_dependencies: {graph}")
    assert any("build_dependencies go round in a circle: a_pkg -> b_pkg" in line
               and "host 'team1-robot', field 'robot_profile'" in line for line in problems), problems


def test_skip_packages_cannot_drop_what_the_profiles_own_service_runs(tmp_path, no_connections):
    side = ("      services:\n        - {name: lab-agent, description: the lab agent, command: ros2 run lab_agent agent}\n"
            "      skip_packages: [lab_agent]")
    problems = profile_problems(tmp_path, side)
    assert any("skips lab_agent (skip_packages), which its service 'lab-agent' runs" in line for line in problems), \
        problems


@pytest.mark.parametrize("define", ["-DCMAKE_INSTALL_PREFIX=/usr", "-DCMAKE_INSTALL_LIBDIR:PATH=/lib",
                                    "-Dfoo_DIR:PATH=/etc"])
def test_an_install_location_in_a_profiles_cmake_args_is_refused(define, tmp_path, no_connections):
    problems = profile_problems(tmp_path, f"      cmake_args: {{a_pkg: ['{define}']}}")
    lines = [line for line in problems if "cmake_args" in line]
    assert len(lines) == 1 and lines[0].startswith("lab.yaml:") and "roslab decides that" in lines[0], problems
