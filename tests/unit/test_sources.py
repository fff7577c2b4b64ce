"""Source workspaces: .repos files checked before connecting, the controller's pinned fetch
(local file:// repositories in tmp), and the underlay's operations (facts in, commands out)."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import textwrap
from pathlib import Path

import pytest
from pyinfra.facts.server import Arch
from fixtures.fake_host import plan

from roslab.sources import fetch as source_fetch
from roslab.sources import repos as sources
from roslab.sources import underlay
from roslab.roster import RosterError, load_roster
from roslab.checked.problems import Report
from roslab.sandbox import git_standins
from roslab.ros.workspace import WorkspaceStamps

COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(autouse=True)
def _fresh(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)
    source_fetch.reset()
    yield
    source_fetch.reset()


def repos_file(tmp_path: Path, body: str, name: str = "robot.repos") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(body))
    return path


def parsed(path: Path) -> tuple[list[dict], list[str]]:
    report = Report(path)
    repositories = sources.parse_repos(path, report)
    return repositories, [str(problem) for problem in report.errors]


# --- the .repos format ------------------------------------------------------------------


def test_a_pinned_repos_file_is_read_into_plain_repositories(tmp_path):
    path = repos_file(tmp_path, f"""\
        repositories:
          drivers/lidar:
            type: git
            url: https://github.com/example/lidar.git
            version: v2.1.0
          osr-rover-code:
            type: git
            url: https://github.com/nasa-jpl/osr-rover-code.git
            version: {COMMIT}
        """)
    repositories, problems = parsed(path)
    assert problems == []
    assert [(r["path"], r["version"]) for r in repositories] == [
        ("drivers/lidar", "v2.1.0"), ("osr-rover-code", COMMIT)]
    assert repositories[0]["file"] == "robot.repos" and repositories[0]["line"] == 5


@pytest.mark.parametrize("body, field, words", [
    ("- just: a list\n", None, "not a vcstool .repos file"),
    ("repos:\n  a: {type: git, url: 'https://x.org/a.git', version: v1}\n", None, "not a vcstool .repos file"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: main}\n", "repositories.a.version",
     "is a branch"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: jazzy}\n", "repositories.a.version",
     "is a branch"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: 0123abc}\n", "repositories.a.version",
     "abbreviated commit"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git'}\n", "repositories.a.version", "is missing"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: 1.0}\n", "repositories.a.version",
     "quote it"),
    ("repositories:\n  ../escape: {type: git, url: 'https://x.org/a.git', version: v1}\n", "repositories.../escape",
     "not a safe path"),
    ("repositories:\n  /etc/x: {type: git, url: 'https://x.org/a.git', version: v1}\n", "repositories./etc/x",
     "not a safe path"),
    ("repositories:\n  a/../../b: {type: git, url: 'https://x.org/a.git', version: v1}\n",
     "repositories.a/../../b", "not a safe path"),
    ("repositories:\n  a: {type: svn, url: 'https://x.org/a', version: v1}\n", "repositories.a.type", "must be git"),
    ("repositories:\n  a: {type: git, url: 'git@github.com:x/a.git', version: v1}\n", "repositories.a.url",
     "only http://"),
    ("repositories:\n  a: {type: git, url: 'ssh://github.com/x/a.git', version: v1}\n", "repositories.a.url",
     "only http://"),
    ("repositories:\n  a: {type: git, url: 'https://user:pw@github.com/x/a.git', version: v1}\n",
     "repositories.a.url", "password"),
    ("repositories:\n  a: {type: git, url: 'file:///etc/a.git', version: v1}\n", "repositories.a.url",
     "leads outside"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: v1, extra: 1}\n",
     "repositories.a.extra", "unknown key"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: v1}\n"
     "  a/b: {type: git, url: 'https://x.org/b.git', version: v1}\n", "repositories.a/b", "overlaps"),
    ("repositories:\n  a: {type: git, url: 'https://x.org/a.git', version: 'v1..2'}\n", "repositories.a.version",
     "neither a commit"),
])
def test_a_repos_file_that_is_not_pinned_vcstool_format_is_refused_naming_file_line_and_field(
        tmp_path, body, field, words):
    _, problems = parsed(repos_file(tmp_path, body))
    assert problems, body
    assert any(words in problem and problem.startswith("robot.repos") for problem in problems), problems
    if field:
        assert any(f"field {field!r}" in problem for problem in problems), problems


def test_url_rewrites_take_the_longest_prefix_like_git_insteadof():
    rewrites = {"https://github.com/": "http://mirror/git/github.com/",
                "https://github.com/ros/": "http://ros-mirror/"}
    assert sources.rewritten("https://github.com/ros/x.git", rewrites) == "http://ros-mirror/x.git"
    assert sources.rewritten("https://github.com/a/x.git", rewrites) == "http://mirror/git/github.com/a/x.git"
    assert sources.rewritten("https://gitlab.com/a/x.git", rewrites) == "https://gitlab.com/a/x.git"
    assert sources.rewrites_problem({"ssh://github.com/": "http://m/"})
    assert sources.rewrites_problem({"https://github.com/": "https://u:p@m/"})
    assert sources.rewrites_problem({"https://github.com/": "http://mirror\x7f/"})  # DEL, as in a URL


# --- the roster refuses, before connecting ---------------------------------------------

ROSTER = """\
    classroom:
      ssh_user: ubuntu
      ros_packages_check: false
    {classroom}
    teams:
      team1:
        ros_domain_id: 11
        hosts:
          team1-main: {{role: main, address: 192.0.2.11}}
          team1-robot:
            role: robot
            address: 192.0.2.12
    {robot}
    """


def roster(tmp_path, classroom="", robot="") -> Path:
    text = textwrap.dedent(ROSTER).format(classroom=textwrap.indent(classroom, "  "),
                                           robot=textwrap.indent(robot, "        "))
    path = tmp_path / "lab.yaml"
    path.write_text(text)
    return path


def errors_of(path: Path) -> list[str]:
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    return [str(problem) for problem in raised.value.problems]


def test_workspace_sources_reach_host_data_and_a_branch_is_refused_naming_file_host_and_field(tmp_path):
    repos_file(tmp_path, "repositories:\n  lidar: {type: git, url: 'https://x.org/l.git', version: v1}\n",
               "good.repos")
    classroom = roster(tmp_path, robot="workspace_sources: [good.repos]")
    hosts = {host.name: host for host in load_roster(classroom).hosts}
    assert [r["path"] for r in hosts["team1-robot"].data["roslab_sources"]] == ["lidar"]
    assert hosts["team1-main"].data["roslab_sources"] == []

    repos_file(tmp_path, "repositories:\n  lidar: {type: git, url: 'https://x.org/l.git', version: master}\n",
               "bad.repos")
    errors = errors_of(roster(tmp_path, robot="workspace_sources: [bad.repos]"))
    assert len(errors) == 1, errors
    assert errors[0].startswith("bad.repos:2: team 'team1', host 'team1-robot', "
                                "field 'workspace_sources: repositories.lidar.version'")
    assert "is a branch" in errors[0]


@pytest.mark.parametrize("value, words", [
    ("[missing.repos]", "no such file"),
    ("[../outside.repos]", "not a .repos file name"),
    ("[lab.yaml]", "not a .repos file name"),
])
def test_a_workspace_sources_entry_that_is_not_a_repos_file_beside_the_roster_is_refused(tmp_path, value, words):
    errors = errors_of(roster(tmp_path, robot=f"workspace_sources: {value}"))
    assert any("workspace_sources" in error and words in error and "team1-robot" in error for error in errors), \
        errors


def test_a_roster_profile_sources_are_relative_to_the_roster_and_conflicts_name_both_files(tmp_path):
    repos_file(tmp_path, "repositories:\n  lidar: {type: git, url: 'https://x.org/l.git', version: v1}\n",
               "profile.repos")
    repos_file(tmp_path, "repositories:\n  lidar: {type: git, url: 'https://x.org/l.git', version: v2}\n",
               "extra.repos")
    text = textwrap.dedent("""\
        profiles:
          rover:
            extends: demo
            robot:
              sources: [profile.repos]
        """) + roster(tmp_path, robot="robot_profile: rover").read_text()
    path = tmp_path / "lab.yaml"
    path.write_text(text.replace("  team1:\n", "  team1:\n    robot_profile: rover\n"))
    robot = {h.name: h for h in load_roster(path).hosts}["team1-robot"]
    assert robot.data["roslab_profile"]["sources"][0]["version"] == "v1"
    assert robot.data["roslab_sources"][0]["version"] == "v1"
    path.write_text(text.replace("  team1:\n", "  team1:\n    robot_profile: rover\n    "
                                              "workspace_sources: [extra.repos]\n"))
    errors = errors_of(path)
    assert any("profile.repos" in e and "extra.repos" in e and "team1-robot" in e for e in errors), errors


# --- the controller's fetch -------------------------------------------------------------


def upstream_repo(tmp_path: Path, name="lidar", tags=("v1",)) -> tuple[Path, str]:
    bare = tmp_path / "upstream" / f"{name}.git"
    made = git_standins.commit(bare, git_standins.package_files(name, [name]), "first", tags)
    return bare, made


def repo_entry(tmp_path: Path, bare: Path, version: str, path="lidar") -> dict:
    return {"path": path, "type": "git", "url": f"file://{bare}", "version": version,
            "file": "robot.repos", "line": 3}


def test_a_second_run_sharing_the_cache_waits_for_the_mirror_another_run_is_fetching(tmp_path):
    """Two runs on one controller (two classes, a second terminal) share sources_cache_dir: a
    repository's mirror is fetched by one at a time (a lock file under the cache's locks/)."""
    import fcntl
    import threading
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    mirror = source_fetch.mirror_path(cache, f"file://{bare}")
    lock = cache / "locks" / f"{mirror.name}.lock"
    lock.parent.mkdir(parents=True)
    got: list = []
    with open(lock, "a") as other_run:  # another open file: flock() conflicts as another process's would
        fcntl.flock(other_run, fcntl.LOCK_EX)
        fetching = threading.Thread(target=lambda: got.append(source_fetch.fetched(repo_entry(tmp_path, bare, "v1"),
                                                                                 cache)))
        fetching.start()
        fetching.join(1.0)
        assert fetching.is_alive() and not mirror.exists()  # waits; the other run's fetch is untouched
        fcntl.flock(other_run, fcntl.LOCK_UN)
    fetching.join(60)
    assert got and got[0].commit == made
    assert [path.name for path in (cache / "git").iterdir()] == [mirror.name]  # no lock file among the mirrors


def test_repositories_recorded_at_once_all_land_in_the_lock_file(tmp_path):
    """The lock file of pins is read, added to and written under the cache's lock: threads (and
    another run) adding different repositories at once lose none of them."""
    import threading
    cache = tmp_path / "cache"
    urls = [f"https://example.org/repo{index}.git" for index in range(24)]
    threads = [threading.Thread(target=source_fetch._record, args=(cache, url, "v1", f"{index:040x}", "0" * 64))
               for index, url in enumerate(urls)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert sorted(json.loads((cache / source_fetch.LOCK_NAME).read_text())) == sorted(urls)


def test_a_tag_is_resolved_once_recorded_with_its_digest_and_later_served_from_the_cache(tmp_path):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    got = source_fetch.fetched(repo_entry(tmp_path, bare, "v1"), cache)
    assert got.commit == made
    import hashlib
    assert got.sha256 == hashlib.sha256(got.archive).hexdigest()
    lock = json.loads((cache / source_fetch.LOCK_NAME).read_text())
    assert lock[f"file://{bare}"] == {"tags": {"v1": made}, "commits": {made: got.sha256}}
    # once per run: a second host asks nothing of upstream (even if it vanished)
    (tmp_path / "upstream").rename(tmp_path / "gone")
    assert source_fetch.fetched(repo_entry(tmp_path, bare, "v1", path="other"), cache).path == "other"
    # offline, the next run: tag through the lock, commit from the mirror
    source_fetch.reset()
    assert source_fetch.fetched(repo_entry(tmp_path, bare, "v1"), cache, offline=True).sha256 == got.sha256
    # and the same archive bytes (a no-op upload on the hosts)
    assert source_fetch.fetched(repo_entry(tmp_path, bare, "v1"), cache, offline=True).archive == got.archive


def test_a_commit_pin_in_the_mirror_needs_no_upstream(tmp_path):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    source_fetch.fetched(repo_entry(tmp_path, bare, made), cache)
    source_fetch.reset()
    (tmp_path / "upstream").rename(tmp_path / "gone")
    assert source_fetch.fetched(repo_entry(tmp_path, bare, made), cache).commit == made


def tag_moved_after_a_first_fetch(tmp_path):
    """(bare, cache, entry, first commit, moved commit): tag v1 fetched into `cache`, then moved upstream."""
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    entry = repo_entry(tmp_path, bare, "v1")
    source_fetch.fetched(entry, cache)
    moved = git_standins.commit(bare, git_standins.package_files("lidar", ["lidar", "other"]), "second",
                                ["v1"], move_tags=True)
    source_fetch.reset()
    return bare, cache, entry, made, moved


def test_a_moved_tag_is_never_taken_and_is_named_when_the_class_changes_its_pins(tmp_path):
    bare, cache, entry, made, moved = tag_moved_after_a_first_fetch(tmp_path)
    # the same pins as the last check: the lock wins, upstream is not asked
    assert source_fetch.fetched(entry, cache).commit == made
    # a teacher changes a pin (another repository here): every tag is checked, the moved one named
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError) as raised:
        source_fetch.fetched(entry, cache, pins={(entry["url"], "v1"), ("https://example.invalid/x.git", "v2")})
    message = str(raised.value)
    assert "repository 'lidar'" in message and "robot.repos" in message
    assert f"now resolves to {moved}" in message and made in message and "sources.lock.json" in message


def test_the_class_locks_commit_wins_on_a_new_controller_and_a_tag_moved_from_it_is_named(tmp_path):
    """classroom.lock's commit for a tag (`locked`): a controller with an empty cache takes the tag
    only if upstream still names that commit; once upstream moved it, the hosts that build it
    stop there, naming the repository, both commits and `roslab lock --update`. The controller
    that checked the tag with the class's pins asks upstream nothing (a converged class's run
    never does) and goes on building the locked commit: never the moved one."""
    bare, made = upstream_repo(tmp_path)
    entry = repo_entry(tmp_path, bare, "v1")
    assert source_fetch.fetched(entry, tmp_path / "the-class-controller", locked=made).commit == made
    moved = git_standins.commit(bare, git_standins.package_files("lidar", ["lidar", "other"]), "second",
                                ["v1"], move_tags=True)
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError) as raised:
        source_fetch.fetched(entry, tmp_path / "a-new-controller", locked=made)
    message = str(raised.value)
    assert message.startswith("repository 'lidar' (") and "robot.repos" in message, message
    assert f"now resolves to {moved}, but the class lock (classroom.lock) locks {made}" in message, message
    assert "`roslab lock --update`" in message
    source_fetch.reset()
    assert source_fetch.fetched(entry, tmp_path / "the-class-controller", locked=made).commit == made


def test_a_lock_update_moves_the_controllers_record_of_a_tag_to_the_class_locks_commit(tmp_path):
    """After `roslab lock --update` took a moved tag's new commit, the controller that recorded the
    old one follows the class lock (upstream names the locked commit), and records it."""
    bare, cache, entry, made, moved = tag_moved_after_a_first_fetch(tmp_path)
    assert source_fetch.fetched(entry, cache, locked=moved).commit == moved
    assert json.loads((cache / source_fetch.LOCK_NAME).read_text())[f"file://{bare}"]["tags"] == {"v1": moved}
    # the next run, the same pins: served from the cache, upstream not asked
    source_fetch.reset()
    (tmp_path / "upstream").rename(tmp_path / "gone")
    assert source_fetch.fetched(entry, cache, locked=moved).commit == moved
    assert made != moved


def test_a_converged_class_asks_upstream_nothing_and_goes_on_with_one_note_when_it_is_down(tmp_path):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    entry = repo_entry(tmp_path, bare, "v1")
    first = source_fetch.fetched(entry, cache)
    (tmp_path / "upstream").rename(tmp_path / "gone")  # any request to upstream now fails
    source_fetch.reset()
    again = source_fetch.fetched(entry, cache)
    assert (again.commit, again.archive, again.notes) == (made, first.archive, ())
    # a changed set of pins would check the tag: upstream down, the lock and mirror hold it
    source_fetch.reset()
    changed = source_fetch.fetched(entry, cache, pins={(entry["url"], "v1"), ("https://example.invalid/x", "v2")})
    assert changed.commit == made
    assert len(changed.notes) == 1 and "cannot be reached" in changed.notes[0] and made in changed.notes[0]
    # a pin the lock does not hold still needs upstream: it fails naming the repository
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError, match="repository 'lidar'"):
        source_fetch.fetched(repo_entry(tmp_path, bare, "v2"), cache)


@pytest.mark.parametrize("damage", ["truncated", "empty", "not-an-object", "bad-commit", "deleted", "fifo",
                                    "directory", "not-utf8"])
def test_a_damaged_or_deleted_lock_is_never_rebuilt_from_upstream(tmp_path, damage):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    entry = repo_entry(tmp_path, bare, "v1")
    source_fetch.fetched(entry, cache)
    lock = cache / source_fetch.LOCK_NAME
    text = lock.read_text()
    git_standins.commit(bare, git_standins.package_files("lidar", ["lidar", "other"]), "moved", ["v1"],
                        move_tags=True)
    if damage == "deleted":
        lock.unlink()
    elif damage in ("fifo", "directory"):
        import os
        lock.unlink()
        os.mkfifo(lock) if damage == "fifo" else lock.mkdir()
    elif damage == "not-utf8":
        lock.write_bytes(b"\xff\xfe{}")
    else:
        lock.write_text({"truncated": text[: len(text) // 2], "empty": "", "not-an-object": "[]",
                         "bad-commit": text.replace(made, "HEAD~1" + made[6:])}[damage])
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError) as raised:
        source_fetch.fetched(entry, cache)
    message = str(raised.value)
    assert "repository 'lidar'" in message and str(lock) in message, message
    words = {"deleted": "is missing", "fifo": "cannot be read", "directory": "cannot be read",
             "not-utf8": "cannot be read"}.get(damage, "is damaged")
    assert f"the lock file {lock} {words}" in message and "backup" in message, message
    import shutil
    if lock.is_dir():
        lock.rmdir()
    assert not lock.is_file() or lock.read_bytes() != text.encode()  # nothing rewritten from upstream
    # deleting the mirrors too is the teacher's way to take upstream as it is today
    lock.unlink(missing_ok=True)
    shutil.rmtree(cache / "git")
    source_fetch.reset()
    assert source_fetch.fetched(entry, cache).commit != made


def test_a_first_run_of_several_repositories_writes_the_lock_it_did_not_find(tmp_path):
    one, _ = upstream_repo(tmp_path, "one")
    two, _ = upstream_repo(tmp_path, "two")
    cache = tmp_path / "cache"
    source_fetch.fetched(repo_entry(tmp_path, one, "v1", path="one"), cache)
    source_fetch.fetched(repo_entry(tmp_path, two, "v1", path="two"), cache)  # mirrors exist, lock written
    assert len(json.loads((cache / source_fetch.LOCK_NAME).read_text())) == 2


def loose_object(mirror: Path, sha: str) -> Path:
    return mirror / "objects" / sha[:2] / sha[2:]


@pytest.mark.parametrize("damage", ["corrupt-commit", "missing-tree", "truncated-pack"])
def test_a_damaged_mirror_is_moved_aside_named_once_and_fetched_afresh(tmp_path, damage):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    entry = repo_entry(tmp_path, bare, "v1")
    first = source_fetch.fetched(entry, cache)
    mirror = source_fetch.mirror_path(cache, entry["url"])
    if damage == "truncated-pack":
        git_standins._git("--git-dir", mirror, "repack", "-a", "-d", "-q")
        pack = next((mirror / "objects" / "pack").glob("*.pack"))
        pack.chmod(0o644)
        pack.write_bytes(pack.read_bytes()[: pack.stat().st_size // 2])
    else:
        sha = made if damage == "corrupt-commit" else git_standins._git(
            "--git-dir", mirror, "rev-parse", f"{made}^{{tree}}").strip()
        path = loose_object(mirror, sha)
        path.chmod(0o644)
        if damage == "corrupt-commit":
            path.write_bytes(b"x\x01garbage")
        else:
            path.unlink()
    source_fetch.reset()
    got = source_fetch.fetched(entry, cache)
    assert got.archive == first.archive
    aside = [p for p in mirror.parent.iterdir() if p.name.startswith(mirror.name + ".damaged-")]
    assert len(aside) == 1 and aside[0].is_dir()  # kept, for whoever wants to look
    assert len(got.notes) == 1 and str(aside[0]) in got.notes[0] and "fetched afresh" in got.notes[0]
    # what git found wrong, not its closing notices
    assert re.search(r"was damaged \((error|fatal|missing|broken|bad)\b", got.notes[0]), got.notes[0]
    source_fetch.reset()
    assert source_fetch.fetched(entry, cache).notes == ()  # healed: the next run says nothing


def test_a_damaged_mirror_that_cannot_be_fetched_afresh_fails_naming_repository_and_folder(tmp_path):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    entry = repo_entry(tmp_path, bare, made)
    source_fetch.fetched(entry, cache)
    mirror = source_fetch.mirror_path(cache, entry["url"])
    path = loose_object(mirror, made)
    path.chmod(0o644)
    path.write_bytes(b"x\x01garbage")
    (tmp_path / "upstream").rename(tmp_path / "gone")
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError) as raised:
        source_fetch.fetched(entry, cache)
    message = str(raised.value)
    assert "repository 'lidar'" in message and str(mirror) in message and "moved aside" in message, message


def test_a_changed_digest_fails_naming_the_repository(tmp_path):
    bare, made = upstream_repo(tmp_path)
    cache = tmp_path / "cache"
    source_fetch.fetched(repo_entry(tmp_path, bare, made), cache)
    lock_path = cache / source_fetch.LOCK_NAME
    lock = json.loads(lock_path.read_text())
    lock[f"file://{bare}"]["commits"][made] = "0" * 64
    lock_path.write_text(json.dumps(lock))
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError, match=r"repository 'lidar'.*now has sha256"):
        source_fetch.fetched(repo_entry(tmp_path, bare, made), cache)


def test_a_version_that_upstream_has_as_a_branch_is_refused_naming_file_repository_and_field(tmp_path):
    bare, _ = upstream_repo(tmp_path)
    git_standins._git("--git-dir", bare, "branch", "feature-x", "main")
    with pytest.raises(source_fetch.SourceError) as raised:
        source_fetch.fetched(repo_entry(tmp_path, bare, "feature-x"), tmp_path / "cache")
    message = str(raised.value)
    assert "repository 'lidar'" in message and "robot.repos" in message and "field 'version'" in message
    assert "is a branch upstream" in message


def test_an_unreachable_repository_fails_once_naming_it_and_offline_without_a_cache_says_so(tmp_path):
    entry = repo_entry(tmp_path, tmp_path / "upstream" / "nothing.git", "v1")
    with pytest.raises(source_fetch.SourceError, match=r"repository 'lidar' \(file://"):
        source_fetch.fetched(entry, tmp_path / "cache")
    with pytest.raises(source_fetch.SourceError, match="repository 'lidar'"):
        source_fetch.fetched(entry, tmp_path / "cache")  # remembered: one timeout per class
    source_fetch.reset()
    with pytest.raises(source_fetch.SourceError, match="offline, and the controller's cache has no commit"):
        source_fetch.fetched(entry, tmp_path / "cache", offline=True)


def test_rewrites_fetch_from_the_mirror_and_record_the_given_url(tmp_path):
    bare, made = upstream_repo(tmp_path)
    entry = {**repo_entry(tmp_path, bare, "v1"), "url": "https://github.com/example/lidar.git"}
    got = source_fetch.fetched(entry, tmp_path / "cache",
                               rewrites={"https://github.com/example/": f"file://{bare.parent}/"})
    assert got.commit == made
    assert list(json.loads((tmp_path / "cache" / source_fetch.LOCK_NAME).read_text())) == [entry["url"]]


# --- the underlay on a host: facts in, commands out ---------------------------------------

UNDERLAY = "/home/ubuntu/roslab_underlay"


def underlay_facts(recorded=None, present=None, build=None, installed=False):
    return {
        underlay.UnderlaySources: {"recorded": recorded or {}, "present": present or []},
        WorkspaceStamps: {"rosdep": None, "build": build, "installed": installed},
    }


def test_only_a_changed_repository_is_copied_and_one_that_left_is_removed():
    repos = [{"path": "lidar", "sha256": "a" * 64, "archive": b"tar-a"},
             {"path": "drivers/imu", "sha256": "b" * 64, "archive": b"tar-b"}]
    result = plan(underlay.sources, underlay_facts(recorded={"lidar": "a" * 64, "old": "c" * 64},
                                                   present=["lidar", "old"]),
                  underlay_dir=UNDERLAY, repositories=repos, user="ubuntu")
    text = "\n".join(line for op in result.operations for line in op.text())
    assert f"upload {underlay.ARCHIVE_DIR}/{'b' * 64}.tar" in text
    assert "a" * 64 + ".tar" not in text  # unchanged: not copied again
    assert "src/drivers/imu.roslab-new" in text and "runuser -u ubuntu" in text
    assert "rm -rf src/old" in text
    assert '"drivers/imu": "' + "b" * 64 in text  # the manifest written, as the user


def test_the_underlay_is_a_no_op_when_every_archive_is_in_place():
    repos = [{"path": "lidar", "sha256": "a" * 64, "archive": b"tar-a"}]
    result = plan(underlay.sources, underlay_facts(recorded={"lidar": "a" * 64}, present=["lidar"]),
                  underlay_dir=UNDERLAY, repositories=repos, user="ubuntu")
    assert result.operations == [] or all(not op.commands for op in result.operations)
    assert any("at their pins" in reason for reason in result.noops)


def test_a_folder_a_student_deleted_is_copied_again():
    repos = [{"path": "lidar", "sha256": "a" * 64, "archive": b"tar-a"}]
    result = plan(underlay.sources, underlay_facts(recorded={"lidar": "a" * 64}, present=[]),
                  underlay_dir=UNDERLAY, repositories=repos, user="ubuntu")
    assert any("upload" in line for op in result.operations for line in op.text())


def test_the_build_runs_only_when_the_stamp_differs_and_keeps_the_last_good_install():
    stamp = underlay.build_stamp({"lidar": "a" * 64}, "jazzy", ["--executor", "sequential"])
    assert stamp != underlay.build_stamp({"lidar": "b" * 64}, "jazzy", ["--executor", "sequential"])
    done = plan(underlay.built, underlay_facts(build=stamp, installed=True), underlay_dir=UNDERLAY,
                distro="jazzy", colcon_args=[], stamp=stamp)
    assert any("built from these sources already" in reason for reason in done.noops)
    todo = plan(underlay.built, underlay_facts(build="old", installed=True), underlay_dir=UNDERLAY,
                distro="jazzy", colcon_args=[], stamp=stamp)
    script = shlex.split(todo.operations[0].text()[0])[-1]
    assert '--install-base "$slot"' in script
    assert "mv -T install.roslab-new install" in script  # the switch: only after success
    assert script.index("mv -T install.roslab-new install") < script.index("\nelse\n")
    assert "roslab: underlay: package ${failed:-?} failed to build: ${first" in script


def test_a_failing_build_names_the_package_and_its_first_error_line_and_keeps_install(tmp_path):
    """The build script itself, with a fake colcon that fails one package like colcon does."""
    import subprocess

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "colcon").write_text(textwrap.dedent("""\
        #!/bin/sh
        mkdir -p log/latest_build/lidar_driver
        printf 'compiling\\nsrc/x.cpp:3: error: expected ;\\nmore\\n' > log/latest_build/lidar_driver/stderr.log
        echo 'Starting >>> lidar_driver'
        echo 'Failed   <<< lidar_driver [0.1s, exited with code 1]'
        exit 1
        """))
    (bin_dir / "colcon").chmod(0o755)
    ros = tmp_path / "opt/ros/jazzy"
    ros.mkdir(parents=True)
    (ros / "setup.bash").write_text("true\n")
    ws = tmp_path / "ws"
    (ws / "install-a").mkdir(parents=True)
    (ws / "install").symlink_to("install-a")
    script = underlay.build_script(str(ws), "jazzy", [], "stamp").replace("/opt/ros/", f"{tmp_path}/opt/ros/")
    done = subprocess.run(["bash", "-c", script], capture_output=True, text=True,
                          env={"PATH": f"{bin_dir}:/usr/bin:/bin"})
    assert done.returncode == 1
    assert ("roslab: underlay: package lidar_driver failed to build: src/x.cpp:3: error: expected ;; "
            "the last good install stays in use") in done.stderr
    assert (ws / "install").resolve() == (ws / "install-a").resolve()
    assert not (ws / ".roslab/build.sha256").exists()


# --- the deploy: fetch once on the controller, then the host's commands -------------------


def deploy_data(tmp_path, bare: Path, version: str, **more) -> dict:
    from fixtures.classroom import host_data

    entry = repo_entry(tmp_path, bare, version)
    return host_data(tmp_path, "noble", role="robot", roslab_sources=[entry],
                     sources_cache_dir=str(tmp_path / "sources-cache"), **more)


def run_sources_deploy():
    from deploy.sources import sources as sources_deploy

    sources_deploy()


def test_the_deploy_pushes_extracts_installs_dependencies_and_builds_then_is_a_no_op(tmp_path):
    from fixtures.fake_ubuntu import FakeUbuntu

    bare, made = upstream_repo(tmp_path)
    data = deploy_data(tmp_path, bare, "v1")
    facts = {**FakeUbuntu().facts(), **underlay_facts()}
    first = plan(run_sources_deploy, facts, data)
    assert not first.failed, first.errors
    text = "\n".join(line for op in first.operations for line in op.text())
    archive = source_fetch.fetched(data["roslab_sources"][0], tmp_path / "sources-cache")
    assert f"upload {underlay.ARCHIVE_DIR}/{archive.sha256}.tar" in text
    assert "rosdep install --from-paths src/lidar" in text
    assert "colcon build --executor sequential --base-paths src" in text
    as_user = [op.arguments.get("_sudo_user") for op in first.operations if "colcon" in "\n".join(op.text())]
    assert as_user == ["student"]

    # The host after that run: the manifest, both stamps, an install. Nothing to do.
    stamp = underlay.build_stamp({"lidar": archive.sha256}, "jazzy", ["--executor", "sequential"])
    done = {**facts, underlay.UnderlaySources: {"recorded": {"lidar": archive.sha256}, "present": ["lidar"]},
            WorkspaceStamps: {"rosdep": f"{stamp}:jazzy", "build": stamp, "installed": True}}
    again = plan(run_sources_deploy, done, data)
    assert [op for op in again.operations if op.commands] == []
    # what the no-op read is what the deploy's reader puts into the probe's one command
    from roslab import probe
    from deploy.sources import sources_reads

    assert {"UnderlaySources", "WorkspaceStamps"} <= set(again.facts_asked)
    assert sources_reads in probe.READERS


def test_a_repository_that_fails_to_fetch_stops_only_that_host_naming_it(tmp_path):
    from fixtures.fake_ubuntu import FakeUbuntu

    data = deploy_data(tmp_path, tmp_path / "upstream" / "missing.git", "v1")
    result = plan(run_sources_deploy, {**FakeUbuntu().facts(), **underlay_facts()}, data)
    assert result.failed
    assert result.operations == []
    assert any("sources: repository 'lidar'" in error and "nothing was changed" in error for error in result.errors)


def test_the_student_workspace_the_shell_and_the_unit_source_the_underlay_first():
    from deploy.shell_env import render_ros_environment
    from deploy.workspace import exec_script
    from roslab.ros.workspace import build_script

    script = exec_script(distro="jazzy", workspace_dir="/home/u/ros2_ws", launch="pkg x.launch.py",
                         underlay_setup="/home/u/roslab_underlay/install/setup.bash")
    assert script.index("/opt/ros/jazzy/setup.bash") < script.index("roslab_underlay/install/setup.bash") \
        < script.index("ros2_ws/install/setup.bash")
    block = render_ros_environment("jazzy", {"ROS_DOMAIN_ID": "11"}, underlay_dir="~/roslab_underlay")
    assert block.index("roslab_underlay/install/setup.bash") < block.index("ros2_ws/install/setup.bash")
    assert "roslab_underlay" not in render_ros_environment("jazzy", {"ROS_DOMAIN_ID": "11"})
    built = build_script("/home/u/ros2_ws", "jazzy", [], "s", underlays=["/home/u/roslab_underlay/install/setup.bash"])
    assert "source /home/u/roslab_underlay/install/setup.bash || exit 1" in built


def test_source_pins_move_a_profiles_pin_and_name_themselves_as_its_origin(tmp_path):
    from roslab.sources.repos import ReposFiles, host_sources

    (tmp_path / "robot.repos").write_text(
        "repositories:\n  agent:\n    type: git\n    url: https://github.com/o/agent.git\n"
        "    version: 08525169cfc35c398b140a3b2df56a96a30aba98\n"
        "  msgs:\n    type: git\n    url: https://github.com/o/msgs.git\n    version: v1.0.0\n")
    data = {"workspace_sources": [], "source_pins": {"agent": "v2.4.3"}}
    own, every, problems = host_sources(data, [(tmp_path, "robot.repos")], tmp_path, ReposFiles())
    assert problems == []
    assert [(r["path"], r["version"], r["file"]) for r in every] == [
        ("agent", "v2.4.3", "source_pins"), ("msgs", "v1.0.0", every[1]["file"])]
    assert own == every


def test_the_sandbox_stands_in_for_a_commit_pin_with_a_tag_its_roster_pins_unless_served_for_real(tmp_path):
    from roslab.sandbox import git_standins
    from roslab.sources.repos import version_problem

    # the built-in profiles pin tags (upstream has them); a roster's profile may pin a commit
    repos = tmp_path / "mine.repos"
    repos.write_text("repositories:\n  my_driver:\n    type: git\n    url: https://github.com/lab/my_driver.git\n"
                     f"    version: {'ab' * 20}\n  tools:\n    type: git\n    url: https://github.com/lab/tools.git\n"
                     "    version: v1.0.0\n")
    pins = git_standins.commit_pins([repos])
    assert pins == {"my_driver": git_standins.STANDIN_TAG}
    assert all(version_problem(tag) is None for tag in pins.values())
    # a repository the sandbox serves from its real bundle keeps its real pin
    assert git_standins.commit_pins([repos], real=("https://github.com/lab/my_driver.git",)) == {}


def test_a_profiles_cmake_args_reach_colcon_through_a_meta_file_and_change_the_stamp(tmp_path):
    """The micro-ROS agent's superbuild switch: colcon gives a package the `cmake-args` of a
    colcon.meta it is pointed at (`--metas`), here roslab's own, beside its build stamp."""
    import subprocess

    args = {"micro_ros_agent": ["-DMICROROSAGENT_SUPERBUILD=OFF"]}
    plain = underlay.build_stamp({"agent": "a" * 64}, "jazzy", [])
    assert underlay.build_stamp({"agent": "a" * 64}, "jazzy", [], args) != plain
    assert underlay.build_stamp({"agent": "a" * 64}, "jazzy", [], {}) == plain

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    # a colcon that records its arguments and the meta file it was pointed at
    (bin_dir / "colcon").write_text('#!/bin/sh\necho "$@" > args.txt\ncp .roslab/colcon.meta seen.meta '
                                    '2>/dev/null || true\nfor a; do last=$a; done; mkdir -p "$last"\n')
    (bin_dir / "colcon").chmod(0o755)
    (tmp_path / "opt/ros/jazzy").mkdir(parents=True)
    (tmp_path / "opt/ros/jazzy/setup.bash").write_text("true\n")
    ws = tmp_path / "ws"
    ws.mkdir()

    def build(cmake_args):
        script = underlay.build_script(str(ws), "jazzy", ["--executor", "sequential"], "s", cmake_args)
        done = subprocess.run(["bash", "-c", script.replace("/opt/ros/", f"{tmp_path}/opt/ros/")],
                              capture_output=True, text=True, env={"PATH": f"{bin_dir}:/usr/bin:/bin"})
        assert done.returncode == 0, done.stderr
        return (ws / "args.txt").read_text().split()

    called = build(args)
    assert called[:4] == ["build", "--executor", "sequential", "--metas"] and called[4] == ".roslab/colcon.meta"
    assert json.loads((ws / "seen.meta").read_text()) == {
        "names": {"micro_ros_agent": {"cmake-args": ["-DMICROROSAGENT_SUPERBUILD=OFF"]}}}
    (ws / "seen.meta").unlink()
    assert "--metas" not in build({})
    assert not (ws / ".roslab/colcon.meta").exists() and not (ws / "seen.meta").exists()


def test_the_deploy_goes_on_from_the_lock_when_upstream_is_down_saying_so_in_one_line(tmp_path, caplog):
    from fixtures.fake_ubuntu import FakeUbuntu

    import deploy.sources as sources_module

    bare, made = upstream_repo(tmp_path)
    data = deploy_data(tmp_path, bare, "v1")
    facts = {**FakeUbuntu().facts(), **underlay_facts()}
    assert not plan(run_sources_deploy, facts, data).failed
    (tmp_path / "upstream").rename(tmp_path / "gone")
    source_fetch.reset()
    sources_module._said.clear()
    # another pin in the class makes this run check its tags: upstream cannot be reached
    other = {**data["roslab_sources"][0], "path": "extra", "url": "file:///nowhere/extra.git", "version": "v9"}
    caplog.clear()
    result = plan(run_sources_deploy, facts, data, hosts_after=[("other-host", {**data, "roslab_sources": [other]})])
    assert not result.failed, result.errors
    said = [record.getMessage() for record in caplog.records if "cannot be reached" in record.getMessage()]
    assert len(said) == 1 and f"tag 'v1' is taken as the lock records it ({made})" in said[0], said


def test_a_tag_moved_from_the_class_locks_commit_stops_the_host_naming_both_commits(tmp_path):
    """A classroom.lock beside the roster locks the host's group's source: a controller that never
    fetched it (a new one) takes the tag only at the locked commit; moved upstream, the host stops
    before anything is changed on it."""
    from fixtures.fake_ubuntu import FakeUbuntu

    from roslab import class_lock

    bare, made = upstream_repo(tmp_path)
    roster = tmp_path / "classroom.yaml"
    roster.write_text("classroom: {}\n")
    data = deploy_data(tmp_path, bare, "v1", roslab_roster_path=str(roster))
    facts = {**FakeUbuntu().facts(), **underlay_facts()}
    machine = facts[Arch]
    key = class_lock.group_key("jazzy", class_lock.DEBIAN_ARCHITECTURES[machine])
    group = class_lock.LockedGroup("2026-11-28T22:00:00Z", "team1-robot",
                                   sources={class_lock.source_key(f"file://{bare}", "v1"): made})
    (tmp_path / class_lock.LOCK_FILE).write_text(class_lock.render_lock(class_lock.ClassLock(groups={key: group})))
    assert not plan(run_sources_deploy, facts, data).failed
    moved = git_standins.commit(bare, git_standins.package_files("lidar", ["lidar", "other"]), "second", ["v1"],
                                move_tags=True)
    shutil.rmtree(tmp_path / "sources-cache")  # a new controller: the class's lock is all it has
    source_fetch.reset()
    result = plan(run_sources_deploy, facts, data)
    assert result.failed and result.operations == []
    (error,) = [error for error in result.errors if "sources:" in error]
    assert f"now resolves to {moved}, but the class lock (classroom.lock) locks {made}" in error, error
    assert error.endswith("nothing was changed on it"), error


def test_every_rosdep_key_the_stand_in_repositories_name_is_in_the_sandboxs_rosdep_data(tmp_path):
    """Issue 40: a stand-in sandbox (no ROSLAB_SANDBOX_SOURCES) must resolve every key of what it
    serves under the built-in .repos files' URLs, or the underlay's rosdep step stops."""
    from roslab.sandbox import real_sources, upstream

    ros_keys, system_keys = upstream.served_keys(upstream.default_nodes_dir(), real_sources.Bundles(None))
    served = set(upstream.ros_keys_for(ros_keys)) | set(system_keys)
    manifests = []
    for repo_path in sorted({path for path, _, _ in git_standins.repositories(upstream.builtin_repos_files())}):
        packages = git_standins.STANDIN_PACKAGES.get(repo_path) or {
            git_standins.package_name(repo_path): [git_standins.package_name(repo_path)]}
        for package, executables in packages.items():
            folder = tmp_path / git_standins.package_name(repo_path) / package
            folder.mkdir(parents=True)
            (folder / "package.xml").write_text(git_standins.package_files(package, executables)[f"{package}/package.xml"])
            manifests.append(folder / "package.xml")
    assert manifests
    named_ros, named_system = upstream.manifest_dependencies(manifests)
    assert named_ros | set(named_system) <= served, (named_ros | set(named_system)) - served


def test_a_stand_in_sandbox_and_a_real_sources_one_keep_their_repositories_apart():
    """The same URL and tag are a stand-in in one sandbox and the real repository in another: one
    controller cache for both would hand a stand-in sandbox the real micro-ROS-Agent (its rosdep
    keys unserved there), or refuse the tag as moved."""
    from roslab.sandbox import upstream

    real = "https://github.com/micro-ROS/micro-ROS-Agent.git"
    settings_of = [upstream.Upstream(url="http://10.213.1.1:8080", ros_apt_source_sha256={}, ros={},
                                     real_repositories=served).roster_settings() for served in ((), (real,))]
    stand_ins, real_ones = (settings["sources_cache_dir"] for settings in settings_of)
    assert stand_ins != real_ones and "stand-ins" in stand_ins and "real" in real_ones
    assert all(path.startswith("~/.cache/roslab/") for path in (stand_ins, real_ones))
