"""apt readiness: the bounded lock wait, the sources, and lists refreshed only when needed."""

from __future__ import annotations

from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy.apt_ready import apt_ready
from deploy.common import supported_host

STAMP = "/var/lib/apt/periodic/update-success-stamp"


def run_apt_ready():
    if supported_host():
        apt_ready()


def test_a_held_dpkg_lock_stops_the_host_with_apts_reason(tmp_path):
    host = FakeUbuntu()
    host.apt_problem = "E: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 812 (unattended-upgr)"
    result = plan(run_apt_ready, host.facts(), host_data(tmp_path, apt_lock_timeout=5))
    assert result.failed and result.operations == []
    assert "after waiting up to 5 s (apt_lock_timeout)" in result.errors[0]
    assert "unattended-upgr" in result.errors[0]


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
    update = result.operation("include the changed sources").text()
    assert update[0].endswith("apt-get -y -o DPkg::Lock::Timeout=600 update")


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
    assert list(result.changing()) == [
        "apt is ready: the dpkg lock is free, the sources complete and the lists fresh"
        " | Ensure the apt lists are younger than apt_cache_max_age"
    ]
