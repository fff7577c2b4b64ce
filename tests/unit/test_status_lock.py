"""`roslab status` and the class lock (roslab.cli.status_lock): facts in, lines out.

The `apt-cache policy` texts in fixtures/apt_policy/ are real output (Debian 12, C locale):
`bookworm.txt` as apt has it, `bookworm-bash-pinned.txt` with bash pinned at its installed
version at priority 1001 as the lock's preferences pin it (`apt-cache -o Dir::Etc::preferences=...`),
while the archive lists a newer one and no source serves the installed one any more.
"""

from __future__ import annotations

import shutil
import subprocess
from datetime import timedelta
from pathlib import Path

import pytest
from fixtures.status_hosts import NOW, PROBE_OUTPUT, reachable_host, unreachable_host
from test_status import free_port, loopback_roster, roslab

from roslab.class_lock import ClassLock, LockedGroup, render_lock
from roslab.cli import status, status_lock
from roslab.cli.status import page_context, parse_probe, render_page

POLICY = Path(__file__).parent / "fixtures" / "apt_policy"
TAKEN = "2026-11-15T08:30:00Z"  # 8 days before NOW


def policy(name: str, architecture: str = "amd64") -> list[str]:
    return [architecture, *(POLICY / name).read_text().splitlines()]


def lock(hold=(), **groups) -> ClassLock:
    return ClassLock(groups={key.replace("_", "/"): LockedGroup(TAKEN, "team1-main", packages)
                             for key, packages in groups.items()}, hold=tuple(hold))


BOOKWORM = {"bash": "5.2.15-2+b8", "coreutils": "9.1-1"}


def host_with(policy_lines, name="team1-main", **changes):
    probe = parse_probe(PROBE_OUTPUT)
    probe["apt_policy"] = status_lock.parse_policy(policy_lines)
    return reachable_host(name=name, probe=probe, **changes)


# apt-cache policy -----------------------------------------------------------------------------


def test_a_policy_gives_the_versions_an_apt_source_lists_not_the_one_only_dpkg_has():
    parsed = status_lock.parse_policy(policy("bookworm-bash-pinned.txt"))
    assert parsed == {"architecture": "amd64", "too_many": False,
                      "offered": {"bash": ["5.2.15-2+b13"], "coreutils": ["9.1-1"]}}
    assert status_lock.parse_policy(policy("bookworm.txt")) == parsed  # the pin changes no offer
    assert status_lock.parse_policy([])["architecture"] == ""
    assert status_lock.parse_policy(["?"])["architecture"] == ""  # no dpkg: no group


@pytest.mark.parametrize("a, b, order", [
    ("5.2.15-2+b13", "5.2.15-2+b8", 1), ("1.0~rc1", "1.0", -1), ("1:0.1", "2.0", 1), ("1.0", "1.0-0", 0),
    ("0.11.0-1noble.20250101.000000", "0.11.0-1noble.20250301.000000", -1), ("1.0a", "1.0+", -1),
    ("2.0~~", "2.0~", -1), ("1.2.3", "1.2.3.0", -1), ("10", "9", 1), ("1.0-1ubuntu0.1", "1.0-1", 1),
])
def test_versions_sort_as_dpkg_sorts_them(a, b, order):
    # Each expectation checked with `dpkg --compare-versions A lt|eq|gt B` on Debian 12.
    result = status_lock.compare_versions(a, b)
    assert (result > 0) - (result < 0) == order
    assert (status_lock.compare_versions(b, a) > 0) - (status_lock.compare_versions(b, a) < 0) == -order


def test_the_probe_asks_apt_only_with_a_lock_and_only_about_the_distros_locked_packages():
    assert status_lock.SECTION not in status.probe_script()
    classroom_lock = lock(jazzy_arm64={"ros-jazzy-ros-base": "0.11.0-1"}, jazzy_amd64={"bash": "5.2.15-2+b8"},
                          humble_arm64={"ros-humble-ros-base": "0.10.0-1"})
    asked = status_lock.asked_packages(classroom_lock, "jazzy")
    assert asked == ("bash", "ros-jazzy-ros-base")
    script = status.probe_script(lock_packages=asked)
    assert "LC_ALL=C apt-cache policy -- bash ros-jazzy-ros-base" in script and "sudo" not in script
    assert "#too-many" in status_lock.policy_command(("a" * 60,) * 2000)


@pytest.mark.skipif(shutil.which("apt-cache") is None, reason="no apt here")
def test_the_section_runs_in_a_posix_shell_and_parses():
    script = status.probe_script(lock_packages=("bash", "coreutils"))
    output = subprocess.run(["sh", "-c", script], capture_output=True, text=True, timeout=30)
    probe = parse_probe(output.stdout.splitlines())
    assert probe["probed"] and probe["apt_policy"]["architecture"]
    assert set(probe["apt_policy"]["offered"]) == {"bash", "coreutils"}


# the lines --------------------------------------------------------------------------------------


def test_a_locked_group_says_when_from_where_and_how_far_the_archive_moved():
    hosts = [host_with(policy("bookworm-bash-pinned.txt")),
             host_with(policy("bookworm.txt"), name="team1-robot", role="robot")]
    lines = status_lock.lock_lines(lock(jazzy_amd64={**BOOKWORM, "curl": "7.88.1-10"}), hosts, NOW)
    assert lines == [
        {"level": "plain", "text": "class lock jazzy/amd64: taken 2026-11-15 (8 days ago) from team1-main; "
                                   "3 packages pinned, 0 held"},
        {"level": "warn", "text": "  1 package newer upstream than the lock on the apt sources of 2 hosts: "
                                  "roslab lock --update --dry lists them"},
    ]


def test_a_held_package_is_counted_apart_and_an_up_to_date_group_says_so():
    hosts = [host_with(policy("bookworm-bash-pinned.txt"))]
    lines = status_lock.lock_lines(lock(hold=["bash"], jazzy_amd64=BOOKWORM), hosts, NOW + timedelta(days=-8))
    assert [line["text"] for line in lines] == [
        "class lock jazzy/amd64: taken 2026-11-15 (today) from team1-main; 2 packages pinned, 1 held",
        "  nothing newer upstream than the lock on the apt sources of 1 host (1 more held back)"]
    assert lines[1]["level"] == "ok"


def test_hosts_not_read_and_groups_not_locked_are_named():
    cut_short = host_with(policy("bookworm.txt", "riscv64"), name="team4-main", team="team4")
    cut_short.probe["probed"] = False  # the bound ended its command: nothing it said is counted
    hosts = [unreachable_host(), host_with(policy("bookworm.txt", "arm64"), name="team2-main", team="team2"),
             host_with(["amd64", "#too-many"], name="team3-main", team="team3"), cut_short]
    lines = status_lock.lock_lines(lock(jazzy_riscv64=BOOKWORM, jazzy_amd64=BOOKWORM), hosts, NOW)
    assert [line["text"] for line in lines] == [
        "class lock jazzy/amd64: taken 2026-11-15 (8 days ago) from team1-main; 2 packages pinned, 0 held",
        "  newer upstream: not read (2 packages are more than one status command can name)",
        "class lock jazzy/riscv64: taken 2026-11-15 (8 days ago) from team1-main; 2 packages pinned, 0 held",
        "  newer upstream: not read (no host of this group answered)",
        "jazzy/arm64 (team2-main): not in the class lock: roslab lock takes it"]
    assert status_lock.lock_lines(None, hosts, NOW) == []  # no lock: status says nothing of one
    assert status_lock.lock_lines(ClassLock(), [], NOW)[0]["text"].endswith("roslab lock takes one")


def test_the_page_shows_the_lines_escaped_and_the_terminal_after_the_table(capsys):
    hosts = [host_with(policy("bookworm-bash-pinned.txt"))]
    context = page_context("c", "classroom.yaml", hosts, NOW)
    context["lock"] = status_lock.lock_lines(lock(jazzy_amd64={"bash": "5.2.15-2+b8"}), hosts, NOW)
    context["lock"].append({"level": "warn", "text": "<b>x</b>"})
    page = render_page(context)
    assert '<p class="warn">  1 package newer upstream than the lock' in page and "&lt;b&gt;x" in page
    assert 'class="lock"' not in render_page(page_context("c", "classroom.yaml", hosts, NOW))


# the command ---------------------------------------------------------------------------------


def test_status_shows_the_lock_beside_the_roster_even_with_no_host_answering(tmp_path):
    roster = loopback_roster(tmp_path, free_port())  # nothing listens: refused at once
    (tmp_path / "classroom.lock").write_text(render_lock(lock(jazzy_arm64={"bash": "5.2.15-2+b8"})))
    result = roslab("status", str(roster), "--limit", "team1-main")
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    lines = result.stdout.splitlines()
    start = next(index for index, line in enumerate(lines) if line.startswith("class lock "))
    assert lines[start - 1] == ""  # after the table, apart from it
    assert lines[start].startswith("class lock jazzy/arm64: taken 2026-11-15 (")
    assert lines[start + 1] == "  newer upstream: not read (no host of this group answered)"
    assert "class lock jazzy/arm64" in (tmp_path / ".roslab-state" / "status.html").read_text()


def test_a_broken_lock_is_one_line_naming_file_and_field(tmp_path):
    roster = loopback_roster(tmp_path, free_port())
    (tmp_path / "classroom.lock").write_text("groups:\n  'jazzy/arm64':\n    taken: 'yesterday'\n"
                                             "    taken_from: 'team1-main'\n    packages: {}\n")
    result = roslab("status", str(roster))
    assert result.returncode == 1 and "Traceback" not in result.stderr
    problems = [line for line in result.stderr.splitlines() if "classroom.lock" in line]
    assert len(problems) == 1 and "groups.jazzy/arm64.taken" in problems[0], result.stderr
