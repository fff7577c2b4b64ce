"""deploy.py on a sandbox classroom, end to end, over real SSH.

The default sandbox classroom: team1 on an emulated Ubuntu 24.04 (team1-main, team1-robot)
and team2 on an emulated Ubuntu 22.04 (team2-main, team2-robot). One host starts with the
old-style ROS apt source (`ros2.list` and `ros-archive-keyring.gpg`) that breaks apt today.

The tests run in file order on one classroom: the session's converge of the default class from
freshly imaged hosts (conftest's `default_class_saved`, restored here: converging it again would
check the same first run at three minutes' cost), re-run, host state, dry run after a roster
change, drift repair, a bad roster, then the faults of issue 9 injected for real: dpkg killed
mid-install, the mirror gone during `apt-get update`, a deleted ~/.bashrc marker.
"""

from __future__ import annotations

import os
import re
import shlex
import threading
import time
from collections import Counter
from dataclasses import dataclass

import pytest
import yaml

from roslab.sandbox import upstream
from roslab.sandbox.instance import UPSTREAM_PORT
from tests.e2e.conftest import LEGACY_HOST, LEGACY_KEY, LEGACY_LIST

pytestmark = pytest.mark.e2e

BASHRC_BEGIN = "# BEGIN roslab managed block"

EXPECTED = {
    "team1-main": {"distro": "jazzy", "variant": "desktop", "domain": 11, "codename": "noble"},
    "team1-robot": {"distro": "jazzy", "variant": "ros-base", "domain": 11, "codename": "noble"},
    "team2-main": {"distro": "humble", "variant": "desktop", "domain": 12, "codename": "jammy"},
    "team2-robot": {"distro": "humble", "variant": "ros-base", "domain": 12, "codename": "jammy"},
}


@pytest.fixture(scope="module")
def sandbox(default_class):
    """The session's converged default class, restored for this module (fresh hosts after it)."""
    assert sorted(host.name for host in default_class.hosts) == sorted(EXPECTED)
    return default_class


@pytest.fixture(scope="module")
def first_run(sandbox, default_class_saved):
    """The class's first run: the session's converge from fresh hosts, one of them (LEGACY_HOST)
    left by a tutorial from before 2025 with the old-style ROS source."""
    return default_class_saved.run


def changed_roster(sandbox, tmp_path, edit):
    """A copy of the sandbox's roster changed by `edit(data)`, as a teacher edits theirs."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    edit(data)
    path = tmp_path / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy_with_roster(sandbox, roster, *args):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def changes(run) -> dict[str, set[str]]:
    """Operation name -> hosts it changed."""
    return run.changed


def changed_hosts(run) -> set[str]:
    return {host for hosts in changes(run).values() for host in hosts}


def changes_on(run, host: str) -> list[str]:
    return sorted(name for name, hosts in changes(run).items() if host in hosts)


def test_first_run_converges_on_every_host(first_run):
    assert first_run.returncode == 0, first_run.stderr[-6000:]
    assert changed_hosts(first_run) == set(EXPECTED)


# Issue 11: a no-op run reads each host in a handful of commands (roslab.probe), not 49.
NOOP_COMMANDS_PER_HOST = 12
REMOTE_COMMAND = re.compile(r"Running command on (\S+?):")  # pyinfra's --debug log, one per command


def test_second_run_changes_nothing_in_a_few_remote_commands_per_host(sandbox, first_run):
    second = sandbox.pyinfra("--debug")
    assert second.returncode == 0, second.stderr[-6000:]
    assert changes(second) == {}, f"a re-run changed: {second.changed}"
    commands = Counter(REMOTE_COMMAND.findall(second.stderr))
    assert set(commands) == set(EXPECTED), commands
    assert max(commands.values()) <= NOOP_COMMANDS_PER_HOST, commands


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
    # ros2-apt-source's ros2.sources carries its signing key inline (field facts: "Signed-By:"
    # holds the armored block), so no keyring file needs to exist for apt to verify the archive.
    assert re.search(r"^Signed-By: -----BEGIN PGP PUBLIC KEY BLOCK-----$", ros_sources, re.M), ros_sources
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
    assert changed_hosts(repair) == {"team1-robot", "team2-main"}, repair.changed
    assert all(".bashrc" in name for name in changes_on(repair, "team1-robot")), repair.changed
    assert all("ssh" in name.lower() for name in changes_on(repair, "team2-main")), repair.changed
    assert sandbox.ssh("team1-robot", f"grep -c '^{BASHRC_BEGIN}' ~/.bashrc").stdout.strip() == "1"
    assert sandbox.ssh("team2-main", "systemctl is-enabled ssh").stdout.strip() == "enabled"


BAD_HOST_VALUES = {
    # A typo in a key: the message suggests the right one.
    "typo": ("ros_varaint", "desktop", "did you mean 'ros_variant'"),
    # Values the deploys used to check only after connecting, or never.
    "subshell in a path": ("workspace_dir", "~/ws$(touch /tmp/pwned)", "'~/ws$(touch /tmp/pwned)'"),
    "one-word launch": ("nodes_launch_main", "roslab_bringup", "is not '<package> <launch file>'"),
    "apt option as a package": ("ros_extra_packages", ["-oAPT::Get::AllowUnauthenticated=1"],
                                "is not a Debian package name"),
    "new line in a unit value": ("nodes_launch_main", "roslab_bringup main.launch.py\nUser=root",
                                 "must be a single line"),
}


@dataclass(frozen=True)
class Logins:
    own: str  # this check's own "Accepted publickey" line
    lines: frozenset[str]  # every other such line in the journal


def accepted_logins(sandbox, host: str) -> Logins:
    """sshd's "Accepted publickey" journal lines on `host`, this check's own apart.

    journald takes sshd's lines through a socket, so a login's line can show up after the
    login's command ran: the check waits for its own line, and every login before it is then
    in the journal too. Its own line is the one of its client port AND of its sshd monitor
    process (the parent of the session's sshd, which logged it): a port alone was reused by
    an earlier login of the session now and then, whose line then passed for the check's own
    while the real one came later, as a login "since".
    """
    command = (
        'port=$(echo "$SSH_CLIENT" | cut -d" " -f2); '
        "monitor=$(awk '/^PPid:/ {print $2}' /proc/$PPID/status); "
        'echo "$monitor $port"; '
        # --sync: journald stores what sshd wrote before it; the wait (up to 60 s, over as soon as
        # the line is there) is for a machine so loaded that journald is late even so (CI saw 10 s
        # pass). By sshd's syslog name, not its unit: journald cannot tell the unit of a line whose
        # process (a pyinfra login's sshd) was gone when it got to it.
        "for _ in $(seq 600); do "
        "  sudo -n journalctl --sync; "
        "  lines=$(sudo -n journalctl -t sshd -o short-unix --no-pager | grep 'Accepted publickey'); "
        '  echo "$lines" | grep "sshd\\[$monitor\\]: " | grep -q " port $port " && break; sleep 0.1; '
        'done; echo "$lines"'
    )
    ids, *lines = sandbox.ssh(host, command, check=True).stdout.splitlines()
    monitor, port = ids.split()
    own = [line for line in lines if f" sshd[{monitor}]: " in line and f" port {port} " in line]
    assert len(own) == 1, (f"sshd on {host} logged this check's login (sshd[{monitor}], port {port}) "
                           f"{len(own)} times")
    return Logins(own[0], frozenset(lines) - {own[0]})


@pytest.mark.parametrize("case", sorted(BAD_HOST_VALUES))
def test_one_bad_host_value_stops_before_any_host_is_contacted(sandbox, first_run, tmp_path, case):
    key, value, message = BAD_HOST_VALUES[case]

    def edit(data):
        data["teams"]["team2"]["hosts"]["team2-main"][key] = value

    roster = changed_roster(sandbox, tmp_path, edit)
    before = accepted_logins(sandbox, "team1-main")

    bad = deploy_with_roster(sandbox, roster)

    output = bad.stdout + bad.stderr
    assert bad.returncode != 0
    assert "roster.yaml" in output and "no host was touched" in output
    assert f"team 'team2', host 'team2-main', field '{key}'" in output
    assert message in output, output
    # No login since but the two checks' own: pyinfra never connected.
    after = accepted_logins(sandbox, "team1-main")
    assert after.lines - before.lines - {before.own} == set(), after.lines - before.lines
    assert sandbox.ssh("team2-main", "ls /tmp/pwned 2>/dev/null || true").stdout.strip() == ""


# --- issue 9: faults injected for real -------------------------------------------------------

SLOW_PACKAGE = "roslab-e2e-slow"
SLOW_REPO = "/opt/roslab-e2e-repo"
SLOW_SOURCE = "/etc/apt/sources.list.d/roslab-e2e-slow.list"
SLOW_BLOCK = "/run/roslab-e2e-block"  # while it exists, the package's postinst waits
SLOW_RUNNING = "/run/roslab-e2e-running"  # the postinst is running: dpkg is mid-install
# A local apt repository on the host with one package whose postinst waits on a flag file,
# so dpkg can be killed at a known point of a real `apt-get install` that roslab runs.
MAKE_SLOW_REPO = f"""set -e
d=$(mktemp -d)
chmod 755 "$d" && mkdir -p "$d/DEBIAN" {SLOW_REPO}
printf '%s\\n' 'Package: {SLOW_PACKAGE}' 'Version: 1.0' 'Architecture: all' \\
  'Maintainer: roslab e2e <e2e@example.invalid>' \\
  'Description: e2e stand-in whose postinst waits while {SLOW_BLOCK} exists' > "$d/DEBIAN/control"
printf '%s\\n' '#!/bin/sh' 'touch {SLOW_RUNNING}' \\
  'while [ -e {SLOW_BLOCK} ]; do sleep 0.2; done' > "$d/DEBIAN/postinst"
chmod 755 "$d/DEBIAN/postinst"
cd {SLOW_REPO}
dpkg-deb --build "$d" {SLOW_PACKAGE}_1.0_all.deb >/dev/null
{{ dpkg-deb -f {SLOW_PACKAGE}_1.0_all.deb; echo "Filename: {SLOW_PACKAGE}_1.0_all.deb"
   echo "Size: $(stat -c %s {SLOW_PACKAGE}_1.0_all.deb)"
   echo "SHA256: $(sha256sum {SLOW_PACKAGE}_1.0_all.deb | cut -d' ' -f1)"; }} > Packages
{{ echo "Date: $(date -Ru)"; echo "SHA256:"
   echo " $(sha256sum Packages | cut -d' ' -f1) $(stat -c %s Packages) Packages"; }} > Release
echo 'deb [trusted=yes] file:{SLOW_REPO} ./' > {SLOW_SOURCE}
apt-get update -q >/dev/null
touch {SLOW_BLOCK}
"""
REMOVE_SLOW_REPO = f"""rm -f {SLOW_BLOCK} {SLOW_RUNNING} {SLOW_SOURCE}
dpkg --purge {SLOW_PACKAGE} >/dev/null 2>&1 || true
rm -rf {SLOW_REPO}
apt-get update -q >/dev/null
"""


def host_lines(run, host: str) -> list[str]:
    """What pyinfra printed about `host` (its lines start with `[host]`)."""
    return [line.strip() for line in run.stderr.splitlines() if line.strip().startswith(f"[{host}]")]


def roslab_lines(run, host: str) -> list[str]:
    """roslab's own report lines (stops, repairs, heals, failed updates) about `host`."""
    return [line for line in host_lines(run, host) if line[len(host) + 2 :].strip().startswith("roslab")]


def kill_dpkg_when_mid_install(sandbox, host: str, seen: list, timeout: float = 900) -> None:
    """Wait for the slow postinst to run (dpkg mid-install), then kill -9 dpkg, as an unplug would."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if sandbox.ssh(host, f"test -e {SLOW_RUNNING}", timeout=30).returncode == 0:
            killed = sandbox.sudo(host, f"kill -9 $(pidof dpkg); rm -f {SLOW_BLOCK}", timeout=30)
            seen.append(killed.returncode)
            return
        time.sleep(0.5)


def test_a_dpkg_killed_mid_install_fails_that_host_only_and_the_next_run_heals_it(sandbox, first_run, tmp_path):
    host = "team1-robot"
    sandbox.sudo(host, MAKE_SLOW_REPO, check=True)
    try:
        def edit(data):
            data["teams"]["team1"]["hosts"][host]["ros_extra_packages"] = [SLOW_PACKAGE]

        roster = changed_roster(sandbox, tmp_path, edit)
        killed: list[int] = []
        killer = threading.Thread(target=kill_dpkg_when_mid_install, args=(sandbox, host, killed))
        killer.start()
        interrupted = deploy_with_roster(sandbox, roster)
        killer.join()

        assert killed == [0], "dpkg was never seen mid-install"
        assert interrupted.returncode == 1, interrupted.stderr[-6000:]
        assert interrupted.failed_hosts == [host], interrupted.failed_hosts
        assert f"[{host}] E: Sub-process /usr/bin/dpkg exited unexpectedly" in host_lines(interrupted, host)
        assert f"[{host}] Error: executed 0 commands" in host_lines(interrupted, host)
        for other in set(EXPECTED) - {host}:
            assert not [line for line in host_lines(interrupted, other) if "Error" in line]
        audit = sandbox.sudo(host, "dpkg --audit; ls -A /var/lib/dpkg/updates").stdout
        assert SLOW_PACKAGE in audit, audit  # dpkg really was left half-done

        heal = deploy_with_roster(sandbox, roster)
        assert heal.returncode == 0, heal.stderr[-6000:]
        assert changed_hosts(heal) == {host}, heal.changed
        assert any("interrupted" in name for name in changes_on(heal, host)), heal.changed
        (report,) = [line for line in roslab_lines(heal, host) if "dpkg was interrupted" in line]
        assert SLOW_PACKAGE in report, report
        assert sandbox.sudo(host, "dpkg --audit").stdout.strip() == ""
        status = sandbox.ssh(host, f"dpkg-query -W -f='${{Status}}' {SLOW_PACKAGE}").stdout
        assert status == "install ok installed", status

        again = deploy_with_roster(sandbox, roster)
        assert again.returncode == 0, again.stderr[-6000:]
        assert changes(again) == {}, again.changed
    finally:
        sandbox.sudo(host, REMOVE_SLOW_REPO)


def test_a_mirror_gone_during_apt_update_fails_that_host_and_the_next_run_updates_again(sandbox, first_run):
    host = "team2-main"
    bridge = next(sandbox.instance.subnet.hosts())
    gone = "/etc/apt/sources.list.d/roslab-e2e-gone.list"
    stamp = "/var/lib/apt/periodic/update-success-stamp"
    # A source whose server is gone (nothing listens on port 9), and lists due for a refresh.
    sandbox.sudo(host, f"echo 'deb [trusted=yes] http://{bridge}:9/gone ./' > {gone} && "
                       f"touch -d '2 days ago' {stamp}", check=True)
    try:
        failed = sandbox.pyinfra()
        assert failed.returncode == 1, failed.stderr[-6000:]
        assert failed.failed_hosts == [host], failed.failed_hosts
        (report,) = roslab_lines(failed, host)
        expected = (f"[{host}] roslab: apt-get update failed, the lists stay stale until one succeeds: "
                    f"E: Failed to fetch http://{bridge}:9/gone/")
        assert " ".join(report.split()).startswith(expected), report
        assert not [line for line in host_lines(failed, host) if line.startswith(f"[{host}] Get:")]
        # Not marked fresh: the next run updates again.
        assert sandbox.sudo(host, f"test -e {stamp}").returncode != 0
    finally:
        sandbox.sudo(host, f"rm -f {gone}")  # the mirror is back

    healed = sandbox.pyinfra()
    assert healed.returncode == 0, healed.stderr[-6000:]
    assert changed_hosts(healed) == {host}, healed.changed
    assert all("apt lists" in name for name in changes_on(healed, host)), healed.changed
    assert sandbox.sudo(host, f"test -e {stamp}").returncode == 0
    again = sandbox.pyinfra()
    assert again.returncode == 0 and changes(again) == {}, again.changed


def test_a_deleted_bashrc_end_marker_is_repaired_keeping_the_students_lines(sandbox, first_run):
    host = "team1-main"
    mine = ["alias ws='cd ~/my_ws'", "echo student-line"]
    appended = " && ".join(f"echo {shlex.quote(line)} >> ~/.bashrc" for line in mine)
    sandbox.ssh(host, f"sed -i '/^# END roslab managed block/d' ~/.bashrc && {appended}", check=True)
    before = sandbox.ssh(host, "cat ~/.bashrc", check=True).stdout.splitlines()

    repair = sandbox.pyinfra()

    assert repair.returncode == 0, repair.stderr[-6000:]
    assert changed_hosts(repair) == {host}, repair.changed
    assert all(".bashrc" in name for name in changes_on(repair, host)), repair.changed
    (report,) = [line for line in roslab_lines(repair, host) if "repairs the markers" in line]
    backup = re.search(r"kept as (\S+)", report).group(1)
    after = sandbox.ssh(host, "cat ~/.bashrc", check=True).stdout.splitlines()
    assert sum(line.startswith("# BEGIN roslab") for line in after) == 1
    assert sum(line.startswith("# END roslab") for line in after) == 1
    assert after[-2:] == mine
    assert [line for line in after if line in before] == before  # every line kept, in order
    assert sandbox.ssh(host, f"cat {backup}", check=True).stdout.splitlines() == before
    assert sandbox.ssh(host, f"stat -c %U {backup}", check=True).stdout.strip() == "ubuntu"
    environment = sandbox.ssh(host, "bash -ic 'echo ROS_DOMAIN_ID=$ROS_DOMAIN_ID' 2>/dev/null", check=True).stdout
    assert "ROS_DOMAIN_ID=11" in environment

    again = sandbox.pyinfra()
    assert again.returncode == 0 and changes(again) == {}, again.changed
    assert sandbox.ssh(host, "cat ~/.bashrc", check=True).stdout.splitlines() == after


# Issue 18: a student's masked unit, someone's link where a deploy writes, upstream down.

NODES_UNIT = "/etc/systemd/system/roslab-nodes.service"
PRECIOUS = "/etc/roslab-e2e-precious"


def summary_line(run, host: str) -> str:
    """roslab's summary line for `host` (printed last, on stderr)."""
    lines = run.stderr[run.stderr.rindex("roslab summary"):].splitlines()
    (line,) = [line.strip() for line in lines if line.strip().startswith(f"{host} ")]
    return " ".join(line.split())


def test_a_masked_unit_is_healed_and_a_foreign_link_stops_only_its_host(sandbox, first_run):
    masked, linked = "team1-main", "team2-robot"
    # `systemctl mask` refuses while the unit file is in /etc, so a student removes it first.
    sandbox.sudo(masked, f"systemctl stop roslab-nodes.service && rm {NODES_UNIT} && "
                         "systemctl mask roslab-nodes.service", check=True)
    assert sandbox.sudo(masked, f"readlink {NODES_UNIT}").stdout.strip() == "/dev/null"
    # Someone's link where the deploy writes the unit, to a file root keeps private.
    sandbox.sudo(linked, f"printf 'precious\\n' > {PRECIOUS} && chmod 600 {PRECIOUS} && "
                         f"rm -f {NODES_UNIT} && ln -s {PRECIOUS} {NODES_UNIT}", check=True)

    run = sandbox.pyinfra()

    assert run.returncode == 1, run.stderr[-6000:]
    assert run.failed_hosts == [linked], run.failed_hosts
    reason = (f"roslab: will not write {NODES_UNIT}: it is a symbolic link (to {PRECIOUS}) "
              "that roslab did not make")
    line = summary_line(run, linked)
    step = "Ensure roslab-nodes.service runs the robot's launch"
    assert line.startswith(f"{linked} failed in \"") and step in line and line.endswith(reason), line
    assert sandbox.sudo(linked, f"stat -c '%a %s' {PRECIOUS} && cat {PRECIOUS}").stdout == "600 9\nprecious\n"
    for host in set(EXPECTED) - {linked}:
        assert not [line for line in host_lines(run, host) if "Error" in line], host_lines(run, host)
        # /dev/null is still the device on every host (the mask's link was never written through)
        assert sandbox.ssh(host, "stat -c %F /dev/null").stdout.strip() == "character special file"
    (report,) = [line for line in host_lines(run, masked) if "masked" in line]
    assert "roslab-nodes.service was masked on this host (systemctl mask): unmasking it" in report
    assert sandbox.sudo(masked, "systemctl is-active roslab-nodes.service").stdout.strip() == "active"
    assert sandbox.sudo(masked, f"test -f {NODES_UNIT} && test ! -L {NODES_UNIT}").returncode == 0

    sandbox.sudo(linked, f"rm -f {NODES_UNIT} {PRECIOUS}", check=True)  # the teacher removes the link
    healed = sandbox.pyinfra()
    assert healed.returncode == 0, healed.stderr[-6000:]
    assert changed_hosts(healed) == {linked}, healed.changed
    assert sandbox.sudo(linked, "systemctl is-active roslab-nodes.service").stdout.strip() == "active"


def controller_requests(sandbox, since: int) -> list:
    """Requests the controller (this machine, at the bridge address) made to the upstream."""
    log = sandbox.instance.state_dir / upstream.REQUEST_LOG
    return [request for request in upstream.read_requests(log)[since:]
            if request.client == sandbox.instance.bridge_address]


def request_count(sandbox) -> int:
    return len(upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG))


def test_a_noop_run_downloads_nothing_upstream_and_upstream_down_uses_the_kept_rosdep_data(sandbox, first_run, tmp_path):
    cache = tmp_path / "rosdep-cache"

    def edit(data):
        data["classroom"]["rosdep_cache_dir"] = str(cache)

    roster = changed_roster(sandbox, tmp_path, edit)
    filled = deploy_with_roster(sandbox, roster)  # a new kept copy, the same data: nothing changes
    assert filled.returncode == 0 and changes(filled) == {}, filled.stderr[-6000:]

    before = request_count(sandbox)
    quiet = deploy_with_roster(sandbox, roster)
    assert quiet.returncode == 0 and changes(quiet) == {}, quiet.stderr[-6000:]
    # A no-op run only asks whether rosdep's data changed: every answer a 304, no body.
    checks = controller_requests(sandbox, before)
    assert checks and all(request.status == 304 and request.bytes == 0 for request in checks), checks

    # The kept copy is older than rosdep_update_max_age, and upstream is down.
    old = time.time() - 8 * 86400
    for path in cache.rglob("*"):
        if path.is_file():
            os.utime(path, (old, old))
    state = sandbox.instance.state_dir
    upstream.stop_server(state / "upstream.pid")
    try:
        down = deploy_with_roster(sandbox, roster)
    finally:
        upstream.start_server(state / "upstream", sandbox.instance.bridge_address, UPSTREAM_PORT,
                              state / "upstream.pid", state / "upstream.log")
    assert down.returncode == 0, down.stderr[-6000:]
    assert changes(down) == {}, down.changed
    for host in EXPECTED:
        reports = [line for line in roslab_lines(down, host) if "rosdep's data" in line]
        assert reports and all("cannot download http://" in line and "using the controller's copy from 8 days ago"
                               in line for line in reports), roslab_lines(down, host)
        assert summary_line(down, host) == f"{host} ok"

    before = request_count(sandbox)
    back = deploy_with_roster(sandbox, roster)  # upstream is back: the copy is checked, then fresh again
    assert back.returncode == 0 and changes(back) == {}, back.stderr[-6000:]
    assert controller_requests(sandbox, before), "the stale copy was never checked upstream"
    assert not [line for host in EXPECTED for line in roslab_lines(back, host) if "rosdep's data" in line]
