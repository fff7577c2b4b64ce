"""The base image: a minimal Debian rootfs every sandbox host boots from.

Built once with mmdebstrap from the machine's own configured Debian sources
(no archive address is written into the project), customised to look like a
Raspberry Pi after first setup (user `ubuntu` with passwordless sudo, SSH on),
and cached under the cache directory keyed by its content. Hosts never write to
it: each one mounts an overlay on top (see hosts.py).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

from roslab.controller_files import file_lock

from . import seeding
from .system import SandboxError, announced, log, run, write_file

# Bump when the way the image is built or customised changes: it is part of the cache key.
BUILDER_VERSION = 7

# What a Pi's server image brings, minus the kernel: the deploys find these installed.
# cloud-init (Debian's) stays disabled unless a host boots from a seed (seeding.py);
# systemd-timesyncd is the time sync a seed's `ntp:` configures (idle in a container).
BASE_PACKAGES = (
    "openssh-server", "sudo", "python3", "locales", "systemd", "systemd-sysv", "dbus",
    "iproute2", "netplan.io", "network-manager", "ca-certificates", "gnupg", "curl",
    "iputils-ping", "procps", "libpam-systemd", "less", "nano", "cloud-init", "systemd-timesyncd",
    "ccache",  # the sandbox's compile cache (COMPILE_CACHE below), not a Pi's
)

# The sandbox's hosts compile C and C++ through ccache, into one cache every host of every
# instance on this machine shares (bound from compile_cache_dir()): a class rehearsed again, or
# two classes building the same micro-ROS agent, compile each unchanged source once. colcon,
# CMake and the linker still run on the host as on a Pi; only a compiler run whose inputs
# ccache has seen (by content) is answered from the cache, and a failing one never is.
# /usr/local/bin comes before /usr/bin in PATH and in sudo's secure_path, so CMake's `cc`/`c++`
# (and `gcc`/`g++`) are ccache's, which runs the real /usr/bin compiler once the deploy installed
# it. `base_dir`: paths under /home are hashed relative, so two hosts' build folders share.
COMPILE_CACHE = "/var/cache/roslab-ccache"
COMPILE_CACHE_CONF = f"""\
# roslab sandbox (not on a Pi): one compile cache shared by the sandbox's hosts (roslab/sandbox/image.py)
cache_dir = {COMPILE_CACHE}
base_dir = /home
hash_dir = false
umask = 000
max_size = 4G
"""
COMPILER_NAMES = ("cc", "c++", "gcc", "g++")

LOGIN_USER = "ubuntu"
LOGIN_UID = 1000


def cache_dir() -> Path:
    """Where images and archives are cached (outside the checkout, shared by instances)."""
    return Path(os.environ.get("ROSLAB_CACHE_DIR", "/var/cache/roslab"))


def compile_cache_dir() -> Path:
    """The sandbox hosts' shared compile cache on this machine (COMPILE_CACHE in each host)."""
    return cache_dir() / "ccache" / "cache"


def ensure_compile_cache() -> Path:
    """Make compile_cache_dir(): writable by every user of every host (their uids differ), so its
    parent is root's alone and no other user of this machine can reach it to plant an object."""
    shared = compile_cache_dir()
    shared.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(shared.parent, 0o700)
    shared.mkdir(exist_ok=True)
    os.chmod(shared, 0o777)
    return shared


def machine_codename(os_release: Path = Path("/etc/os-release")) -> str:
    for line in os_release.read_text().splitlines():
        if line.startswith("VERSION_CODENAME="):
            return line.split("=", 1)[1].strip('"')
    raise SandboxError("cannot tell this machine's Debian codename from /etc/os-release")


def _deb822_stanzas(text: str):
    stanza: dict[str, str] = {}
    for line in text.splitlines() + [""]:
        if not line.strip():
            if stanza:
                yield stanza
            stanza = {}
        elif not line.startswith("#") and ":" in line and not line[0].isspace():
            key, value = line.split(":", 1)
            stanza[key.strip().lower()] = value.strip()


def debian_sources(etc: Path = Path("/etc/apt"), codename: str | None = None) -> str:
    """The machine's configured Debian sources (its codename's suites only) as deb822 text.

    Third-party sources on the machine (other suites) are left out: the image is
    built only from Debian's archive.
    """
    codename = codename or machine_codename()
    entries = []
    for path in sorted(etc.glob("sources.list.d/*.sources")):
        for stanza in _deb822_stanzas(path.read_text()):
            if "deb" not in stanza.get("types", "").split() or stanza.get("enabled", "yes") == "no":
                continue
            entries.append((stanza["uris"].split(), stanza["suites"].split(), stanza.get("signed-by")))
    for path in [etc / "sources.list", *sorted(etc.glob("sources.list.d/*.list"))]:
        if not path.exists():
            continue
        for line in path.read_text().splitlines():
            words = line.split("#", 1)[0].split()
            if not words or words[0] != "deb":
                continue
            options = {}
            if words[1].startswith("["):
                while not words[1].endswith("]"):
                    words[1:3] = [words[1] + " " + words[2]]
                for option in words.pop(1).strip("[]").split():
                    key, _, value = option.partition("=")
                    options[key] = value
            entries.append(([words[1]], [words[2]], options.get("signed-by")))
    stanzas = []
    for uris, suites, signed_by in entries:
        ours = [s for s in suites if s == codename or s.startswith(codename + "-")]
        if not ours:
            continue
        stanza = f"Types: deb\nURIs: {' '.join(uris)}\nSuites: {' '.join(ours)}\nComponents: main\n"
        if signed_by:
            stanza += f"Signed-By: {signed_by}\n"
        stanzas.append(stanza)
    if not stanzas:
        raise SandboxError(f"no Debian {codename} sources configured in /etc/apt: cannot build the sandbox image")
    return "\n".join(stanzas)


def _key(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def base_image() -> Path:
    """Return the cached base rootfs, building it first if the cache lacks it."""
    sources = debian_sources()
    root = cache_dir() / "base" / _key(BUILDER_VERSION, BASE_PACKAGES, sources)
    rootfs = root / "rootfs"
    if rootfs.is_dir():
        return rootfs
    with file_lock(cache_dir() / "lock"):
        if rootfs.is_dir():  # another builder finished while we waited
            return rootfs
        building = root.with_name(root.name + ".building")
        shutil.rmtree(building, ignore_errors=True)
        building.mkdir(parents=True)
        write_file(building / "debian.sources", sources)
        log.warning("building the sandbox base image (once, then cached in %s; about a minute)", cache_dir())
        with announced(f"downloading and unpacking {len(BASE_PACKAGES)} Debian packages and their "
                       "dependencies (mmdebstrap)"):
            run(
                "mmdebstrap", "--variant=minbase", "--mode=root", "--format=directory",
                "--include=" + ",".join(BASE_PACKAGES),
                machine_codename(), building / "rootfs", building / "debian.sources",
            )
        with announced("making the image look like a Pi after its first setup"):
            _customise(building / "rootfs")
        building.rename(root)
    return rootfs


def dpkg_status(rootfs: Path) -> Path:
    return rootfs / "var/lib/dpkg/status"


def _chroot(rootfs: Path, *argv: str) -> None:
    run("chroot", rootfs, *argv, env={"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LC_ALL": "C"})


def _customise(rootfs: Path) -> None:
    """Make the Debian rootfs look like a Pi after its first setup (release-independent parts)."""
    _chroot(rootfs, "useradd", "--create-home", "--shell", "/bin/bash", "--uid", str(LOGIN_UID),
            "--groups", "sudo", LOGIN_USER)
    # What cloud-init's 90-cloud-init-users gives the default user on Ubuntu images.
    write_file(rootfs / "etc/sudoers.d/90-roslab-sandbox",
               f"# roslab sandbox: the login user has passwordless sudo, as on a Pi after setup\n"
               f"{LOGIN_USER} ALL=(ALL) NOPASSWD:ALL\n", mode=0o440)
    # Each host gets its own ed25519 host key at boot preparation; none is baked in.
    for key in (rootfs / "etc/ssh").glob("ssh_host_*"):
        key.unlink()
    write_file(rootfs / "etc/ssh/sshd_config.d/50-roslab-sandbox.conf",
               "# roslab sandbox: hosts carry only an ed25519 host key\n"
               "HostKey /etc/ssh/ssh_host_ed25519_key\n")
    # Ubuntu Server's renderer is networkd (driven by netplan); NetworkManager is
    # installed for desktop-flavoured hosts but stays off here.
    _chroot(rootfs, "systemctl", "enable", "systemd-networkd.service")
    _chroot(rootfs, "systemctl", "disable", "NetworkManager.service", "NetworkManager-wait-online.service")
    # cloud-init runs only on hosts booted from a seed: the others boot without its
    # four stages (seconds each), as a Pi does once cloud-init has done its first boot.
    for path in (rootfs / "var/lib/cloud").glob("*"):
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    write_file(rootfs / seeding.CLOUD_INIT_DISABLED.lstrip("/"), seeding.CLOUD_INIT_DISABLED_TEXT)
    for name, content in seeding.cloud_init_image_files().items():
        write_file(rootfs / name.lstrip("/"), content)
    # dpkg skips its fsync()s here, as Docker's Ubuntu and Debian images do (docker-apt-speedup):
    # a sandbox host's disk is a folder on this machine, so a host's power cut (its container
    # killed) loses nothing the machine's page cache holds, and installing ROS takes a third
    # less time (bench: 38 s -> 23 s for two hosts). A Pi's dpkg keeps its fsync()s.
    write_file(rootfs / "etc/dpkg/dpkg.cfg.d/roslab-sandbox-unsafe-io",
               "# roslab sandbox (not on a Pi): no fsync per unpacked file; the host's disk is a folder\n"
               "force-unsafe-io\n")
    write_file(rootfs / "etc/ccache.conf", COMPILE_CACHE_CONF)
    for name in COMPILER_NAMES:
        (rootfs / "usr/local/bin" / name).symlink_to("/usr/bin/ccache")
    (rootfs / COMPILE_CACHE.lstrip("/")).mkdir(mode=0o777, parents=True, exist_ok=True)
    os.chmod(rootfs / COMPILE_CACHE.lstrip("/"), 0o777)  # the mount point: a host without the bind keeps its own
    # A host's own periodic apt runs would race the tests' apt runs for the dpkg lock.
    _chroot(rootfs, "systemctl", "mask", "apt-daily.timer", "apt-daily-upgrade.timer")
    # Nothing to resolve: hosts reach only the sandbox upstream by address, and an
    # empty resolv.conf keeps apt from waiting on DNS.
    resolv = rootfs / "etc/resolv.conf"
    if resolv.is_symlink() or resolv.exists():
        resolv.unlink()
    write_file(resolv, "")
    # No Debian sources stay inside: hosts get Ubuntu's apt layout (emulation.py).
    for path in [rootfs / "etc/apt/sources.list", *(rootfs / "etc/apt/sources.list.d").iterdir()]:
        if path.exists() or path.is_symlink():
            path.unlink()
    _chroot(rootfs, "apt-get", "clean")
    for path in (rootfs / "var/lib/apt/lists").glob("*"):
        if path.is_file():
            path.unlink()
    write_file(rootfs / "etc/machine-id", "")
    # /proc/uptime is the machine's; pyinfra's server.reboot watches it. lxcfs on the
    # machine provides a per-container one, bound over /proc early in boot.
    write_file(rootfs / "etc/systemd/system/roslab-sandbox-uptime.service", UPTIME_UNIT)
    _chroot(rootfs, "systemctl", "enable", "roslab-sandbox-uptime.service")


UPTIME_UNIT = """\
# roslab sandbox: give the container its own /proc/uptime (from lxcfs), as a booted Pi has.
[Unit]
Description=roslab sandbox: per-host /proc/uptime from lxcfs
DefaultDependencies=no
Before=sysinit.target
ConditionPathExists=/var/lib/lxcfs/proc/uptime

[Service]
Type=oneshot
ExecStart=/bin/mount --bind /var/lib/lxcfs/proc/uptime /proc/uptime

[Install]
WantedBy=sysinit.target
"""
