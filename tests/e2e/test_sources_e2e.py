"""Source workspaces end to end: .repos files fetched once per class, built in the underlay.

Its own sandbox instance ($ROSLAB_SOURCES_E2E_SANDBOX, $ROSLAB_SOURCES_E2E_SUBNET), 3 hosts:
team1 (24.04: main + robot) builds two repositories, team2 (22.04: main) one of them. The
repositories are the sandbox upstream's stand-in git repositories (roslab/sandbox/git_standins.py,
served with git's dumb HTTP protocol under /git/, every request in its request log), each an
ament_python package whose console script prints that it is a stand-in; the sandbox roster's
`source_url_rewrites` points https://github.com/ at them, as a classroom points it at a local
git server. The controller's cache (`sources_cache_dir`) is the test's own folder.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import git_standins, upstream
from tests.e2e.conftest import bring_up, summary_lines

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_SOURCES_E2E_SANDBOX", "roslab-sources-e2e")
SUBNET = os.environ.get("ROSLAB_SOURCES_E2E_SUBNET", "10.213.151.0/24")
RELEASES = "24.04,22.04"
HOSTS = 3  # team1-main, team1-robot (24.04), team2-main (22.04)
LIDAR_URL = "https://github.com/roslab-standin/lidar_driver.git"
IMU_URL = "https://github.com/roslab-standin/imu_tools.git"
TEAM1 = {"team1-main", "team1-robot"}
UNDERLAY = "/home/ubuntu/roslab_underlay"


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases=RELEASES)
    try:
        yield classroom
    finally:
        teardown()


def served(sandbox) -> Path:
    return sandbox.instance.state_dir / "upstream"


def requests_since(sandbox, start: int) -> list:
    return upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG)[start:]


def request_count(sandbox) -> int:
    return len(upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG))


class Classroom:
    """The test's roster folder: the roster, the two teams' .repos files, the controller cache."""

    def __init__(self, sandbox, folder: Path):
        self.sandbox, self.folder = sandbox, folder
        self.roster = folder / "roster.yaml"
        self.lidar_bare, self.lidar_v1 = git_standins.standin_repository(
            served(sandbox), LIDAR_URL, "lidar_driver", tags=["v1.0.0"])
        _, self.imu_commit = git_standins.standin_repository(served(sandbox), IMU_URL, "imu_tools")
        self.write(lidar="v1.0.0")

    def write(self, lidar: str, offline: bool = False) -> None:
        imu = {"type": "git", "url": IMU_URL, "version": self.imu_commit}
        (self.folder / "team1.repos").write_text(yaml.safe_dump({"repositories": {
            "drivers/lidar_driver": {"type": "git", "url": LIDAR_URL, "version": lidar},
            "imu_tools": imu}}))
        (self.folder / "team2.repos").write_text(yaml.safe_dump({"repositories": {"imu_tools": imu}}))
        data = yaml.safe_load(self.sandbox.roster_path.read_text())
        data["classroom"]["sources_cache_dir"] = str(self.folder / "sources-cache")
        if offline:
            data["classroom"]["offline"] = True
        data["teams"]["team1"]["workspace_sources"] = ["team1.repos"]
        data["teams"]["team2"]["workspace_sources"] = ["team2.repos"]
        self.roster.write_text(yaml.safe_dump(data, sort_keys=False))

    def deploy(self):
        return self.sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(self.roster)})


def run_standin(sandbox, host: str, package: str):
    """The stand-in package's console script, as a student runs it: after sourcing the underlay."""
    return sandbox.ssh(host, f"bash -c 'source {UNDERLAY}/install/setup.bash && "
                             f"{UNDERLAY}/install/{package}/lib/{package}/{package}'", check=True).stdout


@pytest.fixture(scope="module")
def classroom(sandbox, tmp_path_factory):
    return Classroom(sandbox, tmp_path_factory.mktemp("sources"))


@pytest.fixture(scope="module")
def first_run(sandbox, classroom):
    start = request_count(sandbox)
    run = classroom.deploy()
    return run, requests_since(sandbox, start)


def git_requests(requests, url: str) -> list:
    prefix = "/" + git_standins.served_path(url) + "/"
    return [request for request in requests if request.path.startswith(prefix)]


def test_the_class_converges_fetching_each_repository_once_and_a_rerun_changes_nothing(
        sandbox, classroom, first_run):
    run, requests = first_run
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.failed_hosts == []
    # Once per class, not per host: two hosts need the lidar and three the IMU, yet each
    # object of each repository was downloaded once (dumb HTTP: one request per object).
    for url in (LIDAR_URL, IMU_URL):
        fetched = [r.path for r in git_requests(requests, url) if "/objects/" in r.path and r.status == 200]
        assert fetched, (url, [r.path for r in requests][-20:])
        assert len(fetched) == len(set(fetched)), url
        # git asks info/refs (?service=git-upload-pack first: a dumb server answers with the file)
        refs = [r for r in git_requests(requests, url) if "/info/refs" in r.path]
        assert 1 <= len(refs) <= 2, refs  # ls-remote (a tag) and the fetch: for the class, not per host
    # no host asked the upstream's git server anything: only the controller did
    hosts = {host.address for host in sandbox.hosts}
    assert not [r for r in requests if r.path.startswith("/git/") and r.client in hosts]

    start = request_count(sandbox)
    again = classroom.deploy()
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed
    # a commit pin in the mirror asks nothing; a tag pin asks whether it moved (git ls-remote:
    # info/refs and HEAD over dumb HTTP), and downloads nothing
    again_git = [r.path for r in requests_since(sandbox, start) if r.path.startswith("/git/")]
    assert not [path for path in again_git if "/objects/" in path], again_git
    assert not git_requests(requests_since(sandbox, start), IMU_URL)


def test_the_underlay_is_built_and_the_students_workspace_overlays_it(sandbox, first_run):
    for host in ("team1-robot", "team1-main"):
        assert "roslab sandbox stand-in: lidar_driver" in run_standin(sandbox, host, "lidar_driver")
    assert sandbox.ssh("team2-main", f"test -e {UNDERLAY}/install/lidar_driver").returncode != 0
    assert "stand-in: imu_tools" in run_standin(sandbox, "team2-main", "imu_tools")
    # the student's shell, the nodes' unit: the underlay before the workspace
    bashrc = sandbox.ssh("team1-robot", "cat ~/.bashrc", check=True).stdout
    assert bashrc.index("roslab_underlay/install/setup.bash") < bashrc.index("ros2_ws/install/setup.bash")
    shell = sandbox.ssh("team1-robot", "bash -ic 'echo $AMENT_PREFIX_PATH' 2>/dev/null", check=True).stdout
    assert f"{UNDERLAY}/install" in shell and "lidar_driver" in shell, shell
    unit = sandbox.ssh("team1-robot", "systemctl show -p ExecStart roslab-nodes", check=True).stdout
    assert "roslab_underlay/install/setup.bash" in unit


def test_a_changed_pin_rebuilds_only_the_workspaces_that_use_it(sandbox, classroom, first_run):
    git_standins.commit(classroom.lidar_bare, git_standins.package_files(
        "lidar_driver", ["lidar_driver"], marker="v1.1.0"), "v1.1.0", ["v1.1.0"])
    classroom.write(lidar="v1.1.0")
    run = classroom.deploy()
    assert run.returncode == 0, run.stderr[-3000:]
    assert set(run.changes_per_host()) <= TEAM1, run.changed
    assert any("underlay" in name and "colcon" in name and hosts == TEAM1 for name, hosts in run.changed.items()), \
        run.changed
    assert "v1.1.0" in run_standin(sandbox, "team1-robot", "lidar_driver")


def test_a_failing_build_fails_its_hosts_naming_the_package_and_keeps_the_last_good_install(
        sandbox, classroom, first_run):
    broken = git_standins.package_files("lidar_driver", ["lidar_driver"])
    # a file the package installs is missing: setuptools' "error: can't copy ..." in colcon's log
    broken["lidar_driver/setup.py"] = broken["lidar_driver/setup.py"].replace(
        "['package.xml']", "['package.xml', 'missing.yaml']")
    git_standins.commit(classroom.lidar_bare, broken, "broken", ["v1.2.0"])
    before = sandbox.ssh("team1-robot", f"readlink {UNDERLAY}/install", check=True).stdout.strip()
    classroom.write(lidar="v1.2.0")
    run = classroom.deploy()
    assert run.returncode != 0
    assert sorted(run.failed_hosts) == sorted(TEAM1), run.failed_hosts
    assert "package lidar_driver failed to build: error: can't copy 'missing.yaml'" in run.stderr, \
        run.stderr[-3000:]
    assert sandbox.ssh("team1-robot", f"readlink {UNDERLAY}/install", check=True).stdout.strip() == before
    assert "v1.1.0" in run_standin(sandbox, "team1-robot", "lidar_driver")  # the last good build, in use
    classroom.write(lidar="v1.1.0")
    assert classroom.deploy().returncode == 0


def test_an_unreachable_repository_fails_only_the_hosts_that_need_it_naming_it(sandbox, classroom, first_run):
    hidden = classroom.lidar_bare.with_name("hidden.git")
    classroom.lidar_bare.rename(hidden)
    try:
        classroom.write(lidar="v1.1.0")  # a tag: the controller must ask whether it moved
        run = classroom.deploy()
        assert sorted(run.failed_hosts) == sorted(TEAM1), (run.failed_hosts, run.stderr[-3000:])
        assert "repository 'drivers/lidar_driver'" in run.stderr
        assert "team2-main" not in run.failed_hosts
    finally:
        hidden.rename(classroom.lidar_bare)


def test_offline_the_class_converges_from_the_controllers_cache(sandbox, classroom, first_run):
    classroom.write(lidar="v1.1.0", offline=True)
    start = request_count(sandbox)
    run = classroom.deploy()
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.changed == {}, run.changed
    assert not [r for r in requests_since(sandbox, start) if r.path.startswith("/git/")]
    shutil.rmtree(classroom.folder / "sources-cache" / "git")  # what offline cannot do without
    run = classroom.deploy()
    # every host stopped while planning: pyinfra then ends without its JSON report, so the
    # run summary is what says it
    assert run.returncode != 0
    assert "offline, and the controller's cache" in run.stderr, run.stderr[-3000:]
    lines = summary_lines(run.stderr)
    for host in sorted(TEAM1 | {"team2-main"}):
        assert any(line.startswith(host + " ") and "failed" in line for line in lines), lines
