"""The sandbox's own SD card image: its host image as a Pi-like preinstalled image.

STAND-IN, said so: Ubuntu's download (ubuntu-24.04.x-preinstalled-server-arm64+raspi.img.xz) is
arm64 and out of reach here, so `roslab sandbox card-image` writes one of the sandbox's host image
instead, laid out as Ubuntu's is: an MBR, a FAT32 partition labelled `system-boot` at 1 MiB (the
board's config.txt and cmdline.txt stand-ins, pi_boot.py, and cloud-init's NoCloud files as Ubuntu
ships them) and an ext4 partition labelled `writable` holding the host image as a Pi's card holds
Ubuntu before its first boot: cloud-init enabled, no SSH host key, hostname `ubuntu`. It is amd64,
as the sandbox's hosts are (`roslab flash --architecture amd64` writes it).

A host boots from a card written with it: roslab/sandbox/card.py.
"""

from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path

from roslab import boards
from roslab.seed import targets

from . import card, emulation, hosts, image, pi_boot
from .emulation import HostIdentity
from .system import SandboxError, run, unmount_all, write_file

MIB, SECTOR = card.MIB, card.SECTOR
FAT32_LBA, LINUX = 0x0C, 0x83  # MBR partition types: system-boot, writable
BOOT_MIB = 256  # Ubuntu's system-boot is 512 MiB; a FAT32 of 256 MiB holds the stand-ins with room
SLACK_MIB = 160  # free space in `writable` beyond the host image, before it is grown on a card
ARCHIVE_ON_A_PI = "http://ports.ubuntu.com/ubuntu-ports"  # the apt sources an arm64 Pi image ships
STANDIN = "roslab sandbox stand-in for Ubuntu's Raspberry Pi preinstalled image (roslab/sandbox/card_image.py)"
# cloud-init's NoCloud files on a fresh image's system-boot, as Ubuntu ships them (in short).
UBUNTU_NOCLOUD = {
    "user-data": f"#cloud-config\n# {STANDIN}\n# Ubuntu's default: user ubuntu, password ubuntu, "
                 "changed at first login\nchpasswd:\n  expire: true\n",
    "meta-data": "instance-id: cloud-image\n",
    "network-config": "version: 2\nethernets:\n  eth0:\n    dhcp4: true\n    optional: true\n",
}


# -- writing the image -------------------------------------------------------------------------

def write_image(out: Path, release: str, board: str = "pi4") -> Path:
    """Write the sandbox's Pi-like image of Ubuntu `release` for `board` to `out`; return it."""
    if out.exists() and not out.is_file():
        raise SandboxError(f"card-image: {out} exists and is not a file: this writes an image file "
                           "(`roslab flash` writes it to cards)")
    problem = boards.release_problem(board, release)
    if problem:
        raise SandboxError(f"card-image: {problem}")
    if not pi_boot.boot_files(board, release):
        raise SandboxError(f"card-image: no boot partition stand-in for a {board} on Ubuntu {release} "
                           f"(releases: {', '.join(sorted(pi_boot.CONFIG_TXT))})")
    rootfs = image.base_image()
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".roslab-card-", dir=out.parent) as scratch:
        work = Path(scratch)
        for name in ("upper", "work", "merged"):
            (work / name).mkdir()
        run("mount", "-t", "overlay", "overlay", "-o",
            f"lowerdir={rootfs},upperdir={work / 'upper'},workdir={work / 'work'}", work / "merged")
        try:
            _as_before_first_boot(work / "merged", release)
            used = int(run("du", "-s", "-B1", "--one-file-system", work / "merged").stdout.split()[0])
            writable_mib = (used * 5 // 4) // MIB + SLACK_MIB
            _partitioned(out, writable_mib)
            _fill_boot(out, board, release)
            run("mkfs.ext4", "-q", "-F", "-L", "writable", "-d", work / "merged",
                "-E", f"offset={(1 + BOOT_MIB) * MIB}", out, f"{writable_mib}M")
        finally:
            unmount_all(work / "merged")
    return out


def _as_before_first_boot(root: Path, release: str) -> None:
    """The host image as Ubuntu's card holds it: Ubuntu `release`'s release files and a Pi's apt
    sources, cloud-init on, NoCloud reading /boot/firmware, no host key, no machine id yet."""
    identity = HostIdentity(hostname="ubuntu", release=release, address="0.0.0.0", prefixlen=24, flavour="server")
    for path, (content, mode) in emulation.host_files(identity, ARCHIVE_ON_A_PI).items():
        if not path.startswith("/etc/netplan/"):  # cloud-init writes it from network-config
            write_file(root / path.lstrip("/"), content, mode=mode)
    # (no stand-in for first-boot unattended-upgrades: a card's first boot adds it, as asked)
    hosts.prepare_seeded_boot(root, apt_lock_seconds=0, user_data=None)
    write_file(root / "etc/machine-id", "", mode=0o444)  # empty: systemd makes one at first boot
    write_file(root / "etc/roslab-sandbox-card", f"{STANDIN}\nUbuntu {release}\n")


def _partitioned(out: Path, writable_mib: int) -> None:
    """An empty image file of the right size with Ubuntu's partition table: an MBR with a
    bootable FAT32 (LBA) system-boot and a Linux writable."""
    out.unlink(missing_ok=True)
    with open(out, "wb") as handle:
        handle.truncate((1 + BOOT_MIB + writable_mib) * MIB)
        handle.write(_mbr([(0x80, FAT32_LBA, MIB // SECTOR, BOOT_MIB * MIB // SECTOR),
                           (0x00, LINUX, (1 + BOOT_MIB) * MIB // SECTOR, writable_mib * MIB // SECTOR)]))


def _mbr(partitions: list[tuple[int, int, int, int]]) -> bytes:
    """A DOS partition table of (status, type, first sector, sectors) primary partitions (no CHS:
    LBA only, as on Ubuntu's images)."""
    table = b"".join(struct.pack("<BBBBBBBBII", status, 0, 0, 0, kind, 0, 0, 0, start, sectors)
                     for status, kind, start, sectors in partitions)
    return bytes(440) + os.urandom(4) + bytes(2) + table + bytes(16 * (4 - len(partitions))) + b"\x55\xaa"


def _fill_boot(out: Path, board: str, release: str) -> None:
    # One sector per cluster: a FAT32 this small has too few clusters otherwise (mtools refuses it).
    run("mkfs.vfat", "-F", "32", "-s", "1", "-n", "system-boot", "--offset", str(MIB // 512), out, str(BOOT_MIB * 1024))
    fat = targets.ImageFat(out, targets.Partition(1, MIB, BOOT_MIB * MIB, "system-boot"))
    files = {Path(path).name: content for path, (content, _) in pi_boot.boot_files(board, release).items()}
    for name, content in {**files, **UBUNTU_NOCLOUD}.items():
        fat.write(name, content.encode())
