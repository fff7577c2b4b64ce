"""One record per Ubuntu/ROS 2 pair: the schema, the roster checks and the sandbox read the same facts."""

from __future__ import annotations

import textwrap

import pytest

from roslab import settings
from roslab.ros import distro
from roslab.roster import RosterError, load_roster
from roslab.sandbox import emulation, upstream
from roslab.sandbox.instance import Instance, releases_by_team
from roslab.sandbox.system import SandboxError

RESOLUTE_PIN = "ab" * 32


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_SANDBOX_RELEASES", raising=False)


def roster(tmp_path, classroom_extra: str = "") -> object:
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent("""\
        classroom:
          ssh_user: ubuntu
          ubuntu_release: "26.04"
        """) + textwrap.indent(textwrap.dedent(classroom_extra), "  ") + textwrap.dedent("""\
        teams:
          team1:
            ros_domain_id: 11
            hosts:
              team1-main: {role: main}
        """))
    return path


def test_every_record_is_consistent_with_the_derived_mappings():
    releases = [p.release for p in distro.PLATFORMS]  # oldest first; a new record is one more
    assert releases == sorted(releases, key=lambda r: tuple(map(int, r.split(".")))) and {"22.04", "24.04"} <= set(releases)
    for platform in distro.PLATFORMS:
        assert distro.codename_for(platform.release) == platform.codename
        assert distro.default_distro(platform.codename) == platform.distro
        distro.check_distro(platform.distro, platform.codename)
        assert f"VERSION_CODENAME={platform.codename}\n" in emulation.os_release(
            emulation.HostIdentity("h", platform.release, "10.0.0.2", 24))
        assert upstream.ROS_DISTROS[platform.codename] == platform.distro
    assert distro.BY_RELEASE["26.04"].distro == "lyrical"
    assert distro.BY_RELEASE["26.04"].gazebo.name == "Jetty"
    assert distro.BY_RELEASE["22.04"].gazebo.ros_package == "gazebo_ros_pkgs"


def test_the_schema_lists_the_records():
    assert settings.SETTINGS["ubuntu_release"].allowed_text() == ", ".join(p.release for p in distro.PLATFORMS)
    assert "resolute: lyrical" in settings.SETTINGS["ros_distro"].doc
    assert settings.SETTINGS["ros_apt_source_sha256"].default == distro.ros_apt_source_pins()


def test_26_04_needs_no_teacher_pin_its_published_sha256_is_in_the_record(tmp_path):
    classroom = load_roster(roster(tmp_path))
    (host,) = classroom.hosts
    assert host.distro == "lyrical"
    assert host.data["ros_apt_source_sha256"]["resolute"] == (
        "a275b9b819874e745a928e83e39c429fa4d607159285c4ef3ebcf75afa732ee3")  # osrf/docker_images' pin


def test_a_release_without_a_known_pin_is_refused_naming_the_setting_to_set(tmp_path):
    """Another ros2-apt-source version: roslab's pins are of 1.2.0, so each release needs the
    roster's own."""
    with pytest.raises(RosterError) as raised:
        load_roster(roster(tmp_path, "ros_apt_source_version: 1.3.0\n"
                                     f"ros_apt_source_sha256: {{noble: '{'ab' * 32}'}}\n"))
    (problem,) = [str(p) for p in raised.value.problems]
    assert "team 'team1', host 'team1-main', field 'ros_apt_source_sha256': " in problem
    assert "roslab knows no sha256 of ros2-apt-source 1.3.0 for Ubuntu 26.04 (resolute)" in problem
    assert "set ros_apt_source_sha256: {resolute: <sha256 of ros2-apt-source_1.3.0.resolute_all.deb>}" in problem
    assert "ros_apt_source_mode: mirror" in problem


def test_26_04_with_its_pin_loads_as_lyrical_and_keeps_the_known_pins(tmp_path):
    classroom = load_roster(roster(tmp_path, f"ros_apt_source_sha256: {{resolute: '{RESOLUTE_PIN}'}}\n"))
    (host,) = classroom.hosts
    assert host.distro == "lyrical"
    assert host.data["roslab_expected_distro"] == "lyrical"
    pins = host.data["ros_apt_source_sha256"]
    assert pins["resolute"] == RESOLUTE_PIN
    assert pins["noble"] == distro.BY_CODENAME["noble"].ros_apt_source_sha256


def test_26_04_in_mirror_mode_needs_no_pin(tmp_path):
    key = tmp_path / "mirror.asc"
    key.write_text("-----BEGIN PGP PUBLIC KEY BLOCK-----\n\nmQINBGtest\n-----END PGP PUBLIC KEY BLOCK-----\n")
    classroom = load_roster(roster(tmp_path, "ros_apt_source_mode: mirror\n"
                                             "ros_apt_mirror_url: http://mirror.invalid/ros2\n"
                                             "ros_apt_mirror_key_file: mirror.asc\n"))
    assert classroom.hosts[0].distro == "lyrical"


def test_the_sandbox_emulates_each_record_and_takes_releases_per_team(monkeypatch):
    assert emulation.os_release(emulation.HostIdentity("h", "26.04", "10.0.0.2", 24)).count("resolute") == 2
    monkeypatch.setenv("ROSLAB_SANDBOX_RELEASES", "24.04,22.04,26.04")
    assert releases_by_team() == ("24.04", "22.04", "26.04")
    hosts = Instance.from_env("h17-unit").plan_hosts(6)
    assert [h.release for h in hosts] == ["24.04", "24.04", "22.04", "22.04", "26.04", "26.04"]
    monkeypatch.setenv("ROSLAB_SANDBOX_RELEASES", "24.04,23.10")
    with pytest.raises(SandboxError, match="23.10 is not a release the sandbox emulates"):
        releases_by_team()


# -- a new Ubuntu/ROS pair is one record ---------------------------------------------------

FAKE_PIN = "cd" * 32


@pytest.fixture
def fake_release():
    """A made-up 28.04 "testudo" with its distro "tortuga" (Fast DDS 3.8), and a Humble-like
    old distro "oldtimer" on it as an override: one Platform and one OtherDistro, nothing else."""
    platform = distro.Platform(
        release="28.04", codename="testudo", python="3.16",
        ros=distro.RosDistro("tortuga", discovery_range=True, fastdds=(3, 8)),
        gazebo=distro.Gazebo("Kestrel", "ros_gz", debian_package="gz-kestrel", conflicts_with=("gazebo11",)),
        ros_apt_source_sha256=FAKE_PIN, pretty="Ubuntu 28.04 LTS", version_text="28.04 LTS (Testy Testudo)",
    )
    old = distro.RosDistro("oldtimer", discovery_range=False, fastdds=(2, 6), lts=False, codenames=("testudo",))
    distro.PLATFORMS.append(platform)
    distro.OTHER_DISTROS.append(old)
    distro.index()
    try:
        yield platform
    finally:
        distro.PLATFORMS.remove(platform)
        distro.OTHER_DISTROS.remove(old)
        distro.index()


def test_a_new_release_record_reaches_every_consumer(tmp_path, fake_release):
    from roslab.ros import discovery
    from roslab.sources import repos as sources
    from fixtures.classroom import typed
    from roslab.ros.environment import host_environment

    # The roster schema and checks: the release loads, with its distro and its ros2-apt-source pin.
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent("""\
        classroom:
          ssh_user: ubuntu
          ubuntu_release: "28.04"
        teams:
          team1:
            ros_domain_id: 11
            hosts:
              team1-main: {role: main}
              team1-robot: {role: robot, ros_distro: oldtimer}
        """))
    main, robot = load_roster(path).hosts
    assert (main.distro, robot.distro) == ("tortuga", "oldtimer")
    assert main.data["ros_apt_source_sha256"]["testudo"] == FAKE_PIN
    assert settings.SETTINGS["ros_distro"].check("tortuga") is None

    # Discovery: the new distro's variables follow its record, not a list of names.
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" in host_environment(typed(main.data), "tortuga", shell=True)
    old_env = host_environment(typed({**robot.data, "ros_automatic_discovery_range": "LOCALHOST"}),
                               "oldtimer", shell=True)
    assert old_env.get("ROS_LOCALHOST_ONLY") == "1" and "ROS_AUTOMATIC_DISCOVERY_RANGE" not in old_env
    assert discovery.profiles_variable("tortuga") == "FASTDDS_DEFAULT_PROFILES_FILE"
    assert discovery.profiles_variable("oldtimer") == "FASTRTPS_DEFAULT_PROFILES_FILE"

    # Sources: a distro's name is a branch, refused as a pin without asking upstream.
    assert {"tortuga", "oldtimer"} <= sources.branch_names()

    # The deploys pick the distro from the host's facts by the same record.
    assert distro.select_distro("testudo") == "tortuga"
    assert distro.select_distro("testudo", "oldtimer") == "oldtimer"

    # The sandbox emulates the release and serves its archive, Gazebo stand-in included.
    assert "VERSION_CODENAME=testudo" in emulation.os_release(emulation.HostIdentity("h", "28.04", "10.0.0.2", 24))
    assert upstream.ROS_DISTROS["testudo"] == "tortuga"
    assert upstream.simulator_of("tortuga", "ros_gz") == "gz-kestrel"
    assert upstream.simulator_standins()["gz-kestrel"][2] == ["gazebo11"]


def test_a_profile_may_name_a_new_records_distro(tmp_path, fake_release):
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent("""\
        classroom:
          ssh_user: ubuntu
          ubuntu_release: "28.04"
        profiles:
          mybot:
            description: a robot that runs only on the new release
            distros: [tortuga]
            verify_topic: /chatter
            verify_type: std_msgs/msg/String
            robot:
              launch: roslab_bringup robot.launch.py
        teams:
          team1:
            ros_domain_id: 11
            robot_profile: mybot
            hosts:
              team1-robot: {role: robot}
        """))
    (host,) = load_roster(path).hosts
    assert host.distro == "tortuga"
