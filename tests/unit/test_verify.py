"""roslab verify: what the main host's check finds, that it is bounded and leaves no daemon,
that the robot is read from the message itself, and the table a teacher reads."""

from __future__ import annotations

from dataclasses import replace

import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from roslab.cli import verify
from roslab.host_settings import settings_of
from roslab.ros.workspace import NodesUnitState

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "nodes" / "roslab_demo"))

from roslab_demo import logic  # noqa: E402  (importable only once the path is set)

ENV = {"ROS_DOMAIN_ID": "11", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}


def stand_in_ros(tmp_path: Path, ros2_body: str | None) -> Path:
    """A home with a stand-in distro whose `ros2` does what `ros2_body` says."""
    home = tmp_path / "home"
    home.mkdir()
    setup = tmp_path / "setup.bash"
    setup.write_text(f"export PATH={tmp_path / 'bin'}:/usr/bin:/bin\n")
    if ros2_body is not None:
        (tmp_path / "bin").mkdir()
        ros2 = tmp_path / "bin" / "ros2"
        ros2.write_text(f"#!/bin/bash\necho \"$*\" >> {tmp_path}/calls\n{ros2_body}\n")
        ros2.chmod(0o755)
    return home


def run_check(tmp_path, ros2_body: str | None, timeout: int = 2, kill_after: int = 1,
              whole: bool = False) -> dict:
    """Run the check as the fact would (`whole`: the fact's command, with its outer bound)."""
    home = stand_in_ros(tmp_path, ros2_body)
    if whole:
        script = verify.NodesHeard().command("jazzy", ENV, "~/ros2_ws", "/chatter", timeout, kill_after)
    else:
        script = verify.check_script("jazzy", ENV, "~/ros2_ws", "/chatter", timeout, kill_after)
    script = script.replace("/opt/ros/jazzy/setup.bash", str(tmp_path / "setup.bash"))
    result = subprocess.run(["bash", "-c", script], capture_output=True, text=True,
                            env={"HOME": str(home)}, timeout=120)
    assert result.returncode == 0  # a fact command must not fail; the result says what happened
    return verify.parse_check_output(result.stdout.splitlines())


def calls(tmp_path) -> list[str]:
    path = tmp_path / "calls"
    return path.read_text().splitlines() if path.exists() else []


# A ros2 that answers like a real one on domain 11, with the demo talker's greeting. If a
# call could use the daemon (no --no-daemon), it "starts" one, as the real ros2 would.
FAKE_ROS2 = """
daemon=$(dirname "$0")/../daemon-running
case " $* " in *" --no-daemon "*) ;; *" topic "*) touch "$daemon" ;; esac
case "$1 $2" in
  "topic list") printf '/chatter\\n/parameter_events\\n/robot_status\\n/rosout\\n' ;;
  "topic echo") [ "$ROS_DOMAIN_ID" = 11 ] && printf '%s\\n---\\n' "$GREETING" ;;
  "daemon status") if [ -e "$daemon" ]; then echo 'The daemon is running'; else echo 'The daemon is not running'; fi ;;
  "daemon stop") rm -f "$daemon"; echo 'The daemon has been stopped' ;;
esac
"""


def with_greeting(text: str) -> str:
    return f"GREETING={shlex.quote(text)}\n{FAKE_ROS2}"


def test_the_main_host_hears_the_robot_on_the_teams_domain(tmp_path):
    heard = run_check(tmp_path, with_greeting(logic.chatter_text("team1-robot", 7)))
    assert heard["ros"] is True and heard["finished"] is False  # (no outer wrapper here)
    assert heard["topics"] == ["/chatter", "/parameter_events", "/robot_status", "/rosout"]
    assert heard["message"] == "Hello from team1-robot #7"
    assert heard["robot"] == "team1-robot"
    assert heard["echo_status"] == 0


def test_the_check_asks_without_the_daemon_for_one_typed_message_as_the_text(tmp_path):
    run_check(tmp_path, with_greeting("Hello from r #1"))
    (echo,) = [call for call in calls(tmp_path) if call.startswith("topic echo")]
    assert echo == "topic echo --no-daemon --once --field data --full-length /chatter std_msgs/msg/String"
    (listing,) = [call for call in calls(tmp_path) if call.startswith("topic list")]
    assert "--no-daemon" in listing
    assert not (tmp_path / "daemon-running").exists()


def test_a_daemon_the_check_started_is_stopped_and_one_already_running_is_left(tmp_path):
    # A ros2 that ignores --no-daemon: the check notices the daemon it left and stops it.
    leaky = FAKE_ROS2.replace('case " $* " in *" --no-daemon "*) ;; *" topic "*)', 'case " $* " in *" topic "*)')
    heard = run_check(tmp_path, with_greeting("Hello from r #1") + leaky)
    assert heard["daemon_stopped"] is True
    assert not (tmp_path / "daemon-running").exists()

    # A daemon the student runs already is theirs: not stopped.
    other = tmp_path / "other"
    other.mkdir()
    (other / "daemon-running").touch()
    heard = run_check(other, with_greeting("Hello from r #1"))
    assert heard["daemon_stopped"] is False and (other / "daemon-running").exists()


def test_no_ros2_command_is_reported_as_no_ros_runtime(tmp_path):
    heard = run_check(tmp_path, None)
    assert heard["ros"] is False and heard["topics"] == [] and heard["message"] is None


def test_the_workspace_is_sourced_from_the_users_home(tmp_path):
    home = stand_in_ros(tmp_path, with_greeting("Hello from r #1"))
    setup = home / "ros2_ws" / "install" / "setup.bash"
    setup.parent.mkdir(parents=True)
    setup.write_text(f"touch {tmp_path}/workspace-sourced\n")
    script = verify.check_script("jazzy", ENV, "~/ros2_ws", "/chatter", 2, 1)
    script = script.replace("/opt/ros/jazzy/setup.bash", str(tmp_path / "setup.bash"))
    subprocess.run(["bash", "-c", script], env={"HOME": str(home)}, check=True, capture_output=True)
    assert (tmp_path / "workspace-sourced").exists()


def test_a_silent_topic_times_out_instead_of_hanging(tmp_path):
    started = time.monotonic()
    heard = run_check(tmp_path, 'case "$2" in list) echo /chatter ;; echo) sleep 30 ;; esac')
    assert time.monotonic() - started < 10
    assert heard["ros"] is True and heard["topics"] == ["/chatter"] and heard["message"] is None
    assert heard["echo_status"] == 124


def test_an_echo_that_ignores_sigterm_is_killed(tmp_path):
    """The hang seen in class: `timeout N ros2 topic echo` sent one SIGTERM and waited >10 min."""
    started = time.monotonic()
    heard = run_check(tmp_path, "trap '' TERM\ncase \"$2\" in echo) sleep 60 ; sleep 60 ;; esac",
                      timeout=1, kill_after=1)
    assert time.monotonic() - started < 15
    assert heard["echo_status"] == 137  # timeout's status after SIGKILL
    assert heard["message"] is None


def test_the_whole_check_has_one_more_bound(tmp_path, monkeypatch):
    # Even a step outside the ros2 calls (here: a setup.bash that hangs) cannot hang the fact.
    monkeypatch.setattr(verify, "check_bound", lambda timeout, kill_after=1: 2)
    home = stand_in_ros(tmp_path, with_greeting("Hello from r #1"))
    (tmp_path / "setup.bash").write_text("trap '' TERM; sleep 60; sleep 60\n")
    command = verify.NodesHeard().command("jazzy", ENV, "~/ros2_ws", "/chatter", 2, 1)
    command = command.replace("/opt/ros/jazzy/setup.bash", str(tmp_path / "setup.bash"))
    started = time.monotonic()
    result = subprocess.run(["bash", "-c", command], capture_output=True, text=True,
                            env={"HOME": str(home), "PATH": "/usr/bin:/bin"}, timeout=60)
    assert time.monotonic() - started < 10
    heard = verify.parse_check_output(result.stdout.splitlines())
    assert heard["finished"] is False and heard["message"] is None
    assert "## exit 137" in result.stdout


def test_a_check_that_finishes_says_so(tmp_path):
    heard = run_check(tmp_path, with_greeting("Hello from r #1"), whole=True)
    assert heard["finished"] is True and heard["robot"] == "r"


def test_the_outer_bound_covers_every_step():
    bound = verify.check_bound(20, 5)
    steps = verify.LIST_TIMEOUT + 20 + 3 * verify.DAEMON_TIMEOUT
    assert bound > steps + 5 * 5
    assert bound < 10 * 60  # the >10 min hang this replaces
    assert verify.NodesHeard().command("jazzy", ENV, "~/ros2_ws", "/chatter", 20).startswith(
        f"timeout --kill-after=5 {bound} bash -c ")


# The robot's name, read from the message itself
# -----------------------------------------------


@pytest.mark.parametrize(
    "robot_name",
    ["team1-robot", "r", "my robot", "rover #2", "Hello from x #1", "robôt-ü", "two\nlines"],
)
@pytest.mark.parametrize("count", [1, 7, 10**9])
def test_verify_reads_the_robot_back_from_what_the_talker_says(robot_name, count):
    text = logic.chatter_text(robot_name, count)
    assert verify.robot_name_from_chatter(text) == robot_name
    assert verify.robot_name_from_chatter(text) == logic.robot_name_from_chatter(text)


@pytest.mark.parametrize(
    "text",
    ["", "hello world", "Hello from team1-robot", "Hello from  #7"[:-1], "Hello from team1-robot #",
     "Hello from team1-robot #7a", "data: Hello from team1-robot #7",
     "[INFO] [talker]: Hello from team1-robot #7"],
)
def test_anything_else_is_not_a_greeting(text):
    assert verify.robot_name_from_chatter(text) is None
    assert logic.robot_name_from_chatter(text) is None


@pytest.mark.parametrize("robot_name", ["team1-robot", "two\nlines", "rover #2"])
def test_the_check_reads_the_robot_from_the_echoed_text(tmp_path, robot_name):
    heard = run_check(tmp_path, with_greeting(logic.chatter_text(robot_name, 3)))
    assert heard["robot"] == robot_name


def test_notes_ros2_prints_before_the_message_are_not_part_of_it():
    lines = ["## message", "Some, but not all, publishers are offering QoSReliabilityPolicy.RELIABLE.",
             "Hello from team1-robot #12", "---", "## echo status 0"]
    heard = verify.parse_check_output(lines)
    assert heard["robot"] == "team1-robot" and heard["message"] == "Hello from team1-robot #12"


def test_a_message_that_is_not_a_greeting_names_no_robot():
    heard = verify.parse_check_output(["## topics", "/chatter", "## message", "hello world", "---"])
    assert heard["robot"] is None and heard["message"] == "hello world"


# The verdict and the table
# -------------------------


def heard(robot=None, ros=True, topics=("/chatter",), message=None, finished=True):
    message = message if message is not None else (logic.chatter_text(robot, 4) if robot else None)
    return {"ros": ros, "topics": list(topics), "message": message, "robot": robot,
            "echo_status": 0 if message else 124, "daemon_stopped": False, "finished": finished}


def result(team="team1", heard=None, robots=None, **kwargs):
    robots = [f"{team}-robot"] if robots is None else robots
    return verify.TeamResult(
        team, main=f"{team}-main", robots=robots, heard=heard,
        services={f"{team}-main": "active (running)", **{r: "active (running)" for r in robots}},
        **kwargs,
    )


def test_table_has_a_row_per_team_and_says_what_failed():
    results = [
        result("team2", heard=heard(ros=False, topics=())),
        result("team1", heard=heard("team1-robot", topics=("/chatter", "/rosout"))),
        result("team3", heard=heard(topics=("/rosout",))),
        result("team4", heard=heard()),
        result("team5", heard=heard("team1-robot")),
        result("team6", heard=heard(message="hello world")),
        result("team7", heard=heard(topics=(), finished=False)),
    ]
    table = verify.format_table(results).splitlines()
    assert table[0].split()[:3] == ["team", "main", "robot"]
    rows = {line.split()[0]: line for line in table[2:]}
    assert "PASS heard team1-robot" in rows["team1"]
    assert "Hello from team1-robot #4" in rows["team1"]
    assert "/rosout" not in rows["team1"]  # ROS's own topics are noise here
    assert "FAIL no ROS runtime on team2-main: not verified" in rows["team2"]
    assert "FAIL team3-main does not see /chatter" in rows["team3"]
    assert "FAIL /chatter listed but no message within 20 s" in rows["team4"]
    # A greeting, but from another team's robot: two teams share a domain.
    assert "FAIL heard 'team1-robot', which is not a robot of team team5 (team5-robot)" in rows["team5"]
    assert "FAIL /chatter carries a message that is not a robot's greeting" in rows["team6"]
    assert "FAIL the check on team7-main did not finish in time" in rows["team7"]
    assert [r.passed for r in results] == [False, True, False, False, False, False, False]


def test_any_of_a_teams_robots_passes_it():
    two = result("team1", heard=heard("team1-robot2"), robots=["team1-robot1", "team1-robot2"])
    assert two.passed and "team1-robot1, team1-robot2" in verify.format_table([two])


def test_a_team_without_a_robot_is_not_verified():
    alone = result("team1", heard=heard(), robots=[])
    assert not alone.passed and "no robot in the team" in alone.verdict()


def test_a_main_whose_profile_runs_no_launch_needs_no_service_but_a_robot_does():
    # A TurtleBot3 team: the bringup runs on the robot, nothing on the main (roslab.profiles).
    team = result("tb3", heard=heard("tb3-robot"), without_service={"tb3-main"})
    team.services["tb3-main"] = "not installed"
    assert team.passed and team.services_down() == []
    team.services["tb3-robot"] = "not installed"  # the robot's bringup is always required
    assert not team.passed and team.services_down() == [("tb3-robot", "not installed")]
    demo = result("team1", heard=heard("team1-robot"))
    demo.services["team1-main"] = "not installed"
    assert not demo.passed
    assert verify.runs_a_launch(main_settings("turtlebot3", {"turtlebot3_model": "burger"})) is False
    assert verify.runs_a_launch(main_settings("demo", {}, nodes_launch="roslab_bringup main.launch.py")) is True
    assert verify.runs_a_launch(settings_of("pi", {"roslab_role": "main"})) is True  # a hand-made inventory: the demo's


def main_settings(profile: str, given: dict, **values):
    """A main host's typed settings with the built-in `profile` resolved for its side."""
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    chosen = builtin_profiles()[profile]
    resolved, problems = resolve_host(chosen, given, distro=chosen.distros[0], role="main")
    assert problems == [], problems
    return settings_of("pi", {"roslab_role": "main", "roslab_profile": resolved, **values})


def test_an_unreachable_host_fails_its_team():
    failed = result("team5", heard=None, error="team5-robot is unreachable")
    assert not failed.passed
    assert "FAIL team5-robot is unreachable" in verify.format_table([failed])


@pytest.mark.parametrize(
    ("state", "cell"),
    [
        ({"LoadState": "loaded", "ActiveState": "active", "SubState": "running"}, "active (running)"),
        ({"LoadState": "loaded", "ActiveState": "failed", "SubState": "failed", "Result": "start-limit-hit"},
         "failed (start-limit-hit)"),
        ({"LoadState": "loaded", "ActiveState": "activating", "SubState": "auto-restart"},
         "activating (auto-restart)"),
        ({"LoadState": "not-found", "ActiveState": "inactive", "SubState": "dead"}, "not installed"),
        ({}, "not installed"),
    ],
)
def test_service_cells_say_what_systemd_says(state, cell):
    assert verify.service_state(state) == cell


def test_verify_reads_the_unit_with_the_workspace_deploys_fact():
    assert verify.NodesUnitState is NodesUnitState


def test_nothing_in_roslab_imports_the_deploys():
    roslab = Path(__file__).resolve().parents[2] / "roslab"
    offenders = [
        str(path.relative_to(roslab)) for path in roslab.rglob("*.py")
        if (roslab / "data") not in path.parents  # the deploy roslab ships (roslab.packaged), not its code
        and any(line.startswith(("from deploy", "import deploy"))
               for line in path.read_text().splitlines())
    ]
    assert offenders == []


def test_a_ros2_that_cannot_even_answer_help_is_no_ros_runtime(tmp_path):
    # Like the sandbox's stand-in ros2: every command but `launch` exits 127.
    heard = run_check(tmp_path, 'echo "stand-in: no ROS runtime" >&2\nexit 127\n')
    assert heard["ros"] is False


@pytest.mark.parametrize("host", ["team1-robot", "team1-main"])
@pytest.mark.parametrize("state", ["inactive (dead)", "activating (auto-restart)", "failed (start-limit-hit)",
                                   "not installed", "?"])
def test_a_message_heard_beside_a_service_that_does_not_run_is_no_pass(host, state):
    # Right after a reboot the main can hear the robot while a service is still starting
    # (or has just failed): verified only once every service of the team really runs.
    team = result("team1", heard=heard("team1-robot"))
    team.services[host] = state
    assert not team.passed
    assert team.verdict() == f"roslab-nodes.service on {host} is {state}"
    row = verify.format_table([team]).splitlines()[2]
    assert f"FAIL roslab-nodes.service on {host} is {state}" in row and "PASS" not in row


# A topic whose messages name no robot (a TurtleBot3's /scan)
# ------------------------------------------------------------

SCAN = "sensor_msgs/msg/LaserScan"


def test_another_message_type_is_asked_for_by_its_type_and_echoed_whole(tmp_path):
    home = stand_in_ros(tmp_path, "case \"$1 $2\" in \"topic echo\") printf 'header:\\n  frame_id: base_scan\\n"
                                  "angle_min: 0.0\\n---\\n' ;; esac")
    script = verify.check_script("jazzy", ENV, "~/ros2_ws", "/scan", 2, 1, SCAN)
    script = script.replace("/opt/ros/jazzy/setup.bash", str(tmp_path / "setup.bash"))
    output = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env={"HOME": str(home)},
                            timeout=120).stdout
    (echo,) = [call for call in calls(tmp_path) if call.startswith("topic echo")]
    assert echo == f"topic echo --no-daemon --once --full-length /scan {SCAN}"
    heard_scan = verify.parse_check_output(output.splitlines())
    assert heard_scan["message"] == "header:\n  frame_id: base_scan\nangle_min: 0.0"
    assert heard_scan["robot"] is None


def test_any_message_of_the_type_passes_a_team_whose_topic_names_no_robot():
    scan = result("team1", heard=heard(topics=("/scan",), message="header:\n  frame_id: base_scan"),
                  topic="/scan", message_type=SCAN)
    assert scan.passed and scan.heard_robots() == ["team1-robot"]
    assert scan.verdict() == f"heard a {SCAN} on /scan"
    silent = result("team2", heard=heard(topics=("/scan",)), topic="/scan", message_type=SCAN)
    assert not silent.passed and silent.verdict() == "/scan listed but no message within 20 s"
    stopped = result("team3", heard=heard(message="header: {}"), topic="/scan", message_type=SCAN)
    stopped.services["team3-robot"] = "failed (exit-code)"
    assert not stopped.passed and "roslab-nodes.service on team3-robot is failed" in stopped.verdict()


# Judged by what the profile runs (roslab.cli.host_services)
# ------------------------------------------------------

from test_profiles import _in_tmp, rosdistro_url, write  # noqa: E402,F401  (fixtures)

from roslab.cli.host_services import HostService, host_services  # noqa: E402
from roslab.roster import load_roster  # noqa: E402

DISCOVERY_SERVER = HostService("roslab-discovery-server.service", "the team's Fast DDS discovery server", "discovery")


def turtlebot3_and_sim_class(tmp_path, url, classroom_extra="", demo_discovery="discovery_server"):
    return load_roster(write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {url}
          rosdep_cache_dir: cache
          {classroom_extra}
        teams:
          blue:
            ubuntu_release: "24.04"
            robot_profile: turtlebot3
            turtlebot3_model: burger
            lds_model: LDS-03
            hosts:
              blue-main: {{role: main}}
              blue-robot: {{role: robot}}
          sim1:
            ubuntu_release: "24.04"
            robot_profile: sim
            hosts:
              sim1-main: {{role: main}}
          demo:
            ubuntu_release: "24.04"
            ros_discovery_mode: {demo_discovery}
            hosts:
              demo-main: {{role: main}}
              demo-robot: {{role: robot}}
        """))


def test_each_host_runs_the_services_its_profile_and_discovery_give_it(tmp_path, rosdistro_url):
    classroom = turtlebot3_and_sim_class(tmp_path, rosdistro_url)
    units = {host.name: [service.unit for service in host_services(host.settings)] for host in classroom.hosts}
    assert units == {
        "blue-main": [],  # a TurtleBot3's main runs nothing: teleop and RViz are the students'
        "blue-robot": ["roslab-nodes.service"],
        "sim1-main": [],  # the simulation is started by hand from the desktop
        "demo-main": ["roslab-discovery-server.service", "roslab-nodes.service"],
        "demo-robot": ["roslab-nodes.service"],
    }


def test_a_zenoh_main_runs_the_router_and_a_switched_off_deploy_runs_nothing(tmp_path, rosdistro_url):
    classroom = turtlebot3_and_sim_class(tmp_path, rosdistro_url, "ros_middleware: rmw_zenoh_cpp", "static")
    units = {host.name: [service.unit for service in host_services(host.settings)] for host in classroom.hosts}
    assert units["blue-main"] == ["roslab-zenoh-router.service"]
    assert units["sim1-main"] == ["roslab-zenoh-router.service"]  # its own router, on the loopback
    assert units["blue-robot"] == ["roslab-nodes.service"]
    main = next(host.settings for host in classroom.hosts if host.name == "blue-main")
    assert host_services(replace(main, discovery_enabled=False)) == []
    robot = next(host.settings for host in classroom.hosts if host.name == "blue-robot")
    assert [s.unit for s in host_services(replace(robot, nodes_service_enabled=False))] == []


def test_a_sim_team_has_no_robot_to_hear_and_is_not_checked_rather_than_passed():
    sim = verify.TeamResult("sim1", main="sim1-main", robots=[], services={"sim1-main": "not installed"},
                            without_service={"sim1-main"}, listens=False, profile="sim")
    assert not sim.passed and sim.unchecked and sim.outcome == "NOT CHECKED"
    assert sim.verdict() == ("not checked, nothing to hear: robot profile sim names no robot on sim1-main; "
                             "roslab runs no service there")
    row = verify.format_table([sim]).splitlines()[2]
    assert "NOT CHECKED not checked, nothing to hear" in row and "PASS" not in row
    assert row.split()[2:5] == ["-", "none", "(sim"] and "not installed" not in row
    # Its services still count: a sim main on Zenoh runs its own router.
    router = HostService("roslab-zenoh-router.service", "the team's Zenoh router", "discovery")
    sim.other_services = [("sim1-main", router, "failed (exit-code)")]
    assert sim.outcome == "FAIL"
    assert sim.verdict().startswith("roslab-zenoh-router.service on sim1-main is failed (exit-code)")


def test_an_uncalibrated_rover_is_not_checked_and_says_what_starts_it(capsys):
    rover = verify.TeamResult("rover", main="rover-main", robots=["rover-robot"],
                              services={"rover-main": "not installed", "rover-robot": "not installed"},
                              without_service={"rover-main", "rover-robot"}, listens=False, profile="osr",
                              not_started=[("rover-robot", "osr_startup",
                                            "osr_calibrated is false (it runs when osr_calibrated: true)")])
    assert rover.outcome == "NOT CHECKED"
    assert "osr_startup on rover-robot not started: osr_calibrated is false" in rover.verdict()
    team1 = result("team1", heard=heard("team1-robot"))
    assert team1.outcome == "PASS"
    # The summary and exit code count only the team really heard.
    assert verify.summarize([rover, team1]) == 3
    out, err = capsys.readouterr()
    assert "1 of 2 teams verified" in out and "not checked (nothing to hear, see the table): rover" in err
    assert "every team" not in out
    assert verify.summarize([team1]) == 0
    silent = result("team2", heard=heard(topics=()))
    assert verify.summarize([rover, team1, silent]) == 1
    # In a terminal the word has its colour: yellow for not checked.
    table = verify.format_table([rover, team1], colour=True)
    assert "\033[33mNOT CHECKED\033[0m" in table and "\033[32mPASS\033[0m" in table


def test_a_main_without_a_nodes_service_passes_whatever_is_left_of_an_old_unit():
    # A main that once ran the demo and is now a TurtleBot3's: the deploy stopped and disabled the unit.
    team = result("tb3", heard=heard(topics=("/scan",), message="header: {}"), topic="/scan",
                  message_type=SCAN, without_service={"tb3-main"})
    team.services["tb3-main"] = "inactive (dead)"
    assert team.passed
    row = verify.format_table([team]).splitlines()[2]
    assert row.split()[3:6] == ["none", "(demo", "main)"] and "inactive" not in row, row
    team.services["tb3-main"] = "?"  # not reached: nothing to say it runs none
    assert verify.format_table([team]).splitlines()[2].split()[3] == "?"


def test_a_stopped_discovery_server_is_named_as_the_cause():
    # Both nodes services run; the main hears nothing because the server is down.
    team = result("team6", heard=heard(topics=()))
    team.other_services = [("team6-main", DISCOVERY_SERVER, "inactive (dead)")]
    assert not team.passed
    assert team.verdict() == ("roslab-discovery-server.service on team6-main is inactive (dead) (the team's Fast "
                              "DDS discovery server: without it the team's hosts do not find each other)")
    team.other_services = [("team6-main", DISCOVERY_SERVER, "active (running)")]
    assert team.verdict() == "team6-main does not see /chatter"


def test_check_shows_each_hosts_profile_and_its_settings(tmp_path, rosdistro_url, capsys):
    from roslab.cli.main import main

    turtlebot3_and_sim_class(tmp_path, rosdistro_url)
    assert main(["check", str(tmp_path / "lab.yaml")]) == 0
    rows = {line.split()[1]: line for line in capsys.readouterr().out.splitlines()[2:]}
    assert rows["blue-main"].endswith("turtlebot3 (burger, LDS-03)")
    assert rows["blue-robot"].endswith("turtlebot3 (burger, LDS-03)")
    assert rows["sim1-main"].endswith("sim (burger)")
    assert rows["demo-main"].endswith("demo")


@pytest.mark.parametrize("command", ["verify", "status"])
def test_a_host_that_accepts_and_hangs_up_is_one_line_not_a_traceback(command, tmp_path):
    """A Pi whose sshd is still starting accepts the TCP connection and closes it: paramiko
    would print two tracebacks ("Error reading SSH protocol banner")."""
    import os
    import socket
    import threading

    import yaml

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    stop = threading.Event()

    def hang_up():
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                connection, _ = server.accept()
            except OSError:
                continue
            connection.close()

    thread = threading.Thread(target=hang_up, daemon=True)
    thread.start()
    roster = tmp_path / "classroom.yaml"
    roster.write_text(yaml.safe_dump({
        "classroom": {"ssh_user": "ubuntu", "ssh_port": server.getsockname()[1], "ubuntu_release": "24.04"},
        "teams": {"team1": {"hosts": {"team1-main": {"role": "main", "address": "127.0.0.1"}}}},
    }))
    env = {key: value for key, value in os.environ.items() if key != "ROSLAB_ROSTER"}
    try:
        result = subprocess.run([sys.executable, "-m", "roslab", command, str(roster),
                                 *(["--html", str(tmp_path / "s.html")] if command == "status" else [])],
                                cwd=Path(__file__).resolve().parents[2], env=env, capture_output=True, text=True,
                                timeout=120)
    finally:
        stop.set()
        thread.join(timeout=5)
        server.close()
    output = result.stdout + result.stderr
    assert result.returncode == 1, output
    assert "Traceback" not in output and "paramiko" not in output, output
    assert any("team1-main" in line and "SSH protocol banner" in line for line in output.splitlines()), output


def test_the_opencr_step_names_the_robot_and_the_page_shows_the_command_as_code(tmp_path, rosdistro_url):
    from roslab.cli import status

    classroom = turtlebot3_and_sim_class(tmp_path, rosdistro_url)
    lists = {entry["host"]: entry["items"] for entry in status.checklists(classroom)}
    (opencr,) = [item for item in lists["blue-robot"] if "OpenCR firmware" in item]
    assert "`roslab opencr-update --limit blue-robot`" in opencr and "HOST" not in opencr
    assert "burger.opencr" in opencr
    page = status.render_page(status.page_context("lab", "lab.yaml", [], status.now_utc(),
                                                  checklists=status.checklists(classroom)))
    assert "<code>roslab opencr-update --limit blue-robot</code>" in page and "`roslab opencr-update" not in page


def test_verify_says_which_main_listens_for_what_before_it_waits():
    from types import SimpleNamespace

    from pyinfra.api import Inventory

    def data(role, topic=None, timeout=20):
        return {"roslab_role": role, "nodes_verify_topic": topic, "nodes_verify_timeout": timeout}

    inventory = Inventory(([("team1-main", data("main", "/chatter")), ("team1-robot", data("robot")),
                            ("blue-main", data("main", "/scan", 30)), ("sim1-main", data("main"))], {}))
    hosts = list(inventory)
    state = SimpleNamespace(inventory=SimpleNamespace(iter_activated_hosts=lambda: hosts), active_hosts=hosts)
    assert verify.listening_line(state) == ("roslab verify: listening on team1-main for /chatter, blue-main for "
                                            "/scan (all at once, each up to 30 s for a message, after the ROS tools "
                                            "start)")
    state.active_hosts = [hosts[3]]
    assert "no main host has a topic to hear" in verify.listening_line(state)


def test_a_running_launch_whose_nodes_keep_dying_fails_naming_the_node():
    rover = verify.TeamResult("rover", main="rover-main", robots=["rover-robot"],
                              services={"rover-main": "not installed", "rover-robot": "not installed"},
                              without_service={"rover-main", "rover-robot"}, listens=False, profile="osr",
                              node_deaths=[("rover-robot", "osr_startup", "roboclaw_wrapper", 198,
                                            "Exception: Unable to connect to serial port /dev/serial1.")])
    assert rover.outcome == "FAIL" and not rover.unchecked
    assert rover.verdict() == ("osr_startup on rover-robot runs, but its node roboclaw_wrapper died 198 times in "
                               "the last minute: Exception: Unable to connect to serial port /dev/serial1.")
    # Heard, but beside a crash-looping node: not a pass either.
    team = result("team1", heard=heard("team1-robot"),
                  node_deaths=[("team1-robot", "x", "driver", 1, "exit code 1")])
    assert team.outcome == "FAIL" and "driver died once in the last minute" in team.verdict()


def test_the_launch_deaths_fact_reads_the_last_minute_of_the_unit():
    fact = verify.LaunchDeaths()
    assert fact.command("osr_startup.service").startswith(
        "journalctl -u osr_startup.service --since=-60s --no-pager -o cat")
    assert fact.process(["a", "b"]) == ["a", "b"]


# The publisher a profile names (verify_publisher: the ESP32 board's flashed node name)
# ------------------------------------------------------------------------------------

INT32 = "std_msgs/msg/Int32"


def board_check(tmp_path, home, timeout: int = 2) -> str:
    """The output of verify's check for team2's ESP32 board, run against the stand-in ros2."""
    script = verify.check_script("jazzy", ENV, "~/ros2_ws", "/esp32/potentiometer", timeout, 1, INT32,
                                 "esp32_board_team2")
    script = script.replace("/opt/ros/jazzy/setup.bash", str(tmp_path / "setup.bash"))
    return subprocess.run(["bash", "-c", script], capture_output=True, text=True, env={"HOME": str(home)},
                          timeout=120).stdout


def test_the_topics_publishers_are_asked_for_only_where_a_profile_names_one(tmp_path):
    home = stand_in_ros(tmp_path, "case \"$1 $2\" in \"topic echo\") printf 'data: 7\\n---\\n' ;;\n"
                                  "\"topic info\") printf 'Type: std_msgs/msg/Int32\\n\\nPublisher count: 1\\n\\n"
                                  "Node name: esp32_board_team2\\nNode namespace: /\\n\\nSubscription count: 1\\n\\n"
                                  "Node name: servo_follower\\n' ;; esac")
    output = board_check(tmp_path, home)
    assert "topic info --no-daemon --spin-time 3 --verbose /esp32/potentiometer" in calls(tmp_path)
    found = verify.parse_check_output(output.splitlines())
    assert found["publishers"] == ["esp32_board_team2"] and found["message"] == "data: 7"  # not the subscriber
    assert "topic info" not in verify.check_script("jazzy", ENV, "~/ros2_ws", "/scan", 2, 1, SCAN)


def test_a_publisher_still_unnamed_is_read_again_until_its_node_name_comes(tmp_path):
    # ROS names a participant _CREATED_BY_BARE_DDS_APP_ until its ros_discovery_info arrives,
    # which under load can be after its first message: the board's name comes on the third read.
    home = stand_in_ros(tmp_path, "case \"$1 $2\" in \"topic echo\") printf 'data: 7\\n---\\n' ;;\n"
                                  "\"topic info\") reads=$(grep -c 'topic info' " + str(tmp_path / "calls") + ")\n"
                                  "  name=_CREATED_BY_BARE_DDS_APP_; [ $reads -ge 3 ] && name=esp32_board_team2\n"
                                  "  printf 'Publisher count: 1\\n\\nNode name: %s\\n' $name ;; esac")
    output = board_check(tmp_path, home)
    found = verify.parse_check_output(output.splitlines())
    assert found["publishers"] == ["esp32_board_team2"]
    assert sum("topic info" in call for call in calls(tmp_path)) == 3


def test_a_silent_topic_is_not_read_again_for_its_publishers(tmp_path):
    home = stand_in_ros(tmp_path, "[ \"$1 $2\" = 'topic echo' ] && sleep 5; exit 0")  # no message: killed at 1 s
    board_check(tmp_path, home, timeout=1)
    assert sum("topic info" in call for call in calls(tmp_path)) == 1


def test_a_publisher_whose_name_never_came_is_not_called_another_teams_board():
    found = {**heard(topics=("/esp32/potentiometer",), message="data: 7"),
             "publishers": [verify.UNNAMED_PUBLISHER]}
    unnamed = result("team2", heard=found, topic="/esp32/potentiometer", message_type=INT32,
                     publisher="esp32_board_team2")
    assert not unnamed.passed
    assert "another team" not in unnamed.verdict()
    assert unnamed.verdict().startswith(f"heard a {INT32} on /esp32/potentiometer, but its publisher's node name "
                                        f"was still unknown after {verify.PUBLISHERS_WAIT} s")
    beside = {**found, "publishers": [verify.UNNAMED_PUBLISHER, "esp32_board_team1"]}
    other = result("team2", heard=beside, topic="/esp32/potentiometer", message_type=INT32,
                   publisher="esp32_board_team2")
    assert "(its publishers: esp32_board_team1): another team's board" in other.verdict()


def test_an_esp32_team_passes_only_on_its_own_boards_node():
    def board(publishers):
        found = {**heard(topics=("/esp32/potentiometer",), message="data: 7"), "publishers": publishers}
        return result("team2", heard=found, topic="/esp32/potentiometer", message_type=INT32,
                      publisher="esp32_board_team2")

    own = board(["esp32_board_team2"])
    assert own.passed and own.verdict() == f"heard a {INT32} on /esp32/potentiometer from esp32_board_team2"
    other = board(["esp32_board_team1"])  # team1's board behind team2's agent, or flashed with team1's values
    assert not other.passed
    assert other.verdict().startswith(f"heard a {INT32} on /esp32/potentiometer, but not from esp32_board_team2 "
                                      "(its publishers: esp32_board_team1): another team's board")
    assert not board([]).passed and "(its publishers: none seen)" in board([]).verdict()
    silent = result("team2", heard=heard(topics=("/esp32/potentiometer",)), topic="/esp32/potentiometer",
                    message_type=INT32, publisher="esp32_board_team2", source="the ESP32 board")
    assert not silent.passed
    assert silent.verdict() == ("no message from esp32_board_team2 on /esp32/potentiometer within 20 s: "
                                "the ESP32 board publishes nothing")
