"""The sandbox classroom itself: hosts a deploy can treat like Pis, and nothing left behind.

Most tests use the session's instance (`e2e_sandbox`); the lifecycle test runs
its own small instance beside it through the `roslab sandbox` command, which
also shows that two instances coexist.
"""

from __future__ import annotations

import hashlib
import ipaddress
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import hosts as sandbox_hosts
from roslab.sandbox import lifecycle
from roslab.sandbox import system as sandbox_system
from roslab.sandbox.instance import Instance

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]

LIFECYCLE_INSTANCE = "roslab-e2e-life"
LIFECYCLE_SUBNET = "10.213.201.0/24"


def test_hosts_take_ssh_as_ubuntu_with_passwordless_sudo(e2e_sandbox):
    for host in e2e_sandbox.hosts:
        result = e2e_sandbox.ssh(host.name, "id -un; sudo -n id -u; hostname", check=True)
        assert result.stdout.split() == ["ubuntu", "0", host.name]


def test_each_host_sets_its_own_address_from_the_cloud_init_netplan_file(e2e_sandbox):
    host_keys = set()
    for host in e2e_sandbox.hosts:
        result = e2e_sandbox.sudo(
            host.name, "ip -4 -o addr show dev eth0; cat /etc/netplan/50-cloud-init.yaml; "
            "cat /etc/ssh/ssh_host_ed25519_key.pub; test -d /etc/cloud/cloud.cfg.d && echo has-cloud-cfg-d; "
            "test -e /etc/cloud/cloud-init.disabled && echo cloud-init-disabled; "
            "systemctl is-active cloud-init-local.service cloud-init.service || true",
            check=True)
        assert f"inet {host.address}/24" in result.stdout
        assert "renderer: networkd" in result.stdout
        # cloud-init is installed but does not run (only a host booted from a seed runs it).
        assert "has-cloud-cfg-d\ncloud-init-disabled\ninactive\ninactive\n" in result.stdout
        host_keys.add(next(line for line in result.stdout.splitlines() if line.startswith("ssh-ed25519")))
    assert len(host_keys) == len(e2e_sandbox.hosts)  # each host has its own host key


def test_os_release_emulates_the_team_release(e2e_sandbox):
    expected = {"team1": ("24.04", "noble"), "team2": ("22.04", "jammy")}
    for host in e2e_sandbox.hosts:
        out = e2e_sandbox.ssh(
            host.name, ". /etc/os-release; echo $ID $VERSION_ID $VERSION_CODENAME $UBUNTU_CODENAME; "
            ". /etc/lsb-release; echo $DISTRIB_CODENAME; head -1 /etc/os-release", check=True).stdout.splitlines()
        release, codename = expected[host.team]
        assert out[0] == f"ubuntu {release} {codename} {codename}"
        assert out[1] == codename
        assert "emulation" in out[2]


def test_apt_update_is_clean_and_reaches_only_the_upstream(e2e_sandbox):
    upstream = e2e_sandbox.instance.upstream_url
    for host in e2e_sandbox.hosts:
        result = e2e_sandbox.sudo(host.name, "apt-get update")
        assert result.returncode == 0, result.stderr
        assert result.stderr == ""
        assert "W:" not in result.stdout and "Err:" not in result.stdout
        fetched = [line.split()[1] for line in result.stdout.splitlines() if line.startswith(("Get:", "Hit:"))]
        assert fetched and all(url == f"{upstream}/ubuntu" for url in fetched)
        sources = e2e_sandbox.ssh(
            host.name, "grep -rhsE '^(deb|URIs:) ' /etc/apt/sources.list /etc/apt/sources.list.d/").stdout
        assert sources and all(f"{upstream}/ubuntu" in line for line in sources.splitlines())
        # As on a Pi server image, universe is off: the ROS tools are not installable yet.
        policy = e2e_sandbox.ssh(host.name, "apt-cache policy python3-rosdep2", check=True).stdout
        assert "Candidate: (none)" in policy or policy.strip() == ""


def test_published_ros_apt_source_and_rosdep_data_work_on_a_fresh_host(fresh_hosts):
    roster = yaml.safe_load(fresh_hosts.roster_path.read_text())["classroom"]
    url = roster["ros_apt_source_url"].format(version=roster["ros_apt_source_version"], codename="noble")
    with urllib.request.urlopen(url, timeout=10) as response:
        assert hashlib.sha256(response.read()).hexdigest() == roster["ros_apt_source_sha256"]["noble"]
    script = f"""set -e
        sed -i 's/^Components: main restricted$/Components: main restricted universe/' \
            /etc/apt/sources.list.d/ubuntu.sources
        curl -fsS -o /tmp/ros2-apt-source.deb {url}
        dpkg -i /tmp/ros2-apt-source.deb >/dev/null
        apt-get update -q >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
            ros-jazzy-ros-workspace python3-rosdep2 >/dev/null
        mkdir -p /etc/ros/rosdep/sources.list.d
        curl -fsS -o /etc/ros/rosdep/sources.list.d/20-default.list {roster['rosdep_sources_list_url']}
    """
    fresh_hosts.sudo("team1-main", script, check=True, timeout=600)
    out = fresh_hosts.ssh("team1-main", f"""
        readlink /etc/apt/sources.list.d/ros2.sources
        bash -c '. /opt/ros/jazzy/setup.bash && echo $ROS_DISTRO $ROS_VERSION'
        python3 -c 'import rclpy' 2>/dev/null && echo rclpy-importable || echo no-rclpy
        ROSDISTRO_INDEX_URL={roster['rosdistro_index_url']} rosdep update >/dev/null 2>&1
        rosdep resolve rclpy python3-pytest --rosdistro jazzy 2>&1 | grep -v '^#'
    """, check=True).stdout.split()
    assert out == ["/usr/share/ros-apt-source/ros2.sources", "jazzy", "2", "no-rclpy",
                   "ros-jazzy-rclpy", "python3-pytest"]


def test_a_host_moves_itself_to_a_new_address_with_netplan(fresh_hosts):
    old_address = fresh_hosts.host("team1-robot").address
    new_address = str(fresh_hosts.instance.subnet.network_address + 111)
    fresh_hosts.sudo("team1-robot", f"""set -e
        sed -i 's#{old_address}/24#{new_address}/24#' /etc/netplan/50-cloud-init.yaml
        netplan generate
        systemd-run --on-active=0.5 sh -c 'networkctl reload && networkctl reconfigure eth0'
    """, check=True)
    # Strict host key checking: the moved host is recognised by its name's known_hosts line.
    argv = lifecycle.ssh_argv(fresh_hosts.instance, new_address, "ip -4 -o addr show dev eth0",
                              host_name="team1-robot")
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        moved = subprocess.run(argv, capture_output=True, text=True, timeout=30)
        if moved.returncode == 0:
            break
        time.sleep(0.2)
    assert f"inet {new_address}/24" in moved.stdout
    assert old_address not in moved.stdout


def test_reset_gives_a_fresh_image_in_about_a_second(e2e_sandbox):
    e2e_sandbox.sudo("team2-robot", "touch /etc/left-by-a-test", check=True)
    seconds = e2e_sandbox.reset("team2-robot")
    assert seconds < 5, f"reset took {seconds:.1f} s"  # about 1 s on an idle machine
    assert e2e_sandbox.ssh("team2-robot", "test -e /etc/left-by-a-test").returncode == 1


def test_reboot_from_inside_brings_the_host_back_with_a_new_uptime(e2e_sandbox):
    e2e_sandbox.ssh("team1-robot", "touch ~/kept; sleep 2", check=True)
    asked = time.monotonic()
    e2e_sandbox.sudo("team1-robot", "systemd-run --on-active=0.2 systemctl reboot", check=True)
    deadline = asked + 60
    while time.monotonic() < deadline:
        result = e2e_sandbox.ssh("team1-robot", "cut -d. -f1 /proc/uptime; ls /home/ubuntu")
        # up for less time than since the reboot was asked for: it booted again (however long
        # sshd took to answer on a loaded machine)
        if result.returncode == 0 and int(result.stdout.split()[0]) < time.monotonic() - asked:
            break
        time.sleep(0.3)
    else:
        pytest.fail("team1-robot did not come back from its reboot with a fresh uptime")
    assert "kept" in result.stdout  # a reboot keeps the disk


def test_reboot_command_restarts_the_host(e2e_sandbox):
    seconds = e2e_sandbox.reboot("team2-main")
    assert seconds < 15, f"reboot took {seconds:.1f} s"
    uptime = float(e2e_sandbox.ssh("team2-main", "cut -d' ' -f1 /proc/uptime", check=True).stdout)
    assert uptime < seconds + 1


def _roslab(*args: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "roslab.sandbox", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)


def _leftovers(instance: Instance) -> list[str]:
    found = []
    netns = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    found += [f"netns {line.split()[0]}" for line in netns.splitlines() if line.startswith(instance.netns_prefix)]
    found += [f"interface {path.name}" for path in Path("/sys/class/net").iterdir()
              if path.name == instance.bridge or path.name.startswith(f"rlv{instance.short_id}")]
    found += [f"mount {point}" for point in sandbox_system.mounts_under(instance.state_dir)]
    found += [f"cgroup {path}" for path in sandbox_hosts.instance_cgroups(instance) if path.exists()]
    if instance.state_dir.exists():
        found.append(f"state {instance.state_dir}")
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if any(str(instance.state_dir).encode() in word for word in words):
            found.append(f"process {cmdline.parent.name}: {b' '.join(words)[:80]!r}")
    return found


def test_up_status_down_leave_nothing_behind(sandbox_support):
    env = {**os.environ, "ROSLAB_SANDBOX": LIFECYCLE_INSTANCE, "ROSLAB_SANDBOX_SUBNET": LIFECYCLE_SUBNET}
    instance = Instance(LIFECYCLE_INSTANCE, ipaddress.IPv4Network(LIFECYCLE_SUBNET))
    try:
        started = time.monotonic()
        up = _roslab("up", "--hosts", "2", "--desktop", "team1-main", env=env)
        assert up.returncode == 0, up.stderr
        assert time.monotonic() - started < 60
        assert "team1-main" in up.stdout and "team1-robot" in up.stdout and "ssh ok" in up.stdout

        again = _roslab("up", env=env)  # already running: nothing to do
        assert again.returncode == 0 and again.stdout == up.stdout

        status = _roslab("status", env=env).stdout
        assert "10.213.201.11   Ubuntu 24.04 Desktop (emulated)  ssh ok" in status
        assert "10.213.201.12   Ubuntu 24.04 Server (emulated)  ssh ok" in status
        network = _roslab("ssh", "team1-main", "systemctl is-active NetworkManager systemd-networkd; "
                          "nmcli -t -f DEVICE,STATE device", env=env).stdout.split()
        assert network[:2] == ["active", "inactive"] and "eth0:connected" in network

        inventory = subprocess.run(
            [str(Path(sys.executable).parent / "pyinfra"), "-y", "inventories/sandbox.py", "exec", "--",
             "sudo -n true"], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
        assert inventory.returncode == 0, inventory.stderr

        # A crashed `up` leaves state without a record of the hosts; the next `up` clears it.
        (instance.state_dir / "sandbox.json").unlink()
        assert _roslab("up", "--hosts", "2", env=env).returncode == 0
        assert _roslab("up", "--hosts", "3", env=env).returncode == 1  # running with other hosts

        assert _roslab("down", env=env).returncode == 0
        assert _leftovers(instance) == []
        assert _roslab("down", env=env).returncode == 0  # twice is safe

        after = subprocess.run([str(Path(sys.executable).parent / "pyinfra"), "inventories/sandbox.py", "exec",
                                "--", "true"], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
        assert after.returncode != 0
        assert f"no sandbox '{LIFECYCLE_INSTANCE}' is running: run `roslab sandbox up`" in after.stderr
    finally:
        _roslab("down", env=env)
