"""The network deploy end to end, on sandbox hosts over real SSH.

Each sandbox host boots with the address an emulated cloud-init netplan file
gives it (`/etc/netplan/50-cloud-init.yaml`, rendered by systemd-networkd). The
tests give one host a new static address in a roster and run the network deploy,
then a last step that records which address its SSH connection reached:

- the host moves, the deploy continues at the new address, cloud-init's file is
  backed up and disabled, the files are root's and 0600, the controller records
  the address, and a second run changes nothing;
- a wrong gateway (nothing answers there) is rolled back by the host itself;
- an address the controller cannot reach (a blackhole route on this machine, the
  test's stand-in for a classroom switch that does not carry it) is rolled back
  when the confirmation does not come;
and in both failure cases the run reports it and the host answers at its old address.

Runs on its own sandbox instance (ROSLAB_SANDBOX=net, subnet 10.213.40.0/24).
"""

from __future__ import annotations

import ipaddress
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import paramiko
import pytest
import yaml

from roslab import netstate
from roslab.roster import load_roster

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
INSTANCE = os.environ.get("ROSLAB_NETWORK_E2E_SANDBOX", "net")
SUBNET = ipaddress.ip_network(os.environ.get("ROSLAB_NETWORK_E2E_SUBNET", "10.213.40.0/24"))
STATE_DIR = Path("/run/roslab/sandbox") / INSTANCE
ENV = {**os.environ, "ROSLAB_SANDBOX": INSTANCE, "ROSLAB_SANDBOX_SUBNET": str(SUBNET)}
BRIDGE = str(next(SUBNET.hosts()))  # the sandbox bridge: the hosts' gateway
TEST_DEPLOY = "tests/e2e/network_then_marker.py"
NETWORK_OP = "network is configured and it answers at"
CONFIRM_TIMEOUT = 20
DESKTOP_HOST = "team3-main"


@pytest.fixture(scope="module")
def classroom():
    if os.geteuid() != 0 or shutil.which("systemd-nspawn") is None:
        pytest.skip("the sandbox needs root and systemd-nspawn")
    # Four Ubuntu Server-like hosts (networkd) and team3-main, an Ubuntu 24.04
    # Desktop-like host where NetworkManager runs the network.
    subprocess.run([str(BIN / "roslab"), "sandbox", "up", "--hosts", "5", "--desktop", DESKTOP_HOST],
                   env=ENV, check=True, cwd=REPO)
    try:
        yield load_roster(STATE_DIR / "roster.yaml")
    finally:
        shutil.rmtree(STATE_DIR / netstate.STATE_DIR, ignore_errors=True)
        subprocess.run([str(BIN / "roslab"), "sandbox", "down"], env=ENV, cwd=REPO)


def write_roster(host_settings: dict[str, dict]) -> Path:
    """The sandbox roster with network settings added to some hosts, beside the original."""
    original = yaml.safe_load((STATE_DIR / "roster.yaml").read_text())
    for team in original["teams"].values():
        for name, host in team["hosts"].items():
            host.update(host_settings.get(name, {}))
    path = STATE_DIR / "roster-network-e2e.yaml"
    path.write_text(yaml.safe_dump(original, sort_keys=False))
    return path


def run_deploy(roster: Path, host: str) -> tuple[subprocess.CompletedProcess, dict]:
    proc = subprocess.run(
        [str(BIN / "pyinfra"), "-y", "--json", "inventories/lab.py", TEST_DEPLOY, "--limit", host],
        cwd=REPO, env={**ENV, "ROSLAB_ROSTER": str(roster)},
        capture_output=True, text=True, timeout=600,
    )
    try:
        results = json.loads(proc.stdout)["results"]
    except (ValueError, KeyError, TypeError):
        results = None
    return proc, results


def network_op(results: dict) -> dict:
    [operation] = [op for op in results["operations"] if NETWORK_OP in op["name"]]
    return operation


def answers_ssh(address: str, seconds: float = 3) -> bool:
    try:
        with socket.create_connection((address, 22), timeout=seconds):
            return True
    except OSError:
        return False


def on_host(host, address: str, command: str) -> str:
    """Run `command` as root on a sandbox host at `address`; its stdout."""
    client = paramiko.SSHClient()
    client.set_missing_host_key_policy(paramiko.AutoAddPolicy())
    client.connect(address, username=host.data.get("ssh_user"), key_filename=host.data.get("ssh_key"),
                   port=int(host.data.get("ssh_port") or 22), timeout=10,
                   allow_agent=False, look_for_keys=False)
    try:
        sudo = "" if host.data.get("ssh_user") in (None, "root") else "sudo -n "
        _, stdout, stderr = client.exec_command(f"{sudo}sh -c '{command}'", timeout=30)
        output = stdout.read().decode()
        assert stdout.channel.recv_exit_status() == 0, stderr.read().decode()
        return output
    finally:
        client.close()


def pick(classroom, index: int):
    return classroom.hosts[index]


def static(address: str, gateway: str = BRIDGE, **extra) -> dict:
    return {"network_address": f"{address}/{SUBNET.prefixlen}", "network_gateway": gateway,
            "network_ipv6": "ignore", "network_confirm_timeout": CONFIRM_TIMEOUT, **extra}


def test_host_moves_and_the_deploy_continues_at_its_new_address(classroom):
    host = pick(classroom, 0)
    new = str(SUBNET.network_address + 77)
    roster = write_roster({host.name: static(new)})

    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert host.name in network_op(results)["success"]

    # The step after the network deploy ran over a connection to the new address.
    assert on_host(host, new, "cat /tmp/roslab-e2e-reached-at").split()[2] == new
    assert not answers_ssh(host.address)
    assert netstate.last_known_address(roster, host.name) == new

    stat = on_host(host, new, "stat -c \"%U %a %n\" /etc/netplan/60-roslab.yaml "
                              "/etc/cloud/cloud.cfg.d/99-disable-network-config.cfg")
    assert stat.splitlines() == [
        "root 600 /etc/netplan/60-roslab.yaml",
        "root 600 /etc/cloud/cloud.cfg.d/99-disable-network-config.cfg",
    ]
    assert "config: disabled" in on_host(host, new, "cat /etc/cloud/cloud.cfg.d/99-disable-network-config.cfg")
    assert on_host(host, new, "ls /etc/netplan").split() == ["60-roslab.yaml"]
    backups = on_host(host, new, "ls /var/backups/roslab/network/*/files/etc/netplan/50-cloud-init.yaml")
    assert backups.strip(), "cloud-init's netplan file was not kept as a backup"
    assert on_host(host, new, "stat -c %a /var/backups/roslab/network").strip() == "700"

    # Run again with the same roster (its `address` is still the old one): nothing changes.
    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    operation = network_op(results)
    assert operation["success"] == [] and operation["no_change"] == [host.name]


def assert_rolled_back(host, proc, results, words: str) -> None:
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0
    if results is not None:  # pyinfra reports no results when its only host failed
        assert host.name in network_op(results)["error"]
    assert "Network change rolled back" in output and words in output, output[-4000:]
    assert f"reachable again at {host.address}" in output
    # Back at its old address with its old files.
    assert answers_ssh(host.address, seconds=10)
    assert on_host(host, host.address, "ls /etc/netplan").split() == ["50-cloud-init.yaml"]
    assert on_host(host, host.address, "cat /run/roslab/network/status.json").count("rolled-back") == 1


def test_wrong_gateway_is_rolled_back_and_reported(classroom):
    host = pick(classroom, 1)
    nobody = str(SUBNET.network_address + 254)
    roster = write_roster({host.name: static(str(SUBNET.network_address + 78), gateway=nobody)})

    started = time.monotonic()
    proc, results = run_deploy(roster, host.name)
    assert_rolled_back(host, proc, results, f"gateway {nobody} does not answer on eth0")
    assert time.monotonic() - started < CONFIRM_TIMEOUT + 30  # reported early, not at the deadline
    assert netstate.last_known_address(roster, host.name) is None


def test_address_the_controller_cannot_reach_is_rolled_back_and_reported(classroom):
    host = pick(classroom, 2)
    unreachable = str(SUBNET.network_address + 79)
    roster = write_roster({host.name: static(unreachable)})

    subprocess.run(["ip", "route", "add", "blackhole", f"{unreachable}/32"], check=True)
    try:
        proc, results = run_deploy(roster, host.name)
    finally:
        subprocess.run(["ip", "route", "del", "blackhole", f"{unreachable}/32"], check=True)
    assert_rolled_back(host, proc, results, f"did not confirm within {CONFIRM_TIMEOUT} s")


def test_desktop_host_moves_by_networkmanager_without_keeping_its_old_address(classroom):
    host = next(h for h in classroom.hosts if h.name == DESKTOP_HOST)
    new = str(SUBNET.network_address + 80)
    roster = write_roster({host.name: static(new)})

    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert host.name in network_op(results)["success"]
    assert on_host(host, new, "systemctl is-active NetworkManager").strip() == "active"
    netplan = on_host(host, new, "cat /etc/netplan/60-roslab.yaml")
    assert "renderer: NetworkManager" in netplan
    # netplan merges files: the Desktop's own profile for eth0 is backed up, not merged,
    # so the host answers at its new address only.
    assert on_host(host, new, "ls /etc/netplan").split() == ["60-roslab.yaml"]
    addresses = on_host(host, new, "ip -4 -o address show dev eth0").split()
    assert f"{new}/{SUBNET.prefixlen}" in addresses and f"{host.address}/{SUBNET.prefixlen}" not in addresses
    assert not answers_ssh(host.address)

    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert network_op(results)["no_change"] == [host.name]
