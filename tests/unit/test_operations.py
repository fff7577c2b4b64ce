"""roslab's pyinfra operations, pyinfra-style: the host's facts in, the commands out."""

from __future__ import annotations

import os
import subprocess

import pytest
from fixtures.fake_host import plan
from pyinfra.facts.files import File, FileContents, Link
from pyinfra.facts.server import Locales, Which

from roslab import quoting
from roslab.ops import apt
from roslab.ops.apt import (
    AptProblem,
    apt_get,
    apt_install_options,
    apt_lists_updated,
    apt_lock_options,
    apt_update_command,
    command_installed,
    REMOVE_UNFETCHABLE_HALF_INSTALLED,
    dpkg_interrupted_install_finished,
    ubuntu_apt_sources,
    with_deb822_suites,
    with_one_line_suites,
)
from roslab.ops.files import BACKUP_SUFFIX, FileAge, block_repair, files_moved_aside, managed_block
from roslab.ops.locale import locale_generated, with_locale_enabled
from roslab.ops.rosdep import rosdep_cache_updated, rosdep_initialized

BASHRC = ["# user's own settings", "alias ll='ls -alF'"]
BLOCK_BEGIN = "# BEGIN roslab managed block (ROS 2 environment)"
BLOCK_END = "# END roslab managed block (ROS 2 environment)"
OWNED = {"user": "student", "group": "student", "mode": 640}


def files(contents: dict):
    """FileContents/File facts for a host holding `contents` (path -> lines)."""
    return {
        FileContents: lambda path: contents.get(path),
        File: lambda path: dict(OWNED) if path in contents else None,
    }


# --- managed_block -----------------------------------------------------------------


def block(facts, path="/home/student/.bashrc", content="export ROS_DOMAIN_ID=11", diff=False):
    return plan(
        managed_block, facts, diff=diff, path=path, content=content,
        label="ROS 2 environment", user="student", group="student", mode="644",
    )


def test_managed_block_is_appended_after_the_users_lines_keeping_owner_and_mode():
    result = block(files({"/home/student/.bashrc": BASHRC}))
    assert result.uploads()["/home/student/.bashrc"] == "\n".join(
        [*BASHRC, "", BLOCK_BEGIN, "export ROS_DOMAIN_ID=11", BLOCK_END]
    ) + "\n"
    # Owner and mode travel with the upload: no chown/chmod after it that could follow a link.
    assert result.changing()["files.managed_block"] == ["upload /home/student/.bashrc"]
    assert owner_and_mode(result) == ("student", "student", 0o640)  # the user's own mode


def test_managed_block_replaces_only_its_own_lines():
    current = [*BASHRC, BLOCK_BEGIN, "export ROS_DOMAIN_ID=3", BLOCK_END, "echo after"]
    result = block(files({"/home/student/.bashrc": current}))
    assert result.uploads()["/home/student/.bashrc"].splitlines() == [
        *BASHRC, BLOCK_BEGIN, "export ROS_DOMAIN_ID=11", BLOCK_END, "echo after"
    ]


def test_managed_block_is_a_noop_when_the_block_is_current():
    current = [*BASHRC, "", BLOCK_BEGIN, "export ROS_DOMAIN_ID=11", BLOCK_END]
    result = block(files({"/home/student/.bashrc": current}))
    assert result.changing() == {}
    assert result.noops == ["block (ROS 2 environment) in /home/student/.bashrc is already up to date"]


def test_managed_block_creates_a_missing_file_with_the_given_owner():
    result = block(files({}))
    assert result.changing()["files.managed_block"] == ["upload /home/student/.bashrc"]
    assert owner_and_mode(result) == ("student", "student", 0o644)


def owner_and_mode(result):
    [upload] = [command for op in result.operations for command in op.commands
                if getattr(command, "dest", None) == "/home/student/.bashrc"]
    return upload.user, upload.group, upload.mode


def test_managed_block_prints_a_unified_diff_under_diff(caplog):
    current = [*BASHRC, BLOCK_BEGIN, "export ROS_DOMAIN_ID=3", BLOCK_END]
    with caplog.at_level("INFO"):
        block(files({"/home/student/.bashrc": current}), diff=True)
    printed = "\n".join(record.getMessage() for record in caplog.records)
    assert "- export ROS_DOMAIN_ID=3" in printed
    assert "+ export ROS_DOMAIN_ID=11" in printed


# --- managed_block: markers someone edited -------------------------------------------

CONTENT = "source /opt/ros/jazzy/setup.bash\nexport ROS_DOMAIN_ID=11"
BODY = CONTENT.split("\n")
BLOCK = [BLOCK_BEGIN, *BODY, BLOCK_END]
OLD_BODY = ["source /opt/ros/jazzy/setup.bash", "export ROS_DOMAIN_ID=3"]  # an older block
MINE = ["# my own settings", "alias gs='git status'", "fi", "export EDITOR=vim"]  # "fi" as in a block
LATER = ["source ~/my_ws/install/setup.bash", "echo hello"]


def is_subsequence(needles: list[str], haystack: list[str]) -> bool:
    remaining = iter(haystack)
    return all(any(line == candidate for candidate in remaining) for line in needles)


def one_block_holding_the_content(lines: list[str]) -> bool:
    begins = [i for i, line in enumerate(lines) if line == BLOCK_BEGIN]
    ends = [i for i, line in enumerate(lines) if line == BLOCK_END]
    return len(begins) == len(ends) == 1 and lines[begins[0] + 1 : ends[0]] == BODY


# accident: (the file, the user's lines in it, the file repaired). Lines between a begin
# marker and its end are roslab's (as when the markers are fine); every other line is the user's.
ACCIDENTS = {
    # A student deleted the end marker (and wrote more lines below the block later).
    "end marker deleted": (
        [*MINE, BLOCK_BEGIN, *BODY, *LATER], [*MINE, *LATER], [*MINE, *BLOCK, *LATER]),
    # ... while the block's content changed too: the old lines stay, as the student's.
    "end marker deleted, old content": (
        [*MINE, BLOCK_BEGIN, *OLD_BODY, *LATER], [*MINE, *OLD_BODY, *LATER],
        [*MINE, *BLOCK, *OLD_BODY, *LATER]),
    "begin marker deleted": (
        [*MINE, *BODY, BLOCK_END, *LATER], [*MINE, *LATER], [*MINE, *BLOCK, *LATER]),
    # What roslab before this fix left after the end marker was deleted: a second block.
    "two begin markers": (
        [*MINE, BLOCK_BEGIN, *BODY, *LATER, "", BLOCK_BEGIN, *BODY, BLOCK_END], [*MINE, *LATER, ""],
        [*MINE, *BLOCK, *LATER, ""]),
    "two blocks": (
        [*MINE, *BLOCK, *LATER, BLOCK_BEGIN, *OLD_BODY, BLOCK_END, "echo end"], [*MINE, *LATER, "echo end"],
        [*MINE, *BLOCK, *LATER, "echo end"]),
    "markers in the wrong order": (
        [*MINE, BLOCK_END, *LATER, BLOCK_BEGIN, *BODY, "echo end"], [*MINE, *LATER, "echo end"],
        [*MINE, *BLOCK, *LATER, "echo end"]),
    "two end markers": (
        [*MINE, *BLOCK, *LATER, BLOCK_END], [*MINE, *LATER], [*MINE, *BLOCK, *LATER]),
    "nested blocks": (
        [*MINE, BLOCK_BEGIN, "x", BLOCK_BEGIN, *OLD_BODY, BLOCK_END, "y", BLOCK_END, *LATER],
        [*MINE, "x", "y", *LATER], [*MINE, *BLOCK, "x", "y", *LATER]),
}


@pytest.mark.parametrize("accident", sorted(ACCIDENTS))
def test_an_edited_marker_is_repaired_without_losing_a_user_line(accident):
    current, user_lines, expected = ACCIDENTS[accident]
    repaired, what = block_repair(current, "ROS 2 environment", CONTENT)
    assert is_subsequence(user_lines, repaired), f"a user line was lost: {user_lines} vs {repaired}"
    assert one_block_holding_the_content(repaired)
    assert repaired == expected
    assert what and "expected one pair" in what
    # Repaired once, then left alone.
    assert block_repair(repaired, "ROS 2 environment", CONTENT) == (repaired, None)


def test_a_repair_backs_the_file_up_first_logs_one_line_and_shows_the_diff(caplog):
    current = [*MINE, BLOCK_BEGIN, *OLD_BODY, *LATER]  # the end marker was deleted
    with caplog.at_level("INFO"):
        result = block(files({"/home/student/.bashrc": current}), content=CONTENT, diff=True)
    commands = result.changing()["files.managed_block"]
    backup = f"/home/student/.bashrc{BACKUP_SUFFIX}"
    assert commands[0] == f"cp -p -- /home/student/.bashrc {backup}"
    assert commands[1] == "upload /home/student/.bashrc"
    uploaded = result.uploads()["/home/student/.bashrc"].splitlines()
    assert uploaded == [*MINE, *BLOCK, *OLD_BODY, *LATER]
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "pi" in warnings[0] and "/home/student/.bashrc" in warnings[0] and backup in warnings[0]
    assert "1 begin and 0 end markers" in warnings[0]
    printed = "\n".join(r.getMessage() for r in caplog.records)
    assert f"+ {BLOCK_END}" in printed


def test_lines_like_the_block_beside_a_lone_marker_stay_unless_they_are_all_of_it():
    # Only the whole old block, right at the marker, is taken as roslab's.
    current = [*MINE, BLOCK_BEGIN, BODY[0], *LATER]
    repaired, _ = block_repair(current, "ROS 2 environment", CONTENT)
    assert repaired == [*MINE, *BLOCK, BODY[0], *LATER]


def test_an_ordinary_update_takes_no_backup():
    result = block(files({"/home/student/.bashrc": [*BASHRC, BLOCK_BEGIN, "old", BLOCK_END]}))
    assert not any(command.startswith("cp ") for command in result.changing()["files.managed_block"])


# --- Ubuntu apt sources -------------------------------------------------------------

NOBLE = [
    "Types: deb",
    "URIs: http://ports.ubuntu.com/ubuntu-ports/",
    "Suites: noble noble-security",
    "Components: main restricted",
    "Signed-By: /usr/share/keyrings/ubuntu-archive-keyring.gpg",
]


def sources(contents):
    return plan(
        ubuntu_apt_sources, files(contents),
        codename=contents.get("codename", "noble"), components=["universe"],
        suites=["updates", "backports"],
    )


def test_deb822_sources_get_universe_and_the_extra_suites_in_place():
    result = sources({"/etc/apt/sources.list.d/ubuntu.sources": NOBLE})
    assert result.uploads()["/etc/apt/sources.list.d/ubuntu.sources"].splitlines() == [
        "Types: deb",
        "URIs: http://ports.ubuntu.com/ubuntu-ports/",
        "Suites: noble noble-security noble-updates noble-backports",
        "Components: main restricted universe",
        "Signed-By: /usr/share/keyrings/ubuntu-archive-keyring.gpg",
    ]


def test_deb822_security_only_stanza_gets_universe_but_no_extra_suites():
    lines = with_deb822_suites(
        ["# comment", *NOBLE, "", "Types: deb", "URIs: http://security.ubuntu.com/ubuntu/",
         "Suites: noble-security", "Components: main"],
        "noble", ["universe"], ["updates"],
    )
    assert lines[0] == "# comment"
    assert lines[-2:] == ["Suites: noble-security", "Components: main universe"]


def test_deb822_sources_of_other_releases_are_left_alone():
    other = ["Types: deb", "URIs: http://x/", "Suites: jammy", "Components: main"]
    assert with_deb822_suites(other, "noble", ["universe"], ["updates"]) == other


def test_one_line_sources_get_universe_and_new_suite_lines_with_the_same_uri():
    lines = with_one_line_suites(
        ["# deb-src http://ports.ubuntu.com/ubuntu-ports jammy main",
         "deb [arch=arm64] http://ports.ubuntu.com/ubuntu-ports jammy main restricted",
         "deb http://ports.ubuntu.com/ubuntu-ports jammy-updates main restricted universe"],
        "jammy", ["universe"], ["updates", "backports"],
    )
    assert lines == [
        "# deb-src http://ports.ubuntu.com/ubuntu-ports jammy main",
        "deb [arch=arm64] http://ports.ubuntu.com/ubuntu-ports jammy main restricted universe",
        # jammy-updates is already listed for this URI, so only backports is added
        "deb [arch=arm64] http://ports.ubuntu.com/ubuntu-ports jammy-backports main restricted universe",
        "deb http://ports.ubuntu.com/ubuntu-ports jammy-updates main restricted universe",
    ]


def test_complete_sources_are_a_noop():
    complete = with_deb822_suites(NOBLE, "noble", ["universe"], ["updates", "backports"])
    result = sources({"/etc/apt/sources.list.d/ubuntu.sources": complete})
    assert result.changing() == {}
    assert result.noops == ["Ubuntu apt sources already enable universe noble-updates noble-backports"]


def test_a_one_line_sources_comment_stays_a_comment():
    lines = with_one_line_suites(
        ["deb http://ports.ubuntu.com/ubuntu-ports jammy main # the Pi's mirror"], "jammy", ["universe"], [],
    )
    assert lines == ["deb http://ports.ubuntu.com/ubuntu-ports jammy main universe # the Pi's mirror"]


def test_the_hosts_own_odd_words_are_kept_as_they_are_never_refused():
    # A word roslab would never write (a control character) in the host's own file: kept, no error.
    odd = ["Types: deb", "URIs: http://x/", "Suites: noble noble-\x1bodd", "Components: main"]
    lines = with_deb822_suites(odd, "noble", ["universe"], ["updates"])
    assert lines[2] == "Suites: noble noble-\x1bodd noble-updates"


@pytest.mark.parametrize("word", ["updates\nTrusted: yes", "updates backports", "up#dates", "[trusted=yes]"])
def test_a_suite_that_would_change_the_sources_meaning_is_refused(word):
    with pytest.raises(ValueError):
        quoting.sources_list_word(word)
    with pytest.raises(ValueError):
        with_deb822_suites(NOBLE, "noble", [], [word])
    with pytest.raises(ValueError):
        with_one_line_suites(["deb http://x jammy main"], "jammy", [], [word])


def test_an_empty_word_is_refused():
    with pytest.raises(ValueError):
        quoting.sources_list_word("")


def test_legal_suites_are_written_as_they_are_in_both_layouts():
    assert with_deb822_suites(NOBLE, "noble", [], ["proposed"])[2] == (
        "Suites: noble noble-security noble-proposed")
    assert with_one_line_suites(["deb http://x jammy main"], "jammy", [], ["proposed"]) == [
        "deb http://x jammy main", "deb http://x jammy-proposed main"]


# --- apt lists, packages, .debs ------------------------------------------------------

STAMP = "/var/lib/apt/periodic/update-success-stamp"


UPDATE = apt_update_command(30)


@pytest.mark.parametrize("age", [None, 90000])
def test_stale_or_missing_apt_lists_are_updated_with_a_bounded_lock_wait(age):
    result = plan(apt_lists_updated, {FileAge: lambda path: age}, lock_timeout=30, max_age=86400)
    assert result.changing()["apt.apt_lists_updated"] == [UPDATE]
    assert "-o DPkg::Lock::Timeout=30 -o APT::Update::Error-Mode=any update" in UPDATE


def run_update(tmp_path, apt_get_script: str, update: str = UPDATE):
    """The update command in a shell, with a stand-in apt-get and the stamp under tmp_path."""
    stamp = tmp_path / "periodic" / "update-success-stamp"
    stamp.parent.mkdir(exist_ok=True)
    stamp.write_text("")
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir(exist_ok=True)
    (fake_bin / "apt-get").write_text("#!/bin/sh\n" + apt_get_script)
    (fake_bin / "apt-get").chmod(0o755)
    command = update.replace(STAMP, str(stamp)).replace("/var/lib/apt/periodic", str(stamp.parent))
    done = subprocess.run(["sh", "-c", command], env={**os.environ, "PATH": f"{fake_bin}:{os.environ['PATH']}"},
                          capture_output=True, text=True)
    return done, stamp


# apt-get update as it behaves when one index fails to download: exit 0 with warnings, or
# (with APT::Update::Error-Mode=any, apt >= 2.1.16) exit 100 with errors.
MIRROR_GONE = """echo "Hit:1 http://10.11.0.1/ubuntu noble InRelease"
echo "Err:2 http://10.11.0.1/ros2/ubuntu noble InRelease"
echo "  Could not connect to 10.11.0.1:80 (10.11.0.1), connection refused"
case "$*" in *Error-Mode=any*) level=E status=100 ;; *) level=W status=0 ;; esac
echo "$level: Failed to fetch http://10.11.0.1/ros2/ubuntu/dists/noble/InRelease  Could not connect"
echo "$level: Some index files failed to download. They have been ignored, or old ones used instead."
exit $status
"""


def test_an_update_with_a_failed_download_fails_in_one_line_and_leaves_the_lists_stale(tmp_path):
    """The mirror gone mid-update: the run fails, and the next run updates again instead of
    trusting lists without the mirror's packages for a day."""
    done, stamp = run_update(tmp_path, MIRROR_GONE)
    assert done.returncode == 100
    assert not stamp.exists()
    assert done.stdout == ""
    (line,) = done.stderr.splitlines()
    assert line.startswith("roslab: apt-get update failed, the lists stay stale until one succeeds: "
                           "E: Failed to fetch http://10.11.0.1/ros2/ubuntu/dists/noble/InRelease")


def test_a_stuck_update_is_stopped_and_said_so_in_one_line(tmp_path, monkeypatch):
    """apt waiting forever on a proxy that dropped a request must not hang the class's run."""
    monkeypatch.setattr(apt, "APT_UPDATE_MAX_SECONDS", 1)
    done, stamp = run_update(tmp_path, "exec sleep 60\n", update=apt_update_command(0))
    assert done.returncode == 124
    assert not stamp.exists()
    (line,) = done.stderr.splitlines()
    assert line == ("roslab: apt-get update was stopped after 1 s without finishing (a stuck download); "
                    "the lists stay stale and the next run updates again")


def test_a_successful_update_marks_the_lists_fresh(tmp_path):
    done, stamp = run_update(tmp_path, 'echo "Hit:1 http://10.11.0.1/ubuntu noble InRelease"\n')
    assert done.returncode == 0 and stamp.exists() and done.stderr == ""


def test_fresh_apt_lists_are_a_noop():
    result = plan(apt_lists_updated, {FileAge: lambda path: 60}, lock_timeout=30, max_age=86400)
    assert result.changing() == {}
    assert result.noops == ["apt lists are 60 s old (max age 86400 s)"]


def test_the_lock_wait_is_spelled_once():
    assert apt_lock_options(600) == "-o DPkg::Lock::Timeout=600"
    assert apt_install_options(5) == "-o DPkg::Lock::Timeout=5 --"
    assert apt_get("update", 7) == "DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout=7 update"


def test_an_interrupted_dpkg_is_finished_then_apt_completes_it():
    result = plan(dpkg_interrupted_install_finished, {}, lock_timeout=30)
    configure, remove, fix = result.changing()["apt.dpkg_interrupted_install_finished"]
    assert remove == REMOVE_UNFETCHABLE_HALF_INSTALLED
    assert configure.startswith("DEBIAN_FRONTEND=noninteractive dpkg --force-confdef --force-confold --configure -a ||")
    assert fix == (
        "DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout=30 "
        "-o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold -f install"
    )


def test_command_installed_installs_the_package_only_when_the_command_is_missing():
    facts = {Which: lambda command: None}
    result = plan(command_installed, facts, command="rosdep", package="python3-rosdep", lock_timeout=5)
    assert result.changing()["apt.command_installed"] == [
        "DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout=5 "
        "-o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold install -- python3-rosdep"
    ]
    facts = {Which: lambda command: "/usr/bin/rosdep"}
    result = plan(command_installed, facts, command="rosdep", package="python3-rosdep", lock_timeout=5)
    assert result.noops == ["rosdep is already installed"]


def test_command_installed_never_passes_an_option_as_a_package():
    with pytest.raises(ValueError, match="starts with '-'"):
        plan(command_installed, {Which: lambda command: None},
             command="rosdep", package="-oAPT::Get::AllowUnauthenticated=1", lock_timeout=5)


def test_old_files_are_moved_aside_and_symlinks_kept_when_asked():
    facts = {
        File: lambda path: {"user": "root"} if path == "/etc/apt/sources.list.d/ros2.list" else (
            False if path == "/etc/apt/sources.list.d/ros2.sources" else None),
        Link: lambda path: {"link_target": "/usr/share/ros-apt-source/ros2.sources"}
        if path == "/etc/apt/sources.list.d/ros2.sources" else None,
    }
    paths = ["/etc/apt/sources.list.d/ros2.list", "/etc/apt/sources.list.d/ros2.sources"]
    result = plan(files_moved_aside, facts, paths=paths, backup_dir="/var/backups/roslab",
                  only_regular_files=True)
    assert result.changing()["files.files_moved_aside"] == [
        "mkdir -p /var/backups/roslab",
        "mv --backup=numbered /etc/apt/sources.list.d/ros2.list /var/backups/roslab",
    ]


def test_nothing_to_move_aside_is_a_noop():
    result = plan(files_moved_aside, {File: lambda path: None, Link: lambda path: None},
                  paths=["/a"], backup_dir="/b")
    assert result.changing() == {} and result.noops == ["none of /a exists"]


# --- locale, rosdep -------------------------------------------------------------------


def test_missing_locale_is_enabled_in_locale_gen_and_generated():
    facts = {Locales: ["C.UTF-8"], **files({"/etc/locale.gen": ["# en_US.UTF-8 UTF-8", "# de_DE.UTF-8 UTF-8"]})}
    result = plan(locale_generated, facts, locale="en_US.UTF-8")
    assert result.uploads()["/etc/locale.gen"].splitlines() == ["en_US.UTF-8 UTF-8", "# de_DE.UTF-8 UTF-8"]
    assert result.changing()["locale.locale_generated"][-1] == "locale-gen en_US.UTF-8"


def test_generated_locale_is_a_noop():
    result = plan(locale_generated, {Locales: ["C.UTF-8", "en_US.UTF-8"]}, locale="en_US.UTF-8")
    assert result.changing() == {} and result.noops == ["locale en_US.UTF-8 is already generated"]


def test_with_locale_enabled_appends_a_locale_the_file_does_not_list():
    assert with_locale_enabled(["# x"], "de_DE.UTF-8") == ["# x", "de_DE.UTF-8 UTF-8"]


def test_rosdep_init_runs_only_without_a_sources_list():
    assert plan(rosdep_initialized, {File: lambda path: None}).changing() == {
        "rosdep.rosdep_initialized": ["rosdep init"]
    }
    result = plan(rosdep_initialized, {File: lambda path: {"user": "root"}})
    assert result.changing() == {}
    assert result.noops == ["/etc/ros/rosdep/sources.list.d/20-default.list already exists"]


def test_rosdep_update_reads_the_rosdistro_index_from_the_setting_when_stale():
    ages = {"/home/student/.ros/rosdep/sources.cache/index": 700000}
    result = plan(rosdep_cache_updated, {FileAge: lambda path: ages.get(path)},
                  home="/home/student", max_age=604800, rosdistro_index_url="http://10.0.0.1/index-v4.yaml")
    assert result.changing()["rosdep.rosdep_cache_updated"] == [
        "env ROSDISTRO_INDEX_URL=http://10.0.0.1/index-v4.yaml rosdep update"
    ]
    ages["/home/student/.ros/rosdep/sources.cache/index"] = 10
    result = plan(rosdep_cache_updated, {FileAge: lambda path: ages.get(path)},
                  home="/home/student", max_age=604800)
    assert result.noops == ["rosdep cache is 10 s old (max age 604800 s)"]


# --- facts ----------------------------------------------------------------------------


def test_apt_problem_fact_is_none_when_apt_check_succeeds_and_dpkg_is_done():
    assert AptProblem().process(["roslab-apt-exit=0"]) is None


def test_apt_problem_fact_reports_apts_verdict_not_its_waiting_lines():
    output = [
        "Waiting for cache lock: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 812 (unattended-upgr)...",
        "E: Unable to acquire the dpkg frontend lock (/var/lib/dpkg/lock-frontend), is another process using it?",
        "roslab-apt-exit=100",
        # unattended-upgrades is mid-install: its journal is no interruption
        "roslab-dpkg-update: 0001",
        "roslab-dpkg-audit: The following packages have been unpacked but not yet configured.",
    ]
    assert AptProblem().process(output) == {"interrupted": False, "message": output[1]}


def test_apt_problem_fact_reports_a_dpkg_interrupted_mid_install():
    output = [
        "E: dpkg was interrupted, you must manually run 'dpkg --configure -a' to correct the problem. ",
        "roslab-apt-exit=100",
        "roslab-dpkg-update: 0000",
        "roslab-dpkg-update: 0001",
        "roslab-dpkg-audit: The following packages are only half configured, probably due to problems",
        "roslab-dpkg-audit:  ros-jazzy-ros-base   ROS 2 stand-in",
    ]
    problem = AptProblem().process(output)
    assert problem["interrupted"] is True
    assert problem["message"].startswith("dpkg was interrupted (2 pending entries in /var/lib/dpkg/updates/; dpkg --audit:")
    assert "ros-jazzy-ros-base" in problem["message"] and "\n" not in problem["message"]


def test_apt_problem_fact_sees_unconfigured_packages_that_apt_check_lets_pass():
    output = ["roslab-apt-exit=0", "roslab-dpkg-audit: The following packages have been unpacked but not yet configured."]
    assert AptProblem().process(output)["interrupted"] is True


def test_apt_problem_fact_waits_with_the_one_lock_option():
    command = AptProblem().command(lock_timeout=42).get_raw_value()
    assert "fi; apt-get -qq -o DPkg::Lock::Timeout=42 check 2>&1;" in command  # after cloud-init's wait
    assert "ls -A /var/lib/dpkg/updates" in command and "dpkg --audit" in command


def test_file_age_fact_parses_seconds_and_missing_files():
    assert FileAge().process(["42"]) == 42
    assert FileAge().process([]) is None


def test_apt_problem_fact_says_who_held_the_lock_when_the_wait_ended_well():
    waiting = "Waiting for cache lock: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 812 (unattended-upgr)..."
    assert AptProblem().process([waiting, waiting, "roslab-apt-exit=0"]) == {
        "interrupted": False, "message": None, "waited": waiting}


def _half_installed_host(tmp_path, archive_versions: dict[str, str]):
    """Stand-ins of dpkg-query, apt-cache and dpkg for the removal script: two half-installed
    packages (ros2-apt-source 1.2.0 from a file, libfoo 2.0), `archive_versions` what apt's
    sources hold; dpkg records what it was asked to remove."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    scripts = {
        "dpkg-query": """case "$3" in
  *Eflag*) printf 'ok installed-pkg\\nreinstreq ros2-apt-source\\nreinstreq libfoo:arm64\\n' ;;
  *) case "$4" in ros2-apt-source) printf 1.2.0 ;; libfoo:arm64) printf 2.0 ;; esac ;;
esac""",
        "apt-cache": "case \"$2\" in " + " ".join(f"{name}) echo ' {name} | {version} | http://archive/ubuntu noble/main';;"
                                                  for name, version in archive_versions.items()) + " esac",
        "dpkg": f"echo \"$@\" >> {tmp_path / 'removed'}",
    }
    for name, text in scripts.items():
        (bin_dir / name).write_text(f"#!/bin/sh\n{text}\n")
        (bin_dir / name).chmod(0o755)
    return {"PATH": f"{bin_dir}:/usr/bin:/bin"}


@pytest.mark.parametrize("archive, removed", [
    ({"libfoo": "2.0"}, ["--remove --force-remove-reinstreq ros2-apt-source"]),
    ({"libfoo": "2.0", "ros2-apt-source": "1.2.0"}, []),
    ({"libfoo": "1.9"}, ["--remove --force-remove-reinstreq ros2-apt-source",
                         "--remove --force-remove-reinstreq libfoo:arm64"]),
])
def test_a_half_installed_package_no_apt_source_holds_is_removed_for_its_step_to_install_again(
        tmp_path, archive, removed):
    """A run interrupted in ros2-apt-source's dpkg -i left it reinst-required; apt then cannot
    reinstall it ("I can't find an archive for it") and every apt-get stops. Only a package whose
    installed version no source holds is removed; apt-get -f reinstalls the others."""
    run = subprocess.run(["sh", "-c", REMOVE_UNFETCHABLE_HALF_INSTALLED], env=_half_installed_host(tmp_path, archive),
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 0, run.stderr
    done = (tmp_path / "removed").read_text().splitlines() if (tmp_path / "removed").exists() else []
    assert done == removed
    assert run.stderr.count("no apt source holds it") == len(removed)
