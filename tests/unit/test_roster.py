"""Roster loading and validation: every bad input is stopped before any host is touched.

Each bad-input test asserts what a teacher would read: the file, the team, the
host and the field, and what is wrong.
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest
import yaml
from fixtures.openpgp_keys import ED25519_ARMORED, ED25519_FINGERPRINT

from roslab import openpgp, roster
from roslab import settings as schema
from roslab.ros.discovery import assign_domain_ids, preferred_domain_id
from roslab.ros.distro import PLATFORMS
from roslab.roster import RosterError, inventory_groups, load_roster

REPO = Path(__file__).resolve().parents[2]
FIXTURES = Path(__file__).parent / "rosters"
EXAMPLE = REPO / "inventories" / "lab.yaml"


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    # Messages name files relative to the working directory: work in tmp_path.
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)


def write(tmp_path: Path, text: str, name: str = "lab.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def write_secrets(tmp_path: Path, text: str, mode: int = 0o600, name="secrets.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    path.chmod(mode)
    return path


def errors_of(path: Path) -> list[str]:
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    return [str(problem) for problem in raised.value.problems]


def one_error(path: Path) -> str:
    errors = errors_of(path)
    assert len(errors) == 1, errors
    return errors[0]


ONE_TEAM = """\
    classroom:
      ssh_user: ubuntu
    teams:
      team1:
        ros_domain_id: 11
        hosts:
          team1-main:
            role: main
            address: 192.0.2.11
{extra}"""


def one_team(tmp_path, extra: str = "", **format_args) -> Path:
    """A one-team roster with `extra` lines appended to team1-main's mapping."""
    lines = textwrap.indent(textwrap.dedent(extra), " " * 12) if extra else ""
    return write(tmp_path, ONE_TEAM.format(extra=lines))


# --- good path ---------------------------------------------------------------------


def test_example_roster_is_valid_and_describes_three_teams():
    classroom = load_roster(EXAMPLE)
    assert [team.name for team in classroom.teams] == ["team1", "team2", "team3"]
    robots = {team.name: [h.name for h in team.hosts if h.role == "robot"] for team in classroom.teams}
    assert robots == {"team1": ["team1-robot"], "team2": ["team2-robot1", "team2-robot2"],
                      "team3": []}
    assert {host.ubuntu_release for host in classroom.hosts} == {"24.04", "22.04"}


def test_example_secrets_file_only_warns_about_its_mode():
    classroom = load_roster(EXAMPLE)
    if os.stat(REPO / "inventories" / "secrets.example.yaml").st_mode & 0o077:
        assert any("chmod 600" in str(w) for w in classroom.warnings)


def test_groups_for_limit_main_robot_team_and_distro():
    classroom = load_roster(FIXTURES / "two_teams.yaml")
    groups = {name: [host for host, _ in members]
              for name, members in inventory_groups(classroom).items()}
    assert groups == {
        "main": ["team1-main", "team2-main"],
        "robot": ["team1-robot"],
        "team1": ["team1-main", "team1-robot"],
        "team_2": ["team2-main"],  # '-' becomes '_' in a group name
        "jazzy": ["team1-main", "team1-robot"],
        "humble": ["team2-main"],
    }


def test_host_data_holds_identity_connection_and_every_setting_with_its_default():
    classroom = load_roster(FIXTURES / "two_teams.yaml")
    data = dict(inventory_groups(classroom)["team_2"])["team2-main"]
    defaults = schema.defaults()
    defaults["ros_apt_source_cache_dir"] = str(Path(defaults["ros_apt_source_cache_dir"]).expanduser())
    assert data == {
        **defaults,
        "roslab_team": "team-2",
        "roslab_role": "main",
        "roslab_hostname": "team2-main",
        "roslab_ubuntu_release": "22.04",
        "roslab_expected_distro": "humble",
        "roslab_roster_path": str(FIXTURES / "two_teams.yaml"),
        "ssh_hostname": "127.0.0.21",
        "ssh_user": "ubuntu",
        # strict host key checking against the classroom's known_hosts (roslab.ssh.identity)
        "ssh_known_hosts_file": str(FIXTURES / ".roslab-state" / "known_hosts"),
        "ssh_strict_host_key_checking": "yes",
        "_sudo": True,
        "ubuntu_release": "22.04",
        "ros_domain_id": 12,
        "roslab_classroom_hosts": [
            {"name": "team1-main", "address": "127.0.0.11"},
            {"name": "team1-robot", "address": "127.0.0.12"},
            {"name": "team2-main", "address": "127.0.0.21"},
        ],
        "roslab_team_hosts": [{"name": "team2-main", "address": "127.0.0.21", "role": "main"}],
        # The default robot profile (demo), resolved for the main on humble.
        "nodes_launch": "roslab_bringup main.launch.py",
        "ros_variant": "desktop",
        "nodes_verify_topic": "/chatter", "nodes_verify_type": "std_msgs/msg/String",
        "roslab_verify_source": "",
        "roslab_verify_publisher": "",
        "roslab_profile": {
            "name": "demo", "distro": "humble", "settings": {}, "ros_packages": [], "packages": [],
            "environment": {}, "groups": [], "udev_rules": "", "launch": "roslab_bringup main.launch.py",
            "launch_arguments": {},
            "variant": "desktop", "verify_topic": "/chatter", "verify_type": "std_msgs/msg/String",
            "verify_source": "", "verify_publisher": "", "discovery": None, "checklist": [], "os_tweaks": {},
            "remove_apt_packages": [], "boot_config": {}, "services": [], "base": None,
            "sources": [],
            "cmake_args": {}, "build_dependencies": {}, "skip_packages": [], "underlay_build_memory_mb": None,
            "python": {"venv": None, "requirements": []},
        },
        "roslab_sources": [],  # the repositories of its .repos files (roslab.sources.repos): none
    }


def test_a_host_the_network_deploy_moved_is_reached_at_its_new_address(tmp_path):
    path = one_team(tmp_path)
    state = tmp_path / ".roslab-state"
    state.mkdir()
    (state / "addresses.yaml").write_text("team1-main: 192.0.2.111\n")
    classroom = load_roster(path)
    assert classroom.hosts[0].address == "192.0.2.11"  # what the roster says, for `check`
    assert dict(inventory_groups(classroom)["main"])["team1-main"]["ssh_hostname"] == "192.0.2.111"


def test_table_fields_resolve_distro_variant_and_domain_by_level(tmp_path):
    path = write(tmp_path, """\
        classroom: {ros_variant_robot: ros-core}
        teams:
          solo:
            hosts:
              solo-main: {role: main, ros_distro: kilted}
              solo-robot: {role: robot}
    """)
    main, robot = load_roster(path).hosts
    assert (main.address, main.distro, main.variant) == ("solo-main", "kilted", "desktop")
    assert (robot.distro, robot.variant) == ("jazzy", "ros-core")
    # A team without one gets a free ID from its name (never 0, everyone's default).
    assert main.ros_domain_id == robot.ros_domain_id == preferred_domain_id("solo") != 0
    assert main.data["ros_domain_id"] == main.ros_domain_id and main.domain_assigned


def test_every_deploy_setting_is_accepted_with_its_default(tmp_path):
    settings = {key: value for key, value in schema.defaults().items()
                if not key.endswith("_secret")}  # a secret reference needs a secrets file
    path = write(tmp_path, yaml.safe_dump({
        "classroom": settings,
        "teams": {"t": {"hosts": {"t-main": {"role": "main"}}}},
    }))
    data = load_roster(path).hosts[0].data
    settings["ros_apt_source_cache_dir"] = str(Path(settings["ros_apt_source_cache_dir"]).expanduser())
    settings["rosdep_cache_dir"] = str(Path(settings["rosdep_cache_dir"]).expanduser())  # set: a path here
    settings["sources_cache_dir"] = str(Path(settings["sources_cache_dir"]).expanduser())
    settings["python_wheelhouse_dir"] = str(Path(settings["python_wheelhouse_dir"]).expanduser())
    settings["class_lock_debs_dir"] = str(Path(settings["class_lock_debs_dir"]).expanduser())
    # None means "the robot profile's": the demo profile's main launch, variant and topic.
    settings["nodes_launch"] = "roslab_bringup main.launch.py"
    settings["ros_variant"] = "desktop"
    settings["nodes_verify_topic"] = "/chatter"
    settings["nodes_verify_type"] = "std_msgs/msg/String"
    settings["ros_domain_id"] = preferred_domain_id("t")  # None: a free ID from the team's name
    assert {key: data[key] for key in settings} == settings


def test_settings_are_checked_against_the_type_of_their_default(tmp_path):
    path = one_team(tmp_path, """\
        apt_lock_timeout: "ten minutes"
        locale_enabled: 1
        apt_extra_suites: updates
    """)
    assert errors_of(path) == [
        "lab.yaml:10: team 'team1', host 'team1-main', field 'apt_lock_timeout': "
        "must be an integer, not 'ten minutes'",
        "lab.yaml:11: team 'team1', host 'team1-main', field 'locale_enabled': "
        "must be true or false, not 1",
        "lab.yaml:12: team 'team1', host 'team1-main', field 'apt_extra_suites': "
        "must be a list, not 'updates'",
    ]


def test_host_overrides_team_overrides_classroom(tmp_path):
    path = write(tmp_path, """\
        classroom: {locale: de_DE.UTF-8}
        teams:
          t:
            locale: fr_FR.UTF-8
            hosts:
              t-main: {role: main, locale: it_IT.UTF-8}
              t-robot: {role: robot}
    """)
    main, robot = load_roster(path).hosts
    assert main.data["locale"] == "it_IT.UTF-8"
    assert robot.data["locale"] == "fr_FR.UTF-8"


def test_connection_paths_are_resolved_beside_the_roster(tmp_path):
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys/id_ed25519").write_text(
        "-----BEGIN OPENSSH PRIVATE KEY-----\na stand-in private key\n-----END OPENSSH PRIVATE KEY-----\n")
    path = one_team(tmp_path, "ssh_key: keys/id_ed25519\nssh_port: 2222\n")
    data = load_roster(path).hosts[0].data
    assert data["ssh_key"] == str(tmp_path / "keys/id_ed25519")
    assert data["ssh_port"] == 2222


def test_root_user_is_not_given_sudo(tmp_path):
    path = one_team(tmp_path, "ssh_user: root\nlogin_user: student\nssh_permit_root_login: prohibit-password\n")
    assert "_sudo" not in load_roster(path).hosts[0].data


def test_root_as_the_ssh_user_is_refused_while_hardening_would_lock_it_out(tmp_path):
    assert one_error(one_team(tmp_path, "ssh_user: root\nlogin_user: student\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ssh_user': roslab logs in as root, and ssh "
        "hardening (PermitRootLogin no) would lock it out: log in as the lab user, or set "
        "ssh_permit_root_login: prohibit-password")
    load_roster(one_team(tmp_path, "ssh_user: root\nlogin_user: student\nssh_hardening_enabled: false\n"))


def test_root_as_the_login_user_is_refused(tmp_path):
    assert one_error(one_team(tmp_path, "ssh_user: root\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ssh_user': the ROS environment "
        "belongs to a student account, not root: set login_user")


def test_errors_are_all_reported_together_one_per_line(tmp_path):
    path = one_team(tmp_path, "ssh_port: 0\nnetwork_gateway: 10.0.0.999\nros_distr: jazzy\n")
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    lines = str(raised.value).splitlines()
    assert len(lines) == 3
    assert all(line.startswith("lab.yaml:") and "host 'team1-main'" in line for line in lines)


def test_validators_hook_reports_through_the_same_report(tmp_path):
    def no_robots_allowed(classroom, report):
        for host in classroom.hosts:
            report.error("robots are banned", team=host.team, host=host.name, field="role",
                         line=host.lines.get("role"))

    path = one_team(tmp_path)
    with pytest.raises(RosterError) as raised:
        load_roster(path, validators=[no_robots_allowed])
    assert str(raised.value) == (
        "lab.yaml:8: team 'team1', host 'team1-main', field 'role': robots are banned")


def test_a_teams_mistake_is_said_once_for_the_team_and_a_hosts_own_for_each_host(tmp_path):
    path = write(tmp_path, """\
        classroom:
          ssh_user: ubuntu
          ubuntu_release: "22.04"
        teams:
          team1:
            robot_profile: turtlebot4
            turtlebot4_model: bogus
            hosts:
              team1-main: {role: main, address: 192.0.2.11}
              team1-robot: {role: robot, address: 192.0.2.12}
          team2:
            hosts:
              team2-main: {role: main, address: 192.0.2.21, robot_profile: osrr}
              team2-robot: {role: robot, address: 192.0.2.22, robot_profile: osrr}
        """)
    errors = errors_of(path)
    assert [error.split(": ", 2)[:2] for error in errors] == [
        ["lab.yaml:7", "team 'team1', field 'turtlebot4_model'"],  # the team's line: once, for the team
        ["lab.yaml:13", "team 'team2', host 'team2-main', field 'robot_profile'"],  # each host's own line
        ["lab.yaml:14", "team 'team2', host 'team2-robot', field 'robot_profile'"],
    ]


def test_a_problem_only_some_of_a_teams_hosts_have_still_names_them():
    from roslab.checked.problems import Problem, team_wide

    main, robot = (Problem("lab.yaml", "no such board", 9, "team1", host, "board") for host in ("m", "r"))
    other = Problem("lab.yaml", "no such board", 9, "team2", "x", "board")
    assert team_wide([main, other, robot], {"team1": {"m", "r"}, "team2": {"x"}}) == [
        Problem("lab.yaml", "no such board", 9, "team1", None, "board"), other]
    assert team_wide([main, robot], {"team1": {"m", "r", "s"}}) == [main, robot]


def test_default_roster_path_prefers_env_then_classroom_then_example(tmp_path, monkeypatch):
    assert roster.default_roster_path(tmp_path) == tmp_path / "inventories/lab.yaml"
    (tmp_path / "inventories").mkdir()
    (tmp_path / "inventories/classroom.yaml").write_text("")
    assert roster.default_roster_path(tmp_path) == tmp_path / "inventories/classroom.yaml"
    (tmp_path / "classroom.yaml").write_text("")  # a classroom folder (roslab init)
    assert roster.default_roster_path(tmp_path) == tmp_path / "classroom.yaml"
    monkeypatch.setenv("ROSLAB_ROSTER", "/elsewhere/r.yaml")
    assert roster.default_roster_path(tmp_path) == Path("/elsewhere/r.yaml")


# --- bad input: one test each --------------------------------------------------------


def test_unknown_key_suggests_the_close_one(tmp_path):
    assert one_error(one_team(tmp_path, "ros_distr: jazzy\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ros_distr': "
        "unknown key 'ros_distr' (did you mean 'ros_distro'?)")


def test_unknown_key_at_classroom_level(tmp_path):
    path = write(tmp_path, """\
        classroom: {ubuntu_relase: "24.04"}
        teams:
          t: {hosts: {t-main: {role: main}}}
    """)
    assert one_error(path) == (
        "lab.yaml:1: field 'ubuntu_relase': unknown key 'ubuntu_relase' "
        "(did you mean 'ubuntu_release'?)")


def test_host_key_on_a_team_is_named_as_such(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            role: main
            hosts: {t-main: {role: main}}
    """)
    assert one_error(path) == (
        "lab.yaml:3: team 't', field 'role': 'role' can only be set on a host, not on a team")


def test_duplicate_key_in_a_host_is_not_silently_dropped(tmp_path):
    path = one_team(tmp_path, "address: 192.0.2.99\n")
    assert one_error(path) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'address': "
        "set twice (also at line 9); YAML would silently keep the last")


def test_duplicate_host_name_within_a_team(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            hosts:
              t-main: {role: main, address: 192.0.2.1}
              t-main: {role: robot, address: 192.0.2.2}
    """)
    assert one_error(path) == (
        "lab.yaml:5: team 't', host 't-main': host 't-main' appears twice in this team "
        "(also at line 4)")


def test_duplicate_host_name_across_teams(tmp_path):
    path = write(tmp_path, """\
        teams:
          a:
            ros_domain_id: 1
            hosts: {pi: {role: main, address: 192.0.2.1}}
          b:
            ros_domain_id: 2
            hosts: {pi: {role: main, address: 192.0.2.2}}
    """)
    assert one_error(path) == (
        "lab.yaml:7: team 'b', host 'pi': the host name is already used by host 'pi' of team 'a'")


def test_duplicate_address(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            hosts:
              t-main: {role: main, address: 192.0.2.1}
              t-robot: {role: robot, address: 192.0.2.1}
    """)
    assert one_error(path) == (
        "lab.yaml:5: team 't', host 't-robot', field 'address': "
        "192.0.2.1 is already used by host 't-main' of team 't'")


def test_duplicate_network_address(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            hosts:
              t-main: {role: main, network_address: 192.0.2.1/24}
              t-robot: {role: robot, network_address: 192.0.2.1/25}
    """)
    assert one_error(path) == (
        "lab.yaml:5: team 't', host 't-robot', field 'network_address': "
        "192.0.2.1 is already used by host 't-main' of team 't'")


def test_malformed_address(tmp_path):
    path = write(tmp_path, ONE_TEAM.format(extra="").replace("192.0.2.11", "192.168.50.300"))
    assert one_error(path) == (
        "lab.yaml:9: team 'team1', host 'team1-main', field 'address': "
        "'192.168.50.300' is neither an IP address nor a valid host name")


def test_dns_names_and_ipv6_are_valid_addresses(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            hosts:
              t-main: {role: main, address: pi-01.lab.example.org}
              t-robot: {role: robot, address: "fd00::12"}
    """)
    assert [h.address for h in load_roster(path).hosts] == ["pi-01.lab.example.org", "fd00::12"]


def test_malformed_network_address_and_gateway(tmp_path):
    path = one_team(tmp_path, "network_address: 192.168.50.11/33\nnetwork_gateway: 192.168.50\n")
    assert errors_of(path) == [
        "lab.yaml:10: team 'team1', host 'team1-main', field 'network_address': "
        "'192.168.50.11/33' is not an IP address (with prefix length), e.g. '192.168.50.11/24'",
        "lab.yaml:11: team 'team1', host 'team1-main', field 'network_gateway': "
        "'192.168.50' is not an IP address written as four decimal numbers (a resolver would read it as "
            "'192.168.0.50')",
    ]


def test_ros_distro_that_does_not_exist(tmp_path):
    assert one_error(one_team(tmp_path, "ros_distro: jazy\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ros_distro': "
        "ROS 2 distro 'jazy' does not exist (known: humble, jazzy, kilted, lyrical)")


def test_jazzy_on_ubuntu_22_04_fails_before_any_host_is_touched(tmp_path):
    path = write(tmp_path, """\
        classroom: {ubuntu_release: "22.04"}
        teams:
          team2:
            hosts:
              team2-robot: {role: robot, ros_distro: jazzy}
    """)
    assert one_error(path) == (
        "lab.yaml:5: team 'team2', host 'team2-robot', field 'ros_distro': "
        "ROS 2 jazzy has no packages for Ubuntu jammy (it has them for: noble)")


def test_unknown_ubuntu_release(tmp_path):
    assert one_error(one_team(tmp_path, 'ubuntu_release: "23.10"\n')) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ubuntu_release': "
        f"Ubuntu 23.10 is not supported (supported: {', '.join(p.release for p in PLATFORMS)})")


def test_unquoted_ubuntu_release_says_to_quote_it(tmp_path):
    assert one_error(one_team(tmp_path, "ubuntu_release: 24.04\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ubuntu_release': "
        'must be a string, not 24.04 (YAML reads 24.04 as a number: quote it, "24.04")')


def test_unknown_variant(tmp_path):
    assert "'ros-desktop' is not one of: desktop, ros-base, ros-core, desktop-full" in one_error(
        one_team(tmp_path, "ros_variant: ros-desktop\n"))


@pytest.mark.parametrize("domain_id", [102, -1])
def test_ros_domain_id_outside_0_to_101(tmp_path, domain_id):
    path = write(tmp_path, ONE_TEAM.format(extra="").replace("ros_domain_id: 11",
                                                             f"ros_domain_id: {domain_id}"))
    assert one_error(path) == (
        f"lab.yaml:5: team 'team1', field 'ros_domain_id': ROS_DOMAIN_ID {domain_id} "
        "is outside 0 to 101 and 215 to 232")


def test_two_teams_on_one_domain_id(tmp_path):
    path = write(tmp_path, """\
        teams:
          team1:
            ros_domain_id: 30
            hosts: {team1-main: {role: main}}
          team2:
            ros_domain_id: 30
            hosts: {team2-main: {role: main}}
    """)
    assert one_error(path) == (
        "lab.yaml:6: team 'team2', field 'ros_domain_id': ROS_DOMAIN_ID 30 is already "
        "team 'team1''s; teams on one domain see and disturb each other's topics")


def test_classroom_wide_domain_id_puts_every_team_on_one_domain(tmp_path):
    path = write(tmp_path, """\
        classroom: {ros_domain_id: 5}
        teams:
          team1: {hosts: {team1-main: {role: main}}}
          team2: {hosts: {team2-main: {role: main}}}
    """)
    assert "ROS_DOMAIN_ID 5 is already team 'team1''s" in one_error(path)


TEAMS_WITHOUT_DOMAINS = """\
    teams:
      {first}:
        ros_domain_id: {taken}
        hosts: {{{first}-main: {{role: main}}}}
      {second}:
        hosts: {{{second}-main: {{role: main}}}}
      {third}:
        hosts: {{{third}-main: {{role: main}}}}
"""


def domains_of(path) -> dict[str, int]:
    return {team.name: team.ros_domain_id for team in load_roster(path).teams}


def test_teams_without_a_domain_id_get_free_ones_from_their_names(tmp_path):
    taken = preferred_domain_id("bravo")  # the roster already holds bravo's preferred ID
    roster = TEAMS_WITHOUT_DOMAINS.format(first="alpha", second="bravo", third="charlie", taken=taken)
    first = domains_of(write(tmp_path, roster))
    assert first["alpha"] == taken
    assert first["bravo"] != taken and first["charlie"] == preferred_domain_id("charlie")
    assert len(set(first.values())) == 3 and 0 not in first.values()
    # The same on every run, and however the roster orders the teams.
    assert domains_of(write(tmp_path, roster)) == first
    reordered = TEAMS_WITHOUT_DOMAINS.format(first="alpha", second="charlie", third="bravo", taken=taken)
    assert domains_of(write(tmp_path, reordered)) == first


def test_assigned_domain_ids_never_collide_even_when_names_hash_alike():
    teams = {f"team{index}": None for index in range(101)}
    assigned = assign_domain_ids(teams)
    assert sorted(assigned.values()) == list(range(1, 102))
    # One team more than there are IDs: exactly one goes without (and the roster is refused).
    assert len(assign_domain_ids({**teams, "late": None})) == 101


def test_no_free_domain_id_left_is_refused_naming_the_team(tmp_path):
    teams = "".join(f"  t{index}:\n    ros_domain_id: {index}\n    hosts: {{t{index}-main: {{role: main}}}}\n"
                    for index in range(1, 102))
    path = write(tmp_path, "teams:\n" + teams + "  late:\n    hosts: {late-main: {role: main}}\n")
    assert one_error(path) == (
        "lab.yaml:305: team 'late', field 'ros_domain_id': no free ROS_DOMAIN_ID is left for this team "
        "(roslab gives out 1 to 101): set its ros_domain_id (215 to 232 also work on Linux)")


def test_domain_id_on_a_single_host_is_refused(tmp_path):
    assert "'ros_domain_id' can only be set on a classroom or a team, not on a host" in one_error(
        one_team(tmp_path, "ros_domain_id: 12\n"))


def test_role_must_be_main_or_robot(tmp_path):
    path = write(tmp_path, ONE_TEAM.format(extra="").replace("role: main", "role: pilot"))
    assert one_error(path) == (
        "lab.yaml:8: team 'team1', host 'team1-main', field 'role': "
        "'pilot' is not one of: main, robot")


def test_host_without_role(tmp_path):
    path = write(tmp_path, "teams:\n  t:\n    hosts:\n      t-main: {address: 192.0.2.1}\n")
    assert one_error(path) == (
        "lab.yaml:4: team 't', host 't-main', field 'role': every host needs a role (main or robot)")


def test_team_has_at_most_one_main(tmp_path):
    path = write(tmp_path, """\
        teams:
          t:
            hosts:
              t-main: {role: main}
              t-main2: {role: main}
    """)
    assert one_error(path) == (
        "lab.yaml:5: team 't', host 't-main2', field 'role': "
        "a team has at most one main host, and 't-main' already is")


def test_team_without_hosts(tmp_path):
    path = write(tmp_path, "teams:\n  t:\n    ros_domain_id: 3\n")
    assert one_error(path) == (
        "lab.yaml:2: team 't', field 'hosts': a team needs at least one host under 'hosts'")


def test_team_named_like_a_builtin_group(tmp_path):
    path = write(tmp_path, "teams:\n  robot:\n    hosts: {r1: {role: robot}}\n")
    assert "team 'robot': the team's group 'robot' is already a pyinfra group" in one_error(path)


def test_teams_whose_groups_collide(tmp_path):
    path = write(tmp_path, """\
        teams:
          team-1: {ros_domain_id: 1, hosts: {a: {role: main}}}
          team_1: {ros_domain_id: 2, hosts: {b: {role: main}}}
    """)
    assert one_error(path) == (
        "lab.yaml:3: team 'team_1': the team's group 'team_1' is also team 'team-1''s "
        "('-' becomes '_'); rename one of them")


def test_host_name_that_cannot_be_a_hostname(tmp_path):
    path = write(tmp_path, "teams:\n  t:\n    hosts:\n      t_main: {role: main}\n")
    assert one_error(path).startswith("lab.yaml:4: team 't', host 't_main': 't_main' is not a valid hostname")


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = write(tmp_path, "teams:\n  t:\n    hosts: {a: [\n")
    assert one_error(path).startswith("lab.yaml:4: not valid YAML:")


def test_missing_roster_file(tmp_path):
    assert one_error(tmp_path / "nope.yaml") == (
        "nope.yaml: cannot read the file: No such file or directory")


# --- secrets ---------------------------------------------------------------------------

SECRET_VALUE = "correct-horse-battery"


def test_secret_is_resolved_masked_and_sudo_password_given_to_pyinfra(tmp_path):
    write_secrets(tmp_path, f"lab_wifi: {SECRET_VALUE}\nsudo: s3cret-sudo\n")
    path = one_team(tmp_path, "wifi_password_secret: lab_wifi\nsudo_password_secret: sudo\n")
    data = load_roster(path).hosts[0].data
    assert data["wifi_password"].unmask() == SECRET_VALUE
    assert SECRET_VALUE not in repr(data) and SECRET_VALUE not in str(data["wifi_password"])
    assert data["wifi_password_secret"] == "lab_wifi"
    # The sudo password stays masked too: roslab.ssh.sudo unmasks it only into the host's askpass file.
    assert data["_sudo_password"].unmask() == "s3cret-sudo" and "s3cret" not in repr(data)


def test_reference_to_a_missing_secret(tmp_path):
    write_secrets(tmp_path, f"other: {SECRET_VALUE}\n")
    error = one_error(one_team(tmp_path, "wifi_password_secret: lab_wifi\n"))
    assert error == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'wifi_password_secret': "
        "names secret 'lab_wifi', which secrets.yaml does not define")


def test_reference_with_no_secrets_file(tmp_path):
    errors = errors_of(one_team(tmp_path, "wifi_password_secret: lab_wifi\n"))
    assert errors == [
        "lab.yaml: field 'secrets_file': secrets file secrets.yaml does not exist "
        "(copy secrets.example.yaml, fill it in, and chmod 600 it)",
        "lab.yaml:10: team 'team1', host 'team1-main', field 'wifi_password_secret': "
        "names secret 'lab_wifi', but the secrets file secrets.yaml is missing or unusable",
    ]


def test_no_secrets_file_needed_when_nothing_refers_to_one(tmp_path):
    assert load_roster(one_team(tmp_path)).hosts


def test_secrets_file_readable_by_others_is_refused(tmp_path):
    write_secrets(tmp_path, f"lab_wifi: {SECRET_VALUE}\n", mode=0o644)
    errors = errors_of(one_team(tmp_path, "wifi_password_secret: lab_wifi\n"))
    assert errors[0] == (
        "lab.yaml: field 'secrets_file': secrets file secrets.yaml is open to other users "
        "(mode 0644); run: chmod 600 secrets.yaml")
    assert not any(SECRET_VALUE in error for error in errors)


def test_example_secrets_file_readable_by_others_only_warns(tmp_path):
    write_secrets(tmp_path, "lab_wifi: placeholder\n", mode=0o644, name="secrets.example.yaml")
    path = write(tmp_path, ONE_TEAM.format(extra="").replace(
        "  ssh_user: ubuntu", "  ssh_user: ubuntu\n      secrets_file: secrets.example.yaml"))
    path.write_text(path.read_text() + "        wifi_password_secret: lab_wifi\n")
    classroom = load_roster(path)
    assert [str(w) for w in classroom.warnings] == [
        "lab.yaml:3: field 'secrets_file': secrets file secrets.example.yaml is open to "
        "other users (mode 0644); run: chmod 600 secrets.example.yaml "
        "(allowed for an example holding placeholders)"]


def test_bad_secrets_file_errors_never_show_a_value(tmp_path):
    write_secrets(tmp_path, f"lab_wifi: [{SECRET_VALUE}]\nlab_wifi: {SECRET_VALUE}\n")
    errors = errors_of(one_team(tmp_path, "wifi_password_secret: lab_wifi\n"))
    assert "secrets.yaml:2: secret 'lab_wifi' is defined twice (also at line 1)" in errors
    assert not any(SECRET_VALUE in error for error in errors)


def test_a_typo_of_a_team_setting_on_a_host_suggests_it_and_where_it_belongs(tmp_path):
    assert one_error(one_team(tmp_path, "ros_domian_id: 3\n")) == (
        "lab.yaml:10: team 'team1', host 'team1-main', field 'ros_domian_id': unknown key "
        "'ros_domian_id' (did you mean 'ros_domain_id', set on a classroom or a team?)")


def test_what_the_loader_adds_after_a_check_read_the_settings_is_in_them_too(tmp_path):
    # add_host_lists runs after the classroom's checks have built each host's typed settings
    path = tmp_path / "lab.yaml"
    path.write_text("teams:\n  solo:\n    hosts:\n      solo-main: {role: main, address: 10.0.0.5}\n")
    host = load_roster(path).hosts[0]
    assert host.settings.roslab_team_hosts == host.data["roslab_team_hosts"] == [
        {"name": "solo-main", "address": "10.0.0.5", "role": "main"}]
    assert host.settings.ros_domain_id == host.data["ros_domain_id"] is not None
    host.set_data(ros_domain_id=7)
    assert host.settings.ros_domain_id == host.data["ros_domain_id"] == 7


# --- snapshot mode (snapshots.ros.org) ----------------------------------------------------------


def snapshot_key(tmp_path) -> Path:
    key = tmp_path / "snapshots.asc"
    key.write_text(ED25519_ARMORED)
    return key


def test_a_snapshot_class_from_a_mirror_of_the_snapshots_loads(tmp_path):
    snapshot_key(tmp_path)
    classroom = load_roster(one_team(tmp_path, """\
        ros_apt_source_mode: snapshot
        ros_apt_snapshot: "2026-08-07"
        ros_apt_snapshot_url: http://10.0.0.1/snapshots
        ros_apt_snapshot_key_file: snapshots.asc
        """))
    assert classroom.hosts[0].settings.ros_apt_snapshot_key_file == str(tmp_path / "snapshots.asc")


def test_snapshot_mode_without_its_snapshot_is_refused_naming_the_field(tmp_path):
    snapshot_key(tmp_path)
    problem = one_error(one_team(tmp_path, """\
        ros_apt_source_mode: snapshot
        ros_apt_snapshot_url: http://10.0.0.1/snapshots
        ros_apt_snapshot_key_file: snapshots.asc
        """))
    assert "host 'team1-main', field 'ros_apt_snapshot'" in problem
    assert "ros_apt_source_mode is 'snapshot', so ros_apt_snapshot must be set" in problem


def test_from_snapshots_ros_org_a_key_that_is_not_its_own_is_refused_before_any_host(tmp_path):
    snapshot_key(tmp_path)
    problem = one_error(one_team(tmp_path, """\
        ros_apt_source_mode: snapshot
        ros_apt_snapshot: final
        ros_apt_snapshot_key_file: snapshots.asc
        """))
    assert "host 'team1-main', field 'ros_apt_snapshot_key_file'" in problem
    assert (f"holds the key {openpgp.spaced(ED25519_FINGERPRINT)}, not snapshots.ros.org's "
            "(4B63 CF8F DE49 746E 98FA  01DD AD19 BAB3 CBF1 25EA)") in problem


def test_snapshot_mode_on_a_distro_without_snapshots_is_refused(tmp_path):
    snapshot_key(tmp_path)
    problem = one_error(one_team(tmp_path, """\
        ros_distro: kilted
        ros_apt_source_mode: snapshot
        ros_apt_snapshot: "2026-08-07"
        ros_apt_snapshot_url: http://10.0.0.1/snapshots
        ros_apt_snapshot_key_file: snapshots.asc
        """))
    assert "ROS kilted is not an LTS distro: snapshots.ros.org keeps LTS distros only" in problem
