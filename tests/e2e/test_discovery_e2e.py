"""Discovery modes end to end on REAL ROS 2 Jazzy: a discovery-server team, a static team, a localhost host.

Its own sandbox instance ($ROSLAB_DISCOVERY_E2E_SANDBOX, $ROSLAB_DISCOVERY_E2E_SUBNET), 5 hosts, all
on an emulated 24.04 (Jazzy, whose real core has Fast DDS and the `fastdds` tools):

    team1  discovery_server   main + robot   (roslab-discovery-server on team1-main)
    team2  static             main + robot   (ROS_STATIC_PEERS, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)
    team3  localhost          main only      (no ros_domain_id: a free one from its name)

The class runs Fast DDS (`ros_middleware: rmw_fastrtps_cpp`, the default). One converge serves the
module: it is a no-op the second time; the discovery server is a service on team1's main only and
comes back after a reboot; each main hears its robot (`roslab verify`); a team-2 host put on team 1's
domain still does not see team 1's topic (static peers reach only its own team); switching team 2 to
discovery_server changes only team 2's hosts and restarts only their services.

Humble's static mode is the middleware's own XML (Humble has no ROS_STATIC_PEERS): the files roslab
writes are read by the real Fast DDS 2.14 and Cyclone DDS 0.10 of the Jazzy core (Humble's Fast DDS
is 2.6, with the same profile format; its Cyclone DDS is 0.10), each with a control that hears
nothing when the peers are not the team's. Zenoh's router is proven by the unit tests only: no Zenoh
exists here.

It needs real ROS (`ROSLAB_SANDBOX_ROS_RUNTIME`, docs/sandbox.md): on stand-ins there is no
`fast-discovery-server` and no node to hear, so every test skips, saying so.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from roslab.ros import discovery
from tests.e2e.conftest import bring_up

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
INSTANCE = os.environ.get("ROSLAB_DISCOVERY_E2E_SANDBOX", "roslab-discovery-e2e")
SUBNET = os.environ.get("ROSLAB_DISCOVERY_E2E_SUBNET", "10.213.131.0/24")
HOSTS = 5
RELEASES = "24.04"
SERVER = "roslab-discovery-server.service"
NODES = "roslab-nodes.service"


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases=RELEASES)
    try:
        if not classroom.real_ros:
            pytest.skip(f"the sandbox serves stand-in ROS 2 ({classroom.ros_served}): set "
                        "ROSLAB_SANDBOX_ROS_RUNTIME (docs/sandbox.md) to prove discovery on real ROS")
        yield classroom
    finally:
        teardown()  # also when a test failed or the module skipped


def class_roster(sandbox, path: Path, team2_mode: str = "static") -> Path:
    """The sandbox's roster with one line per team's mode, as a teacher writes it."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    # Fast DDS, which the discovery server needs (the sandbox's real-runtime roster says Cyclone DDS).
    data["classroom"]["ros_middleware"] = "rmw_fastrtps_cpp"
    data["classroom"]["ros_discovery_mode"] = "static"
    teams = data["teams"]
    teams["team1"]["ros_discovery_mode"] = "discovery_server"
    if team2_mode != "static":
        teams["team2"]["ros_discovery_mode"] = team2_mode
    del teams["team3"]["ros_domain_id"]  # roslab gives it a free one
    (host,) = teams["team3"]["hosts"].values()
    host["ros_discovery_mode"] = "localhost"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy(sandbox, roster: Path):
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def roslab(sandbox, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "roslab"), *args], cwd=REPO, env=sandbox.env, capture_output=True,
                          text=True, timeout=timeout)


def ros(sandbox, host: str, command: str, timeout: float = 120):
    """`command` as the login user in the environment its ~/.bashrc block sets."""
    return sandbox.ssh(host, f"bash -ic {shlex.quote(command)} 2>&1", timeout=timeout)


def show(sandbox, host: str, unit: str, prop: str) -> str:
    return sandbox.ssh(host, f"systemctl show -p {prop} --value {unit}").stdout.strip()


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    return class_roster(sandbox, tmp_path_factory.mktemp("discovery") / "roster.yaml")


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    started = time.monotonic()
    run = deploy(sandbox, roster)
    print(f"\nconverge, {HOSTS} hosts on real Jazzy: {time.monotonic() - started:.0f} s")
    return run


def test_the_class_converges_and_a_rerun_changes_nothing(sandbox, roster, first_run):
    assert first_run.returncode == 0, first_run.stderr[-4000:]
    assert first_run.failed_hosts == []
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-4000:]
    assert again.changed == {}, again.changed


def test_the_discovery_server_is_a_service_on_team1s_main_only(sandbox, first_run):
    assert show(sandbox, "team1-main", SERVER, "ActiveState") == "active"
    assert show(sandbox, "team1-main", SERVER, "UnitFileState") == "enabled"
    listening = sandbox.ssh("team1-main", "ss -uln").stdout
    assert re.search(r":11811\b", listening), listening
    for host in ("team1-robot", "team2-main", "team2-robot", "team3-main"):
        assert show(sandbox, host, SERVER, "LoadState") == "not-found", host
    team1_main = sandbox.host("team1-main").address
    environment = show(sandbox, "team1-robot", NODES, "Environment")
    assert f"ROS_DISCOVERY_SERVER={team1_main}:11811" in environment
    assert "RMW_IMPLEMENTATION=rmw_fastrtps_cpp" in environment
    assert f"ROS_STATIC_PEERS={sandbox.host('team2-main').address}" in show(sandbox, "team2-robot", NODES,
                                                                            "Environment")
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST" in show(sandbox, "team3-main", NODES, "Environment")
    # The students' shell is a super client: it sees the whole graph through the server.
    assert ros(sandbox, "team1-main", 'printf %s "$ROS_SUPER_CLIENT"').stdout.strip().endswith("TRUE")


def table_rows(text: str) -> dict[str, dict[str, str]]:
    """`roslab check`'s table, by host and column (cells are cut where the header's columns start)."""
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("TEAM "))
    starts = [match.start() for match in re.finditer(r"\S+", header)]
    names = header.split()
    rows = {}
    for line in lines[lines.index(header) + 1:]:
        if not line.strip():
            continue
        cells = [line[start:end].strip() for start, end in zip(starts, [*starts[1:], None])]
        rows[cells[1]] = dict(zip(names, cells))
    return rows


def test_status_and_check_show_each_teams_mode_and_the_assigned_domain(sandbox, roster, first_run):
    check = roslab(sandbox, "check", str(roster))
    assert check.returncode == 0, check.stderr
    rows = table_rows(check.stdout)
    assert rows["team1-robot"]["DISCOVERY"] == "discovery_server" and rows["team2-main"]["DISCOVERY"] == "static"
    assert rows["team3-main"]["DOMAIN"].endswith("(auto)") and rows["team3-main"]["DISCOVERY"] == "localhost"
    status = roslab(sandbox, "status", str(roster))
    assert "discovery_server" in status.stdout and "static" in status.stdout, status.stdout


def test_each_main_hears_its_robot_through_its_teams_discovery(sandbox, roster, first_run):
    proc = roslab(sandbox, "verify", str(roster), "--limit", "team1", "--limit", "team2", timeout=400)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for team in ("team1", "team2"):
        assert re.search(rf"^{team} .*PASS heard {team}-robot$", proc.stdout, re.M), proc.stdout


def test_a_static_team_does_not_see_another_teams_topic_even_on_its_domain(sandbox, first_run):
    domain = ros(sandbox, "team1-main", 'printf %s "$ROS_DOMAIN_ID"').stdout.strip().splitlines()[-1]
    # team1's graph, as its main's super client sees it: its robot's talker is there.
    seen = ros(sandbox, "team1-main", "ros2 node list --no-daemon --spin-time 5").stdout.split()
    assert "/talker" in seen, seen
    # team2's main, static: on its own domain its peer list reaches its robot's talker...
    own = ros(sandbox, "team2-main", "ros2 node list --no-daemon --spin-time 5")
    assert own.returncode == 0 and "/talker" in own.stdout.split(), own.stdout
    # ...and on team1's domain, with the same static discovery, no peer of team1 answers: nothing.
    other = ros(sandbox, "team2-main", f"ROS_DOMAIN_ID={shlex.quote(domain)} "
                                       "ros2 node list --no-daemon --spin-time 5")
    assert other.returncode == 0, other.stdout
    assert "/talker" not in other.stdout.split() and "/listener" not in other.stdout.split(), other.stdout


def clean_ros(sandbox, host: str, variables: dict[str, str], command: str, timeout: float = 60):
    """`command` with only the distro's setup and `variables` (not the login shell's block)."""
    exports = " ".join(f"{name}={shlex.quote(value)}" for name, value in variables.items())
    script = f"source /opt/ros/jazzy/setup.bash && env {exports} {command}"
    return sandbox.ssh(host, f"bash -c {shlex.quote(script)} 2>&1", timeout=timeout)


def heard_with_peer_files(sandbox, variable: str, path: str, main_text: str, robot_text: str,
                          variables: dict[str, str]) -> str:
    """Put each side's file at `path`, publish on team2-robot, listen once on team2-main: what it heard."""
    for host, text in (("team2-main", main_text), ("team2-robot", robot_text)):
        sandbox.ssh(host, f"printf %s {shlex.quote(text)} > {path}", check=True)
    value = f"file://{path}" if variable == "CYCLONEDDS_URI" else path
    env = {**variables, variable: value}
    publisher = threading.Thread(target=clean_ros, args=(
        sandbox, "team2-robot", env, "timeout -k 5 25 ros2 topic pub -r 4 /roslab_probe std_msgs/msg/String "
                                     "'{data: through the peer list}'"), kwargs={"timeout": 60})
    publisher.start()
    try:
        heard = clean_ros(sandbox, "team2-main", env,
                          "timeout -k 5 20 ros2 topic echo --once /roslab_probe std_msgs/msg/String")
    finally:
        publisher.join()
    return heard.stdout


@pytest.mark.parametrize("middleware", ["rmw_fastrtps_cpp", "rmw_cyclonedds_cpp"])
def test_humbles_peer_files_work_with_the_real_middleware_and_turn_multicast_off(sandbox, roster, first_run,
                                                                               middleware):
    """The XML roslab writes for Humble's static mode, read by the real Fast DDS (2.14, the same 2.x
    profile format as Humble's 2.6) and the real Cyclone DDS (0.10, Humble's) of the Jazzy core:
    with the team's peers the main hears its robot; with peers that are not the team (multicast
    off in both files) it hears nothing, so the peer list is what carries discovery."""
    main, robot, stranger = (sandbox.host(name).address for name in ("team2-main", "team2-robot", "team3-main"))
    taken = {team["ros_domain_id"] for team in yaml.safe_load(roster.read_text())["teams"].values()
             if "ros_domain_id" in team}
    domain = str(next(candidate for candidate in range(100, 80, -1) if candidate not in taken))
    # SYSTEM_DEFAULT: Jazzy's rmw leaves discovery to the middleware's own configuration, as Humble does.
    variables = {"ROS_DOMAIN_ID": domain, "RMW_IMPLEMENTATION": middleware,
                 "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}
    if middleware == "rmw_cyclonedds_cpp":
        variable, path, render = "CYCLONEDDS_URI", "/tmp/roslab-e2e-cyclonedds.xml", discovery.cyclonedds_peers_xml
    else:
        variable, path, render = "FASTRTPS_DEFAULT_PROFILES_FILE", "/tmp/roslab-e2e-fastdds.xml", \
            discovery.fastdds_peers_xml
    heard = heard_with_peer_files(sandbox, variable, path, render([robot]), render([main]), variables)
    assert "data: through the peer list" in heard, heard
    unheard = heard_with_peer_files(sandbox, variable, path, render([stranger]), render([stranger]), variables)
    assert "data: through the peer list" not in unheard, unheard


def pids(sandbox) -> dict[tuple[str, str], str]:
    out = {}
    for host in ("team1-main", "team1-robot", "team2-main", "team2-robot", "team3-main"):
        for unit in (NODES, SERVER):
            out[(host, unit)] = show(sandbox, host, unit, "MainPID")
    return out


def test_switching_a_team_changes_only_its_hosts_and_restarts_only_its_services(sandbox, tmp_path, first_run):
    before = pids(sandbox)
    switched = class_roster(sandbox, tmp_path / "roster.yaml", team2_mode="discovery_server")
    run = deploy(sandbox, switched)
    assert run.returncode == 0, run.stderr[-4000:]
    changed_hosts = set(run.changes_per_host())
    assert changed_hosts == {"team2-main", "team2-robot"}, run.changed
    after = pids(sandbox)
    for key in before:
        if key[0].startswith("team2"):
            continue
        assert after[key] == before[key], key  # nobody else's service restarted
    assert after[("team2-main", NODES)] != before[("team2-main", NODES)]
    assert after[("team2-robot", NODES)] != before[("team2-robot", NODES)]
    assert show(sandbox, "team2-main", SERVER, "ActiveState") == "active"
    assert deploy(sandbox, switched).changed == {}
    proc = roslab(sandbox, "verify", str(switched), "--limit", "team2", timeout=400)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_the_discovery_server_comes_back_after_a_reboot_and_the_main_hears_its_robot(sandbox, roster, first_run):
    sandbox.reboot("team1-main")
    rebooted = time.monotonic()
    while show(sandbox, "team1-main", SERVER, "ActiveState") != "active":
        assert time.monotonic() - rebooted < 120, "no discovery server 120 s after the reboot"
        time.sleep(2)
    while True:
        proc = roslab(sandbox, "verify", str(roster), "--limit", "team1", timeout=400)
        if proc.returncode == 0:
            break
        assert time.monotonic() - rebooted < 180, proc.stdout + proc.stderr
    assert "PASS heard team1-robot" in proc.stdout
    print(f"\nteam1 verified {time.monotonic() - rebooted:.0f} s after its main rebooted")
