"""The ROS apt source's snapshot mode end to end (issue 39): a class installing from a dated
snapshot of the ROS archive keeps that sync's versions while packages.ros.org moves on.

On the session's converged default class (restored: team1 on 24.04/Jazzy, team2 on 22.04/Humble),
with a copy of its roster switched to snapshot mode from the sandbox's STAND-IN snapshot server
(`upstream.yaml`: /ros-snapshots/<distro>/<date>/ubuntu, the ROS archive as `up` built it, signed
with the sandbox's ROS key; roslab checks snapshots.ros.org's own key only for that server, which
the unit tests cover):

- one run moves every host's ROS source to its distro's snapshot: ros2-apt-source purged, the
  snapshot's key in the ROS keyring, a deb822 source naming <server>/<distro>/<date>/ubuntu, the
  apt lists updated; nothing else changes, and the next run changes nothing;
- the upstream moves (`roslab sandbox publish ros-jazzy-desktop --bump`: the stand-in
  packages.ros.org then lists only the newer version, as after a sync): apt on a Jazzy host
  still lists the snapshot's version and nothing newer, so a re-imaged Pi would install the
  version its teammates have.

The publish is reverted when the module ends (`roslab sandbox publish --revert`).
"""

from __future__ import annotations

import pytest
import yaml

pytestmark = pytest.mark.e2e

BUMPED = "ros-jazzy-desktop"
JAZZY_HOST = "team1-main"
DISTROS = {"team1-main": "jazzy", "team1-robot": "jazzy", "team2-main": "humble", "team2-robot": "humble"}


@pytest.fixture(scope="module")
def sandbox(default_class_publishing):
    """The converged default class; the archives as `up` served them again after the module."""
    return default_class_publishing


@pytest.fixture(scope="module")
def snapshot(sandbox) -> dict:
    """The stand-in snapshot server's settings, as `up` wrote them for a roster to copy."""
    settings = yaml.safe_load((sandbox.instance.state_dir / "upstream.yaml").read_text())
    return {key: value for key, value in settings.items() if key.startswith("ros_apt_snapshot")}


@pytest.fixture(scope="module")
def roster(sandbox, snapshot, tmp_path_factory):
    document = yaml.safe_load(sandbox.roster_path.read_text())
    document["classroom"].update(ros_apt_source_mode="snapshot", **snapshot)
    path = tmp_path_factory.mktemp("snapshot") / "classroom.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def deploy(sandbox, roster):
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def policy(sandbox, host: str, package: str) -> str:
    return sandbox.sudo(host, f"apt-get update -qq && apt-cache policy {package}", check=True).stdout


@pytest.fixture(scope="module")
def switched(sandbox, roster):
    return deploy(sandbox, roster)


def test_one_run_moves_every_hosts_ros_source_to_its_distros_snapshot_and_the_next_changes_nothing(
        sandbox, snapshot, roster, switched):
    assert switched.returncode == 0, switched.stderr[-6000:]
    steps = sorted(switched.changed)
    assert len(steps) == 4 and all(switched.changed[step] == set(DISTROS) for step in steps), switched.changed
    assert any("ros2-apt-source package is not installed" in step for step in steps), steps
    assert any("signing key is in the ROS 2 keyring" in step for step in steps), steps
    assert any("ROS 2 apt source points at the ROS" in step for step in steps), steps
    assert any("apt lists are updated after a source change" in step for step in steps), steps  # the one update
    for host, distro in DISTROS.items():
        source = sandbox.ssh(host, "cat /etc/apt/sources.list.d/ros2.sources", check=True).stdout
        url = f"{snapshot['ros_apt_snapshot_url']}/{distro}/{snapshot['ros_apt_snapshot']}/ubuntu"
        assert f"URIs: {url}" in source.splitlines(), source
        assert sandbox.ssh(host, "dpkg-query -W ros2-apt-source 2>/dev/null").returncode != 0

    again = deploy(sandbox, roster)

    assert again.returncode == 0 and again.changed == {}, again.changed


def test_after_an_upstream_sync_apt_still_offers_only_the_snapshots_version(sandbox, snapshot, switched):
    before = policy(sandbox, JAZZY_HOST, BUMPED)
    published = sandbox.roslab("sandbox", "publish", BUMPED, "--bump")
    assert published.returncode == 0, published.stderr
    (line,) = [line for line in published.stdout.splitlines() if line.startswith(f"published {BUMPED} ")]
    old, new = line.split()[2], line.split()[4]  # "published PACKAGE OLD -> NEW (ROS noble)"

    after = policy(sandbox, JAZZY_HOST, BUMPED)

    assert f"Candidate: {old}" in after and new not in after, after
    assert f"{snapshot['ros_apt_snapshot_url']}/jazzy/{snapshot['ros_apt_snapshot']}/ubuntu" in after, after
    assert after == before, (before, after)
