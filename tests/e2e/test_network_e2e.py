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
Then, for the escaping of values: an awkward but legal SSID and password (quotes,
unicode, `;`, shell syntax, spaces at the ends) reach netplan, wpa_supplicant's
configuration and NetworkManager on the hosts exactly as written in the roster.

Runs on its own sandbox instance (ROSLAB_SANDBOX=net, subnet 10.213.40.0/24).
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from uuid import uuid4

import paramiko
import pytest
import yaml

from roslab.network import state as network_state
from roslab.network.apply import NM_KEYFILE, Plan, staged_path
from roslab.network.operation import APPLY_SCRIPT, NetworkRenderer
from roslab.network.render import Layout, choose_layout, desired_files, keyfile_path, render_keyfile
from roslab.network.settings import network_settings
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
        shutil.rmtree(STATE_DIR / network_state.STATE_DIR, ignore_errors=True)
        subprocess.run([str(BIN / "roslab"), "sandbox", "down"], env=ENV, cwd=REPO)


def write_roster(host_settings: dict[str, dict], secrets: dict[str, str] | None = None) -> Path:
    """The sandbox roster with network settings added to some hosts, beside the original."""
    original = yaml.safe_load((STATE_DIR / "roster.yaml").read_text())
    if secrets:
        secrets_path = STATE_DIR / "secrets-network-e2e.yaml"
        secrets_path.write_text(yaml.safe_dump(secrets, allow_unicode=True))
        secrets_path.chmod(0o600)
        original["classroom"]["secrets_file"] = secrets_path.name
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


def on_host(host, address: str, command: str, stdin: str | None = None) -> str:
    """Run `command` as root on a sandbox host at `address` (with `stdin`, if given); its stdout."""
    client = paramiko.SSHClient()
    client.set_missing_host_key_policy(paramiko.AutoAddPolicy())
    client.connect(address, username=host.data.get("ssh_user"), key_filename=host.data.get("ssh_key"),
                   port=int(host.data.get("ssh_port") or 22), timeout=10,
                   allow_agent=False, look_for_keys=False)
    try:
        sudo = "" if host.data.get("ssh_user") in (None, "root") else "sudo -n "
        channel_in, stdout, stderr = client.exec_command(f"{sudo}sh -c {shlex.quote(command)}", timeout=30)
        if stdin is not None:
            channel_in.write(stdin.encode())
        channel_in.channel.shutdown_write()
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
    assert network_state.last_known_address(roster, host.name) == new

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
    assert network_state.last_known_address(roster, host.name) is None


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
    netplan = yaml.safe_load(on_host(host, new, "cat /etc/netplan/60-roslab.yaml"))
    assert netplan["network"]["renderer"] == "NetworkManager"
    # netplan merges files: the Desktop's own profile for eth0 is backed up, not merged,
    # so the host answers at its new address only.
    assert on_host(host, new, "ls /etc/netplan").split() == ["60-roslab.yaml"]
    addresses = on_host(host, new, "ip -4 -o address show dev eth0").split()
    assert f"{new}/{SUBNET.prefixlen}" in addresses and f"{host.address}/{SUBNET.prefixlen}" not in addresses
    assert not answers_ssh(host.address)

    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert network_op(results)["no_change"] == [host.name]


# Escaping, end to end: an awkward but legal SSID and password reach the host's tools intact.

# 26 bytes of UTF-8: quotes, an em dash, an accent, `#`, `;` and shell syntax.
AWKWARD_SSID = 'Lab "A" — Café #2;\'$(id)'
# Leading and trailing spaces (GKeyFile's \s), a literal backslash, quotes, `;#=`, shell syntax.
AWKWARD_PASSWORD = " $(reboot) `id` \\x27 'q' \"x\";#= "
CHECK_DIR = "/run/roslab/network-e2e-escaping"


def awkward_wifi_host(classroom, index: int, ssid: str = AWKWARD_SSID):
    """A host of a roster (written, then loaded by the real loader) that sets the awkward
    SSID, and its password from a secrets file; with its checked settings and address now."""
    host = pick(classroom, index)
    new = str(SUBNET.network_address + 90 + index)
    roster = write_roster(
        {host.name: static(new, network_kind="wifi", wifi_ssid=ssid, wifi_password_secret="e2e_wifi")},
        secrets={"e2e_wifi": AWKWARD_PASSWORD},
    )
    [loaded] = [h for h in load_roster(roster).hosts if h.name == host.name]
    settings = network_settings(loaded.settings)
    assert (settings.wifi_ssid, settings.password) == (ssid, AWKWARD_PASSWORD)
    return host, settings, network_state.last_known_address(roster, host.name) or host.address


def stage_and_validate(host, address: str, plan: Plan, files: dict[str, str]) -> dict[str, str]:
    """Stage `files` and the on-host script as the operation does (in a run directory of
    their own), run the script's `validate` on them, and read the staged files back."""
    on_host(host, address, f"rm -rf {CHECK_DIR} && install -d -m 0700 {CHECK_DIR}")
    uploads = {**{str(staged_path(plan, path)): content for path, content in files.items()},
               f"{CHECK_DIR}/plan.json": plan.to_json(),
               f"{CHECK_DIR}/network_apply.py": APPLY_SCRIPT.read_text()}
    for path, content in uploads.items():
        on_host(host, address, f"mkdir -p {shlex.quote(str(Path(path).parent))} && cat > {shlex.quote(path)}",
                stdin=content)
    # Exit status 0 or on_host fails the test with the validator's message.
    on_host(host, address, f"python3 {CHECK_DIR}/network_apply.py validate {CHECK_DIR}/plan.json")
    return {path: on_host(host, address, f"cat {shlex.quote(str(staged_path(plan, path)))}") for path in files}


def plan_for(settings, layout_name: str, files: dict[str, str], superseded=()) -> Plan:
    return Plan(token=uuid4().hex, layout=layout_name, interface=settings.interface, files=tuple(files),
                superseded=tuple(superseded), expect_address=str(settings.address), gateway=None,
                confirm_timeout=settings.confirm_timeout, run_dir=CHECK_DIR)


def wpa_supplicant_string(value: str) -> str:
    """A wpa_supplicant.conf string as wpa_supplicant reads it (wpa_config_parse_string):
    "..." is everything between the first and the last quote; otherwise hex bytes."""
    if value.startswith('"'):
        assert value.endswith('"') and len(value) >= 2, value
        return value[1:-1]
    return bytes.fromhex(value).decode()


def keyfile_values(text: str) -> dict[str, str]:
    """`group.key` -> value of a keyfile, with GKeyFile's escapes undone (\\s \\n \\t \\r \\\\)."""
    values, group = {}, None
    for line in text.splitlines():
        if line.startswith("["):
            group = line.strip("[]")
        elif "=" in line and not line.startswith("#"):
            key, _, raw = line.partition("=")
            values[f"{group}.{key}"] = re.sub(
                r"\\(.)", lambda m: {"s": " ", "n": "\n", "t": "\t", "r": "\r"}.get(m[1], m[1]), raw.lstrip())
    return values


def nm_ssid(value: str) -> str:
    """An SSID as NetworkManager reads a keyfile's (unescaped) `ssid=`: a list of byte values
    (how NM itself writes a non-ASCII SSID) or a string where `\\;` stands for `;`."""
    if re.fullmatch(r"(\d{1,3};)+", value):
        return bytes(int(number) for number in value.rstrip(";").split(";")).decode()
    return value.replace("\\;", ";")


def test_awkward_ssid_lands_in_netplan_exactly_as_written(classroom):
    """What this proves, on a Server-like host (netplan with systemd-networkd), with the real
    roster loader, settings check, renderer, layout choice (the host's own facts), upload
    and the on-host script's validation (`netplan generate` on the future /etc/netplan):

    - the staged netplan file reads back byte for byte as rendered, and parses (YAML) to
      the SSID and password exactly as written in the roster and the secrets file;
    - netplan's own parser reads the same values: `netplan get` on a root holding the file;
    - the wpa_supplicant configuration `netplan generate` derives from it holds them too,
      as wpa_supplicant reads its strings.

    The sandbox hosts have no WiFi device, so the file is not applied (that would fail
    for want of wlan0 and be rolled back): everything up to that point is real.
    """
    host, settings, address = awkward_wifi_host(classroom, 3)
    fact = NetworkRenderer()
    found = fact.process(on_host(host, address, fact.command()).splitlines())
    layout = choose_layout(settings.backend, found["renderer"])
    wanted = desired_files(settings, layout, found["cloud_init"])
    [netplan_path] = [path for path in wanted.files if path.endswith(".yaml")]
    plan = plan_for(settings, layout.name, wanted.files, wanted.superseded)
    try:
        staged = stage_and_validate(host, address, plan, wanted.files)
        assert staged[netplan_path] == wanted.files[netplan_path]
        access_points = yaml.safe_load(staged[netplan_path])["network"]["wifis"]["wlan0"]["access-points"]
        assert access_points == {AWKWARD_SSID: {"password": AWKWARD_PASSWORD}}

        root = f"{CHECK_DIR}/root"
        on_host(host, address, f"mkdir -p {root}/etc/netplan && "
                               f"cp {staged_path(plan, netplan_path)} {root}/etc/netplan/ && "
                               f"netplan generate --root-dir {root}")
        read_by_netplan = yaml.safe_load(
            on_host(host, address, f"netplan get --root-dir {root} wifis.wlan0.access-points"))
        assert list(read_by_netplan) == [AWKWARD_SSID]
        assert read_by_netplan[AWKWARD_SSID]["auth"]["password"] == AWKWARD_PASSWORD

        wpa = dict(line.strip().split("=", 1) for line in
                   on_host(host, address, f"cat {root}/run/netplan/wpa-wlan0.conf").splitlines()
                   if line.strip().startswith(("ssid=", "psk=")))
        assert wpa_supplicant_string(wpa["ssid"]) == AWKWARD_SSID
        assert wpa_supplicant_string(wpa["psk"]) == AWKWARD_PASSWORD
    finally:
        on_host(host, address, f"rm -rf {CHECK_DIR}")


# NetworkManager reads an SSID of digits and `;` as byte values unless its `;` are escaped.
@pytest.mark.parametrize("ssid", [AWKWARD_SSID, "12;34;"])
def test_awkward_ssid_lands_in_a_networkmanager_keyfile_exactly_as_written(classroom, ssid):
    """What this proves, on the Desktop-like host (NetworkManager 1.42): the keyfile an
    Ubuntu 22.04 Desktop gets (the layout is forced: this host emulates 24.04, which gets
    a netplan file) passes the on-host script's validation (NetworkManager's own keyfile
    parser, `nmcli --offline`), and NetworkManager reads the SSID and password from it
    exactly as written: its re-serialisation of the profile (it writes a non-ASCII SSID
    as byte values) decodes to the same SSID and password. `12;34;` is the SSID NetworkManager
    would read as the two bytes 12 and 34 if its `;` were not escaped.
    """
    index = next(i for i, h in enumerate(classroom.hosts) if h.name == DESKTOP_HOST)
    host, settings, address = awkward_wifi_host(classroom, index, ssid)
    layout = Layout(NM_KEYFILE, "a 22.04 Desktop's layout, forced for this test")
    wanted = desired_files(settings, layout, cloud_init_present=False)
    path = keyfile_path(settings)
    assert list(wanted.files) == [path] and wanted.files[path] == render_keyfile(settings)
    try:
        staged = stage_and_validate(host, address, plan_for(settings, NM_KEYFILE, wanted.files), wanted.files)
        assert staged[path] == wanted.files[path]
        ours = keyfile_values(staged[path])
        assert nm_ssid(ours["wifi.ssid"]) == ssid and ours["wifi-security.psk"] == AWKWARD_PASSWORD

        read_by_nm = keyfile_values(on_host(
            host, address, "nmcli --offline connection modify connection.autoconnect yes", stdin=staged[path]))
        assert nm_ssid(read_by_nm["wifi.ssid"]) == ssid
        assert read_by_nm["wifi-security.psk"] == AWKWARD_PASSWORD
    finally:
        on_host(host, address, f"rm -rf {CHECK_DIR}")


# Issue 18: a power cut during the confirmation window, and where a WiFi password may be.

def host_root(host) -> Path:
    """The host's / as this machine sees it (through its PID 1), /run included."""
    from roslab.sandbox import hosts as sandbox_hosts
    from roslab.sandbox.instance import Instance

    pid = sandbox_hosts.container_init_pid(Instance(INSTANCE, SUBNET), host.name)
    assert pid is not None, f"{host.name} is not running"
    return Path(f"/proc/{pid}/root")


def apply_status(host) -> dict:
    try:
        return json.loads((host_root(host) / "run/roslab/network/status.json").read_text())
    except (OSError, ValueError, AssertionError):
        return {}


def wait_for(predicate, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.2)


def start_deploy(roster: Path, host: str) -> subprocess.Popen:
    return subprocess.Popen(
        [str(BIN / "pyinfra"), "-y", "inventories/lab.py", TEST_DEPLOY, "--limit", host],
        cwd=REPO, env={**ENV, "ROSLAB_ROSTER": str(roster)}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True,
    )


def test_a_power_cut_during_the_confirmation_window_comes_back_on_the_old_address(classroom):
    from roslab.sandbox import lifecycle
    from roslab.sandbox.instance import Instance

    host = pick(classroom, 1)  # back at its old address after its rolled-back change
    new = str(SUBNET.network_address + 81)
    roster = write_roster({host.name: static(new, network_confirm_timeout=90)})
    instance = Instance(INSTANCE, SUBNET)
    # The controller cannot confirm (as if the switch did not carry the new address yet),
    # so the host sits in its confirmation window when the power goes.
    subprocess.run(["ip", "route", "add", "blackhole", f"{new}/32"], check=True)
    try:
        deploy = start_deploy(roster, host.name)
        wait_for(lambda: apply_status(host).get("state") == "waiting-for-confirmation", 120,
                 "the host to wait for its confirmation")
        assert on_host_file(host, "var/lib/roslab/network/pending.json")
        lifecycle.power_cut(host.name, instance)
        time.sleep(1)
        lifecycle.power_on(host.name, instance, wait_at=host.address)  # at the OLD address
        output, _ = deploy.communicate(timeout=300)
    finally:
        subprocess.run(["ip", "route", "del", "blackhole", f"{new}/32"], check=True)

    assert deploy.returncode == 1, output[-4000:]
    assert "Network change rolled back: the host restarted before the network change of" in output, output[-4000:]
    assert f"reachable again at {host.address}" in output
    assert on_host(host, host.address, "ls /etc/netplan").split() == ["50-cloud-init.yaml"]
    assert on_host(host, host.address, "ip -4 -o address show dev eth0").split()[3] == f"{host.address}/{SUBNET.prefixlen}"
    assert on_host(host, host.address, "ls /var/lib/roslab/network").split() == ["recovered.json"]
    assert network_state.last_known_address(roster, host.name) is None

    # The next run finds the host where it is, says so, and makes the change.
    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0, proc.stderr[-4000:]
    (found,) = [line for line in proc.stderr.splitlines() if "network: found at" in line]
    assert f"network: found at {host.address}: the host restarted before the network change of" in found
    assert on_host(host, new, "cat /tmp/roslab-e2e-reached-at").split()[2] == new
    assert on_host(host, new, "ls /var/lib/roslab/network").split() == []
    proc, results = run_deploy(roster, host.name)
    assert proc.returncode == 0 and network_op(results)["no_change"] == [host.name], proc.stderr[-4000:]


def on_host_file(host, relative: str) -> bool:
    return (host_root(host) / relative).is_file()


class SecretWatcher:
    """Polls every file the host changed (its overlay's upper dir, and /run through its PID 1)
    for `secret`, noting each sighting's path, owner and mode."""

    def __init__(self, host, secret: str):
        from roslab.sandbox.instance import Instance

        self.host, self.secret = host, secret.encode()
        self.upper = Instance(INSTANCE, SUBNET).host_dir(host) / "upper"
        self.sightings: set[tuple[str, int, int]] = set()
        self.stop = False

    def roots(self) -> list[Path]:
        roots = [self.upper]
        try:
            roots.append(host_root(self.host) / "run")
        except AssertionError:
            pass  # powered off
        return roots

    def scan(self) -> set[tuple[str, int, int]]:
        found = set()
        for root in self.roots():
            for directory, _, names in os.walk(root):
                if "/journal" in directory or "/proc" in directory:
                    continue
                for name in names:
                    path = Path(directory, name)
                    try:
                        info = path.lstat()
                        if not path.is_file() or path.is_symlink() or info.st_size > 256 * 1024:
                            continue
                        if self.secret in path.read_bytes():
                            found.add((str(path.relative_to(root)), info.st_uid, info.st_mode & 0o777))
                    except OSError:
                        continue
        return found

    def run(self) -> None:
        while not self.stop:
            self.sightings |= self.scan()
            time.sleep(0.005)


def test_a_wifi_password_is_never_readable_by_others_nor_left_after_a_run_interrupted_or_not(classroom):
    import signal
    import threading

    host = pick(classroom, 2)  # back at its old address after its rolled-back change
    password = f"e2e-watch-{uuid4().hex}"
    # The sandbox has no WiFi: the change is staged, validated, installed, and rolled back.
    roster = write_roster({host.name: static(str(SUBNET.network_address + 82), network_kind="wifi",
                                             wifi_ssid="roslab-e2e", wifi_password_secret="e2e_wifi")},
                          secrets={"e2e_wifi": password})
    watcher = SecretWatcher(host, password)
    thread = threading.Thread(target=watcher.run, daemon=True)
    thread.start()
    try:
        proc, results = run_deploy(roster, host.name)
        assert proc.returncode == 1, proc.stderr[-4000:]
        assert password not in proc.stdout + proc.stderr
        seen_in_run = set(watcher.sightings)

        # Interrupted: Ctrl-C to pyinfra once the host has its staged files or its change.
        interrupted = start_deploy(roster, host.name)
        wait_for(lambda: any(path.startswith(("roslab/network/staging", "etc/netplan/60-roslab"))
                             for path, _, _ in watcher.sightings - seen_in_run) or interrupted.poll() is not None,
                 120, "the change to reach the host")
        interrupted.send_signal(signal.SIGINT)
        output, _ = interrupted.communicate(timeout=120)
        assert password not in output
        # The host rolls the change back on its own (nobody confirms it).
        wait_for(lambda: apply_status(host).get("state") in ("rolled-back", "confirmed"), 120,
                 "the host to end the change")
    finally:
        watcher.stop = True
        thread.join()
    time.sleep(0.5)
    assert watcher.sightings, "the watcher never saw the password: it cannot have watched the change"
    for path, uid, mode in sorted(watcher.sightings):
        assert uid == 0 and mode == 0o600, f"{path} held the WiFi password as uid {uid}, mode {mode:o}"
        assert not path.startswith(("tmp/", "var/tmp/", "home/")), f"{path} held the WiFi password"
    left = watcher.scan()
    assert left == set(), f"the WiFi password was left in {sorted(left)}"
    assert answers_ssh(host.address, seconds=10)
