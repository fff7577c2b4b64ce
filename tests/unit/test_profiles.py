"""Robot profiles: built-in data checked by the schema, resolved per side, refused before connecting.

Every refusal names file:line, team, host and field, as a teacher reads it from `roslab check`
(and `inventories/lab.py`, which loads the roster the same way). The package check runs
against the real rosdistro distribution files (tests/unit/fixtures/rosdistro), served on
loopback as a rosdistro index, exactly as a roster's `rosdistro_index_url` would point at a mirror.
"""

from __future__ import annotations

import functools
import hashlib
import gzip
import http.server
import textwrap
import threading
from pathlib import Path

import pytest

from roslab.cli.main import main
from roslab.ros.distro import PLATFORMS
from roslab.profiles import packages
from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host
from roslab.roster import RosterError, load_roster

FIXTURES = Path(__file__).parent / "fixtures" / "rosdistro"
DISTROS = ("humble", "jazzy", "kilted", "lyrical")


@functools.cache
def distribution(distro: str) -> set[str]:
    return packages.packages_of_distribution(gzip.decompress((FIXTURES / f"{distro}-distribution.yaml.gz")
                                                             .read_bytes()))


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)


@pytest.fixture(scope="module")
def rosdistro_url(tmp_path_factory):
    """A rosdistro index on loopback serving the fixtures' distribution files."""
    root = tmp_path_factory.mktemp("rosdistro")
    index = "%YAML 1.1\n---\ntype: index\nversion: 4\ndistributions:\n"
    for distro in DISTROS:
        (root / distro).mkdir()
        (root / distro / "distribution.yaml").write_bytes(
            gzip.decompress((FIXTURES / f"{distro}-distribution.yaml.gz").read_bytes()))
        index += (f"  {distro}:\n    distribution: [{distro}/distribution.yaml]\n"
                  "    distribution_status: active\n    distribution_type: ros2\n    python_version: 3\n")
    (root / "index-v4.yaml").write_text(index)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/index-v4.yaml"
    server.shutdown()


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def errors_of(path: Path) -> list[str]:
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    return [str(problem) for problem in raised.value.problems]


def tb3_roster(tmp_path, url, team_extra="", host_extra="", release="24.04", classroom_extra=""):
    team_extra = team_extra.replace("\n            ", "\n").replace("\n", "\n" + " " * 12)
    return write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {url}
          rosdep_cache_dir: cache
        {classroom_extra}
        teams:
          tb3:
            ros_domain_id: 30
            ubuntu_release: "{release}"
            robot_profile: turtlebot3
            {team_extra}
            hosts:
              tb3-main: {{role: main}}
              tb3-robot: {{role: robot{host_extra}}}
        """)


def tb4_roster(tmp_path, url, profile="turtlebot4", classroom_extra="") -> Path:
    """A one-team TurtleBot 4 (lite) class on 24.04, its robot a Pi 4."""
    roster = tmp_path / "lab.yaml"
    roster.write_text(textwrap.dedent(f"""\
        classroom:
          ssh_user: ubuntu
          ubuntu_release: "24.04"
          rosdistro_index_url: {url}
          {classroom_extra}
        teams:
          t1:
            ros_domain_id: 11
            robot_profile: {profile}
            turtlebot4_model: lite
            hosts:
              t1-main: {{role: main}}
              t1-robot: {{role: robot, board: pi4}}
        """))
    return roster


# --- the built-in profiles ----------------------------------------------------------------

def test_the_built_in_profiles_load():
    assert {"demo", "turtlebot3", "sim"} <= set(builtin_profiles())
    assert builtin_profiles()["turtlebot3"].distros == ("humble", "jazzy")


def sample_value(setting) -> str:
    """A value a pattern setting takes: a serial number's, or a USB port path's."""
    return next(value for value in ("ABC123", "1-1.2") if setting.problem(value) is None)


@pytest.mark.parametrize("name", sorted(builtin_profiles()))
def test_every_built_in_profile_installs_only_packages_its_distros_have(name):
    profile = builtin_profiles()[name]
    values_per_setting = {key: list(s.allowed) or [s.default or sample_value(s)] for key, s in profile.settings.items()}
    checked = 0
    for distro in profile.distros:
        for role in profile.sides:
            # Every value of every setting (the when blocks), one setting at a time.
            combos = [{}] + [{key: value} for key, values in values_per_setting.items() for value in values]
            for combo in combos:
                given = {key: values[0] for key, values in values_per_setting.items()} | combo
                data, problems = resolve_host(profile, given, distro=distro, role=role)
                assert not problems, problems
                missing = [p for p in data["ros_packages"] if p not in distribution(distro)]
                assert not missing, f"{name} ({role}) on {distro}: {missing} not in rosdistro"
                checked += len(data["ros_packages"])
    assert checked or name == "demo"


def test_turtlebot3_robot_gets_the_driver_of_its_lidar_and_the_device_rules():
    profile = builtin_profiles()["turtlebot3"]
    drivers = {}
    for lds in ("LDS-01", "LDS-02", "LDS-03"):
        data, _ = resolve_host(profile, {"turtlebot3_model": "waffle_pi", "lds_model": lds},
                               distro="jazzy", role="robot")
        drivers[lds] = sorted(p for p in data["ros_packages"] if "driver" in p)
        assert data["environment"] == {"TURTLEBOT3_MODEL": "waffle_pi", "LDS_MODEL": lds}
        assert data["launch"] == "turtlebot3_bringup robot.launch.py"
        assert data["groups"] == ["dialout"]
        assert 'ATTRS{idProduct}=="5740", ENV{ID_MM_DEVICE_IGNORE}="1"' in data["udev_rules"]
        assert 'ATTR{idProduct}=="df11"' in data["udev_rules"]
        # ROBOTIS's 99-turtlebot3-cdc.rules names every CP2102 tb3_lidar, whatever the LDS model
        # (coin_d4_driver, LDS-03, opens it): tests/unit/test_devices_udev.py runs the rules.
        assert 'ATTRS{idProduct}=="ea60"' in data["udev_rules"] and 'SYMLINK+="tb3_lidar"' in data["udev_rules"]
        (opencr,) = [item for item in data["checklist"] if "OpenCR firmware" in item]
        assert "waffle.opencr for waffle and waffle_pi" in opencr and "waffle_pi.opencr" not in opencr
    # Every driver on every robot (as turtlebot3_bringup's own dependencies): a new lidar is a variable.
    assert all(found == ["coin_d4_driver", "hls_lfcd_lds_driver", "ld08_driver"] for found in drivers.values())
    data, _ = resolve_host(profile, {"turtlebot3_model": "burger", "lds_model": "LDS-01",
                                     "lds_usb_serial": "0001"}, distro="humble", role="robot")
    assert 'ATTRS{serial}=="0001"' in data["udev_rules"]
    main_side, _ = resolve_host(profile, {"turtlebot3_model": "burger"}, distro="humble", role="main")
    assert main_side["environment"] == {"TURTLEBOT3_MODEL": "burger"}
    assert main_side["launch"] is None and main_side["udev_rules"] == ""
    assert "ros-humble-turtlebot3-teleop" in main_side["packages"]


def test_sim_brings_each_distros_gazebo_and_keeps_discovery_on_the_host():
    profile = builtin_profiles()["sim"]
    humble, _ = resolve_host(profile, {}, distro="humble", role="main")
    jazzy, _ = resolve_host(profile, {}, distro="jazzy", role="main")
    assert "ros-humble-gazebo-ros-pkgs" in humble["packages"]
    assert "ros-jazzy-ros-gz" in jazzy["packages"]
    assert humble["discovery"] == "localhost"
    assert {p.distro: p.gazebo.ros_package for p in PLATFORMS}["humble"] == "gazebo_ros_pkgs"


# --- a TurtleBot3 class from the roster -----------------------------------------------------

def test_a_turtlebot3_team_loads_with_its_profile_per_side(tmp_path, rosdistro_url):
    classroom = load_roster(tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\nlds_model: LDS-02"))
    main_host, robot = classroom.hosts
    assert robot.data["roslab_profile"]["environment"] == {"TURTLEBOT3_MODEL": "burger", "LDS_MODEL": "LDS-02"}
    assert "ros-jazzy-ld08-driver" in robot.data["roslab_profile"]["packages"]
    assert robot.data["nodes_launch"] == "turtlebot3_bringup robot.launch.py"
    assert (robot.variant, main_host.variant) == ("ros-base", "desktop")
    assert robot.data["nodes_verify_topic"] == "/scan"
    assert main_host.data["roslab_profile"]["environment"] == {"TURTLEBOT3_MODEL": "burger"}
    assert main_host.data["nodes_launch"] is None  # the main runs no service: the students drive


def test_turtlebot3_on_lyrical_is_refused_with_what_would_work(tmp_path, rosdistro_url):
    path = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\n            lds_model: LDS-02",
                      release="26.04", classroom_extra=f"  ros_apt_source_sha256: {{resolute: '{'ab' * 32}'}}")
    errors = errors_of(path)
    assert errors == [  # the team's profile and release: said once, for the team
        "lab.yaml:10: team 'tb3', field 'robot_profile': profile 'turtlebot3' supports "
        "humble, jazzy, not lyrical (this host's distro): set ubuntu_release to 22.04 (humble) or 24.04 "
        "(jazzy), or another robot_profile"]


def test_a_missing_lds_model_is_refused_for_the_robot_only(tmp_path, rosdistro_url):
    errors = errors_of(tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger"))
    assert errors == [
        "lab.yaml:10: team 'tb3', host 'tb3-robot', field 'lds_model': profile 'turtlebot3' needs lds_model "
        "(LDS-01, LDS-02, LDS-03): The lidar (LDS_MODEL); robots sold from 2025 ship the LDS-03."]


def test_a_misspelt_model_is_refused_with_did_you_mean(tmp_path, rosdistro_url):
    errors = errors_of(tb3_roster(tmp_path, rosdistro_url, "lds_model: LDS-02", host_extra=", turtlebot3_model: burgr"))
    assert errors == [
        "lab.yaml:10: team 'tb3', host 'tb3-main', field 'turtlebot3_model': profile 'turtlebot3' needs "
        "turtlebot3_model (burger, waffle, waffle_pi): The TurtleBot3's model (TURTLEBOT3_MODEL; OpenCR "
        "firmware burger.opencr, or waffle.opencr for waffle and waffle_pi).",
        "lab.yaml:14: team 'tb3', host 'tb3-robot', field 'turtlebot3_model': 'burgr' is not one of burger, "
        "waffle, waffle_pi (did you mean 'burger'?)"]


def test_a_package_not_in_the_distro_is_refused_with_did_you_mean(tmp_path, rosdistro_url):
    path = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\n            lds_model: LDS-02",
                      host_extra=', ros_extra_packages: ["ros-{distro}-turtlebot3-bringupp", "htop"]')
    assert errors_of(path) == [
        "lab.yaml:15: team 'tb3', host 'tb3-robot', field 'ros_extra_packages': ros-jazzy-turtlebot3-bringupp "
        f"is not a package of ROS 2 jazzy (rosdistro {rosdistro_url}) (did you mean ros-jazzy-turtlebot3-bringup?)"]


def test_the_package_check_reads_the_controllers_copy_offline(tmp_path, rosdistro_url):
    roster = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\n            lds_model: LDS-02")
    load_roster(roster)  # online: the files are kept in rosdep_cache_dir
    packages._parsed.clear()
    offline = roster.read_text().replace("  ssh_user: ubuntu\n", "  ssh_user: ubuntu\n  offline: true\n")
    roster.write_text(offline.replace('lds_model: LDS-02', 'lds_model: LDS-02\n    '
                                      'ros_extra_packages: ["ros-jazzy-nav2-bringupp"]'))
    errors = errors_of(roster)
    assert len(errors) == 1, errors  # the team's value: said once, for the team
    assert "team 'tb3', field 'ros_extra_packages'" in errors[0]
    error = errors[0]
    assert "ros-jazzy-nav2-bringupp is not a package of ROS 2 jazzy" in error
    assert "did you mean ros-jazzy-nav2-bringup?" in error


def test_unreachable_rosdistro_data_is_a_warning_not_a_silent_pass(tmp_path):
    packages._parsed.clear()
    roster = tb3_roster(tmp_path, "http://127.0.0.1:9/index-v4.yaml",
                        "turtlebot3_model: burger\n            lds_model: LDS-02")
    classroom = load_roster(roster)
    (warning,) = [str(w) for w in classroom.warnings]
    assert "the ROS package names of the jazzy hosts were not checked against rosdistro" in warning
    assert "ros_packages_check: false" in warning


def test_a_profile_naming_an_unknown_setting_is_refused_where_it_is_defined(tmp_path, rosdistro_url):
    path = write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {rosdistro_url}
        profiles:
          mybot:
            extends: turtlebot3
            robot:
              environment:
                MYBOT_ARM: "${{arm_modle}}"
        teams:
          t1:
            robot_profile: mybot
            turtlebot3_model: burger
            lds_model: LDS-03
            hosts:
              t1-robot: {{role: robot}}
        """)
    errors = errors_of(path)
    assert errors[0] == ("lab.yaml:9: field 'profiles.mybot.robot.environment.MYBOT_ARM': names ${arm_modle}, "
                         "which is not a setting of this profile")
    known = ", ".join(sorted(builtin_profiles()))
    assert errors[1] == ("lab.yaml:12: team 't1', host 't1-robot', field 'robot_profile': 'mybot' is not a robot "
                         f"profile (known: {known})")


def test_a_roster_profile_extends_a_built_in_one(tmp_path, rosdistro_url):
    path = write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {rosdistro_url}
          rosdep_cache_dir: cache
        profiles:
          tb3_nav:
            extends: turtlebot3
            settings:
              map_name: {{allowed: [house, world], default: world}}
            main:
              ros_packages: [nav2_bringup, turtlebot3_navigation2]
              environment: {{TB3_MAP: "${{map_name}}"}}
        teams:
          t1:
            robot_profile: tb3_nav
            turtlebot3_model: burger
            lds_model: LDS-03
            hosts:
              t1-main: {{role: main}}
              t1-robot: {{role: robot}}
        """)
    main_host, robot = load_roster(path).hosts
    assert main_host.data["roslab_profile"]["environment"] == {"TURTLEBOT3_MODEL": "burger", "TB3_MAP": "world"}
    assert "ros-jazzy-nav2-bringup" in main_host.data["roslab_profile"]["packages"]
    assert robot.data["roslab_profile"]["launch"] == "turtlebot3_bringup robot.launch.py"


def test_a_profile_setting_on_a_host_whose_profile_lacks_it_is_refused(tmp_path):
    path = write(tmp_path, """\
        classroom:
          ssh_user: ubuntu
        teams:
          t1:
            lds_model: LDS-02
            hosts:
              t1-robot: {role: robot}
        """)
    # whichever profiles declare lds_model (turtlebot3 today): the message names them all
    owners = ", ".join(profile.name for profile in builtin_profiles().values() if "lds_model" in profile.settings)
    assert "turtlebot3" in owners
    assert errors_of(path) == [
        "lab.yaml:5: team 't1', host 't1-robot', field 'lds_model': lds_model is a setting of profile "
        f"{owners}, not of this host's profile 'demo'"]


def test_sim_has_no_robot_and_humble_on_a_pi5_has_no_image(tmp_path):
    path = write(tmp_path, """\
        classroom:
          ssh_user: ubuntu
          ros_packages_check: false
        teams:
          t1:
            ros_domain_id: 1
            robot_profile: sim
            hosts:
              t1-main: {role: main}
              t1-robot: {role: robot}
          t2:
            ros_domain_id: 2
            ubuntu_release: "22.04"
            hosts:
              t2-robot: {role: robot, board: pi5}
        """)
    assert errors_of(path) == [
        "lab.yaml:7: team 't1', host 't1-robot', field 'robot_profile': profile 'sim' has no robot side "
        "(only main): give this host another robot_profile (e.g. demo), or leave it out of the team",
        "lab.yaml:15: team 't2', host 't2-robot', field 'board': there is no Ubuntu 22.04 image for a "
        "Raspberry Pi 5 (its first is 24.04): use ubuntu_release 24.04 (jazzy), or another board for Humble"]


def test_sim_main_keeps_discovery_on_the_host_unless_the_roster_says_otherwise(tmp_path):
    path = write(tmp_path, """\
        classroom:
          ssh_user: ubuntu
          ros_packages_check: false
        teams:
          t1:
            ros_domain_id: 1
            robot_profile: sim
            hosts:
              t1-main: {role: main}
        """)
    (host,) = load_roster(path).hosts
    assert host.data["ros_automatic_discovery_range"] == "LOCALHOST"
    assert host.data["nodes_launch"] is None


def test_roslab_check_refuses_before_connecting(tmp_path, rosdistro_url, capsys):
    path = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burgr\n            lds_model: LDS-02")
    assert main(["check", str(path)]) == 1
    err = capsys.readouterr().err
    assert "lab.yaml:11: team 'tb3', field 'turtlebot3_model': 'burgr' is not one of" in err
    assert err.count("'burgr' is not one of") == 1  # the team's value: once, not once per host


@pytest.mark.parametrize("variables, problem", [
    ({"ROS_DOMAIN_ID": "5"}, "ROS_DOMAIN_ID is not set through an environment mapping"),
    ({"LD_PRELOAD": "/tmp/x.so"}, "LD_PRELOAD is not set through an environment mapping"),
    ({"1BAD": "x"}, "'1BAD' is not a variable name"),
    ({"LAB_GOOD": "two\nlines"}, "the value of LAB_GOOD must be a single line"),
    ({"LAB_GOOD": 5}, "the value of LAB_GOOD must be a string"),
])
def test_ros_environment_refuses_what_no_destination_can_carry(tmp_path, variables, problem):
    import yaml as _yaml
    path = write(tmp_path, "classroom:\n  ssh_user: ubuntu\n  ros_environment: "
                 + _yaml.safe_dump(variables, default_flow_style=True).strip()
                 + "\nteams:\n  t1:\n    hosts:\n      t1-main: {role: main}\n")
    (error,) = errors_of(path)
    assert error.startswith("lab.yaml:3: field 'ros_environment': ") and problem in error


# --- roslab opencr-update ------------------------------------------------------------------

def test_opencr_update_refuses_in_one_line_naming_the_device():
    from roslab.robot_tools.opencr_update import UsbSerialPort, port_problem

    fact = UsbSerialPort()
    assert fact.process(["missing"]) is None
    assert fact.process(["present 0483 5740 "]) == "0483:5740"
    assert fact.process(["present "]) == ""
    assert port_problem("tb3-robot", "/dev/ttyACM0", None) == (
        "no OpenCR board on tb3-robot: /dev/ttyACM0 does not exist (attach the OpenCR to the Pi by USB "
        "and run this again)")
    assert port_problem("tb3-robot", "/dev/ttyACM0", "1a86:7523") == (
        "/dev/ttyACM0 on tb3-robot is 1a86:7523, not an OpenCR (0483:5740): nothing was flashed")
    assert port_problem("tb3-robot", "/dev/ttyACM0", "0483:5740") is None


def test_opencr_update_refuses_a_host_that_is_not_a_turtlebot3_robot(tmp_path, rosdistro_url, capsys):
    path = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\nlds_model: LDS-02")
    assert main(["opencr-update", str(path), "--limit", "tb3-main"]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "roslab opencr-update: tb3-main is not a TurtleBot3 robot in the roster (role robot with robot_profile: "
        "turtlebot3)")
    assert main(["opencr-update", str(path), "--limit", "tb3-robt"]) == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith("roslab opencr-update: --limit 'tb3-robt' selects no host of the roster")
    assert "did you mean 'tb3-robot'?" in err


def test_opencr_update_goes_to_each_turtlebot3_robot_the_limit_selects(tmp_path, rosdistro_url, capsys,
                                                                      monkeypatch):
    """A team or `robot` selects every TurtleBot3 robot in it; one without its board, or out of
    reach, is one line and leaves the others to go on."""
    import pyinfra.api.connect

    from roslab import reach
    from roslab.robot_tools.opencr_update import UsbSerialPort

    text = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\nlds_model: LDS-02").read_text()
    second = text[text.index("  tb3:"):].replace("tb3", "tb4").replace("ros_domain_id: 30", "ros_domain_id: 31")
    path = write(tmp_path, text + second)
    asked = []

    class Robot:
        def __init__(self, name):
            self.name = name

        def get_fact(self, fact, port):
            assert fact is UsbSerialPort and port == "/dev/ttyACM0"
            return None  # no board attached

    class State:
        def __init__(self, names):
            self.active_hosts = [Robot(name) for name in names if name != "tb3-robot"]  # tb3-robot is off
            self.inventory = type("Inventory", (), {"iter_activated_hosts": lambda _: self.active_hosts})()

    def connected_state(groups, limit):
        asked.append(limit)
        return State(limit)

    monkeypatch.setattr(reach, "connected_state", connected_state)
    monkeypatch.setattr(pyinfra.api.connect, "disconnect_all", lambda state: None)
    archive = tmp_path / "opencr_update.tar.bz2"  # had and checked before any robot is reached
    archive.write_bytes(b"an archive")
    source = ["--url", archive.as_uri(), "--sha256", hashlib.sha256(b"an archive").hexdigest()]
    assert main(["opencr-update", str(path), "--limit", "robot", *source]) == 1
    assert asked == [["tb3-robot", "tb4-robot"]]
    assert [line for line in capsys.readouterr().err.splitlines() if "GET /" not in line] == [
        "roslab opencr-update: cannot reach tb3-robot",
        "no OpenCR board on tb4-robot: /dev/ttyACM0 does not exist (attach the OpenCR to the Pi by USB and run "
        "this again)"]
    assert main(["opencr-update", str(path), "--limit", "tb4", *source]) == 1  # the team: its robot, not its main
    assert asked[-1] == ["tb4-robot"]


@pytest.mark.parametrize("profile_text, problem", [
    ("settings: {locale: {allowed: [a]}}", "'locale' is a roslab setting"),
    ("settings: {arm: {pattern: '.*', default: 'a b'}}", "'a b' is not a word"),
    ("robot: {udev_rules: [{rule: 'KERNEL==\"ttyUSB0\", RUN+=\"/bin/sh -c id\"'}]}",
     "a profile declares its devices, not udev rule text"),
    ("robot: {environment: {PATH: /tmp}}", "PATH is not set through an environment mapping"),
    ("robot: {ros_packages: [Nav2]}", "'Nav2' is not a ROS package name"),
    ("robot: {launhc: x y.launch.py}", "unknown key 'launhc' in a profile (did you mean 'launch'?)"),
    ("robot: {when: [{if: {lds_modle: LDS-01}, ros_packages: [x]}]}",
     "tests 'lds_modle', which is not a setting of this profile (did you mean 'lds_model'?)"),
    ("distros: [rolling]", "must list the distros the profile supports"),
    ("robot: {os_tweaks: {mask_units: ['sleep.target; rm -rf /']}}", "is not a unit an OS tweak may mask"),
    ("robot: {os_tweaks: {swap_mb: 2G}}", "must be a whole number of MiB"),
    ("robot: {os_tweaks: {swap_mb: 1000000000}}", "must be a whole number of MiB"),
    ("robot: {os_tweaks: {reboot: true}}", "unknown key 'reboot'"),
])
def test_a_roster_profile_is_checked_like_the_roster(tmp_path, profile_text, problem):
    path = write(tmp_path, "classroom:\n  ssh_user: ubuntu\nprofiles:\n  mine:\n    extends: turtlebot3\n    "
                 + profile_text + "\nteams:\n  t1:\n    hosts:\n      t1-main: {role: main}\n")
    errors = errors_of(path)
    assert any(problem in error and "field 'profiles.mine" in error for error in errors), errors


def test_role_named_keys_are_deprecated_aliases_of_the_role_free_ones(tmp_path):
    path = write(tmp_path, """\
        classroom:
          ssh_user: ubuntu
          ros_variant_robot: ros-core
          nodes_launch_main: my_pkg main.launch.py
        teams:
          t1:
            hosts:
              t1-main: {role: main}
              t1-robot: {role: robot, nodes_launch: other_pkg robot.launch.py}
        """)
    classroom = load_roster(path)
    main_host, robot = classroom.hosts
    assert (main_host.variant, robot.variant) == ("desktop", "ros-core")
    assert main_host.data["nodes_launch"] == "my_pkg main.launch.py"
    assert robot.data["nodes_launch"] == "other_pkg robot.launch.py"
    warnings = sorted({str(w) for w in classroom.warnings})
    assert warnings == [
        "lab.yaml:3: team 't1', field 'ros_variant_robot': ros_variant_robot is deprecated: set ros_variant "
        "(on the host, or in a robot profile's side); it is honoured for now",
        "lab.yaml:4: team 't1', field 'nodes_launch_main': nodes_launch_main is deprecated: set nodes_launch "
        "(on the host, or in a robot profile's side); it is honoured for now"]


def test_a_profile_setting_from_pyinfras_command_line_is_checked_like_the_rosters(tmp_path, rosdistro_url):
    from roslab.roster.overrides import command_line_data

    roster = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\n            lds_model: LDS-02")
    classroom = load_roster(roster, command_line=command_line_data(["pyinfra", "--data", "lds_model=LDS-03"]))
    robot = next(host for host in classroom.hosts if host.role == "robot")
    assert robot.data["roslab_profile"]["environment"]["LDS_MODEL"] == "LDS-03"
    with pytest.raises(RosterError) as raised:
        load_roster(roster, command_line=command_line_data(["pyinfra", "--data", "lds_model=LDS-9"]))
    assert "'LDS-9' is not one of LDS-01, LDS-02, LDS-03" in str(raised.value)
    with pytest.raises(RosterError) as raised:
        load_roster(roster, command_line=command_line_data(["pyinfra", "--data", "lds_model=[1]"]))
    assert "--data lds_model=[1]" in str(raised.value)


def test_a_profiles_apt_packages_get_the_distro_filled_in_and_checked(tmp_path, rosdistro_url):
    profile = ("profiles:\n  tb3_tools:\n    extends: turtlebot3\n    robot:\n"
               "      apt_packages: [\"ros-{distro}-ld08-driver\", htop]\n")
    roster = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: burger\n            lds_model: LDS-02",
                        classroom_extra="")
    text = roster.read_text().replace("teams:\n", profile + "teams:\n").replace(
        "robot_profile: turtlebot3", "robot_profile: tb3_tools")
    roster.write_text(text)
    robot = next(host for host in load_roster(roster).hosts if host.name == "tb3-robot")
    packages = robot.data["roslab_profile"]["packages"]
    assert packages[-1] == "htop" and packages.count("ros-jazzy-ld08-driver") == 1
    roster.write_text(text.replace("ld08-driver", "ld08-drivr"))
    (error,) = errors_of(roster)
    assert "ros-jazzy-ld08-drivr is not a package of ROS 2 jazzy" in error, error
    assert "did you mean ros-jazzy-ld08-driver?" in error


def test_every_file_of_the_builtin_profiles_is_in_the_installed_package():
    """An installed roslab (the wheel) reads its profiles' .repos files as the checkout does:
    pyproject's package data must name every kind of file in profiles/data."""
    import fnmatch
    import tomllib

    root = Path(__file__).resolve().parents[2]
    patterns = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["roslab"]
    data = root / "roslab" / "profiles" / "data"
    missing = [path.name for path in data.iterdir()
               if not any(fnmatch.fnmatch(f"profiles/data/{path.name}", pattern) for pattern in patterns)]
    assert missing == []


def test_the_boards_host_gets_the_agents_cmake_args_and_a_bad_one_is_refused_where_defined(
        tmp_path, rosdistro_url):
    from roslab.profiles import library
    from roslab.profiles.resolve import resolve_host

    esp32 = library.builtin_profiles()["esp32_microros"]
    board = {"esp32_usb_serial": "0001A2B3", "esp32_attached_to": "main"}
    main, _ = resolve_host(esp32, board, distro="jazzy", role="main")
    robot, _ = resolve_host(esp32, board, distro="jazzy", role="robot")
    assert main["cmake_args"]["micro_ros_agent"] == ["-DMICROROSAGENT_SUPERBUILD=OFF",
                                                     "-DCMAKE_CXX_FLAGS=-DFMT_DEPRECATED_OSTREAM"]
    xrce = main["cmake_args"]["microxrcedds_agent"]
    assert {"-DUAGENT_SUPERBUILD=OFF", "-DUAGENT_USE_SYSTEM_FASTDDS=ON", "-DUAGENT_USE_SYSTEM_LOGGER=ON",
            "-DCMAKE_CXX_FLAGS=-DFMT_DEPRECATED_OSTREAM"} <= set(xrce), xrce
    # the edge micro_ros_agent's package.xml forgets, and what the XRCE-DDS agent finds with CMake
    assert main["build_dependencies"] == {"micro_ros_agent": ["microxrcedds_agent"]}
    assert "ros-jazzy-foonathan-memory-vendor" in main["packages"] and "libspdlog-dev" in main["packages"]
    assert robot["cmake_args"] == {} and robot["build_dependencies"] == {}  # the board is on the main
    assert "libspdlog-dev" not in robot["packages"]

    path = write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {rosdistro_url}
        profiles:
          mybot:
            extends: demo
            robot:
              cmake_args:
                my_driver: ["-DX=1; rm -rf ~"]
                My-Driver: [-DX=1]
        teams:
          t1:
            robot_profile: mybot
            hosts:
              t1-robot: {{role: robot}}
        """)
    errors = errors_of(path)
    assert any("field 'profiles.mybot.robot.cmake_args.my_driver': '-DX=1; rm -rf ~' is not a CMake cache "
               "setting" in error for error in errors), errors
    assert any("field 'profiles.mybot.robot.cmake_args': 'My-Driver' is not a ROS package name" in error
               for error in errors), errors


def test_the_rover_skips_its_ros1_and_gazebo_packages_and_bad_package_lists_are_refused_where_defined(
        tmp_path, rosdistro_url):
    from roslab.profiles import library
    from roslab.profiles.resolve import resolve_host

    robot, _ = resolve_host(library.builtin_profiles()["osr"], {}, distro="jazzy", role="robot")
    assert robot["skip_packages"] == ["led_screen", "osr_gazebo"]
    # what the rover's code imports without declaring it (rosdep would miss them)
    assert {"ros-jazzy-tf2-ros", "ros-jazzy-nav-msgs"} <= set(robot["packages"])

    path = write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {rosdistro_url}
        profiles:
          mybot:
            extends: demo
            robot:
              build_dependencies:
                my_driver: [my_driver, "x; rm -rf ~"]
                Bad-Name: [other]
              skip_packages: [ok_name, "../../etc"]
        teams:
          t1:
            robot_profile: mybot
            hosts:
              t1-robot: {{role: robot}}
        """)
    errors = errors_of(path)
    assert any("field 'profiles.mybot.robot.build_dependencies.my_driver': 'my_driver' is not another "
               "package's name" in error for error in errors), errors
    assert any("'x; rm -rf ~' is not another package's name" in error for error in errors), errors
    assert any("field 'profiles.mybot.robot.build_dependencies': 'Bad-Name' is not a package name" in error
               for error in errors), errors
    assert any("field 'profiles.mybot.robot.skip_packages': '../../etc' is not a package name" in error
               for error in errors), errors


# -- a new robot is one profile file -----------------------------------------------------

NEW_ROBOT_CHECK = """\
import json, sys
from roslab.roster import RosterError, load_roster
from roslab.sandbox import upstream
from roslab import settings_doc
try:
    classroom = load_roster(sys.argv[1])
except RosterError as error:
    print(json.dumps({"refused": [str(problem) for problem in error.problems]}))
    sys.exit(0)
hosts = {host.name: host.data["roslab_profile"] for host in classroom.hosts}
print(json.dumps({
    "launch": {name: profile["launch"] for name, profile in hosts.items()},
    "packages": {name: profile["packages"] for name, profile in hosts.items()},
    "stand_ins": sorted(upstream.profile_keys("jazzy")),
    "stand_in_launches": sorted(upstream.profile_launches("jazzy").get("turtlebot4_bringup", {})),
    "verify": [list(key) for key in upstream.profile_verify_topics("jazzy")],
    "readme_row": [line for line in settings_doc.profiles_table().splitlines() if "`mybot4`" in line],
}))
"""


def _files_of(root: Path) -> dict[str, bytes]:
    return {str(path.relative_to(root)): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


def test_a_new_robot_is_one_profile_file_and_nothing_else(tmp_path, rosdistro_url):
    """A copy of roslab with one more file in roslab/profiles/data (the TurtleBot 4's profile under a
    new name): the roster takes it, its launch is chosen by its setting, the package check and the
    sandbox's stand-ins cover it, and the table of docs/robots.md has its row; no other file changed."""
    import json
    import os
    import shutil
    import subprocess
    import sys

    import roslab

    copy = tmp_path / "copy"
    shutil.copytree(Path(roslab.__file__).parent, copy / "roslab", ignore=shutil.ignore_patterns("__pycache__"))
    before = _files_of(copy)
    data = copy / "roslab/profiles/data"
    (data / "mybot4.yaml").write_text(
        (data / "turtlebot4.yaml").read_text().replace("profile: turtlebot4", "profile: mybot4"))
    after = _files_of(copy)
    assert {name for name in after if before.get(name) != after[name]} == {"roslab/profiles/data/mybot4.yaml"}

    roster = tb4_roster(tmp_path, rosdistro_url, profile="mybot4")

    def check() -> dict:
        run = subprocess.run([sys.executable, "-c", NEW_ROBOT_CHECK, str(roster)], capture_output=True, text=True,
                             env={**os.environ, "PYTHONPATH": str(copy)}, cwd=tmp_path, timeout=120)
        assert run.returncode == 0, run.stderr
        return json.loads(run.stdout.splitlines()[-1])

    seen = check()
    assert seen["launch"] == {"t1-main": None, "t1-robot": "turtlebot4_bringup lite.launch.py"}
    assert "ros-jazzy-turtlebot4-robot" in seen["packages"]["t1-robot"]
    assert "ros-jazzy-turtlebot4-desktop" in seen["packages"]["t1-main"]
    assert {"turtlebot4_robot", "turtlebot4_desktop"} <= set(seen["stand_ins"])
    assert seen["stand_in_launches"] == ["lite.launch.py", "standard.launch.py"]
    assert ["turtlebot4_bringup", "lite.launch.py"] in seen["verify"]
    assert len(seen["readme_row"]) == 1 and "standard, lite" in seen["readme_row"][0]

    # The package check covers the new file as it covers the built-in ones: a misspelt package
    # in it is refused before any host is touched, naming the profile and the closest real name.
    (data / "mybot4.yaml").write_text((data / "mybot4.yaml").read_text().replace(
        "turtlebot4_node]", "turtlebot4_nodee]"))
    refused = check()["refused"]
    assert any("mybot4" in line and "ros-jazzy-turtlebot4-nodee" in line and "did you mean ros-jazzy-turtlebot4-node?" in line
               for line in refused), refused


def test_every_built_in_side_resolves_to_exactly_the_typed_keys():
    """host.data.roslab_profile holds the fields ResolvedProfile declares, no more, no fewer, and
    the dataclass a deploy reads is made from it with every value kept."""
    from dataclasses import asdict, fields

    from roslab.profiles.resolve import PythonEnv, ResolvedProfile, ResolvedService

    for profile in builtin_profiles().values():
        given = {name: setting.allowed[0] if setting.allowed else setting.default or sample_value(setting)
                 for name, setting in profile.settings.items()}
        for role in profile.sides:
            resolved, problems = resolve_host(profile, given, distro=profile.distros[0], role=role)
            assert problems == [], (profile.name, role, problems)
            assert set(resolved) == {item.name for item in fields(ResolvedProfile)}, (profile.name, role)
            assert set(resolved["python"]) == {item.name for item in fields(PythonEnv)}
            for service in resolved["services"]:
                assert set(service) == {item.name for item in fields(ResolvedService)}
            typed = ResolvedProfile.from_data(resolved)
            assert asdict(typed) == resolved, (profile.name, role)
            assert all(isinstance(service, ResolvedService) for service in typed.services)


def test_a_checklist_step_that_sets_the_middleware_names_the_classs(tmp_path, rosdistro_url):
    """The TurtleBot 4's Create 3 step says which RMW roslab sets on the base (the trial's teacher
    could not tell): the roster's ros_middleware, filled in by the loader as ${host} is."""
    roster = tb4_roster(tmp_path, rosdistro_url, classroom_extra="ros_middleware: rmw_cyclonedds_cpp")
    robot = next(host for host in load_roster(roster).hosts if host.name == "t1-robot")
    (step,) = [item for item in robot.data["roslab_profile"]["checklist"] if "Create 3 to the Pi" in item]
    assert "sets its domain, namespace, middleware (rmw_cyclonedds_cpp) and NTP server" in step, step
