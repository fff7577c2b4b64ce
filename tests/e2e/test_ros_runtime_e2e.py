"""The demo nodes, launch files and `roslab verify` on REAL ROS 2 Jazzy and Humble.

Runs only when the session's sandbox serves real ROS 2 (`ROSLAB_SANDBOX_ROS_RUNTIME`, which
`.ci/run` sets to `../shared/ros-runtime` when that folder exists; docs/sandbox.md): team1
is Jazzy on an emulated 24.04, team2 Humble on an emulated 22.04. On stand-ins every test
here skips, saying so.

One converge of the classroom (deploy.py, as a teacher runs it) serves the whole module:
real rclpy nodes run under roslab-nodes.service, each team's main hears its own robot
(`roslab verify`, `roslab status --listen`), verify fails with exit 1 for a stopped robot
and for a robot on the wrong domain, a launch argument and a parameter file with an
integer where a float is meant work, `colcon test` passes without a network, a node killed
by a signal is back within seconds, and after a reboot verify passes only once the
service really runs.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
SERVICE = "roslab-nodes.service"
TEAMS = {"team1": "jazzy", "team2": "humble"}
RUNNING = "active (running)"
# How long a node killed by a signal may take to run again: the launch ends, systemd waits
# RestartSec (nodes_restart_sec) and the launch starts every node again.
BACK_WITHIN = 30


@pytest.fixture(scope="module")
def real(e2e_sandbox, request):
    """The session's classroom on real ROS 2, converged: the session's converge from fresh hosts,
    restored for this module (fresh hosts after it)."""
    if not e2e_sandbox.real_ros:
        pytest.skip(f"the sandbox serves stand-in ROS 2 ({e2e_sandbox.ros_served}): set "
                    "ROSLAB_SANDBOX_ROS_RUNTIME (docs/sandbox.md) to run the nodes on real ROS")
    return request.getfixturevalue("default_class")


def roslab(sandbox, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "roslab"), *args], cwd=REPO, env=sandbox.env, capture_output=True,
                          text=True, timeout=timeout)


def verify_rows(proc) -> dict[str, str]:
    """team -> its row of `roslab verify`'s table, whitespace squeezed."""
    return {line.split()[0]: " ".join(line.split()) for line in proc.stdout.splitlines()[2:]
            if line.strip() and not line.startswith("every team")}


def ros(sandbox, host: str, command: str, timeout: float = 120, **kwargs):
    """`command` as the login user in the ROS environment its ~/.bashrc block sets."""
    return sandbox.ssh(host, f"bash -ic {shlex.quote(command)} 2>&1", timeout=timeout, **kwargs)


def talker_pid(sandbox, host: str) -> str:
    return sandbox.ssh(host, "pgrep -f '^/usr/bin/python3 .*/roslab_demo/talker ' || true").stdout.strip()


def service_state(sandbox, host: str) -> str:
    show = sandbox.ssh(host, f"systemctl show -p ActiveState -p SubState --value {SERVICE}").stdout.split()
    return f"{show[0]} ({show[1]})" if len(show) == 2 else " ".join(show)


def test_the_demo_nodes_run_as_real_ros_nodes_and_the_main_sees_its_robots(real):
    for team, distro in TEAMS.items():
        for host in (f"{team}-main", f"{team}-robot"):
            assert service_state(real, host) == RUNNING, host
            assert real.ssh(host, f"test ! -e /opt/ros/{distro}/STANDIN").returncode == 0, "a stand-in ROS"
        # Discovery over the team's domain: the main lists its own nodes and its robot's.
        nodes = ros(real, f"{team}-main", "ros2 node list --no-daemon --spin-time 5").stdout.split()
        expected = {"/listener", "/status_monitor", "/temperature_monitor",
                    "/talker", "/status_publisher", "/temperature_publisher"}
        assert expected <= set(nodes), (team, nodes)


def test_verify_and_status_listen_pass_when_each_main_hears_its_robot(real):
    proc = roslab(real, "verify", str(real.roster_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = verify_rows(proc)
    for team in TEAMS:
        assert f"{RUNNING} {RUNNING}" in rows[team], rows[team]
        assert re.search(rf"Hello from {team}-robot #\d+ PASS heard {team}-robot$", rows[team]), rows[team]

    status = roslab(real, "status", str(real.roster_path), "--listen", "--listen-timeout", "10")
    for team in TEAMS:
        assert f"team {team}: heard {team}-robot" in status.stdout, status.stdout + status.stderr


def test_verify_fails_with_exit_1_for_a_stopped_robot_and_a_robot_on_another_domain(real):
    dropin = "/etc/systemd/system/roslab-nodes.service.d/zz-e2e-wrong-domain.conf"
    real.sudo("team1-robot", f"systemctl stop {SERVICE}", check=True)
    # team2's robot runs, but on a domain no main listens on (as a mistyped ROS_DOMAIN_ID would).
    real.sudo("team2-robot", f"mkdir -p {Path(dropin).parent} && printf '[Service]\\nEnvironment=ROS_DOMAIN_ID=42\\n'"
                             f" > {dropin} && systemctl daemon-reload && systemctl restart {SERVICE}", check=True)
    try:
        proc = roslab(real, "verify", str(real.roster_path))
    finally:
        real.sudo("team1-robot", f"systemctl start {SERVICE}", check=True)
        real.sudo("team2-robot", f"rm -f {dropin} && systemctl daemon-reload && systemctl restart {SERVICE}",
                  check=True)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    rows = verify_rows(proc)
    assert "inactive (dead)" in rows["team1"] and "PASS" not in rows["team1"], rows["team1"]
    assert f"FAIL {SERVICE} on team1-robot is inactive (dead)" in rows["team1"], rows["team1"]
    assert f"{RUNNING} {RUNNING}" in rows["team2"], rows["team2"]  # running, but unheard
    assert re.search(r"FAIL (team2-main does not see /chatter|/chatter listed but no message)", rows["team2"]), \
        rows["team2"]
    assert "not verified: team1, team2" in proc.stderr


def test_a_launch_argument_and_a_parameter_file_with_an_integer_rate_work(real):
    params = ("talker:\n  ros__parameters:\n    topic: e2e_chatter\n    publish_rate_hz: 4\n"
              "    robot_name: e2e-bot\n")
    for team in TEAMS:
        host = f"{team}-robot"
        real.ssh(host, f"printf '%s' {shlex.quote(params)} > /tmp/e2e-params.yaml", check=True)
        # On a domain of its own, beside the service's nodes: 15 s of the robot's launch, of which
        # the launch's and the node's start-up take several on a loaded machine.
        out = ros(real, host, "export ROS_DOMAIN_ID=77; timeout -s INT 15 ros2 launch roslab_bringup "
                              "robot.launch.py params_file:=/tmp/e2e-params.yaml", timeout=60).stdout
        assert "InvalidParameterTypeException" not in out and "Traceback" not in out, out[-3000:]
        # The rate from the talker's own log times (ROS's console format: `[INFO] [<seconds>]
        # [talker]: ...`), not from a count in a window whose start-up varies with the load:
        # 4 per second, where a rate the node ignored would be its default of 1.
        stamps = [float(stamp) for stamp in re.findall(
            r'\[(\d+\.\d+)\] \[[^\]]*\]: Publishing: "Hello from e2e-bot #\d+"', out)]
        assert len(stamps) >= 5, (host, out[-3000:])
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        assert 3.0 <= rate <= 5.0, (host, rate, out[-3000:])


def test_colcon_test_of_the_node_packages_passes_without_a_network(real):
    for team in TEAMS:
        result = ros(real, f"{team}-main", "cd ~/ros2_ws && colcon test --event-handlers console_cohesion- "
                                           ">/dev/null; colcon test-result --verbose", timeout=300)
        assert result.returncode == 0, result.stdout[-4000:]
        summary = re.search(r"Summary: (\d+) tests, (\d+) errors, (\d+) failures, (\d+) skipped", result.stdout)
        assert summary and summary.groups()[1:] == ("0", "0", "0"), result.stdout[-4000:]
        assert int(summary[1]) >= 10, result.stdout  # flake8, pep257, copyright, xml: both packages


def test_a_node_killed_by_a_signal_is_back_within_seconds(real):
    host = "team2-robot"
    before = talker_pid(real, host)
    assert before, "no talker runs"
    real.sudo(host, f"kill -9 {before}", check=True)
    killed = time.monotonic()
    while True:
        now = talker_pid(real, host)
        if now and now != before and service_state(real, host) == RUNNING:
            break
        assert time.monotonic() - killed < BACK_WITHIN, f"no talker {BACK_WITHIN} s after kill -9 (now {now!r})"
        time.sleep(0.5)
    print(f"\ntalker back {time.monotonic() - killed:.1f} s after kill -9")
    restarts = real.ssh(host, f"systemctl show -p NRestarts --value {SERVICE}").stdout.strip()
    assert restarts == "1", restarts  # the service itself followed the node
    proc = roslab(real, "verify", str(real.roster_path), "--limit", "team2")
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_after_a_reboot_verify_passes_only_once_the_service_runs(real):
    host = "team1-robot"
    real.reboot(host)
    rebooted = time.monotonic()
    verdicts = []
    while True:
        proc = roslab(real, "verify", str(real.roster_path), "--limit", "team1")
        row = verify_rows(proc).get("team1", "")
        verdicts.append(row)
        if "PASS" in row:
            break
        assert proc.returncode == 1, proc.stdout
        assert time.monotonic() - rebooted < 180, verdicts
    # Every PASS stands beside two running services, never beside one still starting.
    for row in verdicts:
        if "PASS" in row:
            assert f"{RUNNING} {RUNNING}" in row, verdicts
    assert proc.returncode == 0
    assert service_state(real, host) == RUNNING
    print(f"\nteam1 verified {time.monotonic() - rebooted:.0f} s after the reboot ({len(verdicts)} runs)")
