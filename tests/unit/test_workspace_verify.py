"""The verify step: what the main host's check finds, and the table a teacher reads."""

from __future__ import annotations

import subprocess

from deploy import verify

ENV = {"ROS_DOMAIN_ID": "11", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}


def run_check(tmp_path, ros2_body: str | None) -> dict:
    """Run the check script with a stand-in distro whose `ros2` does what `ros2_body` says."""
    setup = tmp_path / "setup.bash"
    lines = [f"export PATH={tmp_path / 'bin'}:/usr/bin:/bin"]
    if ros2_body is not None:
        (tmp_path / "bin").mkdir()
        ros2 = tmp_path / "bin" / "ros2"
        ros2.write_text(f"#!/bin/bash\n{ros2_body}\n")
        ros2.chmod(0o755)
    setup.write_text("\n".join(lines) + "\n")
    script = verify.check_script("jazzy", ENV, str(tmp_path / "ws"), "/chatter", 2)
    script = script.replace("/opt/ros/jazzy/setup.bash", str(setup))
    result = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env={})
    assert result.returncode == 0  # a fact command must not fail; the result says what happened
    return verify.parse_check_output(result.stdout.splitlines())


FAKE_ROS2 = """
case "$1 $2" in
  "topic list") printf '/chatter\\n/parameter_events\\n/robot_status\\n/rosout\\n' ;;
  "topic echo") [ "$ROS_DOMAIN_ID" = 11 ] && printf "data: 'Hello from team1-robot: 7'\\n---\\n" ;;
esac
"""


def test_the_main_host_hears_the_robot_on_the_teams_domain(tmp_path):
    heard = run_check(tmp_path, FAKE_ROS2)
    assert heard == {
        "ros": True,
        "topics": ["/chatter", "/parameter_events", "/robot_status", "/rosout"],
        "message": "data: 'Hello from team1-robot: 7'",
    }


def test_no_ros2_command_is_reported_as_no_ros_runtime(tmp_path):
    assert run_check(tmp_path, None) == {"ros": False, "topics": [], "message": None}


def test_a_silent_topic_times_out_instead_of_hanging(tmp_path):
    heard = run_check(tmp_path, 'case "$2" in list) echo /chatter ;; echo) sleep 30 ;; esac')
    assert heard == {"ros": True, "topics": ["/chatter"], "message": None}


def result(team="team1", heard=None, **kwargs):
    return verify.TeamResult(
        team, main=f"{team}-main", robot=f"{team}-robot", heard=heard,
        services={f"{team}-main": "active", f"{team}-robot": "active"}, **kwargs,
    )


def test_table_has_a_row_per_team_and_says_what_failed():
    results = [
        result("team2", heard={"ros": False, "topics": [], "message": None}),
        result("team1", heard={"ros": True, "topics": ["/chatter", "/rosout"], "message": "data: hi"}),
        result("team3", heard={"ros": True, "topics": ["/rosout"], "message": None}),
        result("team4", heard={"ros": True, "topics": ["/chatter"], "message": None}),
    ]
    table = verify.format_table(results).splitlines()
    assert table[0].split()[:3] == ["team", "main", "robot"]
    rows = {line.split()[0]: line for line in table[2:]}
    assert "PASS heard team1-robot" in rows["team1"]
    assert "/rosout" not in rows["team1"]  # ROS's own topics are noise here
    assert "FAIL no ROS runtime on team2-main: not verified" in rows["team2"]
    assert "FAIL team3-main does not see /chatter" in rows["team3"]
    assert "FAIL /chatter listed but no message within the timeout" in rows["team4"]
    assert [r.passed for r in results] == [False, True, False, False]


def test_an_unreachable_host_fails_its_team():
    failed = result("team5", heard=None, error="team5-robot is unreachable")
    assert not failed.passed
    assert "FAIL team5-robot is unreachable" in verify.format_table([failed])
