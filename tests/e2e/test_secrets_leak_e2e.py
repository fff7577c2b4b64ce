"""No sudo or WiFi password leaks: not into a host's processes, its files, or any output.

team1's two sandbox hosts are made to require a sudo password for the login user, as on a
Pi whose user has a password and no NOPASSWD rule: the password set with chpasswd (on
stdin), the sandbox's NOPASSWD drop-in replaced by a rule that asks. A copy of the roster
names that password in a secrets file (0600), plus a planted WiFi password for team1-robot.
Both are unique per run.

While pyinfra runs with every verbosity and output (`--dry --diff -vv` with the WiFi
host's network change planned, a converge with `-vvv --debug`, a re-run with `--json -v`,
`debug-inventory`, `roslab verify`), a sampler reads every process's arguments and
environment on both hosts (as root, from this machine's /proc) every 0.1 s. Afterwards the
hosts' whole filesystems and every output are searched for the planted secrets, also in
base64 and hex. Zero hits.

It can fail: the sampler must first catch pyinfra's own sudo command (what roslab.ssh.sudo
replaces) carrying a decoy password, sudo must refuse `sudo -n` on the hosts (so every
sudo of the run needed the password), and the converge must succeed through it.
The deploy is lean (ros_install, rosdep, workspace, locale off: long steps that add no new way to sudo).
"""

from __future__ import annotations

import base64
import math
import os
import shlex
import stat
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import yaml
from pyinfra.api import StringCommand
from pyinfra.connectors.util import ASKPASS_COMMAND, SUDO_ASKPASS_ENV_VAR, make_unix_command

from roslab.sandbox import hosts as sandbox_hosts
from roslab.sandbox import lifecycle

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
TEAM = "team1"
WIFI_HOST = "team1-robot"
LOGIN_USER = "ubuntu"
SAMPLE_INTERVAL = 0.1
# Where a host may keep files outside its overlay's upper dir (tmpfs mounts).
HOST_TMPFS_DIRS = ("tmp", "run", "dev/shm", "var/tmp")


def needles(secret: str) -> dict[str, bytes]:
    """The secret as it could appear: raw, hex, and base64 at each of the 3 byte alignments."""
    raw = secret.encode()
    found = {"raw": raw, "hex": raw.hex().encode(), "HEX": raw.hex().upper().encode()}
    for offset in range(3):
        encoded = base64.b64encode(b"\0" * offset + raw)
        # Only the characters that depend on the secret's bytes alone.
        found[f"base64+{offset}"] = encoded[math.ceil(offset * 8 / 6): (offset + len(raw)) * 8 // 6]
    return found


def hits_in(data: bytes, secrets: dict[str, str]) -> list[str]:
    """Which secret in which form `data` holds (names only: never the secret itself)."""
    return [f"{name}/{form}" for name, secret in secrets.items()
            for form, needle in needles(secret).items() if needle in data]


class ProcessSampler(threading.Thread):
    """Reads /proc/<pid>/cmdline and environ of every process of some sandbox hosts, as root.

    A host's processes are those in its cgroup tree (the sandbox keeps each host there).
    """

    def __init__(self, cgroup_trees: list[Path], secrets: dict[str, str]):
        super().__init__(daemon=True)
        self.trees = cgroup_trees
        self.secrets = secrets
        self.hits: list[str] = []
        self.reads = 0
        self.rounds = 0
        self._stop_event = threading.Event()

    def pids(self) -> set[str]:
        found = set()
        for tree in self.trees:
            for directory, _, files in os.walk(tree):
                if "cgroup.procs" in files:
                    try:
                        found.update(Path(directory, "cgroup.procs").read_text().split())
                    except OSError:
                        continue  # the host's systemd removed the cgroup meanwhile
        return found

    def run(self) -> None:
        while not self._stop_event.is_set():
            for pid in self.pids():
                try:
                    for part in ("cmdline", "environ"):
                        data = Path(f"/proc/{pid}/{part}").read_bytes()
                        self.reads += 1
                        for hit in hits_in(data, self.secrets):
                            comm = Path(f"/proc/{pid}/comm").read_text().strip()
                            self.hits.append(f"{hit} in {part} of {comm}")
                except OSError:
                    continue  # the process ended meanwhile
            self.rounds += 1
            self._stop_event.wait(SAMPLE_INTERVAL)

    def stop(self) -> None:
        self._stop_event.set()
        self.join(timeout=10)


def files_with_secrets(root: Path, secrets: dict[str, str]) -> list[str]:
    """Regular files at or under `root` (not following links) that hold a secret in any form."""
    paths = [root] if root.is_file() else (Path(directory, name) for directory, _, files in os.walk(root)
                                           for name in files)
    found = []
    for path in paths:
        try:
            if not stat.S_ISREG(path.lstat().st_mode):
                continue
            data = path.read_bytes()
        except OSError:
            continue
        found += [f"{hit}: {path}" for hit in hits_in(data, secrets)]
    return found


def require_sudo_password(sandbox, host: str, password: str) -> None:
    """Give the login user a password and make sudo ask for it (the last password-less sudo)."""
    proc = subprocess.run(
        _ssh(sandbox, host, "sudo -n chpasswd"), input=f"{LOGIN_USER}:{password}\n",
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    rule = f"# leak test: {LOGIN_USER} needs a password for sudo\\n{LOGIN_USER} ALL=(ALL:ALL) ALL\\n"
    sandbox.sudo(host, f"printf '{rule}' > /etc/sudoers.d/90-roslab-sandbox", check=True)
    refused = sandbox.ssh(host, "sudo -n true")
    assert refused.returncode != 0 and "a password is required" in refused.stderr, refused


def _ssh(sandbox, host: str, command: str) -> list[str]:
    return lifecycle.ssh_argv(sandbox.instance, sandbox.host(host).address, command)


def run(sandbox, argv: list[str], roster: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    started = time.monotonic()
    proc = subprocess.run(argv, cwd=REPO, env={**sandbox.env, "ROSLAB_ROSTER": str(roster)},
                          capture_output=True, text=True, timeout=timeout)
    print(f"leak test: {' '.join(argv[1:])}: {time.monotonic() - started:.0f} s")  # shown when a test fails
    return proc


def pyinfra(sandbox, roster: Path, *args: str) -> subprocess.CompletedProcess:
    return run(sandbox, [str(BIN / "pyinfra"), *args, "inventories/lab.py", "deploy.py"], roster)


def write_rosters(sandbox, directory: Path, secrets: dict[str, str]) -> tuple[Path, Path]:
    """(the converge roster, the same with the WiFi host's network change for a dry run)."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["teams"] = {TEAM: data["teams"][TEAM]}
    data["classroom"].update({
        "secrets_file": "secrets.yaml", "sudo_password_secret": "lab_sudo",
        # Lean: the steps that use sudo for facts, commands and uploads, without the long
        # package installs (sudo to another user: the `exec --sudo-user` run below).
        "ros_install_enabled": False, "rosdep_enabled": False, "workspace_enabled": False, "locale_enabled": False,
        "nodes_verify_timeout": 3,
    })
    data["teams"][TEAM]["hosts"][WIFI_HOST].update({"wifi_ssid": "LabNet", "wifi_password_secret": "lab_wifi"})
    descriptor = os.open(directory / "secrets.yaml", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as secrets_file:
        secrets_file.write(f"lab_sudo: {secrets['sudo']}\nlab_wifi: {secrets['wifi']}\n")
    converge = directory / "roster.yaml"
    converge.write_text(yaml.safe_dump(data, sort_keys=False))
    robot = data["teams"][TEAM]["hosts"][WIFI_HOST]
    robot.update({"network_kind": "wifi", "network_address": f"{sandbox.host(WIFI_HOST).address}/24"})
    wifi = directory / "wifi-roster.yaml"
    wifi.write_text(yaml.safe_dump(data, sort_keys=False))
    return converge, wifi


def send_pyinfras_own_sudo_command(sandbox, host: str, password: str) -> None:
    """Run on `host` the sudo command pyinfra 3.10 itself would send (before roslab.ssh.sudo)."""
    made = sandbox.ssh(host, ASKPASS_COMMAND.format("/tmp", SUDO_ASKPASS_ENV_VAR), check=True)
    askpass = made.stdout.strip().splitlines()[0]
    command = make_unix_command(StringCommand("true"), _sudo=True, _sudo_password=password,
                                _sudo_askpass_path=askpass).get_raw_value()
    sandbox.ssh(host, command)  # a wrong password: sudo asks askpass 3 times, then gives up
    sandbox.ssh(host, f"rm -f {shlex.quote(askpass)}", check=True)


def test_no_secret_reaches_a_host_process_file_or_output(fresh_hosts, tmp_path):
    sandbox = fresh_hosts
    names = [host.name for host in sandbox.hosts if host.name.startswith(f"{TEAM}-")]
    tag = uuid.uuid4().hex[:12]
    secrets = {"sudo": f"Sudo{tag}Pl4nted", "wifi": f"Wifi{tag}Pl4nted"}
    decoy = {"decoy": f"Decoy{tag}Pl4nted"}
    converge, wifi = write_rosters(sandbox, tmp_path, secrets)
    # The searches find what they look for: the secrets file holds both, and an encoded form counts.
    assert len(files_with_secrets(tmp_path / "secrets.yaml", secrets)) == 2
    assert hits_in(b"x" + base64.b64encode(b"ab" + secrets["sudo"].encode()), secrets) == ["sudo/base64+2"]
    for name in names:
        require_sudo_password(sandbox, name, secrets["sudo"])
    init_pids = [sandbox_hosts.container_init_pid(sandbox.instance, name) for name in names]
    trees = [next(tree for tree in sandbox_hosts.host_cgroups(sandbox.instance, name) if tree.is_dir())
             for name in names]

    # The sampler catches pyinfra's own sudo command (what roslab.ssh.sudo replaces).
    canary = ProcessSampler(trees, decoy)
    canary.start()
    send_pyinfras_own_sudo_command(sandbox, names[0], decoy["decoy"])
    canary.stop()
    assert canary.hits, f"the sampler missed pyinfra's own sudo command ({canary.rounds} rounds)"

    sampler = ProcessSampler(trees, secrets)
    sampler.start()
    outputs: dict[str, subprocess.CompletedProcess] = {}
    try:
        outputs["dry diff -vv, WiFi planned"] = pyinfra(sandbox, wifi, "--dry", "--diff", "-vv")
        outputs["converge -vvv --debug"] = pyinfra(sandbox, converge, "-y", "-vvv", "--debug")
        outputs["re-run --json -v"] = pyinfra(sandbox, converge, "-y", "--json", "-v")
        outputs["exec --sudo-user"] = run(sandbox, [str(BIN / "pyinfra"), "-y", "--data", "_sudo_user=nobody",
                                                    "inventories/lab.py", "exec", "--", "id", "-un"], converge)
        outputs["debug-inventory"] = run(sandbox, [str(BIN / "pyinfra"), "inventories/lab.py", "debug-inventory"],
                                         converge)
        outputs["verify"] = run(sandbox, [str(BIN / "roslab"), "verify"], converge)  # $ROSLAB_ROSTER
    finally:
        sampler.stop()

    dry, first, second = (outputs[key] for key in ("dry diff -vv, WiFi planned", "converge -vvv --debug",
                                                     "re-run --json -v"))
    # The secrets were in play: the WiFi file was planned, and sudo ran with the password.
    assert dry.returncode == 0 and "wifis:" in dry.stderr and "password: ********" in dry.stderr, dry.stderr[-3000:]
    assert first.returncode == 0, first.stderr[-6000:]
    assert "SUDO_ASKPASS=" in first.stderr and "sudo -H -A -k" in first.stderr
    assert second.returncode == 0, second.stderr[-6000:]
    assert "roslab summary" in second.stderr and "0 changed" in second.stderr, second.stderr[-3000:]
    assert outputs["debug-inventory"].returncode == 0, outputs["debug-inventory"].stderr[-3000:]
    assert outputs["exec --sudo-user"].returncode == 0 and "] nobody" in outputs["exec --sudo-user"].stderr, \
        outputs["exec --sudo-user"].stderr[-3000:]
    assert "team1-main" in outputs["verify"].stdout, outputs["verify"].stderr[-3000:]  # it checked the hosts
    assert sampler.rounds > 20 and sampler.reads > 1000, (sampler.rounds, sampler.reads)

    leaks = [f"process: {hit}" for hit in sorted(set(sampler.hits))]
    for label, proc in outputs.items():
        leaks += [f"{hit} in {label} {stream}" for stream in ("stdout", "stderr")
                  for hit in hits_in(getattr(proc, stream).encode(), secrets)]
    for name, pid in zip(names, init_pids):
        host_dir = sandbox.instance.host_dir(sandbox.host(name))
        leaks += files_with_secrets(host_dir / "upper", secrets)
        for directory in HOST_TMPFS_DIRS:
            leaks += files_with_secrets(Path(f"/proc/{pid}/root") / directory, secrets)
        left = sorted(Path(f"/proc/{pid}/root/tmp").glob("roslab-sudo-askpass-*"))
        assert not left, f"{name}: the askpass file outlived the run: {left}"
    # What the runs wrote on this machine: the roster's state dir, a crash log.
    leaks += files_with_secrets(tmp_path / ".roslab-state", secrets)
    leaks += files_with_secrets(REPO / "pyinfra-debug.log", secrets)
    assert not leaks, "planted secrets found (name/form: where):\n" + "\n".join(leaks)
