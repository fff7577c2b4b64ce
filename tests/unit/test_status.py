"""`roslab status`: the record of each run (runs.yaml), the probe, the table and the page.

No host is contacted: the probe's output, the hosts' states and the recorded runs are
fixtures; the command itself runs against loopback ports where nothing (or something that
never answers) listens. The page is checked in a real headless browser in
test_status_browser.py.
"""

from __future__ import annotations

import html.parser
import os
import socket
import subprocess
import sys
import threading
import time
from datetime import timedelta
from pathlib import Path

import pytest
import yaml
from fixtures.status_hosts import (
    HOSTILE, NOW, PROBE_OUTPUT, hostile_page, never_run_host, reachable_host, unreachable_host,
)
from pyinfra.api import Config, Inventory, State
from pyinfra.api.state import StateStage

from roslab.reporting import runs
from roslab.cli import status
from roslab.reporting import summary
from roslab.reporting.runs import HostRun, RunRecord
from roslab.secrets import Secret
from roslab.cli.status import format_table, host_cells, page_context, parse_probe, render_page

REPO = Path(__file__).resolve().parents[2]


# runs.yaml ------------------------------------------------------------------------------


def test_a_run_is_recorded_beside_the_roster_and_read_back(tmp_path):
    roster = tmp_path / "classroom.yaml"
    path = runs.record_runs(roster, [
        HostRun("team1-main", "changed"),
        HostRun("team1-robot", "failed", "Ensure ROS 2 jazzy is installed", "E: Unable to locate package x"),
    ], when=NOW)

    assert path == tmp_path / ".roslab-state" / "runs.yaml"
    assert path.read_text().startswith("# managed by roslab")
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    read = runs.read_runs(roster)
    assert read["team1-main"] == RunRecord(NOW, "changed", None, None, NOW)
    assert read["team1-robot"] == RunRecord(NOW, "failed", "Ensure ROS 2 jazzy is installed",
                                            "E: Unable to locate package x", None)


def test_a_failed_run_keeps_the_last_success_and_other_hosts_are_kept(tmp_path):
    roster = tmp_path / "classroom.yaml"
    earlier = NOW - timedelta(hours=2)
    runs.record_runs(roster, [HostRun("a", "ok"), HostRun("b", "changed")], when=earlier)
    runs.record_runs(roster, [HostRun("a", "failed", "connect", "Could not connect")], when=NOW)

    read = runs.read_runs(roster)
    assert read["a"].result == "failed" and read["a"].last_run == NOW
    assert read["a"].last_success == earlier
    assert read["b"] == RunRecord(earlier, "changed", None, None, earlier)  # --limit a: b untouched


def test_recording_is_atomic_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    roster = tmp_path / "classroom.yaml"
    runs.record_runs(roster, [HostRun("a", "ok")], when=NOW)
    before = runs.runs_path(roster).read_text()

    def crash(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(runs.yaml, "safe_dump", crash)
    with pytest.raises(OSError):
        runs.record_runs(roster, [HostRun("a", "failed")], when=NOW)
    assert runs.runs_path(roster).read_text() == before  # the old record stands, whole
    assert sorted(p.name for p in runs.runs_path(roster).parent.iterdir()) == [".runs.yaml.lock", "runs.yaml"]


def test_two_runs_ending_at_once_both_land(tmp_path):
    roster = tmp_path / "classroom.yaml"
    threads = [threading.Thread(target=runs.record_runs, args=(roster, [HostRun(f"host{i}", "ok")]))
               for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(runs.read_runs(roster)) == [f"host{i}" for i in range(8)]


def test_a_broken_runs_file_is_an_error_for_the_reader_and_replaced_by_the_next_run(tmp_path):
    roster = tmp_path / "classroom.yaml"
    path = runs.runs_path(roster)
    path.parent.mkdir()
    path.write_text("- not\n- a mapping\n")
    with pytest.raises(ValueError):
        runs.read_runs(roster)
    runs.record_runs(roster, [HostRun("a", "ok")], when=NOW)
    assert runs.read_runs(roster)["a"].result == "ok"


def finished_state(names, roster, *, executing: bool, data=None) -> tuple[State, summary.RunSummary]:
    inventory = Inventory(([(name, {"roslab_roster_path": str(roster), **(data or {}).get(name, {})})
                           for name in names], {}))
    state = State(inventory, Config())
    for host in inventory:
        state.activate_host(host)
    state.set_stage(StateStage.Prepare)
    handler = summary.install(state)
    for name in names:
        handler.mark_planned(name)
    if executing:
        state.set_stage(StateStage.Execute)
        state.is_executing = True
        state.set_stage(StateStage.Disconnect)
    return state, handler


def test_the_summary_records_each_host_of_a_real_run(tmp_path):
    roster = tmp_path / "classroom.yaml"
    secret = "hunter2-wifi"
    state, handler = finished_state(["team1-main", "team1-robot"], roster, executing=True,
                                    data={"team1-robot": {"wifi_password": Secret(secret)}})
    handler.record_stop("team1-robot", "Network", f"roslab stops this host: bad password {secret}")
    state.fail_hosts({state.inventory.get_host("team1-robot")})

    assert handler.record(state, when=NOW) == [runs.runs_path(roster)]
    text = runs.runs_path(roster).read_text()
    assert secret not in text
    read = runs.read_runs(roster)
    assert read["team1-main"] == RunRecord(NOW, "ok", None, None, NOW)
    assert read["team1-robot"].result == "failed" and read["team1-robot"].step == "Network"
    assert read["team1-robot"].reason == "bad password ***"
    assert read["team1-robot"].last_success is None


def test_a_dry_run_records_nothing(tmp_path):
    roster = tmp_path / "classroom.yaml"
    state, handler = finished_state(["team1-main"], roster, executing=False)
    assert handler.record(state, when=NOW) == []
    assert not (tmp_path / ".roslab-state").exists()


# the probe --------------------------------------------------------------------------------

def test_the_probe_output_is_parsed():
    probe = parse_probe(PROBE_OUTPUT)
    assert probe["probed"] is True
    assert probe["os"]["VERSION_ID"] == "24.04" and probe["os"]["UBUNTU_CODENAME"] == "noble"
    assert probe["ros"] == ["jazzy"]
    assert status.parse_environment(probe["unit"]["Environment"]) == {
        "ROS_DOMAIN_ID": "11", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_STATIC_PEERS": "a b"}
    assert parse_probe([])["probed"] is False
    assert parse_probe(PROBE_OUTPUT[:-1])["probed"] is False  # cut short: not a whole answer


def test_the_probe_is_one_command_without_sudo_that_a_posix_shell_runs():
    script = status.StatusProbe().command()
    assert "sudo" not in script and "systemctl show --property=" in script and "roslab-nodes.service" in script
    # Run for real here (read-only): /etc/os-release, /opt/ros/*, systemctl show.
    output = subprocess.run(["sh", "-c", script], capture_output=True, text=True, timeout=30)
    assert output.returncode == 0
    probe = parse_probe(output.stdout.splitlines())
    assert probe["probed"] and probe["os"].get("ID")


# the table ------------------------------------------------------------------------------


def test_table_rows_for_a_reachable_an_unreachable_and_a_never_run_host():
    hosts = [reachable_host(), unreachable_host(), never_run_host()]
    lines = format_table(hosts, NOW).splitlines()
    assert lines[0].split("  ")[0] == "TEAM" and "LAST SUCCESS" in lines[0] and lines[1].startswith("----")
    cells = {host.name: {k: v.text for k, v in host_cells(host, NOW).items()} for host in hosts}

    main = cells["team1-main"]
    assert (main["SSH"], main["UBUNTU"], main["ROS"], main["DOMAIN"], main["NODES"]) == (
        "ok", "24.04 noble", "jazzy", "11", "active (running)")
    assert main["LAST RUN"].startswith("changed ") and main["LAST RUN"].endswith("(5 min ago)")
    assert main["NOTE"] == ""

    robot = cells["team1-robot"]
    assert (robot["SSH"], robot["UBUNTU"], robot["ROS"], robot["NODES"]) == ("unreachable", "?", "?", "?")
    assert robot["DOMAIN"] == "11 (roster)"
    assert robot["LAST RUN"].startswith("failed ") and robot["LAST RUN"].endswith("(3 days ago)")
    assert robot["LAST SUCCESS"].endswith("(4 days ago)")
    assert "Connection refused" in robot["NOTE"] and 'last run failed in "connect"' in robot["NOTE"]

    fresh = cells["team2-main"]
    assert (fresh["ROS"], fresh["NODES"], fresh["LAST RUN"], fresh["LAST SUCCESS"]) == (
        "none", "not installed", "never", "never")
    # Every column starts at the same offset on every line.
    offset = lines[0].index("NODES")
    assert all(line[offset - 2:offset] == "  " for line in lines[2:])


def test_a_host_whose_nodes_run_on_another_domain_or_release_is_flagged():
    host = reachable_host(roster_domain=12, expected_release="22.04", expected_distro="humble")
    cells = host_cells(host, NOW)
    assert cells["DOMAIN"].text == "11" and cells["DOMAIN"].level == "bad"
    assert cells["UBUNTU"].level == "bad" and cells["ROS"].level == "warn"
    assert "its nodes run on domain 11, the roster says 12" in cells["NOTE"].text
    assert "the roster expects Ubuntu 22.04" in cells["NOTE"].text


def test_a_failed_service_is_bad():
    host = reachable_host()
    host.probe["unit"].update(ActiveState="failed", SubState="failed", Result="start-limit-hit")
    cells = host_cells(host, NOW)
    assert cells["NODES"].text == "failed (start-limit-hit)" and cells["NODES"].level == "bad"


# the page -------------------------------------------------------------------------------


class Elements(html.parser.HTMLParser):
    """Tags, attributes and text of a page, as a browser's parser would see them."""

    def __init__(self, text: str):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)


def test_the_page_is_one_self_contained_file_with_a_managed_header():
    page = hostile_page()
    assert page.startswith("<!-- managed by roslab")
    tags = Elements(page).tags
    assert not [tag for tag, attrs in tags if tag in ("script", "link", "img", "iframe", "object")]
    assert not [attrs for tag, attrs in tags if attrs.get("src") or (attrs.get("href") or "").startswith("http")]
    assert "http://" not in page and "https://" not in page
    csp = next(attrs["content"] for tag, attrs in tags if attrs.get("http-equiv") == "Content-Security-Policy")
    assert csp.startswith("default-src 'none'")


def test_every_value_on_the_page_is_escaped():
    page = hostile_page(listen=True)
    elements = Elements(page)
    assert [tag for tag, _ in elements.tags].count("script") == 0
    assert "img" not in [tag for tag, _ in elements.tags] and "b" not in [tag for tag, _ in elements.tags]
    text = "".join(elements.text)
    assert HOSTILE in text  # shown as text
    assert "<b>boom</b> & more" in text
    assert "&lt;script&gt;" in page and "<script" not in page
    sections = [attrs for tag, attrs in elements.tags if tag == "section"]
    assert sections[0]["data-team"] == HOSTILE  # an attribute value, not markup


def test_the_page_draws_each_team_with_its_hosts_and_states():
    hosts = [reachable_host(), unreachable_host(), never_run_host()]
    page = render_page(page_context("lab", "classroom.yaml", hosts, NOW))
    tags = Elements(page).tags
    teams = [attrs["data-team"] for tag, attrs in tags if tag == "section"]
    assert teams == ["team1", "team2"]
    boxes = {attrs["data-host"]: attrs["data-level"] for tag, attrs in tags if tag == "g" and "data-host" in attrs}
    assert boxes == {"team1-main": "ok", "team1-robot": "bad", "team2-main": "warn"}
    rows = [attrs["data-host"] for tag, attrs in tags if tag == "tr" and "data-host" in attrs]
    assert rows == ["team1-main", "team1-robot", "team2-main"]
    arrows = [attrs["class"] for tag, attrs in tags if tag == "line"]
    assert arrows == ["arrow unknown"]  # robot -> main, not listened
    assert "topics seen: not checked (roslab status --listen)" in page
    assert "no robot in this team" in page


def test_listening_on_an_esp32_team_names_its_board_as_verify_does():
    """The trial's page said '/esp32/potentiometer listed but no message' (the robot's own servo
    node lists the topic anyway) where verify names the board; and a message is the board's only
    when its node published it."""
    board = "esp32_board_knob"
    source = "the ESP32 board (through micro_ros_agent on the team's robot, udp)"
    main = reachable_host(name="knob-main", team="knob", profile="esp32_microros", runs_nodes=False,
                          verify_source=source, verify_publisher=board)
    robot = reachable_host(name="knob-robot", role="robot", team="knob", profile="esp32_microros")
    main.heard = {"ros": True, "topics": ["/esp32/potentiometer", "/esp32/servo_angle"], "message": None,
                  "robot": None, "echo_status": 124, "daemon_stopped": False, "finished": True, "publishers": []}
    topic_of = {"knob": "/esp32/potentiometer"}
    types = {"knob": "std_msgs/msg/Int32"}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True, topics=topic_of, message_types=types,
                           listen_timeout=20)["teams"][0]
    assert picture["verdict"] == f"no message from {board} on /esp32/potentiometer within 20 s: {source} publishes nothing"
    main.heard = {**main.heard, "message": "data: 3262", "echo_status": 0, "publishers": [board]}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True, topics=topic_of, message_types=types,
                           listen_timeout=20)["teams"][0]
    assert picture["verdict"] == f"heard a std_msgs/msg/Int32 on /esp32/potentiometer from {board}"
    assert picture["verdict_level"] == "ok"


def test_listening_shows_the_topics_heard_and_whether_the_robot_was_heard():
    main, robot = reachable_host(), reachable_host(name="team1-robot", role="robot")
    main.heard = {"ros": True, "topics": ["/chatter", "/robot_status", "/rosout"],
                  "message": "Hello from team1-robot #3", "robot": "team1-robot", "echo_status": 0,
                  "daemon_stopped": False, "finished": True}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True)["teams"][0]
    assert picture["verdict"] == "heard team1-robot" and picture["verdict_level"] == "ok"
    assert [arrow["state"] for arrow in picture["arrows"]] == ["ok"]
    assert [text["text"] for text in picture["texts"]] == ["topics seen:", "  /chatter", "  /robot_status"]

    main.heard = {**main.heard, "message": None, "robot": None, "topics": ["/rosout"]}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True)["teams"][0]
    assert picture["verdict_level"] == "bad" and "does not see /chatter" in picture["verdict"]
    assert [arrow["state"] for arrow in picture["arrows"]] == ["bad"]

    # A main host without a ROS 2 runtime (the sandbox's stand-in) cannot tell: not a "not heard".
    main.heard = {**main.heard, "ros": False, "topics": []}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True)["teams"][0]
    assert picture["verdict"] == "no ROS runtime on team1-main: not verified"
    assert picture["verdict_level"] == "warn"
    assert [arrow["state"] for arrow in picture["arrows"]] == ["unknown"]
    assert [text["text"] for text in picture["texts"]] == ["topics seen: no ROS 2 runtime on the main host"]


# the command (subprocesses: it connects with pyinfra's gevent, as the CLI does) -----------------


def free_port() -> int:
    with socket.socket() as probe_socket:
        probe_socket.bind(("127.0.0.1", 0))
        return probe_socket.getsockname()[1]


def loopback_roster(tmp_path: Path, port: int) -> Path:
    roster = tmp_path / "classroom.yaml"
    roster.write_text(yaml.safe_dump({
        "classroom": {"name": HOSTILE, "ssh_user": "ubuntu", "ssh_port": port, "ubuntu_release": "24.04"},
        "teams": {
            "team1": {"ros_domain_id": 11, "hosts": {
                "team1-main": {"role": "main", "address": "127.0.0.1"},
                "team1-robot": {"role": "robot", "address": "127.0.0.2"}}},
            "team2": {"ros_domain_id": 12, "hosts": {"team2-main": {"role": "main", "address": "127.0.0.3"}}},
        },
    }, sort_keys=False))
    return roster


def roslab(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {key: value for key, value in os.environ.items() if key != "ROSLAB_ROSTER"}
    return subprocess.run([sys.executable, "-m", "roslab", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_unreachable_hosts_are_rows_that_say_so_and_the_page_lands_beside_the_roster(tmp_path):
    roster = loopback_roster(tmp_path, free_port())  # nothing listens there: refused at once
    started = time.monotonic()
    result = roslab("status", str(roster))
    assert time.monotonic() - started < 30
    assert result.returncode == 1, result.stderr
    table = result.stdout.splitlines()
    rows = [line for line in table if line.startswith("team")]
    assert [row.split()[1] for row in rows] == ["team1-main", "team1-robot", "team2-main"]
    assert all(row.split()[4] == "unreachable" for row in rows), table
    assert "3 of 3 hosts unreachable" in result.stderr
    page = tmp_path / ".roslab-state" / "status.html"
    assert f"page: {page}" in result.stdout
    text = page.read_text()
    assert "&lt;script&gt;" in text and "<script" not in text
    assert text.count("Could not connect") == 3


def test_limit_selects_hosts_as_pyinfra_does_and_html_goes_where_asked(tmp_path):
    roster = loopback_roster(tmp_path, free_port())
    page = tmp_path / "out" / "class.html"
    result = roslab("status", str(roster), "--limit", "team2", "--html", str(page))
    rows = [line for line in result.stdout.splitlines() if line.startswith("team")]
    assert [row.split()[1] for row in rows] == ["team2-main"]
    assert page.exists() and not (tmp_path / ".roslab-state" / "status.html").exists()
    assert roslab("status", str(roster), "--limit", "nosuchteam").returncode == 2


def test_a_host_that_accepts_but_never_answers_is_bounded(tmp_path):
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(8)
    accepted = []
    stop = threading.Event()

    def accept():  # take connections and say nothing: no SSH banner ever comes
        silent.settimeout(0.2)
        while not stop.is_set():
            try:
                accepted.append(silent.accept()[0])
            except OSError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        roster = loopback_roster(tmp_path, silent.getsockname()[1])
        started = time.monotonic()
        result = roslab("status", str(roster), "--limit", "team1-main", "--timeout", "3")
        elapsed = time.monotonic() - started
    finally:
        stop.set()
        thread.join()
        for connection in accepted:
            connection.close()
        silent.close()
    assert result.returncode == 1, result.stdout + result.stderr
    assert elapsed < 20, elapsed
    row = next(line for line in result.stdout.splitlines() if line.startswith("team1"))
    assert "unreachable" in row and "no answer within 3 s" in row, row


def test_a_refused_host_key_says_which_roslab_command_to_run():
    from roslab.ssh import identity

    target = identity.HostTarget("status-test-host", "classroom.yaml", ".roslab-state/known_hosts")
    identity.explainer().add_host(target, ["127.0.0.99"])
    message = status.explained("status-test-host", "SSH error (No host key for 127.0.0.99 found in known_hosts)")
    assert message.startswith("no SSH host key of status-test-host (127.0.0.99) is recorded in "
                              ".roslab-state/known_hosts"), message
    assert "`roslab trust classroom.yaml --limit status-test-host`" in message
    assert status.explained("other", "Could not connect (refused)") == "Could not connect (refused)"


def failed_run_host(name="team1-main") -> "status.HostStatus":
    """Reachable, its nodes running, but its last deploy.py run failed."""
    return reachable_host(name=name, run=RunRecord(NOW - timedelta(minutes=2), "failed", "Ensure ROS 2 jazzy",
                                                   "E: Unable to locate package x", NOW - timedelta(days=1)))


def test_a_failed_last_run_is_red_in_the_box_the_row_and_the_chips():
    hosts = [failed_run_host(), reachable_host(name="team1-robot", role="robot")]
    context = page_context("lab", "classroom.yaml", hosts, NOW)
    tags = Elements(render_page(context)).tags
    boxes = {attrs["data-host"]: attrs["data-level"] for tag, attrs in tags if tag == "g" and "data-host" in attrs}
    assert boxes == {"team1-main": "bad", "team1-robot": "ok"}
    cells = host_cells(hosts[0], NOW)
    assert cells["LAST RUN"].level == "bad" and cells["LAST RUN"].text.startswith("failed ")
    assert cells["NOTE"].level == "bad"
    assert 'last run failed in "Ensure ROS 2 jazzy": E: Unable to locate package x' in cells["NOTE"].text
    chips = {count["text"]: count["level"] for count in context["counts"]}
    assert chips["1 failed in their last run"] == "bad"
    assert chips["2 reachable"] == "ok"


def test_status_exits_1_when_a_host_failed_its_last_run_or_is_unreachable():
    assert status.status_problems([reachable_host()]) == []
    assert status.status_problems([failed_run_host(), reachable_host(name="team1-robot")]) == [
        "1 of 2 hosts failed in their last run: team1-main"]
    assert status.status_problems([unreachable_host(), reachable_host()]) == [
        "1 of 2 hosts unreachable: team1-robot", "1 of 2 hosts failed in their last run: team1-robot"]


def test_status_shows_each_hosts_discovery_mode_and_an_auto_domain(tmp_path):
    from fixtures.status_hosts import reachable_host

    from roslab.cli.status import host_cells, page_context

    host = reachable_host(discovery_mode="static", middleware="rmw_fastrtps_cpp", domain_assigned=True)
    cells = host_cells(host, NOW)
    assert cells["DISCOVERY"].text == "static"
    team = page_context("lab", "lab.yaml", [host], NOW)["teams"][0]
    assert team["discovery"] == "static, rmw_fastrtps_cpp" and team["domain"].endswith(" auto")


def test_status_flags_nodes_running_another_middleware_than_the_roster_says():
    from fixtures.status_hosts import reachable_host

    from roslab.cli.status import host_cells

    host = reachable_host(discovery_mode="multicast", middleware="rmw_cyclonedds_cpp")
    host.probe["unit"]["Environment"] = "ROS_DOMAIN_ID=11 RMW_IMPLEMENTATION=rmw_fastrtps_cpp"
    cells = host_cells(host, NOW)
    assert (cells["DISCOVERY"].text, cells["DISCOVERY"].level) == ("multicast (rmw_fastrtps_cpp)", "bad")
    assert "its nodes run rmw_fastrtps_cpp, the roster says rmw_cyclonedds_cpp" in cells["NOTE"].text


# judged by what each host's profile runs (roslab.cli.host_services) ---------------------------

from roslab.cli.host_services import HostService  # noqa: E402

NOT_FOUND = {"LoadState": "not-found", "ActiveState": "inactive", "SubState": "dead"}
DISCOVERY_SERVER = HostService("roslab-discovery-server.service", "the team's Fast DDS discovery server", "discovery")


def turtlebot3_team() -> list:
    main = reachable_host(name="blue-main", team="blue", profile="turtlebot3", runs_nodes=False)
    main.probe = {**main.probe, "unit": dict(NOT_FOUND)}
    robot = reachable_host(name="blue-robot", role="robot", team="blue", profile="turtlebot3")
    return [main, robot]


def test_a_main_whose_profile_runs_no_nodes_is_green_not_not_installed():
    hosts = turtlebot3_team()
    cells = host_cells(hosts[0], NOW)
    assert (cells["NODES"].text, cells["NODES"].level) == ("none (turtlebot3 main)", "ok")
    assert "not installed" not in format_table(hosts, NOW)
    context = page_context("lab", "x", hosts, NOW)
    picture = context["teams"][0]
    assert (picture["verdict"], picture["verdict_level"]) == ("2 of 2 hosts run their services", "ok")
    assert [box["level"] for box in picture["boxes"]] == ["ok", "ok"]
    assert context["counts"][2] == {"text": "2 running their services", "level": "ok"}
    # Listening: the robot heard on /scan passes the team; no "not installed" line over it.
    hosts[0].heard = {"ros": True, "topics": ["/scan"], "message": "header: {}", "robot": None,
                      "echo_status": 0, "daemon_stopped": False, "finished": True}
    picture = page_context("lab", "x", hosts, NOW, listen=True, topics={"blue": "/scan"},
                           message_types={"blue": "sensor_msgs/msg/LaserScan"})["teams"][0]
    assert picture["verdict_level"] == "ok" and "not installed" not in picture["verdict"]


def test_a_sim_team_has_nothing_to_hear_and_is_amber_not_checked():
    sim = reachable_host(name="sim1-main", team="sim1", profile="sim", runs_nodes=False, listens=False)
    sim.probe = {**sim.probe, "unit": dict(NOT_FOUND)}
    for listen in (False, True):
        picture = page_context("lab", "x", [sim], NOW, listen=listen)["teams"][0]
        assert picture["verdict_level"] == "warn", picture["verdict"]
        assert picture["verdict"].startswith(
            "not checked, nothing to hear: robot profile sim names no robot on sim1-main")
        assert picture["texts"][0]["text"] == "topics seen: not checked (sim: no topic)"


def test_an_uncalibrated_rovers_robot_is_amber_and_says_what_starts_it():
    why = "osr_calibrated is false (it runs when osr_calibrated: true)"
    robot = reachable_host(name="rover-robot", team="rover", profile="osr", runs_nodes=False,
                           not_started=[("osr_startup", why)])
    robot.probe = {**robot.probe, "unit": dict(NOT_FOUND)}
    box = status.host_box(robot, 0, 0)
    assert box["level"] == "warn"
    assert box["lines"][3]["text"] == "not started: osr_calibrated"
    assert box["title"].endswith("; osr_startup not started: " + why)
    # the table's NODES cell and the page's chip agree with the amber box (the trial saw both green)
    assert status.nodes_cell(robot, True) == status.Cell("none: osr_startup not started", "warn")
    main = reachable_host(name="rover-main", team="rover", profile="osr", runs_nodes=False)
    main.probe = {**main.probe, "unit": dict(NOT_FOUND)}
    chip = page_context("lab", "x", [main, robot], NOW)["counts"][2]
    assert chip == {"text": "1 running their services", "level": "warn"}


def test_a_stopped_discovery_server_is_named_in_the_row_and_the_team():
    main, robot = reachable_host(discovery_mode="discovery_server"), reachable_host(name="team1-robot", role="robot")
    main.other_services = [DISCOVERY_SERVER]
    main.probe = {**main.probe, "units": {DISCOVERY_SERVER.unit: {"LoadState": "loaded", "ActiveState": "inactive",
                                                                   "SubState": "dead"}}}
    note = host_cells(main, NOW)["NOTE"]
    assert note.level == "warn" and note.text == (
        "roslab-discovery-server.service on team1-main is inactive (dead) (the team's Fast DDS discovery server: "
        "without it the team's hosts do not find each other)")
    picture = page_context("lab", "x", [main, robot], NOW)["teams"][0]
    assert picture["verdict_level"] == "bad" and "roslab-discovery-server.service on team1-main" in picture["verdict"]
    main.heard = {"ros": True, "topics": [], "message": None, "robot": None, "echo_status": 124,
                  "daemon_stopped": False, "finished": True}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True)["teams"][0]
    assert picture["verdict"].startswith("roslab-discovery-server.service on team1-main is inactive (dead)")
    main.probe["units"][DISCOVERY_SERVER.unit] = {"LoadState": "loaded", "ActiveState": "active",
                                                  "SubState": "running"}
    assert host_cells(main, NOW)["NOTE"].text == ""


def test_the_probe_reads_each_other_service_in_its_own_section():
    script = status.probe_script(others=("roslab-discovery-server.service",))
    assert "systemctl show --property=LoadState,ActiveState,SubState,Result roslab-discovery-server.service" in script
    lines = [line for line in PROBE_OUTPUT if line != "## end"] + [
        "## unit roslab-discovery-server.service", "LoadState=loaded", "ActiveState=failed", "SubState=failed",
        "Result=exit-code", "## end"]
    probe = parse_probe(lines)
    assert probe["unit"]["SubState"] == "running"  # the nodes' own section is untouched
    assert probe["units"] == {"roslab-discovery-server.service": {
        "LoadState": "loaded", "ActiveState": "failed", "SubState": "failed", "Result": "exit-code"}}
    output = subprocess.run(["sh", "-c", script], capture_output=True, text=True, timeout=30)
    assert "roslab-discovery-server.service" in parse_probe(output.stdout.splitlines())["units"]


def test_listen_waits_as_long_as_verify_and_says_how_long_it_waited():
    assert status.build_parser().parse_args([]).listen_timeout is None  # the roster's nodes_verify_timeout
    assert status.LISTEN_TIMEOUT >= 20
    main, robot = reachable_host(listen_timeout=20), reachable_host(name="team1-robot", role="robot")
    main.heard = {"ros": True, "topics": ["/chatter"], "message": None, "robot": None, "echo_status": 124,
                  "daemon_stopped": False, "finished": True}
    picture = page_context("lab", "x", [main, robot], NOW, listen=True)["teams"][0]
    assert picture["verdict"] == "/chatter listed but no message within 20 s"
    picture = page_context("lab", "x", [main, robot], NOW, listen=True, listen_timeout=7)["teams"][0]
    assert picture["verdict"] == "/chatter listed but no message within 7 s"


def test_status_reads_what_each_host_runs_from_the_roster(tmp_path):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(yaml.safe_dump({
        "classroom": {"ssh_user": "ubuntu", "ubuntu_release": "24.04", "nodes_verify_timeout": 35},
        "teams": {
            "team1": {"ros_discovery_mode": "discovery_server", "hosts": {
                "team1-main": {"role": "main", "address": "127.0.0.1"},
                "team1-robot": {"role": "robot", "address": "127.0.0.2"}}},
        },
    }, sort_keys=False))
    from roslab.roster import inventory_groups, load_roster

    classroom = load_roster(roster)
    statuses = {s.name: s for s in status.host_statuses(classroom, inventory_groups(classroom))}
    assert [s.unit for s in statuses["team1-main"].other_services] == ["roslab-discovery-server.service"]
    assert statuses["team1-robot"].other_services == [] and statuses["team1-robot"].runs_nodes
    assert statuses["team1-main"].listen_timeout == 35


OSR_STARTUP = HostService("osr_startup.service", "robot profile osr's osr_startup", "profile", launch=True)
RUNNING = {"LoadState": "loaded", "ActiveState": "active", "SubState": "running"}


def test_a_running_launch_whose_nodes_die_is_one_line_per_node_with_its_reason():
    """The rover's osr_startup runs (systemd sees the launch), while its nodes die and start
    again: the note names each, as its journal does (a sandbox rover's, real osr-rover-code)."""
    journal = (Path(__file__).parent / "fixtures/journals/osr_launch_journal.txt").read_text().splitlines()
    rover = reachable_host(name="rover-robot", role="robot", team="rover", profile="osr", runs_nodes=False)
    rover.other_services = [OSR_STARTUP]
    rover.probe = {**rover.probe, "units": {OSR_STARTUP.unit: dict(RUNNING)},
                   "journals": {OSR_STARTUP.unit: journal}}
    note = host_cells(rover, NOW)["NOTE"]
    assert note.level == "warn"
    assert note.text.split("; ") == [
        "osr_startup: roboclaw_wrapper died once in the last minute: Exception: Unable to connect to serial port /dev/serial1.",
        "osr_startup: rover died 2 times in the last minute: ModuleNotFoundError: No module named 'tf2_ros'",
        "osr_startup: servo_control died 2 times in the last minute: ImportError: cannot import name 'ServoKit' from "
        "'adafruit_servokit' (/home/ubuntu/osr_venv/lib/python3.11/site-packages/adafruit_servokit.py)"]
    # a launch whose nodes all run says nothing; a stopped one is named as stopped, not by its journal
    rover.probe["journals"][OSR_STARTUP.unit] = ["[INFO] [rover-3]: process started with pid [7]"]
    assert host_cells(rover, NOW)["NOTE"].text == ""


def test_the_probe_reads_a_launch_services_journal_bounded_and_in_its_own_section():
    script = status.probe_script(others=(OSR_STARTUP.unit,), launches=(OSR_STARTUP.unit,))
    assert "echo '## journal osr_startup.service'; journalctl -u osr_startup.service --since=-60s --no-pager" in script
    probe = parse_probe([line for line in PROBE_OUTPUT if line != "## end"] + [
        "## journal osr_startup.service", "[ERROR] [rover-3]: process has died [pid 1, exit code 1, cmd 'x'].",
        "## end"])
    assert probe["journals"] == {OSR_STARTUP.unit: ["[ERROR] [rover-3]: process has died [pid 1, exit code 1, "
                                                    "cmd 'x']."]}
    assert subprocess.run(["sh", "-c", script], capture_output=True, text=True, timeout=30).returncode == 0


def test_the_rovers_service_is_known_to_run_a_launch():
    from roslab.cli.host_services import host_services as services_of

    from dataclasses import replace

    from roslab.host_settings import settings_of
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import ResolvedService, resolve_host

    osr = builtin_profiles()["osr"]
    resolved, problems = resolve_host(osr, {"osr_calibrated": "true"}, distro=osr.distros[0], role="robot")
    assert problems == []
    typed = settings_of("osr-robot", {"roslab_role": "robot", "roslab_profile": resolved, "discovery_enabled": False})
    services = [ResolvedService("osr_startup", "", "ros2 launch osr_bringup osr_launch.py", {}, True, ""),
                ResolvedService("micro_ros_agent", "", "ros2 run micro_ros_agent micro_ros_agent udp4 --port 8888",
                                {}, True, "")]
    typed = replace(typed, roslab_profile=replace(typed.roslab_profile, services=services))
    launches = {service.unit: service.launch for service in services_of(typed) if service.kind == "profile"}
    assert launches == {"osr_startup.service": True, "micro_ros_agent.service": False}
