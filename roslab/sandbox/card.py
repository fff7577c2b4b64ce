"""A sandbox host booted from a card: the card's own partitions are its disk.

`roslab sandbox reset HOST --card DEV` on a card of the sandbox's own image (card_image.py,
written by `roslab flash`): the card's `writable` partition is the host's root, mounted from the
card, so what the host writes lands on the card. First, as cloud-init's growpart and
resize_rootfs do on a Pi's first boot, `writable` is grown to the end of the card (partition,
then filesystem). The sandbox then writes over the card's system what it writes over every host
of its own (hosts.write_host_files: its apt layout and archive key, the stand-in for first-boot
unattended-upgrades).

STAND-IN for the card's `system-boot` mount: this machine's kernel has no FAT driver (no vfat
in /proc/filesystems, no modules to load), so the partition's files are copied off the card
(mtools) into a folder the host mounts read-write at /boot/firmware, where its cloud-init reads
the seed `roslab flash` wrote, and written back to the card's FAT (changed files, new folders,
deletions) when the card is let go: `reset` without it, `down`.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

from .system import SandboxError, log, run, unmount_all

MIB = 1 << 20
SECTOR = 512
FAT32_LBA, LINUX = 0x0C, 0x83  # MBR partition types: system-boot, writable
FAT_TYPES = (0x01, 0x04, 0x06, 0x0B, 0x0C, 0x0E, 0xEF)
RECORD = "card.json"  # in the host's folder while it runs on a card: which card, where its FAT is
MTOOLS_ENV = {"MTOOLS_SKIP_CHECK": "1"}  # a card's FAT geometry need not match a floppy's


def bootable_here(card: Path) -> bool:
    """Whether the system on the card's `writable` can boot on this machine (its architecture
    is the sandbox image's); an arm64 card (Ubuntu's real image) cannot."""
    from roslab.seed import cards

    try:
        _, architecture = cards.writable_system(card)
    except cards.CardError as error:
        raise SandboxError(f"--card {card}: {error}") from None
    return architecture == run("dpkg", "--print-architecture").stdout.strip()  # the image's: this machine's


def check(host_dir: Path, card: Path, ubuntu_release: str, host_name: str) -> None:
    """SandboxError, with nothing changed or stopped, when the card cannot be the disk of the host
    whose folder is `host_dir`: it is in use (by another host, or mounted here; the card this
    host runs on is its own), or its system is not Ubuntu `ubuntu_release` (the host's)."""
    from roslab.seed import cards

    if _running_on(host_dir) != os.path.realpath(card):
        busy = cards.in_use(str(card), cards.loops_over())
        if busy:
            raise SandboxError(f"--card {busy}")
    try:
        found, _ = cards.writable_system(card)  # read-only
    except cards.CardError as error:
        raise SandboxError(f"--card {card}: {error}") from None
    if found != ubuntu_release:
        raise SandboxError(f"--card {card}: its system is Ubuntu {found}, but {host_name} is on Ubuntu "
                           f"{ubuntu_release}: write a card image of {ubuntu_release} "
                           f"(`roslab sandbox card-image FILE --release {ubuntu_release}`)")


def _running_on(host_dir: Path) -> str | None:
    """The card (its real path) the host runs on, from its record; None when it runs on none."""
    try:
        return os.path.realpath(json.loads((host_dir / RECORD).read_text())["card"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def mount(host_dir: Path, card: Path, ubuntu_release: str, host_name: str) -> tuple[Path, Path]:
    """Make the card the disk of the host whose folder is `host_dir`: its `writable` (grown to
    the card's end first) mounted at `merged`, its system-boot's files in a folder beside it;
    return (root, boot folder). SandboxError, before the card is changed, when it is in use or
    its system is not Ubuntu `ubuntu_release` (the host's)."""
    release(host_dir)
    root, boot = host_dir / "merged", host_dir / "card" / "boot"
    unmount_all(root)
    check(host_dir, card, ubuntu_release, host_name)
    root.mkdir(parents=True, exist_ok=True)
    fat, writable = _partitions(card)
    if _grow_writable(card):
        fat, writable = _partitions(card)
        _resize_filesystem(card, *writable)
    # A loop mount with autoclear: unmounting it lets the card go.
    run("mount", "-o", f"loop,offset={writable[0]},sizelimit={writable[1]}", card, root)
    try:
        shutil.rmtree(boot.parent, ignore_errors=True)
        boot.parent.mkdir(mode=0o700, parents=True)  # user-data may hold a WiFi password
        boot.mkdir(mode=0o755)
        _mtools("mcopy", "-s", "-n", "-m", "-i", _drive(card, fat[0]), "::/*", f"{boot}/")
        (host_dir / RECORD).write_text(json.dumps({"card": str(card), "fat_offset": fat[0]}) + "\n")
    except BaseException:
        unmount_all(root)
        raise
    return root, boot


def release(host_dir: Path) -> None:
    """Let go of the card the host runs on, if any: its system-boot folder written back to the
    card's FAT, its writable unmounted. Nothing when the host runs on no card."""
    record_path = host_dir / RECORD
    if not record_path.is_file():
        return
    record = json.loads(record_path.read_text())
    card, boot = Path(record["card"]), host_dir / "card" / "boot"
    try:
        write_back(boot, _drive(card, int(record["fat_offset"])))
    except (SandboxError, OSError) as error:  # the card was pulled out: its host is let go all the same
        log.warning("the system-boot of card %s was not written back: %s", card, error)
    unmount_all(host_dir / "merged")
    record_path.unlink()


def write_back(folder: Path, drive: str) -> None:
    """Make the FAT at `drive` hold what `folder` holds: new and changed files copied, new
    folders made, what the folder no longer has deleted."""
    listing = _mtools("mdir", "-/", "-b", "-i", drive, "::/").stdout.splitlines()
    on_card = {line[len("::/"):].rstrip("/"): line.endswith("/") for line in listing if line.startswith("::/")}
    here = {path.relative_to(folder).as_posix(): path for path in sorted(folder.rglob("*"))}
    for name, path in here.items():
        if path.is_dir():
            if name not in on_card:
                _mtools("mmd", "-i", drive, f"::/{name}")
        elif path.is_file() and (name not in on_card or _mtools("mtype", "-i", drive, f"::/{name}",
                                                                   text=False).stdout != path.read_bytes()):
            _mtools("mcopy", "-o", "-m", "-i", drive, path, f"::/{name}")
    for name, is_dir in sorted(on_card.items(), key=lambda item: -len(item[0])):  # deepest first
        if name and name not in here:
            _mtools("mrd" if is_dir else "mdel", "-i", drive, f"::/{name}")


def _drive(card: Path, offset: int) -> str:
    return f"{card}@@{offset}"


def _mtools(*argv, text: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run([str(arg) for arg in argv], capture_output=True, text=text,
                            env={**os.environ, **MTOOLS_ENV})
    if result.returncode:
        detail = result.stderr if text else result.stderr.decode(errors="replace")
        raise SandboxError(f"`{' '.join(str(arg) for arg in argv)}` failed: {detail.strip()}")
    return result


def _partitions(card: Path) -> tuple[tuple[int, int], tuple[int, int]]:
    """((start, size) of system-boot, (start, size) of writable) in bytes, from the card's MBR."""
    from roslab.seed import cards

    try:
        found = cards._partitions(card)
    except cards.CardError as error:
        raise SandboxError(f"--card {card}: {error}") from None
    fats = [(start, size) for kind, start, size in found if kind in FAT_TYPES]
    linux = [(start, size) for kind, start, size in found if kind == LINUX]
    if not fats or not linux:
        raise SandboxError(f"--card {card}: no FAT system-boot and Linux writable partition in its MBR")
    return fats[0], linux[0]


def _resize_filesystem(card: Path, start: int, size: int) -> None:
    """Grow the ext4 in the partition at `start` to fill it (checked first, as resize2fs asks)."""
    device = run("losetup", "--find", "--show", "--offset", str(start), "--sizelimit", str(size), card).stdout.strip()
    try:
        checked = run("e2fsck", "-f", "-p", device, check=False)
        if checked.returncode > 1:  # 1: errors corrected
            raise SandboxError(f"--card {card}: its writable partition has errors e2fsck cannot mend: "
                               f"{checked.stdout.strip() or checked.stderr.strip()}")
        run("resize2fs", device)
    finally:
        run("losetup", "--detach", device, check=False)


def _grow_writable(card: Path) -> bool:
    """Grow the `writable` partition to the card's end, as cloud-init's growpart does on a Pi's
    first boot; False when it already ends there."""
    size = int(run("blockdev", "--getsize64", card).stdout) if card.is_block_device() else card.stat().st_size
    with open(card, "r+b") as disk:
        mbr = bytearray(disk.read(SECTOR))
        for index in range(4):
            entry = 446 + 16 * index
            status, _, _, _, kind, _, _, _, start, sectors = struct.unpack("<BBBBBBBBII", mbr[entry:entry + 16])
            if kind != LINUX or not sectors:
                continue
            end = min(size // SECTOR, 0xFFFFFFFF)  # an MBR addresses 2 TiB
            if (start + sectors) * SECTOR + MIB > end * SECTOR:
                return False
            mbr[entry + 12:entry + 16] = struct.pack("<I", end - start)
            disk.seek(0)
            disk.write(mbr)
            disk.flush()
            os.fsync(disk.fileno())
            return True
    return False
