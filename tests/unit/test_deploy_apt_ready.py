"""apt readiness: the bounded lock wait, an interrupted dpkg healed, the sources, and lists
refreshed only when needed (and never trusted after a failed update)."""

from __future__ import annotations

import pytest
from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy.apt_ready import apt_lists, apt_ready
from deploy.common import supported_host
from roslab import settings
from roslab.ops.apt import apt_update_command

STAMP = "/var/lib/apt/periodic/update-success-stamp"
UPDATE = apt_update_command(600)  # fails on any failed download; the stamp only after success
LISTS_UPDATED = ("The apt lists are fresh: one apt-get update after every source is written"
                 " | Ensure the apt lists are updated after a source change"
                 " or apt_cache_max_age")


def run_apt_ready():
    if supported_host():
        apt_ready()
        apt_lists()


def test_a_held_dpkg_lock_stops_the_host_with_apts_reason(tmp_path):
    host = FakeUbuntu()
    host.apt_problem = {
        "interrupted": False,
        "message": "E: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 812 (unattended-upgr)",
    }
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, apt_lock_timeout=5))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "host pi (team team1): apt is not usable after waiting up to 5 s (apt_lock_timeout)" in error
    assert "unattended-upgr" in error


def test_a_dpkg_killed_mid_install_is_finished_first_and_reported_in_one_line(tmp_path, caplog):
    host = FakeUbuntu()
    host.apt_problem = {"interrupted": True, "message": "dpkg was interrupted (1 pending entries in /var/lib/dpkg/updates/)"}
    with caplog.at_level("WARNING"):
        result = plan(run_apt_ready, host.facts(), host_data(tmp_path))
    assert not result.failed, result.errors
    first = result.operations[0]
    assert "install dpkg was interrupted in is finished" in first.name
    assert first.text()[0].startswith("DEBIAN_FRONTEND=noninteractive dpkg --force-confdef --force-confold --configure -a")
    assert "dpkg --remove --force-remove-reinstreq" in first.text()[1]  # what no apt source holds
    assert first.text()[2].endswith("-o DPkg::Lock::Timeout=600 -o Dpkg::Options::=--force-confdef "
                                    "-o Dpkg::Options::=--force-confold -f install")
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "host pi (team team1): dpkg was interrupted" in warning and "\n" not in warning


def test_a_healthy_apt_adds_no_repair_step(tmp_path):
    result = plan(run_apt_ready, FakeUbuntu().facts(), host_data(tmp_path))
    assert not any("interrupted" in op.name for op in result.operations)


def test_changed_sources_refresh_the_lists_even_when_they_are_young(tmp_path):
    host = FakeUbuntu("jammy")
    host.ages[STAMP] = 60
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, "jammy"))
    assert result.uploads()["/etc/apt/sources.list"].splitlines() == [
        "deb http://10.11.0.1/ubuntu jammy main restricted universe",
        "deb http://10.11.0.1/ubuntu jammy-updates main restricted universe",
        "deb http://10.11.0.1/ubuntu jammy-backports main restricted universe",
        "deb http://10.11.0.1/ubuntu jammy-security main restricted universe",
    ]
    assert result.changing()[LISTS_UPDATED] == [UPDATE]


def test_complete_sources_and_young_lists_change_nothing(tmp_path):
    host = FakeUbuntu()
    host.apply(plan(run_apt_ready, host.facts(), host_data(tmp_path)))
    host.ages[STAMP] = 3600
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path))
    assert result.changing() == {}
    assert "apt lists are 3600 s old (max age 86400 s)" in result.noops


def test_lists_older_than_the_max_age_are_refreshed(tmp_path):
    host = FakeUbuntu()
    host.apply(plan(run_apt_ready, host.facts(), host_data(tmp_path)))
    host.ages[STAMP] = 7200
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, apt_cache_max_age=3600))
    assert result.changing() == {LISTS_UPDATED: [UPDATE]}


def test_lists_a_failed_update_left_stale_are_updated_on_the_next_run(tmp_path):
    """The update removes the stamp before it runs: after a failure the stamp is missing."""
    host = FakeUbuntu()
    host.apply(plan(run_apt_ready, host.facts(), host_data(tmp_path)))
    host.ages.pop(STAMP)  # what a failed `apt-get update` leaves
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path))
    assert result.operation("or apt_cache_max_age").text() == [UPDATE]


@pytest.mark.parametrize("suites", [["updates\nTrusted: yes"], ["updates backports"], ["-o"], ["Updates"]])
def test_a_suite_that_is_not_a_plain_word_is_refused_by_the_schema(suites):
    assert settings.check_value(settings.SETTINGS["apt_extra_suites"], suites)


def test_a_legal_extra_suite_is_written_into_the_hosts_layout(tmp_path):
    assert settings.check_value(settings.SETTINGS["apt_extra_suites"], ["proposed"]) is None
    result = plan(run_apt_ready, FakeUbuntu().facts(), host_data(tmp_path, apt_extra_suites=["proposed"]))
    sources = result.uploads()["/etc/apt/sources.list.d/ubuntu.sources"].splitlines()
    assert "Suites: noble noble-security noble-proposed" in sources


def test_the_old_ros_source_is_moved_aside_before_the_update_it_would_fail(tmp_path):
    host = FakeUbuntu("jammy")
    host.ages[STAMP] = 60
    host.files["/etc/apt/sources.list.d/ros2.list"] = ["deb http://packages.ros.org/ros2/ubuntu jammy main"]
    host.files["/etc/apt/sources.list"] = [line.replace("main restricted", "main restricted universe")
                                           for line in host.files["/etc/apt/sources.list"]]
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, "jammy", apt_extra_suites=[]))
    assert list(result.changing()) == [
        "apt is ready: the dpkg lock is free, the sources complete and the lists fresh"
        " | Ensure the old ROS 2 apt source files are gone (kept in /var/backups/roslab)",
        LISTS_UPDATED,
    ]


def test_a_lock_wait_that_ended_well_is_reported_in_one_line_and_the_run_goes_on(tmp_path, caplog):
    host = FakeUbuntu()
    host.apt_problem = {"interrupted": False, "message": None,
                        "waited": "Waiting for cache lock: ... held by process 812 (unattended-upgr)..."}
    with caplog.at_level("WARNING"):
        result = plan(run_apt_ready, host.facts(), host_data(tmp_path, apt_lock_timeout=300))
    assert not result.failed, result.errors
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "host pi (team team1): waited for the dpkg lock (up to 300 s, apt_lock_timeout)" in warning
    assert "unattended-upgr" in warning


# cloud-init's first boot on a freshly seeded Pi: waited for, bounded, inside the probe.

def test_the_probe_waits_for_cloud_init_only_while_it_runs_this_boot():
    from roslab.ops.apt import AptProblem

    command = AptProblem().command(lock_timeout=42).get_raw_value()
    wait = command[: command.index("apt-get")]
    assert wait.startswith("if [ -e /run/cloud-init/enabled ] && [ ! -e /run/cloud-init/result.json ]")
    assert "timeout 42 cloud-init status --wait" in wait


@pytest.mark.parametrize("line, expected", [
    ("roslab-cloud-init=0 37 status: done", {"status": 0, "seconds": 37, "output": "status: done"}),
    ("roslab-cloud-init=124 600 ", {"status": 124, "seconds": 600, "output": ""}),
])
def test_what_the_cloud_init_wait_said_is_kept_beside_apts_verdict(line, expected):
    from roslab.ops.apt import AptProblem

    assert AptProblem().process([line, "roslab-apt-exit=0"]) == {
        "interrupted": False, "message": None, "cloud_init": expected}


def test_a_wait_for_cloud_init_is_one_warning_line_and_apt_carries_on(tmp_path, caplog):
    host = FakeUbuntu()
    host.apt_problem = {"interrupted": False, "message": None,
                        "cloud_init": {"status": 0, "seconds": 37, "output": "status: done"}}
    with caplog.at_level("WARNING"):
        result = plan(run_apt_ready, host.facts(), host_data(tmp_path))
    assert not result.failed, result.errors
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert "host pi (team team1): waited 37 s for cloud-init to finish its first boot" in warning
    assert "\n" not in warning
    assert any("universe" in op.name for op in result.operations)


def test_cloud_init_still_running_at_the_timeout_stops_this_host(tmp_path):
    host = FakeUbuntu()
    host.apt_problem = {"interrupted": False, "message": None,
                        "cloud_init": {"status": 124, "seconds": 5, "output": "status: running"}}
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, apt_lock_timeout=5))
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "cloud-init's first boot is still running after 5 s (apt_lock_timeout): status: running" in error
