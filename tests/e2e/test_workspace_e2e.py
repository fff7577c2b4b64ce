"""The workspace deploy and `roslab verify` end to end, on sandbox hosts over real SSH.

The sandbox's ROS 2 packages are stand-ins (there is no ROS 2 runtime for Debian), but its
colcon and rosdep are the real Debian ones. So these tests check everything up to the
import of rclpy: the workspace is synced and owned by the login user, the real colcon
builds it and installs the console scripts where `ros2 run` looks, and running one stops
at `ModuleNotFoundError: No module named 'rclpy'`.

The stand-in ROS's `ros2` only keeps a launch running; after the first run this module
replaces it on each host (/opt/ros/<distro>/bin/ros2) with one whose `ros2 launch` runs until stopped, as a healthy
launch does, or fails at once while /etc/roslab-e2e-launch-fails exists. With it the nodes units
are really active, can be driven into systemd's failed state, and a re-run of a healthy
classroom must report nothing.

Then the classroom accidents the next run heals, each on one host while the others stay
untouched: a workspace chowned to root, a node with a syntax error (that host fails with
file and line; the fixed file converges), a nodes unit that gave up or was stopped.

Runs on the session's sandbox instance (tests/e2e/conftest.py; ROSLAB_E2E_INSTANCE and
ROSLAB_E2E_SUBNET choose it), starting from its converged default class (the first run is the
session's converge from fresh hosts, restored here), then with a copy of nodes/ given as
`workspace_nodes_dir` (a setting any roster may use) so the tests can edit a node.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from roslab.ros.distro import DEFAULT_DISTRO, UBUNTU_CODENAMES
from roslab.cli import verify
from roslab.roster import load_roster

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
SERVICE = "roslab-nodes.service"
LOGIN_USER = "ubuntu"  # the sandbox's ssh_user, who is also the login user
WORKSPACE = f"/home/{LOGIN_USER}/ros2_ws"

SYNC_OP = "holds the packages of"
OWNED_OP = f"Ensure everything in {WORKSPACE} belongs to {LOGIN_USER}"
DIRECTORY_OP = f"exists, owned by {LOGIN_USER}"
ROSDEP_OP = "system dependencies are installed (rosdep)"
BUILD_OP = "is built from these sources (colcon)"
RESTART_OP = f"{SERVICE} runs the current build and unit"

def stand_in_path(sandbox, host: str) -> str:
    """Where the sandbox's stand-in ROS puts its `ros2` (this module replaces it there)."""
    codename = UBUNTU_CODENAMES[sandbox.host(host).release]
    return f"/opt/ros/{DEFAULT_DISTRO[codename]}/bin/ros2"
LAUNCH_FAILS = "/etc/roslab-e2e-launch-fails"
STAND_IN_ROS2 = f"""#!/bin/sh
# roslab e2e: stands in for ROS 2's ros2 (the sandbox's stand-in ROS has none).
# `ros2 launch` runs until stopped, like a healthy launch, unless {LAUNCH_FAILS} exists.
if [ "$1" = launch ] && [ ! -e {LAUNCH_FAILS} ]; then exec sleep infinity; fi
echo "roslab e2e stand-in ros2: '$*' fails here" >&2
exit 1
"""


def install_stand_in(sandbox, host: str, text: str) -> None:
    path = stand_in_path(sandbox, host)
    sandbox.sudo(host, f"printf '%s' {shlex.quote(text)} > {path} && chmod 755 {path}", check=True)


@pytest.fixture(scope="module")
def sandbox(default_class):
    """The session's converged default class, restored for this module (fresh hosts after it)."""
    return default_class


@pytest.fixture(scope="module")
def classroom(sandbox):
    return load_roster(sandbox.roster_path)


@pytest.fixture(scope="module")
def nodes_copy(tmp_path_factory):
    copy = tmp_path_factory.mktemp("workspace-e2e") / "nodes"
    shutil.copytree(REPO / "nodes", copy, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return copy


def deploy(sandbox, nodes_dir: Path, expect_ok: bool = True):
    """deploy.py on the sandbox with `workspace_nodes_dir` set for every host."""
    started = time.monotonic()
    run = sandbox.pyinfra("--data", f"workspace_nodes_dir={nodes_dir}")
    run.seconds = time.monotonic() - started
    if expect_ok:
        assert run.returncode == 0, run.stderr[-6000:]
    return run


def deploy_with_roster(sandbox, tmp_path, edit):
    """deploy.py through inventories/lab.py on a copy of the sandbox's roster changed by `edit`."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    edit(data)
    roster = tmp_path / "roster.yaml"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def changed(run, fragment: str) -> set[str]:
    """Hosts on which the operation whose name holds `fragment` changed something."""
    matching = [hosts for name, hosts in run.changed.items() if fragment in name]
    assert matching, f"no operation named like {fragment!r} ran: {sorted(run.changed)}"
    return set().union(*matching)


def changes(run) -> dict[str, set[str]]:
    """Operation name (without the deploy's) -> hosts it changed, only those that changed."""
    return {name.split(" | ")[-1]: hosts for name, hosts in run.changed.items() if hosts}


def output_lines(run, *words: str) -> list[str]:
    """Lines of pyinfra's output holding every one of `words`, whitespace squeezed."""
    lines = (run.stdout + "\n" + run.stderr).splitlines()
    return [" ".join(line.split()) for line in lines if all(word in line for word in words)]


def names(classroom) -> set[str]:
    return {host.name for host in classroom.hosts}


def distro(host) -> str:
    return host.data.get("ros_distro") or host.data["roslab_expected_distro"]


def unit_state(sandbox, host: str) -> str:
    return sandbox.sudo(host, f"systemctl show -p ActiveState --value {SERVICE}").stdout.strip()


def wait_for_state(sandbox, host: str, wanted: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while unit_state(sandbox, host) != wanted:
        assert time.monotonic() < deadline, f"{host}: {SERVICE} never became {wanted}"
        time.sleep(1)


def fingerprint(sandbox, host: str) -> str:
    """When the last build ran: the build log's and the stamp's modification times."""
    return sandbox.ssh(host, "stat -c '%n %Y' ~/ros2_ws/log/roslab-build.log ~/ros2_ws/.roslab/build.sha256").stdout


@pytest.fixture(scope="module")
def first_run(sandbox, default_class_saved):
    """The class's first run: the session's converge of the default class from fresh hosts
    (conftest; restored here, as building the same workspaces again would take minutes).
    ROS's ros2 is installed now; this module's takes its place on every host."""
    for host in sandbox.hosts:
        install_stand_in(sandbox, host.name, STAND_IN_ROS2)
    return default_class_saved.run


def test_first_run_builds_and_starts_every_host(classroom, sandbox, first_run):
    everyone = names(classroom)
    assert changed(first_run, SYNC_OP) == everyone
    assert changed(first_run, BUILD_OP) == everyone
    assert changed(first_run, RESTART_OP) == everyone
    for host in everyone:
        assert unit_state(sandbox, host) == "active", host
    # The folders it made are the login user's, group too: nothing to "give back" (issue 40).
    assert output_lines(first_run, "workspace:", "not belong to") == []


def test_workspace_is_synced_and_owned_by_the_login_user(classroom, sandbox, first_run, nodes_copy):
    # Only the ROS packages are synced (nodes/README.md is for people reading the repo).
    packages = {p.parent for p in nodes_copy.glob("*/package.xml")}
    local = sorted(
        p.relative_to(nodes_copy).as_posix()
        for package in packages for p in package.rglob("*") if p.is_file()
    )
    for host in names(classroom):
        listing = sandbox.ssh(host, "cd ~/ros2_ws/src && find roslab_* -type f | sort")
        assert listing.stdout.split() == local, host
        foreign = sandbox.sudo(host, f"find {WORKSPACE} ! -user {LOGIN_USER} -o ! -group {LOGIN_USER}")
        assert foreign.stdout == "", f"{host}: not owned by {LOGIN_USER}: {foreign.stdout}"
        manifest = sandbox.ssh(host, "cat ~/ros2_ws/src/.roslab-manifest").stdout
        assert manifest.splitlines()[-len(packages):] == sorted(package.name for package in packages)
        # The syntax check wrote no byte-code into src/ (it would be synced away every run).
        assert sandbox.ssh(host, "find ~/ros2_ws/src -name __pycache__").stdout == "", host


def test_console_scripts_are_installed_where_ros2_run_looks_and_stop_at_rclpy(classroom, sandbox, first_run):
    """The stand-in ROS has no rclpy: a built node fails exactly at that import, nowhere before."""
    if sandbox.real_ros:
        pytest.skip("the sandbox serves real ROS 2: test_ros_runtime_e2e runs the nodes")
    for host in classroom.hosts:
        lib = "~/ros2_ws/install/roslab_demo/lib/roslab_demo"
        result = sandbox.ssh(
            host.name,
            f"bash -c 'source /opt/ros/{distro(host)}/setup.bash && source ~/ros2_ws/install/setup.bash"
            f" && test -x {lib}/talker && {lib}/talker'",
        )
        assert "ModuleNotFoundError: No module named 'rclpy'" in result.stderr, (
            host.name, result.stdout, result.stderr,
        )


def test_units_run_the_roles_launch_with_the_teams_environment(classroom, sandbox, first_run):
    for team in classroom.teams:
        for host in team.hosts:
            show = sandbox.sudo(host.name, f"systemctl show -p Environment -p User -p ExecStart {SERVICE}").stdout
            assert f"ROS_DOMAIN_ID={team.ros_domain_id}" in show, (host.name, show)
            assert f"User={LOGIN_USER}" in show
            # systemd's own reading of ExecStart: the script as one argument, nothing expanded.
            assert (f"argv[]=/bin/bash -c source /opt/ros/{distro(host)}/setup.bash && "
                    f"source {WORKSPACE}/install/setup.bash && "
                    f"exec ros2 launch roslab_bringup {host.role}.launch.py ;") in show, show
            enabled = sandbox.sudo(host.name, f"systemctl is-enabled {SERVICE}").stdout.strip()
            assert enabled == "enabled", host.name


def test_second_run_neither_rebuilds_nor_restarts(classroom, sandbox, first_run, nodes_copy):
    """The re-run reads the nodes from a copy of nodes/ (`workspace_nodes_dir`): the same
    packages in another folder are the same workspace, nothing to sync, build or restart."""
    before = {host: fingerprint(sandbox, host) for host in names(classroom)}
    second = deploy(sandbox, nodes_copy)
    print(f"no-op re-run, {len(before)} hosts: {second.seconds:.1f} s")
    assert changes(second) == {}, f"a re-run changed: {changes(second)}"
    assert {host: fingerprint(sandbox, host) for host in names(classroom)} == before


def test_editing_one_node_rebuilds_and_restarts_once(classroom, sandbox, first_run, nodes_copy):
    everyone = names(classroom)
    talker = nodes_copy / "roslab_demo" / "roslab_demo" / "talker.py"
    talker.write_text(talker.read_text() + "\n# edited by the workspace e2e test\n")

    third = deploy(sandbox, nodes_copy)

    assert changed(third, SYNC_OP) == everyone
    assert changed(third, BUILD_OP) == everyone
    assert changed(third, RESTART_OP) == everyone
    assert not any(ROSDEP_OP in name for name in changes(third))  # no package.xml changed
    for host in everyone:
        installed = sandbox.ssh(host, "grep -rl 'edited by the workspace e2e test' ~/ros2_ws/src ~/ros2_ws/build")
        assert "src/roslab_demo/roslab_demo/talker.py" in installed.stdout, host
        assert unit_state(sandbox, host) == "active", host

    assert changes(deploy(sandbox, nodes_copy)) == {}


# Classroom accidents, healed by the next run
# -------------------------------------------


def test_a_workspace_chowned_to_root_is_given_back_and_said_so(classroom, sandbox, first_run, nodes_copy):
    host = "team1-main"
    sandbox.sudo(host, f"chown -R root:root {WORKSPACE}", check=True)

    healed = deploy(sandbox, nodes_copy)

    assert changed(healed, OWNED_OP) == {host}
    assert set(healed.changes_per_host()) == {host}  # the other hosts: nothing
    assert set(changes(healed)) <= {OWNED_OP} | {name for name in changes(healed) if DIRECTORY_OP in name}
    (said,) = output_lines(healed, host, "workspace:", "do not belong to")
    assert re.search(rf"workspace: \d+ paths in {WORKSPACE} do not belong to {LOGIN_USER} \(\.", said), said
    assert sandbox.sudo(host, f"find {WORKSPACE} ! -user {LOGIN_USER} -o ! -group {LOGIN_USER}").stdout == ""
    assert unit_state(sandbox, host) == "active"

    assert changes(deploy(sandbox, nodes_copy)) == {}


def test_a_node_with_a_syntax_error_fails_that_host_only_with_file_and_line(
    classroom, sandbox, first_run, nodes_copy, tmp_path,
):
    host = "team2-robot"
    broken = tmp_path / "nodes"
    shutil.copytree(nodes_copy, broken)
    talker = broken / "roslab_demo" / "roslab_demo" / "talker.py"
    good = talker.read_text()
    talker.write_text(good + "\n\ndef broken(:\n    pass\n")
    line = len(good.splitlines()) + 3
    last_build = fingerprint(sandbox, host)

    def roster_with(nodes_dir):
        def edit(data):
            data["classroom"]["workspace_nodes_dir"] = str(nodes_copy)
            data["teams"]["team2"]["hosts"][host]["workspace_nodes_dir"] = str(nodes_dir)
        return edit

    failed = deploy_with_roster(sandbox, tmp_path, roster_with(broken))

    assert failed.returncode != 0
    assert failed.failed_hosts == [host]
    located = output_lines(failed, f"{WORKSPACE}/src/roslab_demo/roslab_demo/talker.py:{line}: SyntaxError")
    assert located, failed.stdout[-3000:] + failed.stderr[-3000:]
    assert all(host in said for said in located)  # named with its host
    assert set(failed.changes_per_host()) <= {host}  # the other hosts: nothing
    assert changed(failed, SYNC_OP) == {host}  # the broken file is there to see...
    assert RESTART_OP not in changes(failed)  # ... but nothing restarted onto it
    assert unit_state(sandbox, host) == "active"  # the last good build keeps running
    assert fingerprint(sandbox, host) != last_build  # the stamp is gone: the next run retries

    talker.write_text(good)  # the teacher fixes the file
    fixed = deploy_with_roster(sandbox, tmp_path, roster_with(broken))

    assert fixed.returncode == 0, fixed.stderr[-6000:]
    assert changed(fixed, BUILD_OP) == {host}
    assert changed(fixed, RESTART_OP) == {host}
    assert set(fixed.changes_per_host()) == {host}
    assert unit_state(sandbox, host) == "active"
    assert changes(deploy(sandbox, nodes_copy)) == {}


@pytest.mark.parametrize(
    ("accident", "said"),
    [
        # systemd keeps the last run's result (exit-code) as the reason it gave up.
        (f"touch {LAUNCH_FAILS} && systemctl restart {SERVICE}", "is failed ("),
        (f"systemctl stop {SERVICE}", "is inactive (stopped)"),
    ],
    ids=["gave-up", "stopped"],
)
def test_a_unit_that_gave_up_or_was_stopped_is_started_by_the_next_run(
    classroom, sandbox, first_run, nodes_copy, accident, said,
):
    host = "team1-robot"
    sandbox.sudo(host, accident, check=True)
    # A launch failing at once: systemd restarts it 5 times, then gives up (start-limit-hit).
    wait_for_state(sandbox, host, "failed" if "failed" in said else "inactive")
    if "failed" in said:  # it gave up after its restarts, it did not just fail once
        restarts = sandbox.sudo(host, f"systemctl show -p NRestarts --value {SERVICE}").stdout.strip()
        assert int(restarts) >= 4, restarts
    sandbox.sudo(host, f"rm -f {LAUNCH_FAILS}", check=True)  # the cause is gone; the unit stays down
    time.sleep(2)
    assert unit_state(sandbox, host) in ("failed", "inactive")

    restarted = deploy(sandbox, nodes_copy)

    assert changes(restarted) == {f"Ensure {RESTART_OP}": {host}}  # that one step, that one host
    said_lines = output_lines(restarted, host, f"workspace: {SERVICE} {said}", "): starting it again")
    assert len(said_lines) == 1, output_lines(restarted, "workspace:")
    wait_for_state(sandbox, host, "active", timeout=30)
    assert changes(deploy(sandbox, nodes_copy)) == {}


# roslab verify
# -------------

# A ros2 that answers the verify check like a real one on the team's domain, as the login
# user and only without the daemon, with a greeting from `robot` (a team's own robot, or
# another team's when two teams share a domain).
VERIFY_ROS2 = """#!/bin/sh
# roslab e2e: a ros2 that answers `roslab verify` (see tests/e2e/test_workspace_e2e.py)
case "$1" in launch) exec sleep infinity ;; esac
[ "$1" = --help ] && exit 0
[ "$(id -un)" = {user} ] && [ "$ROS_DOMAIN_ID" = {domain} ] || exit 1
case " $* " in *" --no-daemon "*|" daemon "*) ;; *) echo "used the daemon" >&2; exit 1 ;; esac
case "$1 $2" in
  "topic list") printf '/chatter\\n/rosout\\n' ;;
  "topic echo") printf '%s\\n---\\n' 'Hello from {robot} #7' ;;
  "daemon status") echo 'The daemon is not running' ;;
esac
"""


def roslab_verify(sandbox):
    started = time.monotonic()
    proc = subprocess.run(
        [str(BIN / "roslab"), "verify", str(sandbox.roster_path)],
        cwd=REPO, env=sandbox.env, capture_output=True, text=True, timeout=600,
    )
    proc.seconds = time.monotonic() - started
    return proc


def test_verify_reads_the_robot_from_the_message_and_catches_crossed_domains(classroom, sandbox, first_run):
    teams = {team.name: team for team in classroom.teams}
    # team1-main hears its own robot; team2-main hears team1's robot: domains crossed.
    for team, robot in (("team1", "team1-robot"), ("team2", "team1-robot")):
        install_stand_in(sandbox, f"{team}-main", VERIFY_ROS2.format(
            user=LOGIN_USER, domain=teams[team].ros_domain_id, robot=robot))
    try:
        proc = roslab_verify(sandbox)
        print(f"roslab verify, answering stand-in: {proc.seconds:.1f} s")
    finally:
        for team in teams:
            install_stand_in(sandbox, f"{team}-main", STAND_IN_ROS2)
    rows = {line.split()[0]: line for line in proc.stdout.splitlines()[2:] if line.strip()}
    assert "PASS heard team1-robot" in rows["team1"], proc.stdout
    assert "FAIL heard 'team1-robot', which is not a robot of team team2 (team2-robot)" in rows["team2"]
    assert proc.returncode == 1 and "not verified: team2" in proc.stderr


def test_verify_says_the_sandbox_has_no_ros_runtime_instead_of_passing(classroom, sandbox, first_run):
    """`roslab verify` on stand-in ROS without a ros2 command: every team fails with the honest reason."""
    for host in names(classroom):
        sandbox.sudo(host, f"rm -f {stand_in_path(sandbox, host)}", check=True)
    try:
        proc = roslab_verify(sandbox)
        print(f"roslab verify, no ros2: {proc.seconds:.1f} s")
    finally:
        for host in names(classroom):
            install_stand_in(sandbox, host, STAND_IN_ROS2)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    for team in classroom.teams:
        main = next(host.name for host in team.hosts if host.role == "main")
        assert f"no ROS runtime on {main}: not verified" in proc.stdout, proc.stdout
    assert "not verified: team1, team2" in proc.stderr


# A ros2 on the main host whose robot stopped answering mid-verify: the topic is gone and
# `ros2 topic echo` never returns, ignoring SIGTERM (as one was seen to for 10 minutes).
SILENT_ROBOT_ROS2 = """#!/bin/sh
# roslab e2e: the robot stopped answering; this echo hears nothing and ignores SIGTERM
case "$1" in launch) exec sleep infinity ;; esac
[ "$1" = --help ] && exit 0
case "$1 $2" in
  "topic list") printf '/rosout\\n' ;;
  "topic echo") trap '' TERM; exec sleep 3600 ;;
  "daemon status") echo 'The daemon is not running' ;;
esac
"""


def test_verify_is_bounded_when_a_robot_stops_answering(classroom, sandbox, first_run):
    mains = [host.name for host in classroom.hosts if host.role == "main"]
    for main in mains:
        install_stand_in(sandbox, main, SILENT_ROBOT_ROS2)
    try:
        proc = roslab_verify(sandbox)
        print(f"roslab verify, robots silent: {proc.seconds:.1f} s")
        leftovers = {main: sandbox.sudo(main, "ps -eo args= | grep -c '^sleep 3600$' || true").stdout.strip()
                     for main in mains}
    finally:
        for main in mains:
            install_stand_in(sandbox, main, STAND_IN_ROS2)
    timeout = classroom.hosts[0].data["nodes_verify_timeout"]
    # Killed after its own timeout plus the kill grace, not hung for minutes.
    assert proc.seconds < timeout + verify.KILL_AFTER + 60, proc.seconds
    assert proc.returncode == 1, proc.stdout + proc.stderr
    for main in mains:
        assert f"{main} does not see /chatter" in proc.stdout, proc.stdout
    assert leftovers == {main: "0" for main in mains}  # nothing of the check left running
