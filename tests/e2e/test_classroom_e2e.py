"""deploy.py on a sandbox classroom, end to end, over real SSH.

The default sandbox classroom: team1 on an emulated Ubuntu 24.04 (team1-main, team1-robot)
and team2 on an emulated Ubuntu 22.04 (team2-main, team2-robot). One host starts with the
old-style ROS apt source (`ros2.list` and `ros-archive-keyring.gpg`) that breaks apt today.

The tests run in file order on one classroom: converge, re-run, host state, dry run after a
roster change, drift repair, and a bad roster.
"""

from __future__ import annotations

import re

import pytest
import yaml

pytestmark = pytest.mark.e2e

LEGACY_HOST = "team2-robot"
LEGACY_LIST = "/etc/apt/sources.list.d/ros2.list"
LEGACY_KEY = "/usr/share/keyrings/ros-archive-keyring.gpg"
BASHRC_BEGIN = "# BEGIN roslab managed block"

EXPECTED = {
    "team1-main": {"distro": "jazzy", "variant": "desktop", "domain": 11, "codename": "noble"},
    "team1-robot": {"distro": "jazzy", "variant": "ros-base", "domain": 11, "codename": "noble"},
    "team2-main": {"distro": "humble", "variant": "desktop", "domain": 12, "codename": "jammy"},
    "team2-robot": {"distro": "humble", "variant": "ros-base", "domain": 12, "codename": "jammy"},
}


@pytest.fixture(scope="module")
def sandbox(e2e_sandbox):
    """The session's classroom, freshly imaged for this module and again after it."""
    assert sorted(host.name for host in e2e_sandbox.hosts) == sorted(EXPECTED)
    e2e_sandbox.reset()
    yield e2e_sandbox
    e2e_sandbox.reset()  # the next module gets the hosts as it expects them: fresh


@pytest.fixture(scope="module")
def first_run(sandbox):
    """Prepare the legacy host the way a tutorial from before 2025 left it, then converge."""
    sandbox.sudo(
        LEGACY_HOST,
        f"echo 'deb [arch=amd64 signed-by={LEGACY_KEY}] http://packages.ros.org/ros2/ubuntu "
        f"jammy main' > {LEGACY_LIST} && echo 'expired key' > {LEGACY_KEY}",
        check=True,
    )
    return sandbox.pyinfra()


def changed_roster(sandbox, tmp_path, edit):
    """A copy of the sandbox's roster changed by `edit(data)`, as a teacher edits theirs."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    edit(data)
    path = tmp_path / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy_with_roster(sandbox, roster, *args):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def changed_hosts(run) -> set[str]:
    return set(run.changes_per_host())


def changes_on(run, host: str) -> list[str]:
    return sorted(name for name, hosts in run.changed.items() if host in hosts)


def test_first_run_converges_on_every_host(first_run):
    assert first_run.returncode == 0, first_run.stderr[-6000:]
    assert changed_hosts(first_run) == set(EXPECTED)


def test_second_run_changes_nothing(sandbox, first_run):
    second = sandbox.pyinfra()
    assert second.returncode == 0, second.stderr[-6000:]
    assert second.changed == {}, f"a re-run changed: {second.changed}"


@pytest.mark.parametrize("host", sorted(EXPECTED))
def test_host_state(sandbox, first_run, host):
    expect = EXPECTED[host]
    def run(command: str) -> str:
        return sandbox.ssh(host, command, check=True).stdout

    # Locale generated and set system-wide.
    assert "en_US.utf8" in run("locale -a")
    assert "LANG=en_US.UTF-8" in run("cat /etc/default/locale")

    # Apt: universe and -updates/-backports in the host's own layout, ROS source signed-by.
    if expect["codename"] == "noble":
        ubuntu_sources = run("cat /etc/apt/sources.list.d/ubuntu.sources")
        assert re.search(r"^Components:.*\buniverse\b", ubuntu_sources, re.M)
        assert "noble-updates" in ubuntu_sources and "noble-backports" in ubuntu_sources
    else:
        sources_list = run("cat /etc/apt/sources.list")
        assert re.search(r"^deb .* jammy .*universe", sources_list, re.M)
        assert re.search(r"^deb .* jammy-updates ", sources_list, re.M)
        assert re.search(r"^deb .* jammy-backports ", sources_list, re.M)
    ros_sources = run("cat /etc/apt/sources.list.d/ros2.sources")
    assert "Signed-By: /usr/share/keyrings/ros2-archive-keyring.gpg" in ros_sources
    assert run("ls /etc/apt/sources.list.d/ | grep -c '^ros2.list$' || true").strip() == "0"
    update = sandbox.sudo(host, "apt-get update 2>&1", check=True)
    assert "Conflicting" not in update.stdout and not re.search(r"^(W|E):", update.stdout, re.M), update.stdout

    # Packages per role.
    installed = run("dpkg-query -W -f='${Package} ${Status}\\n' 'ros-*' 2>/dev/null")
    assert f"ros-{expect['distro']}-{expect['variant']} install ok installed" in installed
    assert "ros-dev-tools install ok installed" in installed
    if expect["variant"] == "ros-base":
        assert f"ros-{expect['distro']}-desktop install ok installed" not in installed

    # rosdep initialised, and updated as the login user (never root).
    run("test -f /etc/ros/rosdep/sources.list.d/20-default.list")
    assert run("stat -c %U ~/.ros/rosdep/sources.cache").strip() == "ubuntu"
    assert sandbox.sudo(host, "test -e /root/.ros/rosdep", check=False).returncode != 0

    # One ~/.bashrc block with the right distro and domain, as an interactive shell sees it.
    assert run(f"grep -c '^{BASHRC_BEGIN}' ~/.bashrc").strip() == "1"
    environment = run("bash -ic 'echo ROS_DISTRO=$ROS_DISTRO ROS_DOMAIN_ID=$ROS_DOMAIN_ID' 2>/dev/null")
    assert f"ROS_DISTRO={expect['distro']} ROS_DOMAIN_ID={expect['domain']}" in environment
    discovery = run("bash -ic 'echo range=$ROS_AUTOMATIC_DISCOVERY_RANGE' 2>/dev/null")
    assert ("range=SUBNET" in discovery) == (expect["distro"] == "jazzy")

    # SSH and identity.
    assert run("systemctl is-enabled ssh").strip() == "enabled"
    assert run("systemctl is-active ssh").strip() == "active"
    assert run("hostname").strip() == host
    etc_hosts = run("cat /etc/hosts")
    for other in EXPECTED:
        assert re.search(rf"^\S+\s+{re.escape(other)}\b", etc_hosts, re.M), f"{other} not in /etc/hosts"


def test_legacy_source_is_replaced_and_kept_as_a_backup(sandbox, first_run):
    leftovers = sandbox.ssh(LEGACY_HOST, f"ls {LEGACY_LIST} {LEGACY_KEY} 2>&1 || true").stdout
    assert "No such file" in leftovers and LEGACY_LIST in leftovers and LEGACY_KEY in leftovers
    backups = sandbox.sudo(LEGACY_HOST, "ls -R /var/backups/roslab").stdout
    assert "ros2.list" in backups and "ros-archive-keyring.gpg" in backups


def test_dry_diff_after_a_roster_change_shows_only_the_affected_hosts(sandbox, first_run, tmp_path):
    def edit(data):
        data["teams"]["team1"]["ros_domain_id"] = 21
        data["teams"]["team2"]["hosts"]["team2-robot"]["ros_extra_packages"] = ["ros-{distro}-turtlesim"]

    roster = changed_roster(sandbox, tmp_path, edit)
    bashrc_before = {h: sandbox.ssh(h, "cat ~/.bashrc", check=True).stdout for h in EXPECTED}

    dry = deploy_with_roster(sandbox, roster, "--dry", "--diff")

    assert dry.returncode == 0, dry.stderr[-6000:]
    assert changed_hosts(dry) == {"team1-main", "team1-robot", "team2-robot"}
    bashrc_ops = {h for name, hosts in dry.changed.items() if ".bashrc" in name for h in hosts}
    assert bashrc_ops == {"team1-main", "team1-robot"}
    assert "team2-robot" in set().union(
        *(hosts for name, hosts in dry.changed.items() if "ROS 2" in name and "install" in name.lower())
    ), dry.changed
    assert re.search(r"^\s*- export ROS_DOMAIN_ID=11$", dry.stderr, re.M), dry.stderr[-4000:]
    assert re.search(r"^\s*\+ export ROS_DOMAIN_ID=21$", dry.stderr, re.M), dry.stderr[-4000:]
    assert "ROS_DOMAIN_ID=12" not in "".join(
        line for line in dry.stderr.splitlines(keepends=True) if line.lstrip().startswith(("+", "-"))
    )
    # Nothing changed on any host.
    assert {h: sandbox.ssh(h, "cat ~/.bashrc", check=True).stdout for h in EXPECTED} == bashrc_before
    assert sandbox.ssh("team2-robot", "dpkg-query -W ros-humble-turtlesim", check=False).returncode != 0


def test_drift_is_repaired_and_only_the_drift_is_reported(sandbox, first_run):
    # A student deleted the ROS block from their .bashrc; another disabled ssh at boot.
    sandbox.ssh("team1-robot", f"sed -i '/^{BASHRC_BEGIN}/,/^# END roslab/d' ~/.bashrc", check=True)
    sandbox.sudo("team2-main", "systemctl disable ssh 2>/dev/null", check=True)
    assert sandbox.ssh("team1-robot", "grep -c 'BEGIN roslab' ~/.bashrc").stdout.strip() == "0"

    repair = sandbox.pyinfra()

    assert repair.returncode == 0, repair.stderr[-6000:]
    assert changed_hosts(repair) == {"team1-robot", "team2-main"}
    assert all(".bashrc" in name for name in changes_on(repair, "team1-robot")), repair.changed
    assert all("ssh" in name.lower() for name in changes_on(repair, "team2-main")), repair.changed
    assert sandbox.ssh("team1-robot", f"grep -c '^{BASHRC_BEGIN}' ~/.bashrc").stdout.strip() == "1"
    assert sandbox.ssh("team2-main", "systemctl is-enabled ssh").stdout.strip() == "enabled"


def test_bad_roster_stops_before_any_host_is_contacted(sandbox, first_run, tmp_path):
    def edit(data):
        data["teams"]["team2"]["hosts"]["team2-main"]["ros_domian_id"] = 3  # a typo

    roster = changed_roster(sandbox, tmp_path, edit)
    logins = "journalctl -u ssh --no-pager | grep -c 'Accepted publickey'"
    before = int(sandbox.sudo("team1-main", logins, check=True).stdout)

    bad = deploy_with_roster(sandbox, roster)

    output = bad.stdout + bad.stderr
    assert bad.returncode != 0
    assert "roster.yaml" in output
    assert "team 'team2'" in output and "host 'team2-main'" in output
    assert "ros_domian_id" in output and "ros_domain_id" in output  # did you mean
    # Only this check's own login since: pyinfra never connected.
    assert int(sandbox.sudo("team1-main", logins, check=True).stdout) == before + 1
