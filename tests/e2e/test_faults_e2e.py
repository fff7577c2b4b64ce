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
  host, and the next run is a no-op.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from roslab.sources import fetch as source_fetch
from roslab.sandbox import git_standins, upstream
from tests.e2e.conftest import bring_up, summary_lines

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
    assert sandbox.ssh(ROBOT, f"test -e /etc/systemd/system/{SERVICE}.service").returncode != 0
    assert sandbox.ssh(ROBOT, f"systemctl is-active {SERVICE}.service").stdout.strip() != "active"
    assert "dialout" not in sandbox.ssh(ROBOT, "id -nG ubuntu", check=True).stdout.split()
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, (again.changed, again.stderr[-3000:])
    assert "faults_bot -> demo" not in again.stderr
