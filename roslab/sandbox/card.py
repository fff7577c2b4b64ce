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
from pathlib import Path

from roslab.seed import cards, targets

from .system import SandboxError, log, run, unmount_all

MIB = 1 << 20
SECTOR = 512
RECORD = "card.json"  # in the host's folder while it runs on a card: which card, where its FAT is


def bootable_here(card: Path) -> bool:
    """Whether the system on the card's `writable` can boot on this machine (its architecture
    is the sandbox image's); an arm64 card (Ubuntu's real image) cannot."""
    try:
        _, architecture = cards.writable_system(card)
    except cards.CardError as error:
        raise SandboxError(f"--card {card}: {error}") from None
    return architecture == run("dpkg", "--print-architecture").stdout.strip()  # the image's: this machine's


def boot_folder(host_dir: Path) -> Path:
    """Where the system-boot's files of the card a host runs on are (its /boot/firmware)."""
    return host_dir / "card" / "boot"


def check(host_dir: Path, card: Path, ubuntu_release: str, host_name: str) -> None:
    """SandboxError, with nothing changed or stopped, when the card cannot be the disk of the host
    whose folder is `host_dir`: it is in use (by another host, or mounted here; the card this
    host runs on is its own), or its system is not Ubuntu `ubuntu_release` (the host's)."""
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
    root, boot = host_dir / "merged", boot_folder(host_dir)
    unmount_all(root)
    check(host_dir, card, ubuntu_release, host_name)
    root.mkdir(parents=True, exist_ok=True)
    fat, writable = _partitions(card)
    if _grow_writable(card, writable[0]):
        fat, writable = _partitions(card)
        _resize_filesystem(card, *writable)
    # A loop mount with autoclear: unmounting it lets the card go.
    run("mount", "-o", f"loop,offset={writable[0]},sizelimit={writable[1]}", card, root)
    try:
        shutil.rmtree(boot.parent, ignore_errors=True)
        boot.parent.mkdir(mode=0o700, parents=True)  # user-data may hold a WiFi password
        boot.mkdir(mode=0o755)
        _fat(card, fat[0]).copy_out(boot)
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
    card, boot = Path(record["card"]), boot_folder(host_dir)
    try:
        write_back(boot, _fat(card, int(record["fat_offset"])))
    except (targets.TargetError, OSError) as error:  # the card was pulled out: its host is let go all the same
        log.warning("the system-boot of card %s was not written back: %s", card, error)
    unmount_all(host_dir / "merged")
    record_path.unlink()


def write_back(folder: Path, fat: targets.ImageFat) -> None:
    """Make the FAT partition `fat` hold what `folder` holds: new and changed files copied, new
    folders made, what the folder no longer has deleted."""
    on_card = fat.names()
    here = {path.relative_to(folder).as_posix(): path for path in sorted(folder.rglob("*"))}
    for name, path in here.items():
        if path.is_dir():
            if name not in on_card:
                fat.make_folder(name)
        elif path.is_file() and (name not in on_card or fat.read(name) != path.read_bytes()):
            fat.write(name, path.read_bytes())
    for name, is_folder in sorted(on_card.items(), key=lambda item: -len(item[0])):  # deepest first
        if name not in here:
            fat.remove(name, folder=is_folder)


def _fat(card: Path, start: int) -> targets.ImageFat:
    """The card's FAT partition that starts at byte `start` (mtools needs only its start)."""
    return targets.ImageFat(card, targets.Partition(0, start, 0, "system-boot"))


def _partitions(card: Path) -> tuple[tuple[int, int], tuple[int, int]]:
    """((start, size) of system-boot, (start, size) of writable) in bytes: the FAT partition and
    the ext4 one, found as `roslab flash` and `roslab seed` find them."""
    try:
        fat = targets.boot_partition(card)
        return (fat.start, fat.size), cards._writable(card)
    except (targets.TargetError, cards.CardError) as error:
        raise SandboxError(f"--card {card}: no FAT system-boot and Linux writable partition in its MBR "
                           f"({error})") from None


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


def _grow_writable(card: Path, start: int) -> bool:
    """Grow the `writable` partition (the MBR entry that starts at byte `start`) to the card's
    end, as cloud-init's growpart does on a Pi's first boot; False when it already ends there."""
    size = int(run("blockdev", "--getsize64", card).stdout) if card.is_block_device() else card.stat().st_size
    end = min(size // SECTOR, 0xFFFFFFFF)  # an MBR addresses 2 TiB
    with open(card, "r+b") as disk:
        mbr = bytearray(disk.read(SECTOR))
        for index in range(4):
            entry = 446 + 16 * index
            first, sectors = struct.unpack("<II", mbr[entry + 8:entry + 16])
            if first * SECTOR != start or not sectors:
                continue
            if (first + sectors) * SECTOR + MIB > end * SECTOR:
                return False
            mbr[entry + 12:entry + 16] = struct.pack("<I", end - first)
            disk.seek(0)
            disk.write(mbr)
            disk.flush()
            os.fsync(disk.fileno())
            return True
    return False
