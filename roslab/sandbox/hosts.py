"""Sandbox hosts: systemd-booted containers, each in its own network namespace.

A host is an overlay mount over the shared read-only base image (so a reset
wipes only its upper directory), a network namespace wired to the instance's
bridge by a veth pair (`eth0` inside), and a supervisor shell running
systemd-nspawn in a loop so that `reboot` inside works (nspawn exits 133).
The supervisor first moves itself into the host's own cgroups, so stopping a
host is killing what is in them.
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import os
import shlex
import shutil
import signal
import socket
import subprocess
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from . import card, emulation, image, pi_boot, seeding
from .instance import STATE_ROOT, Instance, SandboxHost
from .system import SandboxError, discard, log, run, terminate, unmount_all, write_file

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
    pids: set[int] = set()
    for directory, _, files in os.walk(tree):  # os.walk skips directories that vanish
        if "cgroup.procs" in files:
            try:
                pids.update(int(line) for line in Path(directory, "cgroup.procs").read_text().split())
            except OSError:
                pass
    return pids


def kill_cgroup_trees(trees: list[Path], timeout: float = 120.0) -> None:
    """SIGKILL every process in the cgroup trees, then remove the cgroups.

    A killed process can take long to go: on a busy disk the kernel first frees its files
    (seen: over 10 s in discard). Said once after a few seconds, then waited for, bounded.
    At the bound, a process that is only a zombie whose last thread is still in the kernel
    (seen: 12 minutes of ext4 discard on a disk shared by five sandboxes), or one waiting on the
    disk with the SIGKILL pending (seen in CI: 120 s under disk load), is dead to everything
    above the kernel and goes on its own: it is named and left, with its cgroup, to the
    kernel; one that still runs is an error."""
    trees = [tree for tree in trees if tree.is_dir()]
    started = time.monotonic()
    deadline = started + timeout
    said = False
    while True:
        pids = set().union(*(_pids_in(tree) for tree in trees)) if trees else set()
        if not pids:
            break
        if not said and time.monotonic() - started > 5:
            said = True
            logging.getLogger(__name__).info(
                "waiting for %d killed process(es) in %s to exit (the kernel is still freeing their files)",
                len(pids), trees[0])
        if time.monotonic() > deadline:
            running = sorted(pid for pid in pids if not _is_dying(pid))
            if running:
                raise SandboxError(f"processes {running} in {trees[0]} survived SIGKILL")
            logging.getLogger(__name__).warning(
                "killed process(es) %s in %s are zombies, or wait on the disk with SIGKILL pending, still "
                "in the kernel; leaving them (and their cgroup) to exit on their own", sorted(pids), trees[0])
            break
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
            except OSError as error:
                if error.errno != errno.EBUSY:  # busy: a zombie left above still holds it
                    raise


def _is_dying(pid: int) -> bool:
    """Whether a killed process is past running (gone: True too): see status_is_dying."""
    try:
        return status_is_dying(Path(f"/proc/{pid}/status").read_text())
    except OSError:
        return True


SIGKILL_BIT = 1 << (signal.SIGKILL - 1)  # in /proc/PID/status's pending-signal masks


def status_is_dying(status: str) -> bool:
    """Whether /proc/PID/status says the process can no longer run a line of its own: a zombie,
    or a process in uninterruptible sleep (state D: waiting on the disk) with SIGKILL pending,
    which dies the moment the kernel's call returns (seen in CI: over 120 s under disk load)."""
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    state = fields.get("State", "").split()[:1]
    if state == ["Z"]:
        return True
    pending = 0
    for mask in ("SigPnd", "ShdPnd"):
        try:
            pending |= int(fields.get(mask, "0").strip(), 16)
        except ValueError:
            pass
    return state == ["D"] and bool(pending & SIGKILL_BIT)


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

def _host_paths(instance: Instance, host: SandboxHost) -> dict[str, Path]:
    base = instance.host_dir(host)
    return {name: base / name for name in ("upper", "work", "merged")}


def release_card(instance: Instance, host: SandboxHost) -> None:
    """Let go of the card the host was booted from, if any (card.release: its system-boot
    written back, its writable unmounted), and unmount whatever else is at its root."""
    card.release(instance.host_dir(host))
    unmount_all(_host_paths(instance, host)["merged"])


def mount_fresh(instance: Instance, host: SandboxHost, rootfs: Path, layers: Sequence[Path] = ()) -> Path:
    """Mount a fresh overlay for the host (any earlier changes are wiped); return the merged dir.

    `layers`: saved disk states (`lifecycle.save`), topmost first, laid read-only over the
    base image, so the host boots as it was saved while the saved layers stay as they are."""
    paths = _host_paths(instance, host)
    release_card(instance, host)
    for name in ("upper", "work"):
        discard(paths[name], STATE_ROOT)  # a converged host's upper dir is large: deleted in the background
    for path in paths.values():
        path.mkdir(parents=True, exist_ok=True)
    write_file(layers_file(instance, host), "".join(f"{layer}\n" for layer in layers))
    lower = ":".join(str(path) for path in [*layers, rootfs])
    run("mount", "-t", "overlay", "overlay", "-o",
        f"lowerdir={lower},upperdir={paths['upper']},workdir={paths['work']}", paths["merged"])
    return paths["merged"]


def layers_file(instance: Instance, host: SandboxHost) -> Path:
    """Where a host's saved layers below its own changes are listed, one per line, topmost first."""
    return instance.host_dir(host) / "layers"


def host_layers(instance: Instance, host: SandboxHost) -> list[Path]:
    """The saved layers the host's disk lies on (none: a fresh image)."""
    try:
        return [Path(line) for line in layers_file(instance, host).read_text().splitlines() if line]
    except FileNotFoundError:
        return []


@dataclass(frozen=True)
class Boot:
    """How a host boots: with a given SSH host key, or "as flashed" from a NoCloud seed.

    `host_key` is (private key, public key line) written as the host's ed25519 key;
    with `card`, the host's root is that card's `writable` and its seed the card's system-boot;
    with `seed` (a directory holding user-data, meta-data, network-config) cloud-init
    runs on the seed instead, which brings the key, user, hostname and address, and a
    stand-in for first-boot unattended-upgrades holds the dpkg lock `apt_lock_seconds`.
    """

    host_key: tuple[str, str] | None = None
    seed: Path | None = None
    apt_lock_seconds: float = seeding.FIRST_BOOT_APT_LOCK_SECONDS
    card: Path | None = None  # boot from this card's own partitions (card.py); its seed is `seed`


def write_host_files(instance: Instance, host: SandboxHost, root: Path, ubuntu_keyring: bytes, boot: Boot) -> None:
    """Write what makes this host itself: identity, keys, and the Ubuntu emulation.

    A host booted from a seed gets only the emulation (Ubuntu's release files and apt
    layout): its user, keys, hostname and network come from the seed, through cloud-init.
    A card that has booted before (its cloud-init has an instance) gets nothing: it is the
    host's disk as the host left it.
    """
    # (cloud-init's `instance` is an absolute symlink: it points into the card, not here)
    if boot.card and os.path.lexists(root / "var/lib/cloud/instance"):
        return  # a card that has booted before: its system as it is, host key and all, as on a Pi
    identity = host.identity(instance.subnet.prefixlen)
    for path, (content, mode) in emulation.host_files(identity, f"{instance.upstream_url}/ubuntu").items():
        if boot.seed and path.startswith("/etc/netplan/"):
            continue  # cloud-init writes 50-cloud-init.yaml from the seed's network-config
        write_file(root / path.lstrip("/"), content, mode=mode)
    if host.flavour == "desktop":
        # As on Ubuntu Desktop: NetworkManager runs the network, networkd is off.
        run("systemctl", f"--root={root}", "disable", "--quiet", "systemd-networkd.service",
            "systemd-networkd.socket", "systemd-networkd-wait-online.service")
        run("systemctl", f"--root={root}", "enable", "--quiet", "NetworkManager.service")
    write_file(root / "etc/machine-id", uuid.uuid4().hex + "\n", mode=0o444)
    # Ubuntu's keyring in both places ubuntu-keyring installs it; the key is the sandbox's.
    write_file(root / emulation.UBUNTU_KEYRING.lstrip("/"), ubuntu_keyring)
    write_file(root / "etc/apt/trusted.gpg.d/ubuntu-keyring-2018-archive.gpg", ubuntu_keyring)
    if boot.seed:
        user_data = boot.seed / "user-data"
        prepare_seeded_boot(root, boot.apt_lock_seconds, user_data.read_text() if user_data.is_file() else None)
        return
    # A Pi's boot partition (stand-ins of Ubuntu's files); a seeded host has its seed there instead.
    for path, (content, mode) in pi_boot.boot_files(host.board, host.release).items():
        write_file(root / path.lstrip("/"), content, mode=mode)
    write_file(root / "etc/hostname", f"{host.name}\n")
    write_file(root / "etc/hosts", f"127.0.0.1 localhost\n127.0.1.1 {host.name}\n"
               "::1 localhost ip6-localhost ip6-loopback\n")
    if boot.host_key is None:
        raise SandboxError(f"host {host.name!r}: no host key and no seed to boot with")
    private, public = boot.host_key
    write_file(root / "etc/ssh/ssh_host_ed25519_key", private, mode=0o600)
    write_file(root / "etc/ssh/ssh_host_ed25519_key.pub", public.rstrip("\n") + "\n", mode=0o644)
    uid = image.LOGIN_UID
    ssh_dir = root / "home" / image.LOGIN_USER / ".ssh"
    ssh_dir.mkdir(mode=0o700, exist_ok=True)
    os.chown(ssh_dir, uid, uid)
    write_file(ssh_dir / "authorized_keys", instance.key_path.with_suffix(".pub").read_bytes(),
               mode=0o600, owner=(uid, uid))


def prepare_seeded_boot(root: Path, apt_lock_seconds: float, user_data: str | None) -> None:
    """A freshly flashed card: cloud-init enabled, the seed where NoCloud finds it, no host key yet
    (the locales the seed's `user_data` names enabled, as Ubuntu's image has them generated)."""
    (root / seeding.CLOUD_INIT_DISABLED.lstrip("/")).unlink(missing_ok=True)
    for key in (root / "etc/ssh").glob("ssh_host_*"):
        key.unlink()
    # The image's own name and hosts file until cloud-init sets the roster's hostname.
    write_file(root / "etc/hostname", "ubuntu\n")
    write_file(root / "etc/hosts", "127.0.0.1 localhost\n::1 localhost ip6-localhost ip6-loopback\n")
    # Stand-in for the lookup of the boot partition by its label (a container has no block devices).
    link = root / seeding.NOCLOUD_SEED_DIR.lstrip("/")
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(seeding.BOOT_PARTITION)
    (root / seeding.BOOT_PARTITION.lstrip("/")).mkdir(parents=True, exist_ok=True)
    for path, (content, mode) in seeding.seeded_boot_files(apt_lock_seconds).items():
        write_file(root / path.lstrip("/"), content, mode=mode)
    if apt_lock_seconds:
        run("systemctl", f"--root={root}", "enable", "--quiet", seeding.FIRST_BOOT_UNIT)
    locale_gen = root / "etc/locale.gen"
    if locale_gen.exists() and user_data is not None:
        write_file(locale_gen, seeding.seed_locale_enabled(locale_gen.read_text(), user_data))


def random_host_key(instance: Instance, host: SandboxHost) -> tuple[str, str]:
    """A new ed25519 host key (private, public line), as a Pi flashed without a seed makes itself."""
    key = instance.host_dir(host) / "ssh_host_ed25519_key"
    key.parent.mkdir(parents=True, exist_ok=True)
    for path in (key, key.with_name(key.name + ".pub")):
        path.unlink(missing_ok=True)
    run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"root@{host.name}", "-f", key)
    return key.read_text(), key.with_name(key.name + ".pub").read_text().strip()


def keep_seed(instance: Instance, host: SandboxHost, seed: Path) -> Path:
    """Copy a seed beside the host (root-only: it may hold a WiFi password); return the copy.

    The copy is the host's "card": a later plain reset boots from it again.
    """
    copy = instance.host_dir(host) / "seed"
    if seed.resolve() == copy.resolve():
        return copy
    shutil.rmtree(copy, ignore_errors=True)
    copy.mkdir(mode=0o700, parents=True)
    for name in seeding.SEED_FILES:
        if (seed / name).is_file():
            write_file(copy / name, (seed / name).read_bytes(), mode=0o600)
    return copy


# -- processes ---------------------------------------------------------------------------

def nspawn_argv(instance: Instance, host: SandboxHost, merged: Path, seed: Path | None = None,
                card: bool = False) -> list[str]:
    """The host's systemd-nspawn command: `merged` its root, `seed` at /boot/firmware, read-only
    (a seed folder) or, with `card`, read-write (a card's system-boot, as a Pi mounts it)."""
    argv = [
        "systemd-nspawn", "--boot", f"--directory={merged}", f"--machine={instance.machine_name(host)}",
        f"--network-namespace-path=/run/netns/{instance.netns(host)}",
        # No systemd as PID 1 on the machine: nspawn must neither register nor make a scope.
        "--register=no", "--keep-unit",
        "--console=read-only", "--resolv-conf=off", "--timezone=off", "--link-journal=no",
        # A host configures its own address (netplan, NetworkManager), as a Pi does.
        "--capability=CAP_NET_ADMIN",
        f"--bind={image.compile_cache_dir()}:{image.COMPILE_CACHE}",
    ]
    if lxcfs_running():
        argv.append(f"--bind-ro={LXCFS_DIR}")
    if seed:  # the seed where a Pi's boot partition is mounted
        argv.append(f"--bind{'' if card else '-ro'}={seed}:{seeding.BOOT_PARTITION}")
    return argv


def start(instance: Instance, host: SandboxHost, merged: Path, seed: Path | None = None, card: bool = False) -> None:
    """Boot the host under a supervisor that restarts nspawn when the host reboots (`seed` and
    `card` as nspawn_argv takes them)."""
    cgroups = host_cgroups(instance, host.name)
    for path in cgroups:
        path.mkdir(parents=True, exist_ok=True)
    image.ensure_compile_cache()
    join = "".join(f'echo $$ > {shlex.quote(str(path / "cgroup.procs"))}\n' for path in cgroups)
    script = (
        join
        + "while :; do\n"
        + f"  {shlex.join(nspawn_argv(instance, host, merged, seed, card))}\n"
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
    """True if lxcfs answers; a mount left by a killed lxcfs raises ENOTCONN and is not running."""
    try:
        return (LXCFS_DIR / "proc/uptime").exists()
    except OSError:
        return False


def _unmount_stale_lxcfs() -> None:
    """Drop a FUSE mount whose lxcfs died (a killed run), so a new lxcfs can serve the directory."""
    try:
        mounted = LXCFS_DIR.is_mount()
    except OSError:
        mounted = True  # stat on a dead FUSE mount fails with ENOTCONN
    if mounted:
        run("umount", "--lazy", LXCFS_DIR, check=False)


def start_lxcfs(pid_file: Path, log_file: Path) -> bool:
    """Start lxcfs unless something already serves it; return True if we started it."""
    if lxcfs_running() or not shutil.which("lxcfs"):
        return False
    _unmount_stale_lxcfs()
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
    _unmount_stale_lxcfs()
    pid_file.unlink(missing_ok=True)
    log_file.unlink(missing_ok=True)
