"""The class lock end to end (issue 39): one set of versions per group, moved only on purpose.

On the session's converged default class (restored: team1 on 24.04/Jazzy, team2 on 22.04/Humble),
with a copy of its roster in a folder of the test's, as a teacher keeps one in git:

- with `class_lock_auto: true` and no lock, a no-op run writes a group per (distro, architecture)
  itself, from a host of each, in one line; the next run pins the hosts and does not rewrite it,
  the one after changes nothing (in a folder of its own; its pins are removed after);
- `roslab lock` writes classroom.lock beside the roster, a group per (distro, architecture), taken
  from a host of each; the next run pins every host to it, the one after changes nothing;
- the sandbox's upstream moves (`roslab sandbox publish PACKAGE --bump`): a newer ros-jazzy-desktop,
  whose index then lists only the newer version (as packages.ros.org does after a sync), and a
  newer python3-colcon-core in every release's -updates suite (as an Ubuntu update);
- the no-op stays a no-op; a re-imaged robot converges to the locked versions, not the newer
  ones (its dpkg-query agrees with its teammate's); a re-imaged main, whose locked desktop no
  archive serves any more: from a controller that kept no .debs, it fails in its ROS install step
  with apt's line naming the package and the version, no ROS package installed; from the one that
  kept them (`roslab lock` keeps the locked .debs, class_lock_debs_dir), it is served the dropped
  version from a local source and ends on exactly the packages it had before it was re-imaged;
- `roslab lock --update --dry` lists exactly the bumped packages, old -> new, with their hosts, and
  writes nothing; `roslab lock --update` moves the lock and the kept .debs with it; the next run
  moves every host and removes the main's local source; the run after changes nothing.

The publishes are reverted when the module ends (`roslab sandbox publish --revert`): the session's
instance serves its archives as `up` did for the next module.
"""

from __future__ import annotations

import pytest
import yaml

from roslab import class_debs
from roslab.ops import class_lock as lock_ops
from tests.e2e.conftest import summary_lines

pytestmark = pytest.mark.e2e

ROS_BUMPED = "ros-jazzy-desktop"  # on team1-main only (Jazzy's desktop)
DEBIAN_BUMPED = "python3-colcon-core"  # on every host (ros-dev-tools' colcon)
REIMAGED_ROBOT = "team1-robot"
REIMAGED_MAIN = "team1-main"
GROUP_HOSTS = {"jazzy/amd64": ["team1-main", "team1-robot"], "humble/amd64": ["team2-main", "team2-robot"]}
HOSTS = [name for names in GROUP_HOSTS.values() for name in names]


@pytest.fixture(scope="module")
def sandbox(default_class_publishing):
    """The converged default class; the archives as `up` served them again after the module."""
    return default_class_publishing


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    """The class's roster in a folder of its own, where classroom.lock is written beside it, and
    the controller's kept .debs in a folder of the test's (class_lock_debs_dir)."""
    path = tmp_path_factory.mktemp("class-lock") / "classroom.yaml"
    document = yaml.safe_load(sandbox.roster_path.read_text())
    document["classroom"]["class_lock_debs_dir"] = str(path.parent / "class-debs")
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def kept_versions(roster, key: str) -> dict[str, str]:
    """package -> version of each .deb the controller keeps for group `key` (its Packages file)."""
    root = class_debs.class_root(roster.parent / "class-debs", roster)
    return {name: version for name, version in class_debs.read_kept(root, key)}


def deploy(sandbox, roster):
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def lock_of(roster) -> dict:
    return yaml.safe_load((roster.parent / "classroom.lock").read_text())


def versions(sandbox, host: str) -> dict[str, str]:
    """package -> version of every package installed on `host` (dpkg-query)."""
    out = sandbox.ssh(host, "dpkg-query -W -f='${db:Status-Abbrev} ${Package} ${Version}\\n'", check=True).stdout
    return {fields[1]: fields[2] for fields in (line.split() for line in out.splitlines())
            if len(fields) == 3 and fields[0] == "ii"}


def test_with_class_lock_auto_a_no_op_run_takes_each_group_and_no_later_run_rewrites_it(sandbox, tmp_path):
    """class_lock_auto: true and no lock: a run of the converged class writes a group per (distro,
    architecture), each from a host of it, and says so in one line; the next run pins the hosts to it
    and leaves the file as it was; the one after changes nothing. (The pins are removed after, so
    the module's `roslab lock` below starts from a class without a lock, as before.)"""
    document = yaml.safe_load(sandbox.roster_path.read_text())
    document["classroom"]["class_lock_auto"] = True
    roster = tmp_path / "classroom.yaml"
    roster.write_text(yaml.safe_dump(document, sort_keys=False))
    lock_file = tmp_path / "classroom.lock"
    try:
        first = deploy(sandbox, roster)

        assert first.returncode == 0, first.stderr[-6000:]
        (read_op,) = [name for name in first.changed if "Read the installed versions for classroom.lock" in name]
        assert first.changed == {read_op: set(HOSTS)}, first.changed  # nothing else: the class was converged
        said = [line for line in first.stderr.splitlines() if line.startswith("--> roslab class lock: ")]
        lock = lock_of(roster)
        assert sorted(lock["groups"]) == sorted(GROUP_HOSTS)
        for key, names in GROUP_HOSTS.items():
            group = lock["groups"][key]
            assert group["taken_from"] in names, group["taken_from"]
            assert f"{key} from {group['taken_from']} ({len(group['packages'])} packages, 0 wheels)" in said[0], said
            installed = versions(sandbox, group["taken_from"])
            assert group["packages"][DEBIAN_BUMPED] == installed[DEBIAN_BUMPED]
            assert len(group["packages"]) > 100 and "ros2-apt-source" not in group["packages"]
        assert len(said) == 1 and said[0].endswith("commit it; `roslab lock --update` moves it on purpose"), said
        text = lock_file.read_text()

        pinned = deploy(sandbox, roster)

        assert pinned.returncode == 0, pinned.stderr[-6000:]
        pin_op = [name for name in pinned.changed if "Ensure apt installs the class lock's versions" in name]
        assert len(pin_op) == 1 and pinned.changed == {pin_op[0]: set(HOSTS)}, pinned.changed  # no read: locked
        assert lock_file.read_text() == text and "--> roslab class lock: " not in pinned.stderr
        again = deploy(sandbox, roster)
        assert again.returncode == 0 and again.changed == {}, again.changed
        assert lock_file.read_text() == text
    finally:
        for name in HOSTS:
            sandbox.sudo(name, f"rm -f {lock_ops.PREFERENCES_FILE}", check=True)


@pytest.fixture(scope="module")
def locked(sandbox, roster):
    taken = sandbox.roslab("lock", str(roster))
    assert taken.returncode == 0, taken.stdout + taken.stderr
    pinned = deploy(sandbox, roster)
    assert pinned.returncode == 0, pinned.stderr[-6000:]
    return taken, pinned


def test_the_lock_is_taken_from_each_group_and_the_next_run_pins_every_host(sandbox, roster, locked):
    taken, pinned = locked
    lock = lock_of(roster)
    assert sorted(lock["groups"]) == sorted(GROUP_HOSTS)
    for key, names in GROUP_HOSTS.items():
        group = lock["groups"][key]
        assert group["taken_from"] in names, group["taken_from"]
        assert f"{key}: {len(group['packages'])} packages locked from {group['taken_from']}" in taken.stdout
        assert group["packages"][DEBIAN_BUMPED] == versions(sandbox, names[0])[DEBIAN_BUMPED]
    assert lock["groups"]["jazzy/amd64"]["packages"][ROS_BUMPED] == versions(sandbox, REIMAGED_MAIN)[ROS_BUMPED]
    for key in GROUP_HOSTS:  # what the runs installed, kept at the locked versions, checked by sha256
        kept = kept_versions(roster, key)
        folder = class_debs.folder(class_debs.class_root(roster.parent / "class-debs", roster), key)
        assert f"{key}: {len(kept)} .debs kept in {folder} (" in taken.stdout, taken.stdout
        assert kept[DEBIAN_BUMPED] == lock["groups"][key]["packages"][DEBIAN_BUMPED]
        assert all(lock["groups"][key]["packages"][name] == version for name, version in kept.items())
    assert kept_versions(roster, "jazzy/amd64")[ROS_BUMPED] == lock["groups"]["jazzy/amd64"]["packages"][ROS_BUMPED]
    assert "not kept" not in taken.stdout, taken.stdout
    pins = {host for name, hosts in pinned.changed.items() if "class lock's versions" in name for host in hosts}
    assert pins == set(HOSTS), pinned.changed
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, again.changed


@pytest.fixture(scope="module")
def bumped(sandbox, roster, locked):
    """The upstream moves on: the moves `lock --update --dry` listed before it (the baseline),
    and the lines of each publish."""
    before = sandbox.roslab("lock", str(roster), "--update", "--dry")
    assert before.returncode == 0, before.stdout + before.stderr
    published = []
    for package in (ROS_BUMPED, DEBIAN_BUMPED):
        result = sandbox.roslab("sandbox", "publish", package, "--bump")
        assert result.returncode == 0, result.stdout + result.stderr
        published += result.stdout.splitlines()
    return set(before.stdout.splitlines()), published


def test_after_an_upstream_bump_the_no_op_stays_a_no_op(sandbox, roster, bumped):
    _, published = bumped
    assert f"published {ROS_BUMPED} 0.0.0-1noble -> 0.0.0-1noble+roslab1 (ROS noble)" in published, published
    assert any(line.startswith(f"published {DEBIAN_BUMPED} ") and "(Ubuntu noble-updates)" in line
               for line in published), published
    run = deploy(sandbox, roster)
    assert run.returncode == 0 and run.changed == {}, run.changed


def test_a_reimaged_robot_converges_to_its_teammates_locked_versions_not_the_newer_ones(sandbox, roster, bumped):
    locked_jazzy = lock_of(roster)["groups"]["jazzy/amd64"]["packages"]
    sandbox.reset(REIMAGED_ROBOT)

    run = deploy(sandbox, roster)

    assert run.returncode == 0, run.stderr[-6000:]
    robot, teammate = versions(sandbox, REIMAGED_ROBOT), versions(sandbox, "team1-main")
    assert robot[DEBIAN_BUMPED] == locked_jazzy[DEBIAN_BUMPED]  # not the newer one in noble-updates
    common = sorted(set(robot) & set(teammate))
    assert len(common) > 100 and "ros-jazzy-ros-base" in common, common
    assert {name: robot[name] for name in common} == {name: teammate[name] for name in common}


@pytest.fixture(scope="module")
def reimaged_main(sandbox, roster, bumped, tmp_path_factory):
    """team1-main's packages before it is re-imaged, and a run of it from the same roster and
    lock on a controller that kept no .debs (class_lock_debs_dir: null, a folder of its own)."""
    before = versions(sandbox, REIMAGED_MAIN)
    bare = tmp_path_factory.mktemp("no-kept-debs") / "classroom.yaml"
    document = yaml.safe_load(roster.read_text())
    document["classroom"]["class_lock_debs_dir"] = None
    bare.write_text(yaml.safe_dump(document, sort_keys=False))
    (bare.parent / "classroom.lock").write_text((roster.parent / "classroom.lock").read_text())
    sandbox.reset(REIMAGED_MAIN)
    return before, deploy(sandbox, bare)


def test_without_kept_debs_a_reimaged_main_whose_locked_version_no_archive_serves_installs_nothing_of_ros(
        sandbox, roster, reimaged_main):
    """A fresh host's ROS source comes with the run, so the run cannot know beforehand what it
    lists: the install asks apt for the locked versions, and apt refuses, naming them."""
    locked_jazzy = lock_of(roster)["groups"]["jazzy/amd64"]["packages"]
    _, run = reimaged_main

    assert run.returncode == 1, run.stderr[-6000:]
    assert run.failed_hosts == [REIMAGED_MAIN], run.failed_hosts
    assert not [name for name in versions(sandbox, REIMAGED_MAIN) if name.startswith("ros-jazzy-")]
    (line,) = [row for row in summary_lines(run.stderr) if row.startswith(f"{REIMAGED_MAIN} ")]
    assert line.startswith(f'{REIMAGED_MAIN} failed in "') and 'Ensure ROS 2 jazzy is installed' in line, line
    assert line.endswith(f"E: Version '{locked_jazzy[ROS_BUMPED]}' for '{ROS_BUMPED}' was not found"), line


def test_with_the_kept_debs_the_reimaged_main_ends_on_exactly_its_packages_of_before(sandbox, roster, reimaged_main):
    """The controller kept the locked desktop (roslab lock): the run serves the re-imaged main the
    one version its sources dropped, from a local source, and the main ends on the very versions
    it had before it was re-imaged (its whole dpkg-query); the next run changes nothing."""
    before, _ = reimaged_main
    locked_jazzy = lock_of(roster)["groups"]["jazzy/amd64"]["packages"]

    run = deploy(sandbox, roster)

    assert run.returncode == 0, run.stderr[-6000:]
    served = [name for name, hosts in run.changed.items() if "its sources dropped" in name]
    assert served and all(run.changed[name] == {REIMAGED_MAIN} for name in served), run.changed
    after = versions(sandbox, REIMAGED_MAIN)
    assert after[ROS_BUMPED] == locked_jazzy[ROS_BUMPED]
    assert after == before, {name: (before.get(name), after.get(name)) for name in set(before) | set(after)
                             if before.get(name) != after.get(name)}
    policy = sandbox.ssh(REIMAGED_MAIN, f"apt-cache policy {ROS_BUMPED}", check=True).stdout
    assert "file:/var/lib/roslab/class-debs ./ Packages" in policy, policy
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, again.changed


def test_lock_update_dry_lists_exactly_the_bumped_packages_and_writes_nothing(sandbox, roster, bumped):
    baseline, _ = bumped
    lock_file = roster.parent / "classroom.lock"
    before = lock_file.read_text()
    dry = sandbox.roslab("lock", str(roster), "--update", "--dry")
    assert dry.returncode == 0, dry.stdout + dry.stderr
    locked = lock_of(roster)["groups"]
    listed = set(dry.stdout.splitlines()) - baseline - {"--dry: classroom.lock was not changed"}
    jazzy, humble = locked["jazzy/amd64"]["packages"], locked["humble/amd64"]["packages"]
    jazzy_hosts, humble_hosts = ", ".join(GROUP_HOSTS["jazzy/amd64"]), ", ".join(GROUP_HOSTS["humble/amd64"])
    assert listed == {
        f"jazzy/amd64: {ROS_BUMPED} {jazzy[ROS_BUMPED]} -> {jazzy[ROS_BUMPED]}+roslab1 ({jazzy_hosts})",
        f"jazzy/amd64: {DEBIAN_BUMPED} {jazzy[DEBIAN_BUMPED]} -> {jazzy[DEBIAN_BUMPED]}+roslab1 ({jazzy_hosts})",
        f"humble/amd64: {DEBIAN_BUMPED} {humble[DEBIAN_BUMPED]} -> {humble[DEBIAN_BUMPED]}+roslab1 ({humble_hosts})",
    } - baseline, dry.stdout
    assert lock_file.read_text() == before


def test_lock_update_then_one_run_moves_every_host_and_the_next_changes_nothing(sandbox, roster, bumped):
    old = lock_of(roster)["groups"]
    moved = sandbox.roslab("lock", str(roster), "--update")
    assert moved.returncode == 0, moved.stdout + moved.stderr
    new = lock_of(roster)["groups"]
    assert new["jazzy/amd64"]["packages"][ROS_BUMPED] == old["jazzy/amd64"]["packages"][ROS_BUMPED] + "+roslab1"
    # the kept .debs follow the lock: the versions moved to are kept, the ones moved from removed
    kept = kept_versions(roster, "jazzy/amd64")
    assert kept[ROS_BUMPED] == new["jazzy/amd64"]["packages"][ROS_BUMPED], moved.stdout
    assert kept[DEBIAN_BUMPED] == new["jazzy/amd64"]["packages"][DEBIAN_BUMPED], moved.stdout

    run = deploy(sandbox, roster)

    assert run.returncode == 0, run.stderr[-6000:]
    for key, names in GROUP_HOSTS.items():
        for name in names:
            installed = versions(sandbox, name)
            assert installed[DEBIAN_BUMPED] == new[key]["packages"][DEBIAN_BUMPED], name
            assert installed[DEBIAN_BUMPED].endswith("+roslab1"), name
    assert versions(sandbox, REIMAGED_MAIN)[ROS_BUMPED] == new["jazzy/amd64"]["packages"][ROS_BUMPED]
    # every locked version is listed upstream again: the local source of kept .debs is gone
    gone = sandbox.ssh(REIMAGED_MAIN, "ls /etc/apt/sources.list.d/ /var/lib/roslab/", check=True).stdout
    assert "roslab-class-debs" not in gone and "class-debs" not in gone, gone
    again = deploy(sandbox, roster)
    assert again.returncode == 0 and again.changed == {}, again.changed
