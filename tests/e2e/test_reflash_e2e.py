"""Re-flashing a Pi, played by a sandbox host: with a seed it keeps its identity, without one it is refused.

- A host re-flashed from a card seeded by `roslab seed --image` (`roslab sandbox reset HOST
  --card IMG`, the card a stand-in Pi image) boots "as flashed": Debian's cloud-init reads
  the seed the card's system-boot holds from the boot partition and the
  host comes up with the roster's hostname, lab user, authorised key, address and the host
  key stored beside the roster, while a stand-in for Ubuntu's first-boot unattended-upgrades
  holds the dpkg lock. The deploy connects with strict host key checking, waits for the lock,
  converges, and a second run changes nothing.
- A card `roslab flash` wrote with the sandbox's own Pi-like image (`sandbox card-image`) is the
  host's disk (`reset HOST --card DEV`): it boots from it, converges, and stays converged when
  it boots from the card again; what the deploy wrote is on the card.
- A host re-flashed without a seed (`reset --unseeded`) shows a new host key: the deploy
  refuses it with the command to run, and after `roslab forget` + `roslab trust` it is
  reachable again.

Runs on its own sandbox instance (ROSLAB_REFLASH_E2E_SANDBOX, default reflash-e2e, on
ROSLAB_REFLASH_E2E_SUBNET, default 10.213.41.0/24), always taken down at the end.
"""

from __future__ import annotations

import atexit
import ipaddress
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent.parent))
import pi_image  # noqa: E402  (the tests' stand-in image)

from roslab.ssh import identity  # noqa: E402
from roslab.sandbox import card, lifecycle, seeding  # noqa: E402
from roslab.sandbox import hosts as sandbox_hosts  # noqa: E402
from roslab.sandbox.instance import Instance  # noqa: E402

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
INSTANCE = Instance(os.environ.get("ROSLAB_REFLASH_E2E_SANDBOX", "reflash-e2e"),
                    ipaddress.IPv4Network(os.environ.get("ROSLAB_REFLASH_E2E_SUBNET", "10.213.41.0/24")))
ENV = {**os.environ, "ROSLAB_SANDBOX": INSTANCE.name, "ROSLAB_SANDBOX_SUBNET": str(INSTANCE.subnet)}
SEEDED = "team1-robot"  # re-flashed with a seed
UNSEEDED = "team1-main"  # re-flashed without one
LAB_USER = "lab"  # not in the sandbox image: only cloud-init can make it, from the seed
# Long enough that the deploy, started once cloud-init's config stage is done, meets the lock.
APT_LOCK_SECONDS = 40


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")  # pytest unwinds through the finalizers


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    """Two sandbox hosts (Ubuntu 24.04), always taken down again."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    atexit.register(lifecycle.down, INSTANCE)  # a last resort; down is idempotent
    try:
        yield lifecycle.up(2, INSTANCE)
    finally:
        lifecycle.down(INSTANCE)
        signal.signal(signal.SIGTERM, previous)


@pytest.fixture(scope="module")
def classroom_copy(sandbox, tmp_path_factory) -> Path:
    """A teacher's roster for the sandbox's hosts, in its own folder (its own identity store):
    a lab user the image does not have, and a static address for the seeded host."""
    data = yaml.safe_load(INSTANCE.roster_path.read_text())
    for key in ("ssh_known_hosts_file", "ssh_strict_host_key_checking"):  # roslab's defaults apply
        data["classroom"].pop(key)
    data["classroom"]["ssh_user"] = LAB_USER
    # Lean: the steps a re-flash concerns (apt and its lock, the ROS source, locale, shell,
    # SSH, network); installing ROS and building the nodes are tested elsewhere.
    data["classroom"].update(ros_install_enabled=False, rosdep_enabled=False, workspace_enabled=False)
    host = data["teams"]["team1"]["hosts"][SEEDED]
    host["network_address"] = f"{host['address']}/{INSTANCE.subnet.prefixlen}"
    path = tmp_path_factory.mktemp("classroom") / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def roslab(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(BIN / "roslab"), *args], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=600)
    if check:
        assert proc.returncode == 0, f"roslab {' '.join(args)}:\n{proc.stdout}\n{proc.stderr}"
    return proc


def strict_ssh(known_hosts: Path, user: str, address: str, command: str) -> subprocess.CompletedProcess:
    """ssh with strict host key checking against `known_hosts` only, retried while sshd restarts
    (cloud-init restarts it once after changing its configuration)."""
    argv = ["ssh", "-i", str(INSTANCE.key_path), "-o", "IdentitiesOnly=yes", "-o", "BatchMode=yes",
            "-o", f"UserKnownHostsFile={known_hosts}", "-o", "GlobalKnownHostsFile=/dev/null",
            "-o", "StrictHostKeyChecking=yes", "-o", "ConnectTimeout=5", f"{user}@{address}", command]
    deadline = time.monotonic() + 30
    while True:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=120)
        if proc.returncode != 255 or "Connection refused" not in proc.stderr or time.monotonic() > deadline:
            return proc
        time.sleep(0.5)


def deploy(roster: Path, host: str) -> tuple[subprocess.CompletedProcess, dict[str, set[str]]]:
    """deploy.py on one host of `roster` (inventories/lab.py); the run and its changes per operation."""
    proc = subprocess.run(
        [str(BIN / "pyinfra"), "-y", "--json", "inventories/lab.py", "deploy.py", "--limit", host],
        cwd=REPO, env={**ENV, "ROSLAB_ROSTER": str(roster)}, capture_output=True, text=True, timeout=1200,
    )
    changed: dict[str, set[str]] = {}
    try:
        for op in json.loads(proc.stdout)["results"]["operations"]:
            if op["success"]:
                changed[op["name"]] = set(op["success"])
    except (ValueError, KeyError, TypeError):
        pass  # pyinfra stopped before reporting: the return code and stderr say why
    return proc, changed


def test_a_host_reflashed_with_its_seed_boots_as_flashed_and_the_deploy_converges(sandbox, classroom_copy):
    # The card: a stand-in for Ubuntu's Pi image (tests/pi_image.py), seeded as a teacher seeds one.
    card = pi_image.write(classroom_copy.parent / "card.img")
    roslab("seed", str(classroom_copy), "--image", str(card), "--limit", SEEDED)
    known_hosts = identity.known_hosts_path(classroom_copy)
    stored_key = identity.host_keys(classroom_copy, SEEDED).public_line()
    address = sandbox.host(SEEDED).address

    flashed = roslab("sandbox", "reset", SEEDED, "--card", str(card), "--apt-lock-seconds", str(APT_LOCK_SECONDS))
    assert "booted from the card's seed with cloud-init" in flashed.stdout

    # Reached as the seed's user, with strict checking against the roster's known_hosts only:
    # the host serves the key stored beside the roster.
    def on_host(command: str) -> str:
        proc = strict_ssh(known_hosts, LAB_USER, address, command)
        assert proc.returncode == 0, f"{command}: {proc.stderr}"
        return proc.stdout

    assert on_host("hostname").strip() == SEEDED
    assert "sudo" in on_host("id -nG").split()
    login_key = INSTANCE.key_path.with_suffix(".pub").read_text()
    assert on_host("cat ~/.ssh/authorized_keys").split()[:2] == login_key.split()[:2]
    assert on_host("sudo -n cat /etc/ssh/ssh_host_ed25519_key.pub").split()[:2] == stored_key.split()[:2]
    # The address comes from the seed's network-config, written out by cloud-init.
    assert f"inet {address}/24" in on_host("ip -4 -o addr show dev eth0")
    assert "information provided by the datasource" in on_host("sudo -n cat /etc/netplan/50-cloud-init.yaml")

    # cloud-init's stages so far went through without an error (schema, users, keys, locale, time).
    assert json.loads(on_host("cloud-init status --format json"))["errors"] == []

    # The deploy starts while the stand-in for first-boot unattended-upgrades holds the dpkg lock,
    # once cloud-init's config stage (which restarts sshd) is done, as a teacher's first deploy would.
    deadline = time.monotonic() + 120
    while strict_ssh(known_hosts, LAB_USER, address,
                     "systemctl is-active -q cloud-config.service || systemctl is-failed -q cloud-config.service"
                     ).returncode != 0:
        assert time.monotonic() < deadline, "cloud-init's config stage did not finish"
        time.sleep(1)
    holding, started = on_host(f"systemctl is-active {seeding.FIRST_BOOT_UNIT}; date +%s.%N").split()
    assert holding == "active", "the lock was released before the deploy began: raise APT_LOCK_SECONDS"

    first, changed = deploy(classroom_copy, SEEDED)
    output = first.stdout + first.stderr
    assert first.returncode == 0, output[-6000:]
    assert changed, "a freshly flashed host needs provisioning"
    # Issue 18: apt_ready waits for cloud-init's first boot, so cloud-init's own package step
    # never loses the dpkg lock to the deploy; when it had to wait, it said so in one line.
    # (cloud-init's final stage finishes within seconds of the deploy's start here, so
    # whether the probe still found it running depends on the machine's load.)
    status = json.loads(on_host("cloud-init status --format json"))
    assert status["status"] == "done" and status["errors"] == [], status
    # (The run's first read waits for the host to finish booting, cloud-init's final stage
    # included, and says so; apt_ready's own wait for cloud-init then finds it done.)
    waited = [line for line in output.splitlines()
              if "for cloud-init to finish its first boot" in line or "for the host to finish booting" in line]
    finished = float(on_host("stat -c %Y /run/cloud-init/result.json"))
    ran_for = finished - float(started)
    assert len(waited) <= 1 and all(
        re.search(rf"\[{SEEDED}\] roslab: .*waited \d+ s for (cloud-init|the host to finish booting)", line)
        for line in waited), waited
    print(f"cloud-init's first boot ended {ran_for:.0f} s after the deploy began; waited: {waited}")
    if ran_for > 15:  # still running long after the probe: the deploy must have waited
        assert waited, (ran_for, on_host("ls /run/cloud-init"), output[-3000:])
    # The deploy began while the dpkg lock was held, so its apt steps waited for the release.
    released = on_host(f"date -r {seeding.FIRST_BOOT_DONE} +%s.%N")
    assert float(started) < float(released)

    again, changed = deploy(classroom_copy, SEEDED)
    assert again.returncode == 0, (again.stdout + again.stderr)[-6000:]
    assert changed == {}, changed


def test_a_host_reflashed_without_a_seed_is_refused_until_forgotten_and_trusted(sandbox):
    roster = INSTANCE.roster_path
    roslab("sandbox", "reset", "--unseeded", UNSEEDED)

    refused, _ = deploy(roster, UNSEEDED)
    assert refused.returncode != 0
    output = refused.stdout + refused.stderr
    assert "`roslab forget " in output and f"--limit {UNSEEDED}` then" in output, output[-4000:]
    assert "ssh-keygen -R" not in output  # pyinfra's hint edits another known_hosts
    assert roslab("sandbox", "ssh", UNSEEDED, "true", check=False).returncode != 0  # strict there too

    roslab("forget", str(roster), "--limit", UNSEEDED)
    trusted = roslab("trust", str(roster), "--limit", UNSEEDED)
    assert "SHA256:" in trusted.stdout + trusted.stderr  # the fingerprint to compare

    reached = subprocess.run(
        [str(BIN / "pyinfra"), "-y", "inventories/lab.py", "exec", "--limit", UNSEEDED, "--", "hostname"],
        cwd=REPO, env={**ENV, "ROSLAB_ROSTER": str(roster)}, capture_output=True, text=True, timeout=300,
    )
    assert reached.returncode == 0, (reached.stdout + reached.stderr)[-4000:]
    assert roslab("sandbox", "ssh", UNSEEDED, "hostname").stdout.strip() == UNSEEDED


def test_trust_and_forget_keep_to_the_known_hosts_file_the_run_reads(sandbox, tmp_path):
    """A roster that names its own known_hosts file: `roslab trust` records the key there (so the
    strict run reaches the host), also when the host's last confirmed address is gone, and
    `roslab forget` removes it there (so the run refuses the host again)."""
    # Not the seeded host: the first test leaves it booted from a seed whose lab user is
    # not the sandbox roster's. The unseeded one is reached as the roster's user.
    host = UNSEEDED
    data = yaml.safe_load(INSTANCE.roster_path.read_text())
    own = tmp_path / "lab_known_hosts"
    data["classroom"]["ssh_known_hosts_file"] = str(own)
    data["classroom"]["ssh_strict_host_key_checking"] = "yes"
    roster = tmp_path / "roster.yaml"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))
    address = data["teams"]["team1"]["hosts"][host]["address"]

    def hostname() -> subprocess.CompletedProcess:
        return subprocess.run(
            [str(BIN / "pyinfra"), "-y", "inventories/lab.py", "exec", "--limit", host, "--", "hostname"],
            cwd=REPO, env={**ENV, "ROSLAB_ROSTER": str(roster)}, capture_output=True, text=True, timeout=300)

    assert hostname().returncode != 0  # nothing recorded in the roster's file yet

    # The last confirmed address answers no more (an unused address of the sandbox's subnet).
    gone = str(INSTANCE.subnet.network_address + 250)
    state = tmp_path / ".roslab-state"
    state.mkdir()
    (state / "addresses.yaml").write_text(yaml.safe_dump({host: gone}))
    trusted = roslab("trust", str(roster), "--limit", host)
    assert f"{host} ({address}): ssh-ed25519 SHA256:" in trusted.stdout
    assert f"recorded in {own}" in trusted.stdout
    assert not identity.known_hosts_path(roster).exists()  # not the classroom's own file
    (state / "addresses.yaml").unlink()

    reached = hostname()
    assert reached.returncode == 0, (reached.stdout + reached.stderr)[-4000:]

    forgotten = roslab("forget", str(roster), "--limit", host)
    assert f"removed from {own}" in forgotten.stdout
    assert hostname().returncode != 0


@pytest.fixture
def loop_card(sandbox, tmp_path):
    """A 3 GiB "SD card": a loop device over a sparse file. Whatever happens, the host running
    on it lets it go (its system-boot written back) before the card is detached."""
    backing = tmp_path / "card.bin"
    with open(backing, "wb") as handle:
        handle.truncate(3 << 30)
    device = subprocess.run(["losetup", "--find", "--show", str(backing)], capture_output=True, text=True,
                            check=True).stdout.strip()
    try:
        yield Path(device)
    finally:
        host = lifecycle.load(INSTANCE).host(SEEDED)
        sandbox_hosts.stop(INSTANCE, SEEDED)
        card.release(INSTANCE.host_dir(host))
        subprocess.run(["losetup", "--detach", device], check=False)


def test_a_card_roslab_flashed_with_the_sandboxs_image_boots_as_the_hosts_disk_converges_and_stays_converged(
        sandbox, classroom_copy, loop_card, tmp_path):
    """Issue 38's "flash -> boot -> deploy -> no-op": the sandbox's own Pi-like image (a stand-in for
    Ubuntu's, amd64 as the hosts are) is written to a card by `roslab flash` with the host's seed,
    and the host boots from the card itself: its writable the root (grown to the card's end, as
    cloud-init's growpart does), its system-boot at /boot/firmware, where cloud-init reads the seed."""
    image = tmp_path / "sandbox-24.04.img"
    made = roslab("sandbox", "card-image", str(image), "--release", "24.04")
    assert "stand-in" in made.stdout
    flash = ["flash", str(classroom_copy), "--limit", SEEDED, "--image", str(image), "--device", str(loop_card), "-y"]
    # A Pi's image is what flash writes; the sandbox's amd64 one only when named.
    refused = roslab(*flash, check=False)
    assert refused.returncode == 1, refused.stdout
    assert "the image is for amd64, not a Raspberry Pi: nothing was written" in refused.stderr
    flashed = roslab(*flash, "--architecture", "amd64")
    assert re.search(rf"^{SEEDED}\s+{loop_card}\s+\S+\s+verified$", flashed.stdout, re.MULTILINE), flashed.stdout

    booted = roslab("sandbox", "reset", SEEDED, "--card", str(loop_card), "--apt-lock-seconds", "0")
    assert "booted from the card itself" in booted.stdout
    known_hosts, address = identity.known_hosts_path(classroom_copy), sandbox.host(SEEDED).address

    def on_host(command: str) -> str:
        proc = strict_ssh(known_hosts, LAB_USER, address, command)
        assert proc.returncode == 0, f"{command}: {proc.stderr}"
        return proc.stdout

    assert on_host("hostname").strip() == SEEDED
    assert json.loads(on_host("cat /boot/firmware/roslab-flash.json"))["host"] == SEEDED
    # The card is the disk, grown from the image's ~0.7 GB writable to the 3 GiB card's end.
    assert int(on_host("df -B1 --output=size / | tail -1")) > 2.5e9
    # A card a host runs on is in use: flash refuses it without writing a byte.
    busy = roslab(*flash, "--architecture", "amd64", "--force", check=False)
    assert busy.returncode == 1 and f"{loop_card} is in use" in busy.stderr, busy.stderr

    first, changed = deploy(classroom_copy, SEEDED)
    assert first.returncode == 0, (first.stdout + first.stderr)[-6000:]
    assert changed, "a freshly flashed host needs provisioning"
    again, changed = deploy(classroom_copy, SEEDED)
    assert again.returncode == 0 and changed == {}, changed

    # Booted from the same card again, the host is as it left its disk: still converged.
    assert "booted from the card itself" in roslab("sandbox", "reset", SEEDED, "--card", str(loop_card)).stdout
    third, changed = deploy(classroom_copy, SEEDED)
    assert third.returncode == 0 and changed == {}, changed

    # What the deploy wrote is on the card's own partitions once the host lets it go.
    sandbox_hosts.stop(INSTANCE, SEEDED)
    card.release(INSTANCE.host_dir(sandbox.host(SEEDED)))
    _, (start, size) = card._partitions(loop_card)
    writable = subprocess.run(["losetup", "--find", "--show", "--read-only", "--offset", str(start),
                               "--sizelimit", str(size), str(loop_card)], capture_output=True, text=True,
                              check=True).stdout.strip()
    try:
        dropin = subprocess.run(["debugfs", "-R", "cat /etc/ssh/sshd_config.d/01-roslab.conf", writable],
                                capture_output=True, text=True).stdout
    finally:
        subprocess.run(["losetup", "--detach", writable], check=False)
    assert "PasswordAuthentication no" in dropin, dropin
