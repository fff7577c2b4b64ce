"""The ESP32 board: the firmware (firmware/esp32_microros) and the sandbox's emulated board
(roslab/sandbox/board/esp32_board_standin.c) held to the same topics, types, node name rule,
domain rule, reconnect behaviour and build variables, by reading both sources; the values each
board is flashed with, from the roster (`roslab esp32-firmware`); `roslab sandbox board`'s
start, status and stop of a board process; the agent unit's XRCE_DOMAIN_ID_OVERRIDE.

The board process in the start/stop tests is a STAND-IN of the emulated board (a shell script
in tmp_path that prints what the real one prints): it proves the process handling and the
environment the board is given, not the DDS-XRCE traffic (the robots e2e does that)."""

from __future__ import annotations

import re
import stat
from pathlib import Path

import pytest
from test_profiles import _in_tmp, rosdistro_url  # noqa: F401  (fixtures)
from test_robots import BASE, problems_of, resolved, roster

from deploy.profile_services import host_filled, unit_text
from roslab.cli.main import main
from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import ResolvedService
from roslab.robot_tools import esp32_firmware
from roslab.roster import load_roster
from roslab.sandbox import esp32_board
from roslab.sandbox.system import SandboxError

ROOT = Path(__file__).resolve().parents[2]
FIRMWARE = (ROOT / "firmware/esp32_microros/src/main.cpp").read_text()
PLATFORMIO = (ROOT / "firmware/esp32_microros/platformio.ini").read_text()
STANDIN = esp32_board.SOURCE.read_text()
INT32 = ("std_msgs", "msg", "Int32")


def firmware_topics() -> dict[str, tuple[str, ...]]:
    """{topic: (package, msg, type)} of each rclc publisher and subscription the firmware creates."""
    found = re.findall(r"rclc_(?:publisher|subscription)_init_default\(\s*&\w+,\s*&node,\s*"
                       r"ROSIDL_GET_MSG_TYPE_SUPPORT\((\w+), (\w+), (\w+)\),\s*\"([^\"]+)\"\)", FIRMWARE)
    return {f"/{topic}": (package, kind, name) for package, kind, name, topic in found}


def standin_topics() -> dict[str, tuple[str, ...]]:
    """{topic: (package, msg, type)} of each DDS topic the emulated board creates (ROS 2's names
    in DDS: rt/<topic>, <package>::msg::dds_::<Type>_)."""
    found = re.findall(r"uxr_buffer_create_topic_bin\([^\"]+\"rt(/[^\"]+)\",\s*\"(\w+)::(\w+)::dds_::(\w+)_\"",
                       STANDIN)
    return {topic: (package, kind, name) for topic, package, kind, name in found}


def test_both_boards_publish_and_subscribe_the_same_topics_and_types_and_verify_listens_to_one():
    topics = firmware_topics()
    assert topics == {"/esp32/potentiometer": INT32, "/esp32/servo_angle": INT32}
    assert standin_topics() == topics
    profile = builtin_profiles()["esp32_microros"]
    assert profile.verify_topic in topics and profile.verify_type == "/".join(topics[profile.verify_topic])


def test_both_boards_are_flashed_from_the_same_environment_variables():
    ini = set(re.findall(r"\$\{sysenv\.(\w+)\}", PLATFORMIO))
    names = {esp32_firmware.DOMAIN_ENV, esp32_firmware.NODE_ENV, esp32_firmware.AGENT_IP_ENV,
             esp32_firmware.AGENT_PORT_ENV}
    assert ini == names | set(esp32_firmware.WIFI_ENVS)
    assert set(re.findall(r'required\("(\w+)"\)', STANDIN)) == names
    # each becomes the build flag of its own name, which the firmware's source uses
    for name in ini:
        assert f'-D{name}=\\"${{sysenv.{name}}}\\"' in PLATFORMIO
        assert name in FIRMWARE


def test_both_boards_name_their_node_and_set_the_domain_from_those_variables():
    # the firmware: rcl init options with the domain, never plain rclc_support_init (domain 0)
    assert "rcl_init_options_set_domain_id(&init_options, kDomainId)" in FIRMWARE
    assert "rclc_support_init_with_options(&support, 0, nullptr, &init_options, &allocator)" in FIRMWARE
    assert "rclc_support_init(&" not in FIRMWARE
    assert "constexpr size_t kDomainId = parsed(ROSLAB_ROS_DOMAIN_ID, 0);" in FIRMWARE
    assert "rclc_node_init_default(&node, ROSLAB_NODE_NAME, \"\", &support)" in FIRMWARE
    # the emulated board: its participant (the agent's node) is named so, in that domain
    assert "uxr_buffer_create_participant_bin(s, board->out, participant, domain, node, UXR_REPLACE)" in STANDIN
    assert "create_entities(&board, (int16_t)domain, node)" in STANDIN


def constant(source: str, pattern: str) -> int:
    return int(re.search(pattern, source).group(1))


def test_both_boards_reconnect_the_same_way_and_at_the_same_pace():
    # The firmware: wait (ping, 500 ms apart) -> create -> connected (ping each turn) -> lost
    # (destroy, session timeout 0) -> wait. The emulated board: the same loop.
    waiting = FIRMWARE.index("case Link::kWaitingForAgent:")
    connected = FIRMWARE.index("case Link::kConnected:")
    lost = FIRMWARE.index("case Link::kLost:")
    assert "rmw_uros_ping_agent(kAgentPingTimeoutMs, 1) == RMW_RET_OK" in FIRMWARE[waiting:connected]
    assert "create_entities()" in FIRMWARE[waiting:connected] and "delay(500)" in FIRMWARE[waiting:connected]
    assert "rmw_uros_ping_agent(kAgentPingTimeoutMs, 1) != RMW_RET_OK" in FIRMWARE[connected:lost]
    assert "destroy_entities();" in FIRMWARE[lost:] and "Link::kWaitingForAgent" in FIRMWARE[lost:]
    assert "rmw_uros_set_context_entity_destroy_session_timeout(context, 0)" in FIRMWARE
    loop = STANDIN[STANDIN.index("for (;;)"):]
    steps = ["uxr_ping_agent_attempts(&board.transport.comm, PING_TIMEOUT_MS, 1)", "sleep_ms(WAIT_MS)",
             "create_entities(&board", "while (uxr_ping_agent_session(&board.session, PING_TIMEOUT_MS, 1))",
             "uxr_delete_session_retries(&board.session, 0)"]
    assert [loop.index(step) for step in steps] == sorted(loop.index(step) for step in steps)
    assert constant(STANDIN, r"#define PUBLISH_PERIOD_MS (\d+)") == constant(FIRMWARE, r"kPublishPeriodMs = (\d+);")
    assert constant(STANDIN, r"#define PING_TIMEOUT_MS (\d+)") == constant(FIRMWARE, r"kAgentPingTimeoutMs = (\d+);")
    assert constant(STANDIN, r"#define WAIT_MS (\d+)") == 500


@pytest.mark.parametrize("team, name", [("team2", "esp32_board_team2"), ("blue-team", "esp32_board_blue_team"),
                                        ("2nd", "esp32_board_2nd")])
def test_the_node_name_says_whose_board_it_is_as_a_ros_name(team, name):
    assert esp32_firmware.node_name(team) == name
    assert re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name)


def esp32_roster(tmp_path, url, extra="esp32_transport: udp\nesp32_udp_port: '9999'", host=""):
    return roster(tmp_path, url, "esp32_microros", f"esp32_usb_serial: A1B2C3\n{extra}",
                  robot_extra=f", address: 10.0.0.21{host}", main_extra=", address: 10.0.0.20",
                  classroom_extra="ros_domain_id: 42")


def test_a_board_is_flashed_with_the_values_its_agents_host_gets(tmp_path, rosdistro_url):
    classroom = load_roster(esp32_roster(tmp_path, rosdistro_url))
    robot = next(host for host in classroom.hosts if host.role == "robot")
    values = esp32_firmware.board_values(classroom, "t1")
    assert values == esp32_firmware.BoardValues(
        team="t1", agent_host="t1-robot", domain_id=robot.ros_domain_id, node_name="esp32_board_t1",
        transport="udp", agent_address="10.0.0.21", agent_port=9999, distro="jazzy")
    assert values.domain_id == 42
    assert values.pio_command() == ("ROSLAB_ROS_DOMAIN_ID=42 ROSLAB_NODE_NAME=esp32_board_t1 "
                                    "ROSLAB_AGENT_IP=10.0.0.21 ROSLAB_AGENT_PORT=9999 pio run -e udp_jazzy -t upload")
    assert esp32_firmware.board_values(classroom, "nobody") is None


def test_roslab_esp32_firmware_prints_each_teams_command_and_no_secret(tmp_path, rosdistro_url, capsys):
    path = esp32_roster(tmp_path, rosdistro_url, extra="esp32_attached_to: main")
    assert main(["esp32-firmware", str(path), "--limit", "t1"]) == 0
    out = capsys.readouterr().out
    assert "t1: node esp32_board_t1, domain 42, agent on t1-main (serial)" in out
    assert "  ROSLAB_ROS_DOMAIN_ID=42 ROSLAB_NODE_NAME=esp32_board_t1 pio run -e serial_jazzy -t upload" in out
    assert "ROSLAB_WIFI" not in out


def test_roslab_esp32_firmware_on_a_class_without_an_esp32_team_says_so(tmp_path, rosdistro_url, capsys):
    path = roster(tmp_path, rosdistro_url, "osr")
    assert main(["esp32-firmware", str(path)]) == 1
    assert "no esp32_microros team among the selected hosts" in capsys.readouterr().err


def test_the_agents_unit_gets_the_hosts_domain_as_xrce_domain_id_override():
    service = ResolvedService.from_data(resolved("esp32_microros", esp32_usb_serial="A1")["services"][0])
    assert service.environment["XRCE_DOMAIN_ID_OVERRIDE"] == "${ros_domain_id}"
    text = unit_text(service=service, profile="esp32_microros", user="ubuntu", home="/home/ubuntu",
                     workspace_dir="/home/ubuntu/ros2_ws", distro="jazzy",
                     environment={"ROS_DOMAIN_ID": "42", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"})
    assert '"XRCE_DOMAIN_ID_OVERRIDE=42"' in text or "XRCE_DOMAIN_ID_OVERRIDE=42" in text
    assert host_filled({"A": "${ros_domain_id}", "B": "b"}, {}) == {"B": "b"}


# --- `roslab sandbox board`'s process handling, with a stand-in board program -------------------

def fake_board(tmp_path: Path, publishes: bool = True) -> Path:
    """A STAND-IN of the emulated board's program: prints its environment's values as the real
    one prints its state, then runs until SIGTERM (or exits 2 when told to refuse)."""
    path = tmp_path / esp32_board.EXECUTABLE
    say = ('echo "esp32 stand-in: publishing /esp32/potentiometer through the agent at '
           '$ROSLAB_AGENT_IP:$ROSLAB_AGENT_PORT (domain $ROSLAB_ROS_DOMAIN_ID, node $ROSLAB_NODE_NAME)"'
           if publishes else 'echo "esp32 stand-in: ROSLAB_ROS_DOMAIN_ID is not set" >&2; exit 2')
    path.write_text(f"#!/bin/sh\ntrap 'exit 0' TERM\n{say}\nwhile :; do sleep 0.05; done\n")
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


VALUES = esp32_firmware.BoardValues(team="t1", agent_host="t1-robot", domain_id=42, node_name="esp32_board_t1",
                                    transport="udp", agent_address="10.0.0.21", agent_port=9999, distro="jazzy")


def test_a_board_starts_with_the_firmwares_values_reports_its_state_and_stops(tmp_path):
    state_dir = tmp_path / "state"
    assert esp32_board.state(state_dir, "t1") == "stopped"
    try:
        assert esp32_board.start(fake_board(tmp_path), VALUES, state_dir, timeout=5) is True
        log = esp32_board.board_files(state_dir, "t1")[1].read_text()
        assert "10.0.0.21:9999 (domain 42, node esp32_board_t1)" in log
        assert esp32_board.state(state_dir, "t1").startswith("publishing (pid ")
        assert esp32_board.start(fake_board(tmp_path), VALUES, state_dir) is True  # running: left as it is
    finally:
        assert esp32_board.stop(state_dir, "t1") is True
    assert esp32_board.state(state_dir, "t1") == "stopped"
    assert esp32_board.stop(state_dir, "t1") is False


def test_a_board_that_exits_at_once_is_an_error_with_its_words(tmp_path):
    with pytest.raises(SandboxError, match="exited .rc 2.: esp32 stand-in: ROSLAB_ROS_DOMAIN_ID is not set"):
        esp32_board.start(fake_board(tmp_path, publishes=False), VALUES, tmp_path / "state", timeout=5)
    assert esp32_board.state(tmp_path / "state", "t1") == "stopped"


def test_a_pid_file_naming_another_program_is_not_a_board(tmp_path):
    pid_file, _ = esp32_board.board_files(tmp_path, "t1")
    pid_file.parent.mkdir(parents=True)
    pid_file.write_text("1\n")  # init: never a board, never signalled
    assert esp32_board.running_pid(pid_file) is None
    assert esp32_board.stop(tmp_path, "t1") is False and not pid_file.exists()


def test_the_roster_gives_the_main_the_boards_node_name_for_verify(tmp_path, rosdistro_url):
    classroom = load_roster(esp32_roster(tmp_path, rosdistro_url))
    main_host = next(host for host in classroom.hosts if host.role == "main")
    assert main_host.data["roslab_verify_publisher"] == esp32_firmware.node_name("t1") == "esp32_board_t1"
    assert builtin_profiles()["esp32_microros"].verify_publisher == "esp32_board_${team}"


def publisher_problems(value: str) -> list[str]:
    return [problem for problem in problems_of({**BASE, "verify_topic": "/x", "verify_publisher": value})
            if "verify_publisher" in problem]


@pytest.mark.parametrize("value", ["esp32 board", "x; rm -rf /", "${nosuch}_board", "1board"])
def test_a_verify_publisher_that_is_no_node_name_is_refused(value):
    assert publisher_problems(value)


def test_a_verify_publisher_may_name_the_team_and_the_profiles_settings():
    assert publisher_problems("b_${team}_${on}") == []


def test_the_sandboxs_down_stops_every_board(tmp_path):
    state_dir = tmp_path / "state"
    teams = ("t1", "t2")
    for team in teams:
        values = esp32_firmware.BoardValues(**{**VALUES.__dict__, "team": team})
        assert esp32_board.start(fake_board(tmp_path), values, state_dir, timeout=5)
    esp32_board.stop_all(state_dir)
    assert [esp32_board.state(state_dir, team) for team in teams] == ["stopped", "stopped"]
