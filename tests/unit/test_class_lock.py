"""The class lock (roslab.class_lock): its format, its errors, its merge, and the apt pin it puts on a host."""

from __future__ import annotations

from pathlib import Path

import pytest
from fixtures.fake_host import plan
from pyinfra.facts.files import FileContents

from roslab import class_lock
from roslab.ops import class_lock as lock_ops
from roslab.checked.problems import Report

KEY = "jazzy/arm64"
TAKEN = "2026-11-28T22:00:00Z"
INSTALLED = {"ros-jazzy-ros-base": "0.11.0-1noble.20250101.000000", "libc6": "2.39-0ubuntu8.4"}
ROSTERS = Path(__file__).parent / "rosters"
COMMIT = "0123456789abcdef0123456789abcdef01234567"
SHA = "ab" * 32
OTHER_SHA = "cd" * 32
OTHER_COMMIT = "89abcdef0123456789abcdef0123456789abcdef"
SOURCE = "https://github.com/ROBOTIS-GIT/turtlebot3.git@2.2.9"  # URL@VERSION, as a .repos file pins it


def first_lock() -> class_lock.ClassLock:
    lock, _ = class_lock.merged(class_lock.ClassLock(), KEY, INSTALLED, {SOURCE: COMMIT}, TAKEN, "robot1-1")
    return lock


def test_lock_round_trips_sorted_and_quoted(tmp_path):
    lock = class_lock.ClassLock(groups=first_lock().groups, hold=("libc6",))
    text = class_lock.render_lock(lock)
    assert text.index("'libc6'") < text.index("'ros-jazzy-ros-base'")  # sorted: a small git diff
    path = tmp_path / "classroom.lock"
    path.write_text(text)
    again, report = class_lock.read_lock(path)
    assert report.errors == []
    assert again == lock
    assert class_lock.render_lock(again) == text


def test_a_missing_lock_is_an_empty_one(tmp_path):
    lock, report = class_lock.read_lock(tmp_path / "classroom.lock")
    assert lock == class_lock.ClassLock() and report.errors == []


@pytest.mark.parametrize(("document", "field", "words"), [
    ({"groups": {"jazzy": {}}}, "groups.jazzy", "distro/architecture"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "packages": {"-oAPT::x": "1.0"}}}},
     f"groups.{KEY}.packages.-oAPT::x", "not a name"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "packages": {"libc6": "1.0; rm -rf /"}}}},
     f"groups.{KEY}.packages.libc6", "Debian version"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {SOURCE: "main"}}}},
     f"groups.{KEY}.sources.{SOURCE}", "40-hex-digit commit"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {"tb3": COMMIT}}}},
     f"groups.{KEY}.sources.tb3", "URL@VERSION"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {"https://github.com/x/tb3.git@main": COMMIT}}}},
     f"groups.{KEY}.sources.https://github.com/x/tb3.git@main", "is a branch"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {"https://u:pw@github.com/x.git@v1": COMMIT}}}},
     f"groups.{KEY}.sources.https://u:pw@github.com/x.git@v1", "user name or password"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {"ssh://github.com/x.git@v1": COMMIT}}}},
     f"groups.{KEY}.sources.ssh://github.com/x.git@v1", "only http://"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "sources": {"https://github.com/x.git@": COMMIT}}}},
     f"groups.{KEY}.sources.https://github.com/x.git@", "names no version"),
    ({"groups": {KEY: {"taken": "yesterday", "taken_from": "r1"}}}, f"groups.{KEY}.taken", "UTC time"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "extra": 1}}}, f"groups.{KEY}.extra", "unknown key"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "wheels": {"RPi.GPIO": {"version": "0.7.1",
                                                                                "sha256": SHA}}}}},
     f"groups.{KEY}.wheels.RPi.GPIO", "PEP 503"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "wheels": {"torch": {"version": "2.1+cpu",
                                                                             "sha256": SHA}}}}},
     f"groups.{KEY}.wheels.torch.version", "PEP 440 public version"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "wheels": {"ina260": {"version": "0.0.3",
                                                                              "sha256": "md5:abc"}}}}},
     f"groups.{KEY}.wheels.ina260.sha256", "64 hex digits"),
    ({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1", "wheels": {"ina260": "0.0.3"}}}},
     f"groups.{KEY}.wheels.ina260", "version and sha256"),
    ({"hold": ["Bad Name"]}, "hold", "Debian package name"),
    ({"pins": {}}, "pins", "unknown key"),
])
def test_hostile_values_are_refused_naming_file_and_field(document, field, words):
    report = Report("classroom.lock")
    class_lock.parse_lock(document, report)
    assert [p.field for p in report.errors] == [field]
    assert words in str(report.errors[0]) and str(report.errors[0]).startswith("classroom.lock: ")


def test_broken_yaml_names_the_file(tmp_path):
    path = tmp_path / "classroom.lock"
    path.write_text("groups: [\n")
    lock, report = class_lock.read_lock(path)
    assert lock is None and "not valid YAML" in str(report.errors[0])


def test_merge_locks_a_new_package_at_first_install_and_never_moves_a_locked_one():
    newer = {**INSTALLED, "libc6": "2.39-0ubuntu8.5", "ros-jazzy-turtlesim": "1.8.3-1noble"}
    lock, added = class_lock.merged(first_lock(), KEY, newer, {SOURCE: "f" * 40}, "2026-12-01T08:00:00Z", "r2")
    group = lock.groups[KEY]
    assert added == ["ros-jazzy-turtlesim"]
    assert group.packages["libc6"] == "2.39-0ubuntu8.4"  # locked: only `lock --update` moves it
    assert group.packages["ros-jazzy-turtlesim"] == "1.8.3-1noble"
    assert (group.taken, group.taken_from, group.sources[SOURCE]) == (TAKEN, "robot1-1", COMMIT)
    same, added = class_lock.merged(lock, KEY, newer, {}, TAKEN, "r2")
    assert same is lock and added == []  # nothing new: the file is not rewritten


def test_update_lists_old_to_new_and_keeps_held_packages_back():
    lock = class_lock.ClassLock(groups=first_lock().groups, hold=("libc6",))
    candidates = {"libc6": "2.39-0ubuntu9", "ros-jazzy-ros-base": "0.11.0-1noble.20260101.000000"}
    moves = class_lock.updates(lock, KEY, candidates)
    assert moves == [("ros-jazzy-ros-base", INSTALLED["ros-jazzy-ros-base"], candidates["ros-jazzy-ros-base"])]
    moved = class_lock.updated(lock, KEY, moves, "2026-12-01T08:00:00Z")
    assert moved.groups[KEY].packages["ros-jazzy-ros-base"] == candidates["ros-jazzy-ros-base"]
    assert moved.groups[KEY].packages["libc6"] == INSTALLED["libc6"]
    assert class_lock.updates(moved, KEY, candidates) == []


def test_a_version_nobody_serves_is_one_line_naming_package_version_and_what_to_do():
    group = first_lock().groups[KEY]
    lines = lock_ops.unmet(group, ["libc6", "ros-jazzy-ros-base"],
                             {"libc6": ["2.39-0ubuntu9"], "ros-jazzy-ros-base": [INSTALLED["ros-jazzy-ros-base"]]})
    assert lines == [
        "libc6=2.39-0ubuntu8.4 is locked but no apt source of the host lists it any more and the controller "
        "kept no .deb of it (class_lock_debs_dir): move the lock with `roslab lock --update`"
    ]
    dropped_ros = lock_ops.unmet(group, ["ros-jazzy-ros-base"], {"ros-jazzy-ros-base": ["0.99.0-1noble"]})
    assert dropped_ros == [
        f"ros-jazzy-ros-base={INSTALLED['ros-jazzy-ros-base']} is locked but no apt source of the host lists "
        "it any more and the controller kept no .deb of it (class_lock_debs_dir): install ROS from a snapshot that has it (ros_apt_source_mode: snapshot), or move the "
        "lock with `roslab lock --update`"
    ]


def test_apt_is_pinned_to_the_locked_versions_by_one_whole_file():
    group = first_lock().groups[KEY]
    result = plan(lock_ops.locked_versions_pinned, {FileContents: lambda path: None}, group=group)
    text = result.uploads()[lock_ops.PREFERENCES_FILE]
    assert "Package: libc6\nPin: version 2.39-0ubuntu8.4\nPin-Priority: 1001\n" in text
    current = text.splitlines()
    result = plan(lock_ops.locked_versions_pinned, {FileContents: lambda path: current}, group=group)
    assert result.changing() == {} and result.noops == ["apt is pinned to the class lock's 2 versions"]


def test_a_broken_lock_beside_the_roster_stops_the_roster_before_any_host(tmp_path):
    from roslab.roster import RosterError, load_roster

    roster = tmp_path / "classroom.yaml"
    roster.write_text((ROSTERS / "two_teams.yaml").read_text())
    load_roster(roster)  # no lock yet: nothing to check
    (tmp_path / "classroom.lock").write_text(
        "groups:\n  jazzy/arm64:\n    taken: '2026-11-28T22:00:00Z'\n    taken_from: r1\n"
        "    packages:\n      libc6: '1.0\\nPackage: *'\n")
    with pytest.raises(RosterError, match=r"classroom.lock: field 'groups.jazzy/arm64.packages.libc6'"):
        load_roster(roster)


def test_a_hosts_installed_packages_are_read_for_its_architecture_and_checked():
    from roslab.ops.class_lock import parse_installed
    from roslab.cli.lock import update_lines

    reading = parse_installed(["arm64", "ii \tlibc6\tarm64\t2.39-0ubuntu8.4", "ii \ttzdata\tall\t2024a-3ubuntu1",
                               "ii \tlibc6\ti386\t2.39-0ubuntu8.4", "rc \told\tarm64\t1.0",
                               "ii \tros2-apt-source\tall\t1.1.0~noble",
                               "ii \tevil\tarm64\t1.0\nPackage: *"])
    assert reading == {"architecture": "arm64", "packages": {"libc6": "2.39-0ubuntu8.4", "tzdata": "2024a-3ubuntu1"}}
    lines = update_lines({KEY: [("libc6", "2.39-0ubuntu8.4", "2.39-0ubuntu9")], "humble/arm64": []},
                         {KEY: ["team1-main", "team2-main"], "humble/arm64": ["old-robot"]})
    assert lines == ["humble/arm64: the archives offer nothing newer than the lock",
                     "jazzy/arm64: libc6 2.39-0ubuntu8.4 -> 2.39-0ubuntu9 (team1-main, team2-main)"]


def test_ros2_apt_source_is_the_rosters_to_version_never_the_locks():
    lock, added = class_lock.merged(class_lock.ClassLock(), KEY, {**INSTALLED, "ros2-apt-source": "1.1.0"}, {},
                                    TAKEN, "r1")
    assert "ros2-apt-source" not in lock.groups[KEY].packages and "ros2-apt-source" not in added
    report = Report("classroom.lock")
    class_lock.parse_lock({"groups": {KEY: {"taken": TAKEN, "taken_from": "r1",
                                            "packages": {"ros2-apt-source": "1.1.0"}}}}, report)
    assert "ros_apt_source_version" in str(report.errors[0])


def test_lock_update_asks_each_group_for_its_candidates_as_pyinfra_takes_fact_arguments(monkeypatch):
    """`roslab lock --update` reads the candidates with pyinfra's get_fact, whose fact arguments
    go in `kwargs=` (pyinfra 3.10): a keyword of the fact's own was a TypeError (found by mypy)."""
    import inspect
    from types import SimpleNamespace

    import pyinfra.api.facts
    from roslab.cli import lock as lock_cli

    real = inspect.signature(pyinfra.api.facts.get_fact)
    asked = []

    def get_fact(*args, **kwargs):
        bound = real.bind(*args, **kwargs)  # a TypeError, as pyinfra's own, for a wrong call
        asked.append((bound.arguments["cls"], bound.arguments.get("kwargs")))
        if bound.arguments["cls"] is lock_ops.AptVersionsNow:
            return {"ros-jazzy-ros-base": ["0.11.0-1noble.20260101.000000"]}
        return {"architecture": "arm64", "packages": INSTALLED}

    class Pi:  # pyinfra's Host as read_hosts uses it: a name and data (no profile: no wheels to read)
        name = "robot1-1"
        data = SimpleNamespace(dict=lambda: {})

    pi = Pi()
    state = SimpleNamespace(inventory=[pi], active_hosts=[pi])
    monkeypatch.setattr(pyinfra.api.facts, "get_fact", get_fact)
    monkeypatch.setattr(lock_cli, "connected_state", lambda groups, limit: state)
    classroom = SimpleNamespace(hosts=[SimpleNamespace(name="robot1-1", distro="jazzy")])
    found = lock_cli.read_hosts(SimpleNamespace(limit=None), classroom, {}, first_lock())
    assert found[KEY]["candidates"] == {"ros-jazzy-ros-base": "0.11.0-1noble.20260101.000000"}
    # after `apt-get update` (as root, as every roster host's facts run): what the archives offer now
    assert asked[-1] == (lock_ops.AptVersionsNow, {"packages": sorted(INSTALLED)})
    command = lock_ops.AptVersionsNow().command(["ros-jazzy-ros-base", "-oAPT::x=1"])
    assert command.startswith("DEBIAN_FRONTEND=noninteractive apt-get -q -o DPkg::Lock::Timeout=120 update ")
    assert command.endswith("apt-cache madison -- ros-jazzy-ros-base || true")


# --- wheels --------------------------------------------------------------------------------

def wheel_files(sha=SHA):
    from roslab.python_env.wheelhouse import File

    return [File("RPi.GPIO-0.7.1.tar.gz", sha, True), File("ina260-0.0.3-py3-none-any.whl", sha, False),
            File("torch-2.1.0+cpu-cp312-cp312-linux_aarch64.whl", sha, False)]


def test_each_wheel_is_locked_by_its_normalised_name_with_version_and_sha256(tmp_path):
    wheels = class_lock.wheels_of(wheel_files())
    assert wheels == {"rpi-gpio": class_lock.LockedWheel("0.7.1", SHA), "ina260": class_lock.LockedWheel("0.0.3", SHA)}
    lock, added = class_lock.merged(class_lock.ClassLock(), KEY, INSTALLED, {}, TAKEN, "robot1-1", wheels)
    assert added[-2:] == ["ina260", "rpi-gpio"]
    text = class_lock.render_lock(lock)
    assert f"      'rpi-gpio': {{version: '0.7.1', sha256: '{SHA}'}}\n" in text  # one line per wheel
    path = tmp_path / "classroom.lock"
    path.write_text(text)
    again, report = class_lock.read_lock(path)
    assert report.errors == [] and again == lock


def test_a_wheelhouse_file_whose_hash_differs_from_the_lock_is_one_line_with_both_hashes_and_what_to_do():
    group = class_lock.LockedGroup(TAKEN, "r1", wheels=class_lock.wheels_of(wheel_files()))
    assert class_lock.wheel_mismatches(group, wheel_files()) == []
    from roslab.python_env.wheelhouse import File

    repinned = [File("ina260-0.0.4-py3-none-any.whl", OTHER_SHA, False)]  # another version: not this check's
    assert class_lock.wheel_mismatches(group, repinned) == []
    assert class_lock.wheel_mismatches(group, wheel_files(OTHER_SHA))[1] == (
        f"ina260-0.0.3-py3-none-any.whl has sha256 {OTHER_SHA} in the class's wheelhouse but the class lock has "
        f"{SHA} for ina260 0.0.3: nothing was installed; put the locked file back in the wheelhouse, or take "
        "the new one with `roslab lock --update`")


def test_merge_never_moves_a_locked_wheel_and_update_moves_it():
    wheels = class_lock.wheels_of(wheel_files())
    lock, _ = class_lock.merged(class_lock.ClassLock(), KEY, INSTALLED, {}, TAKEN, "r1", wheels)
    newer = class_lock.wheels_of(wheel_files(OTHER_SHA))
    same, added = class_lock.merged(lock, KEY, INSTALLED, {}, TAKEN, "r1", newer)
    assert same is lock and added == []
    moves = class_lock.wheel_updates(lock.groups[KEY], newer)
    assert moves == [("ina260", "0.0.3 sha256:abababababab", "0.0.3 sha256:cdcdcdcdcdcd"),
                     ("rpi-gpio", "0.7.1 sha256:abababababab", "0.7.1 sha256:cdcdcdcdcdcd")]
    moved = class_lock.updated(lock, KEY, [], "2026-12-01T08:00:00Z", newer)
    assert moved.groups[KEY].wheels == newer and moved.groups[KEY].packages == lock.groups[KEY].packages


def test_a_held_wheel_stays_at_its_locked_file_while_the_others_move(capsys, tmp_path):
    from dataclasses import replace

    from roslab.cli import lock as lock_cli

    wheels = class_lock.wheels_of(wheel_files())
    lock, _ = class_lock.merged(class_lock.ClassLock(), KEY, INSTALLED, {}, TAKEN, "r1", wheels)
    lock = replace(lock, hold=("rpi-gpio",))
    newer = class_lock.wheels_of(wheel_files(OTHER_SHA))
    assert [name for name, _old, _new in class_lock.wheel_updates(lock.groups[KEY], newer, lock.hold)] == ["ina260"]
    moved = lock_cli.moved_lock(lock, {KEY: {"hosts": ["r1"], "candidates": {}, "wheels": newer}},
                                "2026-12-01T08:00:00Z")
    assert moved.groups[KEY].wheels == {**wheels, "ina260": newer["ina260"]}
    assert "rpi-gpio" not in capsys.readouterr().out
    path = tmp_path / class_lock.LOCK_FILE
    path.write_text(class_lock.render_lock(moved))
    again, report = class_lock.read_lock(path)  # a wheel's name is one `hold:` accepts
    assert not report.errors and again.hold == ("rpi-gpio",)


def test_lock_update_lists_a_moved_wheel_apart_from_a_package_of_the_same_name(capsys):
    from roslab.cli import lock as lock_cli

    wheels = class_lock.wheels_of(wheel_files())
    lock, _ = class_lock.merged(class_lock.ClassLock(), KEY, {**INSTALLED, "ina260": "1.0-1"}, {}, TAKEN, "r1",
                                wheels)
    found = {KEY: {"hosts": ["r1"], "candidates": {"ina260": "1.1-1"},
                   "wheels": {**wheels, "ina260": class_lock.LockedWheel("0.0.3", OTHER_SHA)}}}
    moved = lock_cli.moved_lock(lock, found, "2026-12-01T08:00:00Z")
    assert capsys.readouterr().out.splitlines() == [
        f"{KEY}: ina260 1.0-1 -> 1.1-1 (r1)",
        f"{KEY}: wheel ina260 0.0.3 sha256:abababababab -> 0.0.3 sha256:cdcdcdcdcdcd (r1)"]
    group = moved.groups[KEY]
    assert group.packages["ina260"] == "1.1-1" and group.wheels["ina260"].sha256 == OTHER_SHA
    assert group.wheels["rpi-gpio"].sha256 == SHA


# --- sources -------------------------------------------------------------------------------


def test_a_moved_source_tag_is_listed_old_to_new_and_moved_only_by_update(capsys):
    from roslab.cli import lock as lock_cli

    lock = first_lock()
    same, added = class_lock.merged(lock, KEY, INSTALLED, {SOURCE: OTHER_COMMIT}, TAKEN, "r1")
    assert same is lock and added == []  # taking never moves a locked commit
    assert class_lock.source_updates(lock.groups[KEY], {SOURCE: COMMIT}) == []
    found = {KEY: {"hosts": ["robot1-1", "robot1-2"], "candidates": {}, "upstream_sources": {SOURCE: OTHER_COMMIT}}}
    moved = lock_cli.moved_lock(lock, found, "2026-12-01T08:00:00Z")
    assert capsys.readouterr().out.splitlines() == [
        f"{KEY}: source {SOURCE} {COMMIT} -> {OTHER_COMMIT} (robot1-1, robot1-2)"]
    assert moved.groups[KEY].sources == {SOURCE: OTHER_COMMIT}
    assert moved.groups[KEY].packages == lock.groups[KEY].packages


def test_lock_takes_each_built_repositorys_commit_and_update_asks_upstream_for_a_moved_tag(tmp_path):
    """`roslab lock` records URL@VERSION -> commit for the repositories a host builds, as the
    controller's cache fetched them; `--update` asks upstream (git ls-remote) for each locked tag
    and lists a moved one old -> new."""
    from types import SimpleNamespace

    from roslab.cli import lock as lock_cli
    from roslab.sandbox import git_standins
    from roslab.sources import fetch as source_fetch

    bare = tmp_path / "upstream" / "lidar.git"
    made = git_standins.commit(bare, git_standins.package_files("lidar", ["lidar"]), "first", ["v1"])
    url, cache = f"file://{bare}", tmp_path / "sources"
    repos = [{"path": "lidar", "type": "git", "url": url, "version": "v1", "file": "robot.repos", "line": 3},
             {"path": "pinned", "type": "git", "url": url, "version": made, "file": "robot.repos", "line": 7}]

    class Pi:  # pyinfra's Host as the lock command reads it: a name and its roster data
        name = "robot1-1"
        data = SimpleNamespace(dict=lambda: {"roslab_sources": repos, "sources_cache_dir": str(cache)})

    assert lock_cli.kept_sources(Pi()) == {f"{url}@{made}": made}  # no run fetched the tag yet: not read
    source_fetch.reset()
    source_fetch.fetched(repos[0], cache)
    taken = lock_cli.kept_sources(Pi())
    assert taken == {f"{url}@v1": made, f"{url}@{made}": made}
    group = class_lock.LockedGroup(TAKEN, "robot1-1", sources=taken)
    assert lock_cli.upstream_sources(Pi(), group) == ({f"{url}@v1": made}, [])
    moved = git_standins.commit(bare, git_standins.package_files("lidar", ["lidar", "other"]), "second", ["v1"],
                                move_tags=True)
    assert class_lock.source_updates(group, lock_cli.upstream_sources(Pi(), group)[0]) == [
        (f"{url}@v1", made, moved)]
