"""Faults of the controller's source cache that a re-run must heal, or refuse in one true line.

Its own sandbox instance ($ROSLAB_FAULTS_E2E_SANDBOX, $ROSLAB_FAULTS_E2E_SUBNET), 2 hosts (team1's
main and robot, demo profile), both building the class's own tools (`workspace_sources`: a
stand-in repository pinned to a tag, roslab/sandbox/git_standins.py) in their underlay. The
roster switches off the concerns these faults do not touch, so each run stays short; the steps
that remain (apt, the ROS packages, the sources) run as in any class.

What a teacher notices, checked here:
- a converged class's re-run asks the git upstream nothing, and goes on when upstream is down;
- a damaged mirror in the controller's cache is moved aside, named once, fetched afresh;
- a truncated or deleted lock file stops the hosts that need sources, naming the file, and is
  never rebuilt from what upstream says now (a tag moved meanwhile is not taken);
- a team switching profile (the roster's own `faults_bot`, whose robot has a service and the
  dialout group, to demo) loses the old profile's unit and group, is told so in one line per
  host, and the next run is a no-op;
- a host whose power is cut in the middle of a step (held there by something the test holds on
  the host, never by a race with a sleep), while roslab reads it or while a step runs a command,
  is named in the summary in one line as lost in that step; the other host converges; once it is
  powered on again one re-run heals it and the next is a no-op;
- two runs at once (two teachers): the second waits for the host's run lock for run_lock_wait
  seconds, then stops each host in one line naming the first run (controller, user, pid, start);
  the first run ends as if alone, and the next run is a no-op with no lock left behind;
- a controller killed (SIGKILL) after a host applied a network change and before the change was
  confirmed: one re-run inside the host's confirmation window finds it at its new address (the
  inventory tries it when the old one does not answer), confirms the change and says so in one
  line; the one after is a no-op.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from roslab.sources import fetch as source_fetch
from roslab.ssh import keepalive as ssh_keepalive
from roslab.network import state as network_state
from roslab.network.confirm import ROLLBACK_GRACE
from roslab.sandbox import git_standins, hosts, lifecycle, upstream
from roslab.reporting.summary import LOST_CONNECTION
from tests.e2e.conftest import BIN, REPO, bring_up, summary_lines

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_FAULTS_E2E_SANDBOX", "faults-e2e")
SUBNET = os.environ.get("ROSLAB_FAULTS_E2E_SUBNET", "10.213.151.0/24")
HOSTS = 2
TOOLS_URL = "https://github.com/roslab-standin/faults_tools.git"
TAG = "v1.0.0"
ROBOT = "team1-robot"
SERVICE = "faults_bot_driver"
# The team's first profile: the demo's, plus what a robot's driver brings (a unit, a group).
FAULTS_BOT = {"extends": "demo", "robot": {"groups": ["dialout"], "services": [
    {"name": SERVICE, "description": "a stand-in driver that only sleeps", "command": "sleep infinity"}]}}
# The concerns these faults do not touch (each a teacher's own switch).
SWITCHED_OFF = ("locale", "rosdep", "python_env", "shell_env", "discovery", "ssh_identity", "ssh_hardening",
                "network", "workspace")


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS)
    try:
        yield classroom
    finally:
        teardown()


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("faults")
    git_standins.standin_repository(sandbox.instance.state_dir / "upstream", TOOLS_URL, "faults_tools", tags=[TAG])
    (folder / "class.repos").write_text(yaml.safe_dump({"repositories": {
        "faults_tools": {"type": "git", "url": TOOLS_URL, "version": TAG}}}))
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"].update({f"{concern}_enabled": False for concern in SWITCHED_OFF})
    data["classroom"].update(sources_cache_dir=str(folder / "sources-cache"), workspace_sources=["class.repos"],
                             sources_rosdep_install=False)
    data["profiles"] = {"faults_bot": FAULTS_BOT}
    data["teams"]["team1"]["robot_profile"] = "faults_bot"
    path = folder / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy(sandbox, roster: Path):
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def cache(roster: Path) -> Path:
    return roster.parent / "sources-cache"


def git_requests_since(sandbox, start: int) -> list:
    requests = upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG)[start:]
    return [request.path for request in requests if request.path.startswith("/git/")]


def request_count(sandbox) -> int:
    return len(upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG))


def served(sandbox) -> Path:
    return sandbox.instance.state_dir / "upstream" / git_standins.served_path(TOOLS_URL)


def built_marker(sandbox, host: str) -> str:
    """The underlay's record of what it holds (path -> sha256 of the archive)."""
    return sandbox.ssh(host, "cat /home/ubuntu/roslab_underlay/.roslab/sources.json", check=True).stdout


@pytest.fixture(scope="module")
def converged(sandbox, roster):
    run = deploy(sandbox, roster)
    assert run.returncode == 0, run.stderr[-4000:]
    assert (cache(roster) / source_fetch.LOCK_NAME).is_file()
    return {host.name: built_marker(sandbox, host.name) for host in sandbox.hosts}


def test_a_converged_class_asks_the_git_upstream_nothing_even_when_it_is_down(sandbox, roster, converged):
    hidden = served(sandbox).with_name("hidden.git")
    served(sandbox).rename(hidden)  # upstream down: any request for the repository would fail
    try:
        start = request_count(sandbox)
        again = deploy(sandbox, roster)
        assert again.returncode == 0, again.stderr[-3000:]
        assert again.changed == {}, again.changed
        assert git_requests_since(sandbox, start) == []
        assert "cannot be reached" not in again.stderr
    finally:
        hidden.rename(served(sandbox))


def corrupt_commit(mirror: Path, commit: str) -> None:
    """Damage the object that holds `commit`: its loose file, else the pack that has it."""
    loose = mirror / "objects" / commit[:2] / commit[2:]
    if loose.is_file():
        loose.chmod(0o644)
        loose.write_bytes(b"x\x01 not zlib")
        return
    for pack in (mirror / "objects" / "pack").glob("*.pack"):
        pack.chmod(0o644)
        pack.write_bytes(pack.read_bytes()[: pack.stat().st_size // 2])


def test_a_damaged_mirror_is_moved_aside_named_once_and_fetched_afresh(sandbox, roster, converged):
    lock = (cache(roster) / source_fetch.LOCK_NAME).read_text()
    commit = yaml.safe_load(lock)[TOOLS_URL]["tags"][TAG]
    mirror = source_fetch.mirror_path(cache(roster), TOOLS_URL)
    corrupt_commit(mirror, commit)
    run = deploy(sandbox, roster)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.changed == {}, run.changed  # the same archive reached the hosts: nothing to do
    named = [line for line in run.stderr.splitlines() if "moved aside" in line]
    aside = [path for path in mirror.parent.iterdir() if path.name.startswith(mirror.name + ".damaged-")]
    assert len(named) == 1 and len(aside) == 1 and str(aside[0]) in named[0], (named, aside)
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, again.stderr[-3000:]
    assert "moved aside" not in again.stderr


def test_a_truncated_or_deleted_lock_stops_the_hosts_naming_it_and_a_moved_tag_is_not_taken(
        sandbox, roster, converged):
    lock_path = cache(roster) / source_fetch.LOCK_NAME
    kept = lock_path.read_text()
    bare = served(sandbox)
    before = git_standins._git("--git-dir", bare, "rev-parse", f"refs/tags/{TAG}")
    git_standins.commit(bare, git_standins.package_files("faults_tools", ["faults_tools"], marker="moved"),
                        "someone moved the tag", [TAG], move_tags=True)
    try:
        for damage, words in (("truncated", "is damaged"), ("deleted", "is missing")):
            if damage == "truncated":
                lock_path.write_text(kept[: len(kept) // 2])
            else:
                lock_path.unlink()
            run = deploy(sandbox, roster)
            # every host stops while planning (both build the class's tools), naming the file
            assert run.returncode != 0, run.stderr[-3000:]
            lines = summary_lines(run.stderr)
            for host in sandbox.hosts:
                assert any(line.startswith(host.name + " ") and "failed" in line for line in lines), lines
            assert sum(f"the lock file {lock_path} {words}" in line for line in run.stderr.splitlines()) >= 2
            assert not lock_path.exists() or lock_path.read_text() != kept  # not rebuilt from upstream
        assert {host.name: built_marker(sandbox, host.name) for host in sandbox.hosts} == converged
        # the teacher restores the lock from a backup: the class is converged as before, the moved
        # tag is not taken (the class's pins did not change)
        lock_path.write_text(kept)
        healed = deploy(sandbox, roster)
        assert healed.returncode == 0 and healed.changed == {}, healed.stderr[-3000:]
    finally:
        git_standins._git("--git-dir", bare, "tag", "-f", TAG, before)
        git_standins._git("--git-dir", bare, "update-server-info")


def test_a_team_switching_profile_loses_the_old_units_and_groups_says_so_once_then_nothing(
        sandbox, roster, converged):
    assert sandbox.ssh(ROBOT, f"systemctl is-active {SERVICE}.service").stdout.strip() == "active"
    assert "dialout" in sandbox.ssh(ROBOT, "id -nG ubuntu", check=True).stdout.split()
    data = yaml.safe_load(roster.read_text())
    data["teams"]["team1"]["robot_profile"] = "demo"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))
    run = deploy(sandbox, roster)
    assert run.returncode == 0, run.stderr[-3000:]
    said = [line for line in run.stderr.splitlines() if "robot profile faults_bot -> demo" in line]
    assert len(said) == 1 and ROBOT in said[0], said
    assert f"removed {SERVICE}.service; ubuntu from groups dialout" in said[0], said
    # The class's workspace_sources keep the underlay sourced: no line may tell to delete it.
    assert "underlay" not in said[0] and "no longer source" not in run.stderr, said
    assert json.loads(sandbox.ssh(ROBOT, "cat /var/lib/roslab/profile.json", check=True).stdout)["sources"] is True
    assert sandbox.ssh(ROBOT, f"test -e /etc/systemd/system/{SERVICE}.service").returncode != 0
    assert sandbox.ssh(ROBOT, f"systemctl is-active {SERVICE}.service").stdout.strip() != "active"
    assert "dialout" not in sandbox.ssh(ROBOT, "id -nG ubuntu", check=True).stdout.split()
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])
    assert "faults_bot -> demo" not in again.stderr


# dpkg's record of ros2-apt-source as a run killed in its `dpkg -i` leaves it: reinst-required.
HALF_INSTALL_APT_SOURCE = (
    "python3 -c \"import re; p = '/var/lib/dpkg/status'; s = open(p).read(); "
    "s = re.sub(r'(Package: ros2-apt-source\\n(?:.+\\n)*?)Status: .*', "
    "r'\\1Status: install reinstreq half-installed', s, count=1); open(p, 'w').write(s)\"")


def test_a_package_left_half_installed_that_no_archive_holds_heals_in_one_run(sandbox, roster, converged):
    """ros2-apt-source comes from its .deb, not an archive: a run interrupted in its dpkg -i leaves
    it reinst-required, and then every apt-get stops ("needs to be reinstalled, but I can't find
    an archive for it"). One re-run removes it and installs it again; the next changes nothing."""
    sandbox.sudo(ROBOT, HALF_INSTALL_APT_SOURCE, check=True)
    stuck = sandbox.sudo(ROBOT, "apt-get -s install curl")
    assert "can't find an archive for it" in stuck.stdout + stuck.stderr, stuck
    run = deploy(sandbox, roster)
    assert run.returncode == 0 and not run.failed_hosts, run.stderr[-3000:]
    assert set(run.changes_per_host()) == {ROBOT}, run.changed
    state = sandbox.ssh(ROBOT, "dpkg-query -W -f '${db:Status-Abbrev}' ros2-apt-source", check=True).stdout
    assert state.strip() == "ii", state
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])


# Issue 28: a host lost in the middle of a step, a controller killed in the middle of a network
# change. Each test leaves the class as it found it (hosts running at their roster addresses,
# converged), also when it fails.

MAIN = "team1-main"


def start_deploy(sandbox, roster: Path) -> subprocess.Popen:
    """deploy.py on the class as a teacher runs it, in the background (the test acts meanwhile);
    its output goes to a file, so a full pipe never holds it."""
    output = tempfile.TemporaryFile("w+")
    run = subprocess.Popen([str(BIN / "pyinfra"), "-y", "inventories/lab.py", "deploy.py"], cwd=REPO,
                           env={**sandbox.env, "ROSLAB_ROSTER": str(roster)},
                           stdout=subprocess.DEVNULL, stderr=output, text=True)
    run.output = output
    return run


def finished(run: subprocess.Popen) -> str:
    """The run's output once it ended by itself."""
    run.wait(timeout=300)
    run.output.seek(0)
    return run.output.read()


def ended(run: subprocess.Popen) -> None:
    """A run still going when a test fails is killed, so nothing of it outlives the test."""
    if run.poll() is None:
        run.kill()
    run.wait()
    run.output.close()


def host_root(sandbox, host: str) -> Path | None:
    """The host's / as this machine sees it (through its PID 1), or None when it is off."""
    pid = hosts.container_init_pid(sandbox.instance, host)
    return Path(f"/proc/{pid}/root") if pid is not None else None


def wait_for(predicate, seconds: float, what: str, run: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert run is None or run.poll() is None, f"the run ended (exit {run.returncode}) before {what}"
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.2)


def powered_on(sandbox, host: str) -> None:
    if not hosts.is_running(sandbox.instance, host):
        lifecycle.power_on(host, sandbox.instance)


def lines_naming(stderr: str, host: str) -> list[str]:
    return [line for line in summary_lines(stderr) if line.split(" ", 1)[0] == host]


# What holds a host in the middle of a step until its power is cut, by when it holds it: (the
# command that arms it on the host, how the test sees the host held, the command that disarms
# it, the step the summary names).
DPKG_HELD_UNIT = "roslab-faults-e2e-dpkg-held"
APT_GATE = "/run/roslab-faults-e2e-gate"
APT_GATE_CONF = "/etc/apt/apt.conf.d/00-roslab-faults-e2e-gate"
HOLDS = {
    # roslab reads the host in one command (the probe), whose apt-get check waits for the dpkg
    # lock (apt_lock_timeout): the test holds that lock.
    "while roslab reads it": (
        f"systemd-run --unit={DPKG_HELD_UNIT} --collect python3 -c 'import fcntl, time; "
        "lock = open(\"/var/lib/dpkg/lock-frontend\", \"w\"); fcntl.lockf(lock, fcntl.LOCK_EX); "
        "time.sleep(3600)'",
        lambda sandbox, host: sandbox.ssh(host, "pgrep -x apt-get").returncode == 0,
        f"systemctl stop {DPKG_HELD_UNIT} 2>/dev/null; true",
        "The host runs an Ubuntu release that has packages for its ROS 2 distro",
    ),
    # a step running a command: the lists made stale, apt-get update runs its Pre-Invoke hook,
    # which waits on a FIFO nobody writes.
    "while a step runs a command": (
        f"mkfifo -m 0600 {APT_GATE} && printf '%s\\n' "
        f"'APT::Update::Pre-Invoke {{\"touch {APT_GATE}.reached; cat {APT_GATE}\";}};' > {APT_GATE_CONF} && "
        "rm -f /var/lib/apt/periodic/update-success-stamp",
        lambda sandbox, host: (root := host_root(sandbox, host)) is not None
        and (root / f"{APT_GATE.lstrip('/')}.reached").exists(),
        # (a host still running lets its held hook go: opened for writing too, the FIFO ends its `cat`)
        f"rm -f {APT_GATE_CONF}; if [ -p {APT_GATE} ]; then : <> {APT_GATE}; fi; rm -f {APT_GATE} {APT_GATE}.reached",
        "The apt lists are fresh: one apt-get update after every source is written",
    ),
}


def set_link(sandbox, host: str, state: str) -> None:
    netns = sandbox.instance.netns(sandbox.host(host))
    subprocess.run(["ip", "-n", netns, "link", "set", "eth0", state], check=True)


@pytest.mark.parametrize("when, silently", [
    ("while roslab reads it", False),
    ("while a step runs a command", False),
    # A Pi's power cut sends nothing, not even the end of its connections (the container's kill
    # would): its link goes first. The run must not wait for it forever (roslab.ssh.keepalive).
    ("while a step runs a command", True),
], ids=["reading", "step", "step-silent"])
def test_a_host_losing_its_power_mid_step_is_named_lost_in_that_step_and_one_rerun_heals_it(
        sandbox, roster, converged, when, silently):
    arm, held, disarm, step = HOLDS[when]
    sandbox.sudo(MAIN, arm, check=True)
    run = start_deploy(sandbox, roster)
    try:
        wait_for(lambda: held(sandbox, MAIN), 120, f"{MAIN} to be held {when}", run)
        if silently:
            set_link(sandbox, MAIN, "down")
        lifecycle.power_cut(MAIN, sandbox.instance)
        cut = time.monotonic()
        stderr = finished(run)
        assert time.monotonic() - cut < ssh_keepalive.SILENT_FOR + 30  # found lost in seconds
    finally:
        ended(run)
        if silently:
            set_link(sandbox, MAIN, "up")
        powered_on(sandbox, MAIN)
        sandbox.sudo(MAIN, disarm)
    assert run.returncode == 1, stderr[-3000:]
    (line,) = lines_naming(stderr, MAIN)
    assert line.startswith(f'{MAIN} failed in "{step}'), line
    assert line.endswith(f": {LOST_CONNECTION}"), line  # nothing of pyinfra's own words
    assert lines_naming(stderr, ROBOT) == [f"{ROBOT} ok"], summary_lines(stderr)  # the other host carried on

    healed = deploy(sandbox, roster)
    assert healed.returncode == 0, healed.stderr[-3000:]
    assert set(healed.changes_per_host()) <= {MAIN}, healed.changed
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])


def test_two_runs_at_once_the_second_stops_naming_the_first_and_one_rerun_after_it_is_a_no_op(
        sandbox, roster, converged):
    # The first run is held in its apt step on the main (the gate above), holding both hosts' run lock.
    arm, held, disarm, _ = HOLDS["while a step runs a command"]
    impatient = roster.parent / "impatient.yaml"
    data = yaml.safe_load(roster.read_text())
    data["classroom"]["run_lock_wait"] = 3
    impatient.write_text(yaml.safe_dump(data, sort_keys=False))
    sandbox.sudo(MAIN, arm, check=True)
    first = start_deploy(sandbox, roster)
    try:
        wait_for(lambda: held(sandbox, MAIN), 120, f"{MAIN} to be held in its apt step", first)
        owner = sandbox.ssh(MAIN, "cat /run/roslab/run.owner", check=True).stdout.strip()
        assert "(user " in owner and f", pid {first.pid}, started " in owner, owner
        second = deploy(sandbox, impatient)
        sandbox.sudo(MAIN, disarm, check=True)
        stderr = finished(first)
    finally:
        ended(first)
        sandbox.sudo(MAIN, disarm)
    assert second.returncode == 1, second.stderr[-3000:]
    (line,) = lines_naming(second.stderr, MAIN)
    assert f"another roslab run holds this host: {owner}; waited 3 s (run_lock_wait)" in line, line
    assert "roslab-new" not in second.stderr
    assert first.returncode == 0, stderr[-3000:]  # the first run never saw the second
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])
    # no stale lock: a run's holder sees its session end within its poll (2 s)
    wait_for(lambda: sandbox.sudo(MAIN, "flock -n /run/roslab/run.lock true").returncode == 0, 15,
             "the last run's lock to go with its session")


def answers_ssh(address: str) -> bool:
    try:
        with socket.create_connection((address, 22), timeout=3):
            return True
    except OSError:
        return False


def network_status(sandbox, host: str) -> dict:
    """The host's status file of its last network change (roslab.network.apply)."""
    root = host_root(sandbox, host)
    try:
        return json.loads((root / "run/roslab/network/status.json").read_text()) if root else {}
    except (OSError, ValueError):
        return {}


CONFIRM_TIMEOUT = 120  # the host's window: a run started right after the kill connects well within it


def network_roster(sandbox, roster: Path, address: str) -> Path:
    """The class's roster with the robot's static address: beside the sandbox's own roster, whose
    known_hosts (and so every address the robot gets) it shares."""
    folder = sandbox.instance.state_dir
    (folder / "class.repos").write_text((roster.parent / "class.repos").read_text())
    data = yaml.safe_load(roster.read_text())
    data["classroom"]["network_enabled"] = True
    data["teams"]["team1"]["hosts"][ROBOT].update(
        network_address=f"{address}/{sandbox.instance.subnet.prefixlen}",
        network_gateway=str(next(sandbox.instance.subnet.hosts())), network_ipv6="ignore",
        network_confirm_timeout=CONFIRM_TIMEOUT)
    path = folder / "roster-faults-network.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_controller_killed_mid_network_change_one_rerun_in_its_window_confirms_it_then_nothing(
        sandbox, roster, converged):
    robot = sandbox.host(ROBOT)
    old = robot.address
    new = str(sandbox.instance.subnet.network_address + 77)
    moving = network_roster(sandbox, roster, new)
    blackhole = ["ip", "route", "add", "blackhole", f"{new}/32"]
    # The controller cannot reach the new address (a switch that does not carry it yet), so the
    # host waits in its confirmation window for as long as the test needs to kill the controller.
    subprocess.run(blackhole, check=True)
    run = start_deploy(sandbox, moving)
    try:
        wait_for(lambda: network_status(sandbox, ROBOT).get("state") == "waiting-for-confirmation", 180,
                 f"{ROBOT} to wait for its network change's confirmation", run)
        assert network_state.pending_changes(moving)[ROBOT]["to"] == new  # launched, not confirmed
        run.send_signal(signal.SIGKILL)
        run.wait(timeout=60)
        subprocess.run(["ip", "route", "del", "blackhole", f"{new}/32"], check=True)

        # In the window: the host waits at its new address; one re-run finds it there and confirms.
        healed = deploy(sandbox, moving)
        assert healed.returncode == 0, healed.stderr[-3000:]
        said = [line for line in healed.stderr.splitlines() if "network: found at" in line]
        assert len(said) == 1 and f"[{ROBOT}]" in said[0], said
        assert f"found at {new} waiting for the confirmation of a change an earlier run started (its controller " \
               "stopped during it): confirmed now, the host keeps it" in said[0], said[0]
        assert lines_naming(healed.stderr, MAIN) == [f"{MAIN} ok"]
        assert network_status(sandbox, ROBOT).get("state") == "confirmed"
        assert network_state.last_known_address(moving, ROBOT) == new and answers_ssh(new) and not answers_ssh(old)
        assert network_state.pending_changes(moving) == {}
        again = deploy(sandbox, moving)
        assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])
        assert "network: found at" not in again.stderr
    finally:
        ended(run)
        subprocess.run(["ip", "route", "del", "blackhole", f"{new}/32"], capture_output=True)
        back_to_its_roster_address(sandbox, roster, moving, old, new)


def back_to_its_roster_address(sandbox, roster: Path, moving: Path, old: str, new: str) -> None:
    """The robot at its roster address again for the class's other rosters (whose state does not
    know it moved): once a change in flight ended, moved back by the same deploy if it is elsewhere."""
    deadline = time.monotonic() + CONFIRM_TIMEOUT + ROLLBACK_GRACE
    while network_status(sandbox, ROBOT).get("state") in ("applying", "waiting-for-confirmation") \
            and time.monotonic() < deadline:
        time.sleep(1)
    if not answers_ssh(old):
        back = deploy(sandbox, network_roster(sandbox, roster, old))
        assert answers_ssh(old), back.stderr[-3000:]
    moving.unlink(missing_ok=True)
