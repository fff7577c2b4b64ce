"""Sandbox hosts: systemd-booted containers, each in its own network namespace.

A host is an overlay mount over the shared read-only base image (so a reset
wipes only its upper directory), a network namespace wired to the instance's
bridge by a veth pair (`eth0` inside), and a supervisor shell running
systemd-nspawn in a loop so that `reboot` inside works (nspawn exits 133).
The supervisor first moves itself into the host's own cgroups, so stopping a
host is killing what is in them.
"""

from __future__ import annotations

import ipaddress
import os
import shlex
import shutil
import signal
import socket
import subprocess
import time
import uuid
from pathlib import Path

from . import emulation, image
from .instance import Instance, SandboxHost
from .system import SandboxError, log, run, terminate, write_file

LXCFS_DIR = Path("/var/lib/lxcfs")
REBOOT_EXIT_CODE = 133  # what systemd-nspawn returns when the container asked to reboot


# -- cgroups ----------------------------------------------------------------------------

def cgroup_roots() -> list[Path]:
    """The cgroup hierarchies a host must be placed in (v1 name=systemd + unified, or pure v2)."""
    base = Path("/sys/fs/cgroup")
    if (base / "cgroup.controllers").exists():
        return [base]
    return [base / name for name in ("systemd", "unified") if (base / name).is_dir()]


def instance_cgroups(instance: Instance) -> list[Path]:
    return [root / "roslab" / instance.name for root in cgroup_roots()]


def host_cgroups(instance: Instance, host_name: str) -> list[Path]:
    return [path / host_name for path in instance_cgroups(instance)]


def _pids_in(tree: Path) -> set[int]:
    """Every pid in a cgroup tree (the host's systemd adds and removes cgroups meanwhile)."""
    pids = set()
    for directory, _, files in os.walk(tree):  # os.walk skips directories that vanish
        if "cgroup.procs" in files:
            try:
                pids.update(int(line) for line in Path(directory, "cgroup.procs").read_text().split())
            except OSError:
                pass
    return pids


def kill_cgroup_trees(trees: list[Path], timeout: float = 10.0) -> None:
    """SIGKILL every process in the cgroup trees, then remove the cgroups."""
    trees = [tree for tree in trees if tree.is_dir()]
    deadline = time.monotonic() + timeout
    while True:
        pids = set().union(*(_pids_in(tree) for tree in trees)) if trees else set()
        if not pids:
            break
        if time.monotonic() > deadline:
            raise SandboxError(f"processes {sorted(pids)} in {trees[0]} survived SIGKILL")
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.02)
    for tree in trees:
        for directory, _, _ in sorted(os.walk(tree), key=lambda entry: -len(entry[0])):
            try:
                os.rmdir(directory)
            except FileNotFoundError:
                pass


# -- network ----------------------------------------------------------------------------

def ensure_bridge(instance: Instance) -> None:
    if Path(f"/sys/class/net/{instance.bridge}").exists():
        return
    _check_subnet_free(instance)
    run("ip", "link", "add", instance.bridge, "type", "bridge")
    run("ip", "addr", "add", f"{instance.bridge_address}/{instance.subnet.prefixlen}", "dev", instance.bridge)
    run("ip", "link", "set", instance.bridge, "up")


def _check_subnet_free(instance: Instance) -> None:
    """Refuse a subnet some other interface (another instance, a VPN) already routes."""
    for line in run("ip", "-4", "-o", "route", "show").stdout.splitlines():
        words = line.split()
        try:
            network = ipaddress.IPv4Network(words[0], strict=False)
        except (ValueError, IndexError):
            continue  # "default via ..."
        if network.overlaps(instance.subnet):
            device = words[words.index("dev") + 1] if "dev" in words else "?"
            raise SandboxError(
                f"sandbox {instance.name!r} wants {instance.subnet}, but {network} is already on {device}: "
                "choose another with ROSLAB_SANDBOX_SUBNET"
            )


def remove_network(instance: Instance) -> None:
    """Delete the instance's netns (taking their veth ends with them), stray veths and the bridge."""
    for line in run("ip", "netns", "list", check=False).stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        if name.startswith(instance.netns_prefix):
            run("ip", "netns", "delete", name, check=False)
    for path in Path("/sys/class/net").iterdir():
        if path.name.startswith(f"rlv{instance.short_id}") or path.name == instance.bridge:
            run("ip", "link", "delete", path.name, check=False)


def wire_host(instance: Instance, host: SandboxHost) -> None:
    """Give the host its netns with `eth0` on the bridge (the address is set from inside)."""
    netns, veth = instance.netns(host), instance.veth(host)
    if not Path(f"/run/netns/{netns}").exists():
        run("ip", "netns", "add", netns)
    if not Path(f"/sys/class/net/{veth}").exists():
        run("ip", "link", "add", veth, "type", "veth", "peer", "name", "eth0", "netns", netns)
    run("ip", "link", "set", veth, "master", instance.bridge, "up")


# -- mounts and files --------------------------------------------------------------------

def mounts_under(directory: Path) -> list[Path]:
    """Mount points at or below `directory`, deepest first."""
    found = []
    prefix = str(directory).rstrip("/") + "/"
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        point = line.split()[4].replace("\\040", " ")
        if point == str(directory) or point.startswith(prefix):
            found.append(Path(point))
    return sorted(found, key=lambda p: -len(str(p)))


def unmount_all(directory: Path) -> None:
    for point in mounts_under(directory):
        if run("umount", point, check=False).returncode != 0:
            run("umount", "--lazy", point, check=False)
    if mounts_under(directory):
        raise SandboxError(f"cannot unmount {mounts_under(directory)[0]}")


def _host_paths(instance: Instance, host: SandboxHost) -> dict[str, Path]:
    base = instance.host_dir(host)
    return {name: base / name for name in ("upper", "work", "merged")}


def mount_fresh(instance: Instance, host: SandboxHost, rootfs: Path) -> Path:
    """Mount a fresh overlay for the host (any earlier changes are wiped); return the merged dir."""
    paths = _host_paths(instance, host)
    unmount_all(paths["merged"])
    for name in ("upper", "work"):
        shutil.rmtree(paths[name], ignore_errors=True)
    for path in paths.values():
        path.mkdir(parents=True, exist_ok=True)
    run("mount", "-t", "overlay", "overlay", "-o",
        f"lowerdir={rootfs},upperdir={paths['upper']},workdir={paths['work']}", paths["merged"])
    return paths["merged"]


def write_host_files(instance: Instance, host: SandboxHost, root: Path, ubuntu_keyring: bytes) -> None:
    """Write what makes this host itself: identity, keys, and the Ubuntu emulation."""
    identity = host.identity(instance.subnet.prefixlen)
    for path, (content, mode) in emulation.host_files(identity, f"{instance.upstream_url}/ubuntu").items():
        write_file(root / path.lstrip("/"), content, mode=mode)
    if host.flavour == "desktop":
        # As on Ubuntu Desktop: NetworkManager runs the network, networkd is off.
        run("systemctl", f"--root={root}", "disable", "--quiet", "systemd-networkd.service",
            "systemd-networkd.socket", "systemd-networkd-wait-online.service")
        run("systemctl", f"--root={root}", "enable", "--quiet", "NetworkManager.service")
    write_file(root / "etc/hostname", f"{host.name}\n")
    write_file(root / "etc/hosts", f"127.0.0.1 localhost\n127.0.1.1 {host.name}\n"
               "::1 localhost ip6-localhost ip6-loopback\n")
    write_file(root / "etc/machine-id", uuid.uuid4().hex + "\n", mode=0o444)
    # Ubuntu's keyring in both places ubuntu-keyring installs it; the key is the sandbox's.
    write_file(root / emulation.UBUNTU_KEYRING.lstrip("/"), ubuntu_keyring)
    write_file(root / "etc/apt/trusted.gpg.d/ubuntu-keyring-2018-archive.gpg", ubuntu_keyring)
    host_key = instance.host_dir(host) / "ssh_host_ed25519_key"
    for suffix, mode in (("", 0o600), (".pub", 0o644)):
        source = host_key.with_name(host_key.name + suffix)
        write_file(root / "etc/ssh" / source.name, source.read_bytes(), mode=mode)
    uid = image.LOGIN_UID
    ssh_dir = root / "home" / image.LOGIN_USER / ".ssh"
    ssh_dir.mkdir(mode=0o700, exist_ok=True)
    os.chown(ssh_dir, uid, uid)
    write_file(ssh_dir / "authorized_keys", instance.key_path.with_suffix(".pub").read_bytes(),
               mode=0o600, owner=(uid, uid))


def ensure_host_key(instance: Instance, host: SandboxHost) -> None:
    key = instance.host_dir(host) / "ssh_host_ed25519_key"
    if not key.exists():
        key.parent.mkdir(parents=True, exist_ok=True)
        run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"root@{host.name}", "-f", key)


# -- processes ---------------------------------------------------------------------------

def nspawn_argv(instance: Instance, host: SandboxHost, merged: Path) -> list[str]:
    argv = [
        "systemd-nspawn", "--boot", f"--directory={merged}", f"--machine={instance.machine_name(host)}",
        f"--network-namespace-path=/run/netns/{instance.netns(host)}",
        # No systemd as PID 1 on the machine: nspawn must neither register nor make a scope.
        "--register=no", "--keep-unit",
        "--console=read-only", "--resolv-conf=off", "--timezone=off", "--link-journal=no",
        # A host configures its own address (netplan, NetworkManager), as a Pi does.
        "--capability=CAP_NET_ADMIN",
    ]
    if lxcfs_running():
        argv.append(f"--bind-ro={LXCFS_DIR}")
    return argv


def start(instance: Instance, host: SandboxHost, merged: Path) -> None:
    """Boot the host under a supervisor that restarts nspawn when the host reboots."""
    cgroups = host_cgroups(instance, host.name)
    for path in cgroups:
        path.mkdir(parents=True, exist_ok=True)
    join = "".join(f'echo $$ > {shlex.quote(str(path / "cgroup.procs"))}\n' for path in cgroups)
    script = (
        join
        + "while :; do\n"
        + f"  {shlex.join(nspawn_argv(instance, host, merged))}\n"
        + "  rc=$?\n"
        + f'  [ "$rc" -eq {REBOOT_EXIT_CODE} ] || exit "$rc"\n'
        + "done\n"
    )
    console = instance.host_dir(host) / "console.log"
    with open(console, "ab") as handle:
        subprocess.Popen(["sh", "-c", script], stdin=subprocess.DEVNULL, stdout=handle, stderr=handle,
                         start_new_session=True)


def stop(instance: Instance, host_name: str) -> None:
    """Power the host off hard (a throwaway host needs no clean shutdown)."""
    kill_cgroup_trees(host_cgroups(instance, host_name))


def is_running(instance: Instance, host_name: str) -> bool:
    return any(_pids_in(path) for path in host_cgroups(instance, host_name) if path.is_dir())


def container_init_pid(instance: Instance, host_name: str) -> int | None:
    """The machine-side pid of the host's PID 1 (its systemd)."""
    for path in host_cgroups(instance, host_name):
        if not path.is_dir():
            continue
        for pid in _pids_in(path):
            try:
                status = Path(f"/proc/{pid}/status").read_text()
            except OSError:
                continue
            for line in status.splitlines():
                if line.startswith("NSpid:") and len(line.split()) == 3 and line.split()[2] == "1":
                    return pid
    return None


def request_reboot(instance: Instance, host_name: str) -> None:
    """Ask the host's systemd to reboot (SIGINT = ctrl-alt-del.target), as `reboot` inside would."""
    pid = container_init_pid(instance, host_name)
    if pid is None:
        raise SandboxError(f"host {host_name!r} of sandbox {instance.name!r} is not running")
    os.kill(pid, signal.SIGINT)


def wait_for_ssh(address: str, timeout: float = 60.0) -> float:
    """Wait until sshd on `address` sends its banner; return the seconds waited."""
    started = time.monotonic()
    deadline = started + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((address, 22), timeout=0.5) as conn:
                conn.settimeout(1.0)
                if conn.recv(4).startswith(b"SSH-"):
                    return time.monotonic() - started
        except OSError:
            pass
        time.sleep(0.05)
    raise SandboxError(f"host {address} did not offer SSH within {timeout:.0f} s")


# -- lxcfs (per-host /proc/uptime) -------------------------------------------------------

def lxcfs_running() -> bool:
    return (LXCFS_DIR / "proc/uptime").exists()


def start_lxcfs(pid_file: Path, log_file: Path) -> bool:
    """Start lxcfs unless something already serves it; return True if we started it."""
    if lxcfs_running() or not shutil.which("lxcfs"):
        return False
    LXCFS_DIR.mkdir(parents=True, exist_ok=True)
    with open(log_file, "ab") as handle:
        subprocess.Popen(["lxcfs", "--foreground", "--pidfile", str(pid_file), str(LXCFS_DIR)],
                         stdin=subprocess.DEVNULL, stdout=handle, stderr=handle, start_new_session=True)
    for _ in range(100):
        if lxcfs_running():
            return True
        time.sleep(0.02)
    log.warning("lxcfs did not start: hosts will show the machine's uptime")
    return True


def stop_lxcfs(pid_file: Path, log_file: Path) -> None:
    try:
        pid = int(pid_file.read_text())
    except (OSError, ValueError):
        return
    try:
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        comm = ""
    if comm == "lxcfs":
        terminate(pid)
    if LXCFS_DIR.is_mount():
        run("umount", "--lazy", LXCFS_DIR, check=False)
    pid_file.unlink(missing_ok=True)
    log_file.unlink(missing_ok=True)
