"""roslab's pyinfra operations, pyinfra-style: the host's facts in, the commands out."""

from __future__ import annotations

import pytest
from fixtures.fake_host import plan
from pyinfra.facts.deb import DebPackage, DebPackages
from pyinfra.facts.files import File, FileContents, Link
from pyinfra.facts.server import Locales, Which

from roslab import operations
from roslab.facts import AptProblem, FileAge

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
        operations.managed_block, facts, diff=diff, path=path, content=content,
        label="ROS 2 environment", user="student", group="student", mode="644",
    )


def test_managed_block_is_appended_after_the_users_lines_keeping_owner_and_mode():
    result = block(files({"/home/student/.bashrc": BASHRC}))
    assert result.uploads()["/home/student/.bashrc"] == "\n".join(
        [*BASHRC, "", BLOCK_BEGIN, "export ROS_DOMAIN_ID=11", BLOCK_END]
    ) + "\n"
    commands = result.changing()["operations.managed_block"]
    assert commands[1:] == [
        "chown student:student /home/student/.bashrc",
        "chmod 640 /home/student/.bashrc",  # the user's own mode, not the default for new files
    ]


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
    assert result.changing()["operations.managed_block"][1:] == [
        "chown student:student /home/student/.bashrc",
        "chmod 644 /home/student/.bashrc",
    ]


def test_managed_block_prints_a_unified_diff_under_diff(caplog):
    current = [*BASHRC, BLOCK_BEGIN, "export ROS_DOMAIN_ID=3", BLOCK_END]
    with caplog.at_level("INFO"):
        block(files({"/home/student/.bashrc": current}), diff=True)
    printed = "\n".join(record.getMessage() for record in caplog.records)
    assert "- export ROS_DOMAIN_ID=3" in printed
    assert "+ export ROS_DOMAIN_ID=11" in printed


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
        operations.ubuntu_apt_sources, files(contents),
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
    lines = operations.with_deb822_suites(
        ["# comment", *NOBLE, "", "Types: deb", "URIs: http://security.ubuntu.com/ubuntu/",
         "Suites: noble-security", "Components: main"],
        "noble", ["universe"], ["updates"],
    )
    assert lines[0] == "# comment"
    assert lines[-2:] == ["Suites: noble-security", "Components: main universe"]


def test_deb822_sources_of_other_releases_are_left_alone():
    other = ["Types: deb", "URIs: http://x/", "Suites: jammy", "Components: main"]
    assert operations.with_deb822_suites(other, "noble", ["universe"], ["updates"]) == other


def test_one_line_sources_get_universe_and_new_suite_lines_with_the_same_uri():
    lines = operations.with_one_line_suites(
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
    complete = operations.with_deb822_suites(NOBLE, "noble", ["universe"], ["updates", "backports"])
    result = sources({"/etc/apt/sources.list.d/ubuntu.sources": complete})
    assert result.changing() == {}
    assert result.noops == ["Ubuntu apt sources already enable universe noble-updates noble-backports"]


# --- apt lists, packages, .debs ------------------------------------------------------

STAMP = "/var/lib/apt/periodic/update-success-stamp"


@pytest.mark.parametrize("age", [None, 90000])
def test_stale_or_missing_apt_lists_are_updated_with_a_bounded_lock_wait(age):
    result = plan(operations.apt_lists_updated, {FileAge: lambda path: age}, lock_timeout=30, max_age=86400)
    assert result.changing()["operations.apt_lists_updated"] == [
        "DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout=30 update",
        f"mkdir -p /var/lib/apt/periodic && touch {STAMP}",
    ]


def test_fresh_apt_lists_are_a_noop():
    result = plan(operations.apt_lists_updated, {FileAge: lambda path: 60}, lock_timeout=30, max_age=86400)
    assert result.changing() == {}
    assert result.noops == ["apt lists are 60 s old (max age 86400 s)"]


def test_deb_file_is_installed_when_its_version_is_not():
    facts = {
        DebPackage: lambda package: {"name": "ros2-apt-source", "version": "1.2.0"},
        DebPackages: {"ros2-apt-source": {"1.1.0"}},
    }
    result = plan(operations.deb_file_installed, facts, src="/var/cache/roslab/x.deb")
    assert result.changing() == {
        "operations.deb_file_installed": ["dpkg --force-confdef --force-confold -i /var/cache/roslab/x.deb"]
    }
    facts[DebPackages] = {"ros2-apt-source": {"1.2.0"}}
    result = plan(operations.deb_file_installed, facts, src="/var/cache/roslab/x.deb")
    assert result.changing() == {}
    assert result.noops == ["ros2-apt-source 1.2.0 is already installed"]


def test_command_installed_installs_the_package_only_when_the_command_is_missing():
    facts = {Which: lambda command: None}
    result = plan(operations.command_installed, facts, command="rosdep", package="python3-rosdep", lock_timeout=5)
    assert result.changing()["operations.command_installed"] == [
        "DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout=5 install python3-rosdep"
    ]
    facts = {Which: lambda command: "/usr/bin/rosdep"}
    result = plan(operations.command_installed, facts, command="rosdep", package="python3-rosdep", lock_timeout=5)
    assert result.noops == ["rosdep is already installed"]


def test_old_files_are_moved_aside_and_symlinks_kept_when_asked():
    facts = {
        File: lambda path: {"user": "root"} if path == "/etc/apt/sources.list.d/ros2.list" else (
            False if path == "/etc/apt/sources.list.d/ros2.sources" else None),
        Link: lambda path: {"link_target": "/usr/share/ros-apt-source/ros2.sources"}
        if path == "/etc/apt/sources.list.d/ros2.sources" else None,
    }
    paths = ["/etc/apt/sources.list.d/ros2.list", "/etc/apt/sources.list.d/ros2.sources"]
    result = plan(operations.files_moved_aside, facts, paths=paths, backup_dir="/var/backups/roslab",
                  only_regular_files=True)
    assert result.changing()["operations.files_moved_aside"] == [
        "mkdir -p /var/backups/roslab",
        "mv --backup=numbered /etc/apt/sources.list.d/ros2.list /var/backups/roslab",
    ]


def test_nothing_to_move_aside_is_a_noop():
    result = plan(operations.files_moved_aside, {File: lambda path: None, Link: lambda path: None},
                  paths=["/a"], backup_dir="/b")
    assert result.changing() == {} and result.noops == ["none of /a exists"]


# --- locale, rosdep -------------------------------------------------------------------


def test_missing_locale_is_enabled_in_locale_gen_and_generated():
    facts = {Locales: ["C.UTF-8"], **files({"/etc/locale.gen": ["# en_US.UTF-8 UTF-8", "# de_DE.UTF-8 UTF-8"]})}
    result = plan(operations.locale_generated, facts, locale="en_US.UTF-8")
    assert result.uploads()["/etc/locale.gen"].splitlines() == ["en_US.UTF-8 UTF-8", "# de_DE.UTF-8 UTF-8"]
    assert result.changing()["operations.locale_generated"][-1] == "locale-gen en_US.UTF-8"


def test_generated_locale_is_a_noop():
    result = plan(operations.locale_generated, {Locales: ["C.UTF-8", "en_US.UTF-8"]}, locale="en_US.UTF-8")
    assert result.changing() == {} and result.noops == ["locale en_US.UTF-8 is already generated"]


def test_with_locale_enabled_appends_a_locale_the_file_does_not_list():
    assert operations.with_locale_enabled(["# x"], "de_DE.UTF-8") == ["# x", "de_DE.UTF-8 UTF-8"]


def test_rosdep_init_runs_only_without_a_sources_list():
    assert plan(operations.rosdep_initialized, {File: lambda path: None}).changing() == {
        "operations.rosdep_initialized": ["rosdep init"]
    }
    result = plan(operations.rosdep_initialized, {File: lambda path: {"user": "root"}})
    assert result.changing() == {}
    assert result.noops == ["/etc/ros/rosdep/sources.list.d/20-default.list already exists"]


def test_rosdep_update_reads_the_rosdistro_index_from_the_setting_when_stale():
    ages = {"/home/student/.ros/rosdep/sources.cache/index": 700000}
    result = plan(operations.rosdep_cache_updated, {FileAge: lambda path: ages.get(path)},
                  home="/home/student", max_age=604800, rosdistro_index_url="http://10.0.0.1/index-v4.yaml")
    assert result.changing()["operations.rosdep_cache_updated"] == [
        "env ROSDISTRO_INDEX_URL=http://10.0.0.1/index-v4.yaml rosdep update"
    ]
    ages["/home/student/.ros/rosdep/sources.cache/index"] = 10
    result = plan(operations.rosdep_cache_updated, {FileAge: lambda path: ages.get(path)},
                  home="/home/student", max_age=604800)
    assert result.noops == ["rosdep cache is 10 s old (max age 604800 s)"]


# --- facts ----------------------------------------------------------------------------


def test_apt_problem_fact_is_none_when_apt_check_succeeds():
    assert AptProblem().process(["roslab-apt-exit=0"]) is None


def test_apt_problem_fact_reports_apts_verdict_not_its_waiting_lines():
    output = [
        "Waiting for cache lock: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 812 (unattended-upgr)...",
        "E: Unable to acquire the dpkg frontend lock (/var/lib/dpkg/lock-frontend), is another process using it?",
        "roslab-apt-exit=100",
    ]
    assert AptProblem().process(output) == output[1]


def test_file_age_fact_parses_seconds_and_missing_files():
    assert FileAge().process(["42"]) == 42
    assert FileAge().process([]) is None
