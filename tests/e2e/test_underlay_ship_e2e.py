"""A class compiles once (issue 31), end to end: two ESP32 teams on Jazzy, one build per group.

Its own sandbox instance ($ROSLAB_UNDERLAY_E2E_SANDBOX, $ROSLAB_UNDERLAY_E2E_SUBNET), 4 hosts:

    team1, team2   esp32_microros, 24.04: main + robot, the board attached to the robot (UDP)

Two groups: the robots (the micro-ROS agent's .repos) and the mains (the class's lab_tools,
`workspace_sources` on the mains). Each group's first host runs colcon, the other receives the
install tree from the controller's cache; the proof is each host's own underlay: colcon's
`log/build_*` folders (one per colcon run there), the build folder of the tree in use, and the
origin record `roslab status` shows. Then: the re-run is a no-op; a changed pin of lab_tools,
with `underlay_builder` naming team2-main, rebuilds the mains once, on team2-main; a broken
commit fails the mains' group (both hosts, naming the builder and the package) and not the
robots.

With ROSLAB_SANDBOX_SOURCES and a real runtime (as CI runs), the agent is the real one: it is
built once, on one robot, and runs on both (about 2 minutes more than the stand-ins).
ROSLAB_UNDERLAY_E2E_REAL=0 keeps the sandbox's stand-in repositories for a quicker run.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import git_standins
from tests.e2e.conftest import bring_up, summary_lines

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_UNDERLAY_E2E_SANDBOX", "roslab-underlay-e2e")
SUBNET = os.environ.get("ROSLAB_UNDERLAY_E2E_SUBNET", "10.213.210.0/24")
REAL = os.environ.get("ROSLAB_UNDERLAY_E2E_REAL", "1") != "0"
HOSTS = 4
ROBOTS = ("team1-robot", "team2-robot")
MAINS = ("team1-main", "team2-main")
UNDERLAY = "/home/ubuntu/roslab_underlay"
AGENT_PORT = 8888
LAB_TOOLS_URL = "https://github.com/roslab-standin/lab_tools.git"
AGENT_URL = "https://github.com/micro-ROS/micro-ROS-Agent.git"


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    kept = None if REAL else os.environ.pop("ROSLAB_SANDBOX_SOURCES", None)
    try:
        classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases="24.04,24.04")
    finally:
        if kept is not None:
            os.environ["ROSLAB_SANDBOX_SOURCES"] = kept
    try:
        yield classroom
    finally:
        teardown()


def real_agent(sandbox) -> bool:
    return sandbox.real_ros and AGENT_URL in sandbox.real_repositories


def write_roster(sandbox, path: Path, lab_pin: str = "v1.0.0", builder: str | None = None,
                 offline: bool = False) -> Path:
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"]["sources_cache_dir"] = str(path.parent / "sources-cache")
    if offline:
        data["classroom"]["offline"] = True
    teams = data["teams"]
    assert sorted(teams) == ["team1", "team2"], teams
    for name, team in teams.items():
        team.update(robot_profile="esp32_microros", esp32_usb_serial=f"0001A2B{name[-1]}",
                    esp32_attached_to="robot", esp32_transport="udp", esp32_udp_port=str(AGENT_PORT),
                    esp32_present=real_agent(sandbox))
        for host_name, host in team["hosts"].items():
            if host_name in MAINS:
                host["workspace_sources"] = ["class.repos"]
                if builder:
                    host["underlay_builder"] = builder
    (path.parent / "class.repos").write_text(yaml.safe_dump({"repositories": {
        "lab_tools": {"type": "git", "url": LAB_TOOLS_URL, "version": lab_pin}}}))
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    git_standins.standin_repository(sandbox.instance.state_dir / "upstream", LAB_TOOLS_URL, "lab_tools",
                                    tags=["v1.0.0"])
    return write_roster(sandbox, tmp_path_factory.mktemp("underlay") / "roster.yaml")


def deploy(sandbox, roster: Path, *args: str):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def colcon_runs(sandbox, host: str) -> int:
    """How many times colcon built in the host's underlay (colcon keeps a log folder per run)."""
    out = sandbox.ssh(host, f"ls -d {UNDERLAY}/log/build_* 2>/dev/null | wc -l", check=True).stdout
    return int(out.split()[0])


def underlay_state(sandbox, host: str) -> dict:
    """The tree in use, whether its build folder is here, and the origin record."""
    out = sandbox.ssh(host, f"cd {UNDERLAY} && readlink install; "
                            "test -d build-$(readlink install) && echo built-here-folder; "
                            "cat .roslab/underlay-origin", check=True).stdout.split("\n")
    return {"slot": out[0].strip(), "build_folder": "built-here-folder" in out,
            "origin": next((line.strip() for line in out if line.startswith(("built here", "shipped from"))), "")}


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    return deploy(sandbox, roster)


def test_the_class_converges_with_one_colcon_run_per_group(sandbox, first_run):
    assert first_run.returncode == 0, first_run.stderr[-4000:]
    assert first_run.failed_hosts == []
    runs = {host.name: colcon_runs(sandbox, host.name) for host in sandbox.hosts}
    assert runs == {"team1-robot": 1, "team2-robot": 0, "team1-main": 1, "team2-main": 0}, runs
    states = {host.name: underlay_state(sandbox, host.name) for host in sandbox.hosts}
    for builder, receiver in (ROBOTS, MAINS):
        built, got = states[builder], states[receiver]
        assert built["build_folder"] and not got["build_folder"], states
        # the same install path on both: the tree lands where it was built
        assert built["slot"] == got["slot"] and re.fullmatch(r"install-[0-9a-f]{12}", got["slot"]), states
        digest = built["origin"].split()[-1]
        assert built["origin"] == f"built here {digest}", states
        assert got["origin"] == f"shipped from {builder} {digest}", states
    assert states["team1-robot"]["slot"] != states["team1-main"]["slot"]  # two groups, two builds


def sandbox_cache(roster: Path) -> Path:
    return roster.parent / "sources-cache" / "underlays"


def test_the_controller_keeps_each_groups_build_by_digest(sandbox, roster, first_run):
    kept = {p.name for p in sandbox_cache(roster).iterdir()}
    digests = {underlay_state(sandbox, host)["origin"].split()[-1] for host in ("team1-robot", "team1-main")}
    assert {f"{digest}.tar.gz" for digest in digests} <= kept, kept


def test_every_robot_has_the_agent_and_its_service_where_it_was_built(sandbox, first_run):
    for host in ROBOTS:
        packages = sandbox.ssh(host, f"ls {UNDERLAY}/install", check=True).stdout.split()
        assert {"micro_ros_agent", "microxrcedds_agent"} <= set(packages), (host, packages)
        props = sandbox.ssh(host, "systemctl show micro_ros_agent.service -p LoadState -p ActiveState",
                            check=True).stdout
        assert "LoadState=loaded" in props, (host, props)
        if real_agent(sandbox):
            assert "ActiveState=active" in props, (host, props)
            listening = sandbox.ssh(host, "ss -ulnpH", check=True).stdout
            assert f":{AGENT_PORT} " in listening, (host, listening)
        else:
            # the stand-in agent runs from the shipped tree: sourced and started as the unit does
            ran = run_standin(sandbox, host, "micro_ros_agent")
            assert ran.returncode == 0 and "stand-in: micro_ros_agent" in ran.stdout, (host, ran.stdout, ran.stderr)
    # the receiving main runs the shipped lab_tools
    ran = run_standin(sandbox, "team2-main", "lab_tools")
    assert ran.returncode == 0 and "stand-in: lab_tools" in ran.stdout, (ran.stdout, ran.stderr)


def run_standin(sandbox, host: str, package: str):
    """A stand-in package's console script, from the host's underlay as its setup sources it."""
    return sandbox.ssh(host, f"bash -c 'source {UNDERLAY}/install/setup.bash && "
                             f"{UNDERLAY}/install/{package}/lib/{package}/{package}'")


def test_status_shows_where_each_underlay_came_from(sandbox, roster, first_run):
    result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster)], env=sandbox.env,
                            capture_output=True, text=True, timeout=120)
    rows = {line.split()[1]: line for line in result.stdout.splitlines() if line.startswith("team")}
    assert re.search(r"built here [0-9a-f]{12}\b", rows["team1-robot"]), rows
    assert re.search(r"shipped from team1-robot [0-9a-f]{12}\b", rows["team2-robot"]), rows
    assert re.search(r"shipped from team1-main [0-9a-f]{12}\b", rows["team2-main"]), rows


def test_a_rerun_builds_nothing_and_changes_nothing_in_a_few_commands_per_host(sandbox, roster, first_run):
    from collections import Counter

    from tests.e2e.test_classroom_e2e import NOOP_COMMANDS_PER_HOST, REMOTE_COMMAND

    again = deploy(sandbox, roster, "--debug")
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed
    # the group's facts (architecture) are in each host's one read: a converged class asks no peer
    commands = Counter(REMOTE_COMMAND.findall(again.stderr))
    assert set(commands) == {host.name for host in sandbox.hosts}, commands
    assert max(commands.values()) <= NOOP_COMMANDS_PER_HOST, commands
    runs = {host.name: colcon_runs(sandbox, host.name) for host in sandbox.hosts}
    assert runs == {"team1-robot": 1, "team2-robot": 0, "team1-main": 1, "team2-main": 0}, runs


def underlay_lost(sandbox, host: str) -> dict[str, int]:
    """`host` re-imaged, as far as its underlay goes; every host's colcon runs before."""
    before = {each.name: colcon_runs(sandbox, each.name) for each in sandbox.hosts}
    sandbox.ssh(host, f"rm -rf {UNDERLAY}/install {UNDERLAY}/install-* {UNDERLAY}/.roslab/build.sha256",
                check=True)
    return before


def received_and_nothing_built(sandbox, run, host: str, source: str, before: dict[str, int]) -> None:
    """The run changed only `host`, which holds the agent shipped from `source`; no colcon ran."""
    assert run.returncode == 0, run.stderr[-3000:]
    assert set(run.changes_per_host()) == {host}, run.changed
    assert {each.name: colcon_runs(sandbox, each.name) for each in sandbox.hosts} == before
    assert underlay_state(sandbox, host)["origin"].startswith(f"shipped from {source} ")
    assert {"micro_ros_agent", "microxrcedds_agent"} <= set(
        sandbox.ssh(host, f"ls {UNDERLAY}/install", check=True).stdout.split())


def test_offline_a_host_that_lost_its_underlay_receives_it_from_the_cache_and_nothing_builds(
        sandbox, roster, first_run):
    before = underlay_lost(sandbox, "team2-robot")
    run = deploy(sandbox, write_roster(sandbox, roster, offline=True))
    try:
        received_and_nothing_built(sandbox, run, "team2-robot", "team1-robot", before)
    finally:
        write_roster(sandbox, roster)


def test_a_reimaged_builder_without_the_controllers_cache_receives_a_teammates_tree(sandbox, roster, first_run):
    """team1-robot built the robots' underlay; it is re-imaged and the controller's cache is gone:
    team2-robot holds the same build, so it is packed there and shipped, and nothing compiles."""
    before = underlay_lost(sandbox, "team1-robot")
    shutil.rmtree(sandbox_cache(roster))
    run = deploy(sandbox, roster)
    received_and_nothing_built(sandbox, run, "team1-robot", "team2-robot", before)


def test_a_changed_pin_rebuilds_once_on_the_named_builder(sandbox, roster, first_run):
    git_standins.commit(sandbox.instance.state_dir / "upstream" / git_standins.served_path(LAB_TOOLS_URL),
                        git_standins.package_files("lab_tools", ["lab_tools"], marker="roslab-e2e-v2"),
                        "lab_tools v2", ["v2.0.0"])
    run = deploy(sandbox, write_roster(sandbox, roster, lab_pin="v2.0.0", builder="team2-main"))
    assert run.returncode == 0, run.stderr[-3000:]
    assert set(run.changes_per_host()) == set(MAINS), run.changed
    runs = {host.name: colcon_runs(sandbox, host.name) for host in sandbox.hosts}
    assert runs == {"team1-robot": 1, "team2-robot": 0, "team1-main": 1, "team2-main": 1}, runs
    states = {host: underlay_state(sandbox, host) for host in MAINS}
    digest = states["team2-main"]["origin"].split()[-1]
    assert states["team2-main"]["origin"] == f"built here {digest}"
    assert states["team1-main"]["origin"] == f"shipped from team2-main {digest}"
    ran = run_standin(sandbox, "team1-main", "lab_tools")
    assert ran.returncode == 0 and "roslab-e2e-v2" in ran.stdout, (ran.stdout, ran.stderr)


def test_a_failed_build_fails_only_its_group_naming_the_builder_and_the_package(sandbox, roster, first_run):
    """Last: the mains are left with a failed build (their last good install in use)."""
    files = git_standins.package_files("lab_tools", ["lab_tools"], marker="roslab-e2e-broken")
    files["lab_tools/setup.py"] = files["lab_tools/setup.py"].replace("['package.xml']",
                                                                      "['package.xml', 'missing.yaml']")
    git_standins.commit(sandbox.instance.state_dir / "upstream" / git_standins.served_path(LAB_TOOLS_URL), files,
                        "lab_tools broken", ["v3.0.0"])
    before = {host: underlay_state(sandbox, host)["slot"] for host in MAINS}
    run = deploy(sandbox, write_roster(sandbox, roster, lab_pin="v3.0.0", builder="team2-main"))
    assert run.returncode != 0
    assert sorted(run.failed_hosts) == sorted(MAINS), (run.failed_hosts, run.stderr[-3000:])
    lines = summary_lines(run.stderr)
    receiver = next(line for line in lines if line.startswith("team1-main "))
    assert "builder team2-main failed to build it: package lab_tools failed to build" in receiver, lines
    for host in ROBOTS:
        assert any(line.startswith(host + " ") and " ok" in line for line in lines), lines
    assert {host: underlay_state(sandbox, host)["slot"] for host in MAINS} == before
    assert colcon_runs(sandbox, "team1-main") == 1  # the receiver never ran colcon
