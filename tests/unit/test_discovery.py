"""Discovery modes and the class's middleware: what each host gets, per mode, middleware and distro,
and the combinations refused before connecting (roslab/ros/discovery.py, deploy/discovery.py)."""

from __future__ import annotations

import shlex
import textwrap
import xml.etree.ElementTree as ET

import pytest
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy import discovery as deploy_discovery
from deploy import workspace as deploy_ws
from deploy.shell_env import render_ros_environment
from roslab import settings
from roslab.ros import discovery
from roslab.ros import workspace
from roslab.roster import RosterError, load_roster
from roslab.host_settings import HostSettings, settings_of
from roslab.ros.environment import host_environment

MAIN_IP, ROBOT_IP = "10.0.0.11", "10.0.0.12"
TEAM = [{"name": "team1-main", "address": MAIN_IP, "role": "main"},
        {"name": "team1-robot", "address": ROBOT_IP, "role": "robot"}]
PEERS_XML = "/etc/roslab/discovery/fastdds-static-peers.xml"
SUPER_XML = "/etc/roslab/discovery/fastdds-super-client.xml"
CYCLONE_XML = "/etc/roslab/discovery/cyclonedds-static-peers.xml"
FAST = {"ROS_DOMAIN_ID": "11", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


def data_of(role: str, mode: str, middleware: str = "rmw_fastrtps_cpp", **more) -> dict:
    name = f"team1-{role}"
    return {**settings.defaults(), "ros_domain_id": 11, "roslab_role": role, "roslab_hostname": name,
            "roslab_team_hosts": TEAM, "ros_discovery_mode": mode, "ros_middleware": middleware, **more}


def typed(data: dict) -> HostSettings:
    """The helpers read a host's typed settings, built from its data as the deploys build them."""
    return settings_of(data.get("roslab_hostname") or "team1-host", data)


def typed_of(role: str, mode: str, middleware: str = "rmw_fastrtps_cpp", **more) -> HostSettings:
    return typed(data_of(role, mode, middleware, **more))


# distro, mode, role -> (variables, shell-only variables, files, service)
FAST_DDS_CASES = {
    ("humble", "multicast", "main"): (FAST, {}, set(), None),
    ("humble", "multicast", "robot"): (FAST, {}, set(), None),
    ("jazzy", "multicast", "main"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, {}, set(), None),
    ("lyrical", "multicast", "robot"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, {}, set(), None),
    ("humble", "static", "main"): ({**FAST, "FASTRTPS_DEFAULT_PROFILES_FILE": PEERS_XML}, {}, {PEERS_XML}, None),
    ("humble", "static", "robot"): ({**FAST, "FASTRTPS_DEFAULT_PROFILES_FILE": PEERS_XML}, {}, {PEERS_XML}, None),
    ("jazzy", "static", "main"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                                   "ROS_STATIC_PEERS": ROBOT_IP}, {}, set(), None),
    ("jazzy", "static", "robot"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                                    "ROS_STATIC_PEERS": MAIN_IP}, {}, set(), None),
    ("lyrical", "static", "robot"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                                      "ROS_STATIC_PEERS": MAIN_IP}, {}, set(), None),
    ("humble", "discovery_server", "main"): ({**FAST, "ROS_DISCOVERY_SERVER": "127.0.0.1:11811"},
                                             {"FASTRTPS_DEFAULT_PROFILES_FILE": SUPER_XML}, {SUPER_XML},
                                             "roslab-discovery-server"),
    ("humble", "discovery_server", "robot"): ({**FAST, "ROS_DISCOVERY_SERVER": f"{MAIN_IP}:11811"},
                                              {"FASTRTPS_DEFAULT_PROFILES_FILE": SUPER_XML}, {SUPER_XML}, None),
    ("jazzy", "discovery_server", "main"): ({**FAST, "ROS_DISCOVERY_SERVER": "127.0.0.1:11811"},
                                            {"ROS_SUPER_CLIENT": "TRUE"}, set(), "roslab-discovery-server"),
    ("jazzy", "discovery_server", "robot"): ({**FAST, "ROS_DISCOVERY_SERVER": f"{MAIN_IP}:11811"},
                                             {"ROS_SUPER_CLIENT": "TRUE"}, set(), None),
    ("lyrical", "discovery_server", "main"): ({**FAST, "ROS_DISCOVERY_SERVER": "127.0.0.1:11811"},
                                              {"ROS_SUPER_CLIENT": "TRUE"}, set(), "roslab-discovery-server"),
    ("humble", "localhost", "main"): ({**FAST, "ROS_LOCALHOST_ONLY": "1"}, {}, set(), None),
    ("jazzy", "localhost", "main"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, {}, set(), None),
    ("lyrical", "localhost", "robot"): ({**FAST, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, {}, set(), None),
}


@pytest.mark.parametrize("case", sorted(FAST_DDS_CASES), ids="-".join)
def test_fast_dds_each_mode_and_distro_gives_exactly_these_variables_files_and_service(case):
    distro, mode, role = case
    variables, shell, files, service = FAST_DDS_CASES[case]
    setup = discovery.host_discovery(typed_of(role, mode), distro)
    assert setup.variables == variables
    assert setup.shell_variables == shell
    assert set(setup.files) == files
    assert (setup.service.name if setup.service else None) == service


def test_every_mode_and_distro_of_the_matrix_is_pinned():
    assert {(d, m) for d, m, _ in FAST_DDS_CASES} == {
        (d, m) for d in ("humble", "jazzy", "lyrical") for m in discovery.MODES}


def parsed(text: str) -> ET.Element:
    assert text.startswith('<?xml version="1.0" encoding="UTF-8"?>\n<!-- managed by roslab')
    return ET.fromstring(text.encode())


def test_humble_static_fast_dds_profile_turns_multicast_off_and_lists_the_team():
    text = discovery.host_discovery(typed_of("robot", "static", ros_static_peers=["teacher-pc"]), "humble").files[
        PEERS_XML]
    root = parsed(text)
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    participant = root.find("p:participant", ns)
    assert participant.get("is_default_profile") == "true"
    builtin = participant.find("p:rtps/p:builtin", ns)
    # One empty unicast locator: Fast DDS then drops its default multicast metatraffic locator.
    assert [len(loc) for loc in builtin.findall("p:metatrafficUnicastLocatorList/p:locator", ns)] == [0]
    peers = [a.text for a in builtin.findall("p:initialPeersList/p:locator/p:udpv4/p:address", ns)]
    assert peers == ["127.0.0.1", MAIN_IP, "teacher-pc"]


def test_humble_super_client_profile_names_the_teams_server():
    text = discovery.host_discovery(typed_of("robot", "discovery_server", ros_discovery_server_port=11900),
                                    "humble").files[SUPER_XML]
    root = parsed(text)
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    config = root.find("p:profiles/p:participant/p:rtps/p:builtin/p:discovery_config", ns)
    assert config.find("p:discoveryProtocol", ns).text == "SUPER_CLIENT"
    server = config.find("p:discoveryServersList/p:RemoteServer", ns)
    assert server.get("prefix") == "44.53.00.5f.45.50.52.4f.53.49.4d.41"  # server 0, as `-i 0`
    udp = server.find("p:metatrafficUnicastLocatorList/p:locator/p:udpv4", ns)
    assert (udp.find("p:address", ns).text, udp.find("p:port", ns).text) == (MAIN_IP, "11900")


def test_humble_static_cyclone_dds_configuration_lists_the_team_without_multicast():
    setup = discovery.host_discovery(typed_of("main", "static", "rmw_cyclonedds_cpp"), "humble")
    assert setup.variables == {"ROS_DOMAIN_ID": "11", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
                               "CYCLONEDDS_URI": f"file://{CYCLONE_XML}"}
    root = parsed(setup.files[CYCLONE_XML])
    ns = {"c": "https://cdds.io/config"}
    assert root.find("c:Domain/c:General/c:AllowMulticast", ns).text == "false"
    assert [p.get("address") for p in root.findall("c:Domain/c:Discovery/c:Peers/c:Peer", ns)] == [
        "127.0.0.1", ROBOT_IP]


def test_jazzy_static_cyclone_dds_uses_ros_static_peers_like_fast_dds():
    setup = discovery.host_discovery(typed_of("robot", "static", "rmw_cyclonedds_cpp"), "jazzy")
    assert setup.variables == {"ROS_DOMAIN_ID": "11", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
                               "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": MAIN_IP}
    assert setup.files == {} and setup.service is None


@pytest.mark.parametrize("distro", ["humble", "jazzy", "lyrical"])
def test_zenoh_the_main_runs_the_router_and_the_robot_connects_to_it(distro):
    main = discovery.host_discovery(typed_of("main", "static", "rmw_zenoh_cpp"), distro)
    robot = discovery.host_discovery(typed_of("robot", "static", "rmw_zenoh_cpp"), distro)
    zenoh = {"ROS_DOMAIN_ID": "11", "RMW_IMPLEMENTATION": "rmw_zenoh_cpp"}
    assert main.variables == {**zenoh, "ZENOH_CONFIG_OVERRIDE": 'connect/endpoints=["tcp/127.0.0.1:7447"]'}
    assert robot.variables == {**zenoh, "ZENOH_CONFIG_OVERRIDE": f'connect/endpoints=["tcp/{MAIN_IP}:7447"]'}
    assert main.service.name == "roslab-zenoh-router" and robot.service is None
    assert main.service.command == ("ros2", "run", "rmw_zenoh_cpp", "rmw_zenohd")
    # Multicast scouting off: two teams' routers never join each other.
    assert main.service.environment == {
        "ZENOH_CONFIG_OVERRIDE": 'listen/endpoints=["tcp/0.0.0.0:7447"];scouting/multicast/enabled=false'}
    assert main.files == robot.files == {}


def test_zenoh_localhost_host_runs_its_own_router_on_the_loopback():
    setup = discovery.host_discovery(typed_of("robot", "localhost", "rmw_zenoh_cpp"), "jazzy")
    assert setup.service.environment["ZENOH_CONFIG_OVERRIDE"].startswith('listen/endpoints=["tcp/127.0.0.1:7447"]')
    assert setup.variables["ZENOH_CONFIG_OVERRIDE"] == 'connect/endpoints=["tcp/127.0.0.1:7447"]'


def test_the_discovery_server_listens_on_every_interface_of_the_main_at_the_port():
    setup = discovery.host_discovery(typed_of("main", "discovery_server", ros_discovery_server_port=12000), "jazzy")
    assert setup.service.command == ("fast-discovery-server", "-i", "0", "-l", "0.0.0.0", "-p", "12000")


def test_a_host_without_a_domain_id_exports_none_rather_than_the_word_none():
    # a roster host (a hand-made inventory must set one: host_rules refuses a null domain there)
    unset = typed_of("main", "multicast", ros_domain_id=None, roslab_roster_path="/classroom.yaml")
    assert "ROS_DOMAIN_ID" not in discovery.host_discovery(unset, "jazzy").variables


@pytest.mark.parametrize("middleware, package", [
    ("rmw_fastrtps_cpp", None), ("rmw_cyclonedds_cpp", "ros-humble-rmw-cyclonedds-cpp"),
    ("rmw_zenoh_cpp", "ros-humble-rmw-zenoh-cpp")])
def test_the_middleware_package_is_installed_beside_the_variant(middleware, package):
    from deploy.ros_install import ros_packages

    packages = ros_packages("humble", "robot", typed_of("robot", "multicast", middleware))
    assert packages[0] == "ros-humble-ros-base"
    extra = [name for name in packages if "rmw" in name]
    assert extra == ([package] if package else [])


# --- the shell block and the unit ---------------------------------------------------------------


def exported(block: str) -> dict[str, str]:
    out = {}
    for line in block.splitlines():
        if line.startswith("export ") and not line.startswith("export ROSDISTRO_INDEX_URL"):
            name, _, value = line[len("export "):].partition("=")
            out[name] = shlex.split(value)[0]
    return out


def unit_environment(text: str) -> dict[str, str]:
    return dict(shlex.split(line.removeprefix("Environment="))[0].split("=", 1)
                for line in text.splitlines() if line.startswith("Environment="))


def nodes_unit(data: dict, distro: str) -> str:
    return deploy_ws.unit_text(role=data["roslab_role"], user="student", home="/home/student",
                               workspace_dir="/home/student/ros2_ws", distro=distro,
                               launch="roslab_bringup robot.launch.py",
                               environment=host_environment(typed(data), distro),
                               discovery_files=discovery.host_discovery(typed(data), distro).files)


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
@pytest.mark.parametrize("mode", discovery.MODES)
def test_the_shell_and_the_unit_share_the_variables_the_shell_adds_the_super_client(distro, mode):
    data = data_of("robot", mode)
    block = render_ros_environment(distro, host_environment(typed(data), distro, shell=True))
    setup = discovery.host_discovery(typed(data), distro)
    assert exported(block) == {**setup.variables, **setup.shell_variables}
    assert unit_environment(nodes_unit(data, distro)) == setup.variables


def test_a_changed_peer_file_changes_the_nodes_unit_so_the_nodes_restart():
    before = nodes_unit(data_of("robot", "static"), "humble")
    moved = [TEAM[0] | {"address": "10.0.0.99"}, TEAM[1]]
    after = nodes_unit(data_of("robot", "static", roslab_team_hosts=moved), "humble")
    assert unit_environment(before) == unit_environment(after)  # the same variables...
    assert before != after  # ...but the file they name changed
    assert "sha256" not in nodes_unit(data_of("robot", "multicast"), "humble")


# --- the roster: modes per team, refusals before connecting --------------------------------------


def write(tmp_path, text: str):
    path = tmp_path / "lab.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def errors(path) -> list[str]:
    with pytest.raises(RosterError) as caught:
        load_roster(path, validators=[])
    return [str(problem).replace(f"{path.parent}/", "") for problem in caught.value.problems]


CLASS = """\
    classroom:
      ros_discovery_mode: static
      {classroom}
    teams:
      alpha:
        {alpha}
        hosts:
          alpha-main: {{role: main, address: 10.0.1.1}}
          alpha-robot: {{role: robot, address: 10.0.1.2}}
      bravo:
        ros_discovery_mode: discovery_server
        hosts:
          bravo-main: {{role: main, address: 10.0.2.1}}
          bravo-robot: {{role: robot, address: 10.0.2.2}}
      charlie:
        ros_discovery_mode: multicast
        hosts:
          charlie-main: {{role: main, address: 10.0.3.1}}
      delta:
        robot_profile: sim
        hosts:
          delta-main: {{role: main, address: 10.0.4.1}}
"""


def test_one_line_for_the_class_a_team_overrides_it_a_sim_team_stays_on_its_host(tmp_path):
    classroom = load_roster(write(tmp_path, CLASS.format(classroom="", alpha="")), validators=[])
    modes = {host.name: host.data["ros_discovery_mode"] for host in classroom.hosts}
    assert modes == {"alpha-main": "static", "alpha-robot": "static", "bravo-main": "discovery_server",
                     "bravo-robot": "discovery_server", "charlie-main": "multicast", "delta-main": "localhost"}
    robot = next(host for host in classroom.hosts if host.name == "bravo-robot")
    assert host_environment(typed(robot.data), "jazzy")["ROS_DISCOVERY_SERVER"] == "10.0.2.1:11811"
    alpha = next(host for host in classroom.hosts if host.name == "alpha-robot")
    assert host_environment(typed(alpha.data), "humble")["FASTRTPS_DEFAULT_PROFILES_FILE"] == PEERS_XML
    assert "10.0.1.1" in discovery.host_discovery(typed(alpha.data), "humble").files[PEERS_XML]
    assert "10.0.2" not in discovery.host_discovery(typed(alpha.data), "humble").files[PEERS_XML]


def test_a_discovery_server_with_cyclone_dds_is_refused_naming_file_line_team_and_field(tmp_path):
    path = write(tmp_path, CLASS.format(classroom="ros_middleware: rmw_cyclonedds_cpp", alpha=""))
    problems = errors(path)
    assert problems == [  # the team's mode: said once, for the team
        "lab.yaml:11: team 'bravo', field 'ros_discovery_mode': a discovery server is Fast "
        "DDS's: ros_middleware rmw_cyclonedds_cpp has none (use ros_discovery_mode static, or ros_middleware "
        "rmw_fastrtps_cpp)"]


def test_a_discovery_server_with_zenoh_is_refused(tmp_path):
    path = write(tmp_path, CLASS.format(classroom="ros_middleware: rmw_zenoh_cpp", alpha=""))
    assert all("a discovery server is Fast DDS's: ros_middleware rmw_zenoh_cpp" in p for p in errors(path))


def test_the_micro_ros_agent_with_zenoh_is_refused(tmp_path):
    path = write(tmp_path, """\
        classroom: {ros_middleware: rmw_zenoh_cpp}
        teams:
          alpha:
            hosts:
              alpha-main: {role: main}
              alpha-robot: {role: robot, nodes_launch: micro_ros_agent agent.launch.py}
    """)
    assert errors(path) == [
        "lab.yaml:1: team 'alpha', host 'alpha-robot', field 'ros_middleware': the micro-ROS agent speaks DDS "
        "only, so its robot would be invisible under rmw_zenoh_cpp: use rmw_fastrtps_cpp for this class"]


def test_a_host_set_to_a_team_mode_is_refused_localhost_is_allowed(tmp_path):
    path = write(tmp_path, """\
        teams:
          alpha:
            hosts:
              alpha-main: {role: main, ros_discovery_mode: localhost}
              alpha-robot: {role: robot, ros_discovery_mode: static}
    """)
    assert errors(path) == [
        "lab.yaml:5: team 'alpha', host 'alpha-robot', field 'ros_discovery_mode': a host may only be set to "
        "localhost (a simulation-only host); set static on its team, where its team mates get it too"]


def test_a_discovery_server_team_without_a_main_is_refused(tmp_path):
    path = write(tmp_path, """\
        teams:
          alpha:
            ros_discovery_mode: discovery_server
            hosts:
              alpha-robot: {role: robot}
    """)
    assert errors(path) == [
        "lab.yaml:3: team 'alpha', host 'alpha-robot', field 'ros_discovery_mode': the discovery server runs "
        "on the team's main host, and this team has none: give it a host with role: main"]


def test_a_middleware_set_on_a_team_is_refused_it_is_one_for_the_class(tmp_path):
    path = write(tmp_path, CLASS.format(classroom="", alpha="ros_middleware: rmw_cyclonedds_cpp"))
    (problem,) = errors(path)
    assert problem.startswith("lab.yaml:6: team 'alpha'") and "'ros_middleware' can only be set on a classroom" \
        in problem


def test_a_distro_without_the_middleware_package_is_refused(tmp_path, monkeypatch):
    from roslab.profiles import packages

    known = {"ros_base", "desktop", "rmw_fastrtps_cpp", "roslab_bringup"}
    monkeypatch.setattr(packages, "distro_packages", lambda *args, **kwargs: known)
    path = write(tmp_path, """\
        classroom: {ros_middleware: rmw_zenoh_cpp}
        teams:
          alpha:
            hosts:
              alpha-main: {role: main}
    """)
    with pytest.raises(RosterError) as caught:
        load_roster(path, validators=[packages.check_classroom])
    problems = [str(problem).replace(f"{path.parent}/", "") for problem in caught.value.problems]
    assert any(problem.startswith("lab.yaml:1: team 'alpha', host 'alpha-main', field 'ros_middleware': "
                                  "ros-jazzy-rmw-zenoh-cpp is not a package of ROS 2 jazzy")
               for problem in problems), problems


# --- the deploy: files and services, facts in, commands out --------------------------------------


class DiscoveryHost(FakeUbuntu):
    def __init__(self, codename: str = "noble"):
        super().__init__(codename)
        self.unit_state = {"LoadState": "not-found", "ActiveState": "inactive", "SubState": "dead",
                           "Result": "success"}

    def facts(self) -> dict:
        return {**super().facts(), workspace.NodesUnitState: lambda service: dict(self.unit_state)}


def run(fake: DiscoveryHost, role: str, mode: str, **more):
    data = {**data_of(role, mode, **more), "ssh_user": "student"}
    return plan(deploy_discovery.discovery_in_place, fake.facts(), data)


def test_the_main_of_a_discovery_server_team_runs_it_as_a_service_and_a_rerun_changes_nothing():
    fake = DiscoveryHost()
    first = run(fake, "main", "discovery_server")
    assert not first.failed, first.errors
    unit = first.uploads()["/etc/systemd/system/roslab-discovery-server.service"]
    assert "fast-discovery-server" in unit and "User=student" in unit and "WantedBy=multi-user.target" in unit
    assert "Restart=always" in unit
    changing = first.changing()
    assert any("restart roslab-discovery-server.service" in " ".join(cmds) for cmds in changing.values())
    assert any("enable" in " ".join(cmds) for cmds in changing.values())
    fake.apply(first)
    fake.enabled_units["roslab-discovery-server.service"] = True
    fake.unit_state = {"LoadState": "loaded", "ActiveState": "active", "SubState": "running", "Result": "success"}
    again = run(fake, "main", "discovery_server")
    assert again.changing() == {}


def test_a_robot_runs_no_service_and_a_switched_team_retires_its_server_and_stale_files():
    fake = DiscoveryHost()
    assert run(fake, "robot", "discovery_server").changing() == {}  # Jazzy: no files, no service
    first = run(fake, "main", "discovery_server", ros_distro="humble")
    fake.apply(first)
    fake.enabled_units["roslab-discovery-server.service"] = True  # enabled and running, as systemd has it
    assert SUPER_XML in fake.files and "/etc/systemd/system/roslab-discovery-server.service" in fake.files
    switched = run(fake, "main", "multicast", ros_distro="humble")
    text = {name: " ".join(cmds) for name, cmds in switched.changing().items()}
    assert any("stop" in cmds and "roslab-discovery-server" in cmds for cmds in text.values())
    assert any(SUPER_XML in name for name in text)  # the super client's profile goes too
    assert any("roslab-discovery-server.service is gone" in name for name in text)


@pytest.mark.parametrize("codename", ["jammy", "noble"])
def test_deploy_py_on_a_discovery_server_main_converges_then_reads_the_host_in_two_commands(tmp_path, codename):
    from fixtures.classroom import host_data, run_deploy_py, with_stand_in_deb

    fake = with_stand_in_deb(DiscoveryHost(codename), codename)
    data = host_data(tmp_path, codename, "main", ros_discovery_mode="discovery_server", roslab_team_hosts=TEAM)
    first = plan(run_deploy_py, fake.facts(), data)
    assert not first.failed, first.errors
    assert "/etc/systemd/system/roslab-discovery-server.service" in first.uploads()
    assert (SUPER_XML in first.uploads()) == (codename == "jammy")  # Humble's super client is XML
    fake.apply(first)
    fake.enabled_units["roslab-discovery-server.service"] = True
    fake.unit_state = {"LoadState": "loaded", "ActiveState": "active", "SubState": "running", "Result": "success"}
    second = plan(run_deploy_py, fake.facts(), data)
    assert second.changing() == {}
    assert second.facts_asked == ["HostProbe", "HostProbe"]


def test_a_server_team_whose_main_keeps_discovery_on_itself_is_refused(tmp_path):
    path = write(tmp_path, """\
        teams:
          alpha:
            ros_discovery_mode: discovery_server
            hosts:
              alpha-main: {role: main, ros_discovery_mode: localhost}
              alpha-robot: {role: robot}
    """)
    assert errors(path) == [
        "lab.yaml:5: team 'alpha', host 'alpha-robot', field 'ros_discovery_mode': the discovery server runs "
        "on the team's main host, and 'alpha-main' keeps its discovery on itself (ros_discovery_mode "
        "localhost): this host would find nobody"]
