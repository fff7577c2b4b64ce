"""Where a seed is written: a directory per host, a mounted boot partition, or an image file.

Each target writes only the files whose bytes differ and reports which, so a second
`roslab seed` with the same roster writes nothing. A boot partition's or image's own
user-data, network-config and meta-data (Ubuntu's defaults) are copied to
`<name>.before-roslab` the first time roslab replaces them.

An image is written without mounting it: its partition table (MBR or GPT) is read here,
the FAT partition labelled `system-boot` (else the first FAT partition) is found by its
boot sector, and mtools (`mcopy -i IMAGE@@OFFSET`) reads and writes the files in it.
"""

from __future__ import annotations

import os
import struct
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from roslab.controller_files import replace_file
from roslab.seed.documents import SEED_FILES, SeedFile

BACKUP_SUFFIX = ".before-roslab"
SECTOR = 512
# MBR partition types of FAT file systems (FAT12/16/32, CHS and LBA).
FAT_MBR_TYPES = {0x01, 0x04, 0x06, 0x0B, 0x0C, 0x0E}
GPT_BASIC_DATA = "EBD0A0A2-B9E5-4433-87C0-68B6B72699C7"
GPT_EFI_SYSTEM = "C12A7328-F81F-11D2-BA4B-00A0C93EC93B"
PI_BOOT_FILES = ("config.txt", "cmdline.txt")


class TargetError(ValueError):
    """A target roslab will not write a seed into (not a Pi boot partition, no FAT partition)."""


def _write_private_or_public(path: Path, seed_file: SeedFile) -> None:
    """Atomically replace `path` with the file, never wider than 0600 before its final mode."""
    replace_file(path, seed_file.content, seed_file.mode, sync=False)  # flushed with the others after


def write_directory(directory: Path, files: dict[str, SeedFile]) -> list[str]:
    """Write `files` into `directory` (created 0700); the names that changed."""
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    changed = []
    for name in SEED_FILES:
        seed_file, path = files[name], directory / name
        same = path.is_file() and path.read_bytes() == seed_file.content
        if same and (path.stat().st_mode & 0o777) == seed_file.mode:
            continue
        if same:
            os.chmod(path, seed_file.mode)
        else:
            _write_private_or_public(path, seed_file)
        changed.append(name)
    return changed


# --- a mounted boot partition ---------------------------------------------------------


def check_boot_partition(path: Path) -> None:
    if not path.is_dir():
        raise TargetError(f"{path} is not a directory (give the mounted system-boot partition)")
    missing = [name for name in PI_BOOT_FILES if not (path / name).is_file()]
    if missing or not any((path / name).is_file() for name in ("user-data", "meta-data")):
        raise TargetError(
            f"{path} is not an Ubuntu Raspberry Pi boot partition (system-boot): it has no "
            f"{', '.join(missing) if missing else 'user-data or meta-data'}; "
            "flash Ubuntu Server for Raspberry Pi onto the card first and give its mount point")


def write_boot_partition(path: Path, files: dict[str, SeedFile]) -> list[str]:
    """Write the seed into a mounted system-boot partition; back up Ubuntu's files once."""
    check_boot_partition(path)
    changed = []
    for name in SEED_FILES:
        target = path / name
        old = target.read_bytes() if target.is_file() else None
        if old == files[name].content:
            continue
        backup = path / (name + BACKUP_SUFFIX)
        written = [name]
        if old is not None and not backup.exists():
            backup.write_bytes(old)
            written.append(backup.name)
        _write_private_or_public(target, files[name])
        changed.append(name)
        _flush(path, written)
    return changed


def _flush(path: Path, names: list[str]) -> None:
    """The files just written and their folder flushed to the card (fsync): it may be pulled at once.

    Only these: the whole machine's os.sync() (Python has no os.syncfs) waited minutes for
    every other filesystem's writes on a busy controller. A folder that refuses fsync: os.sync()."""
    for name in names:
        fd = os.open(path / name, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        os.sync()


# --- an image file ----------------------------------------------------------------------


@dataclass(frozen=True)
class Partition:
    number: int
    start: int  # bytes
    size: int  # bytes
    label: str  # the FAT volume label, "" when none


def _fat_label(boot_sector: bytes) -> str | None:
    """The volume label of a FAT boot sector, or None when it is not one."""
    if len(boot_sector) < SECTOR or boot_sector[510:512] != b"\x55\xaa":
        return None
    if boot_sector[82:87] == b"FAT32":
        return boot_sector[71:82].decode("ascii", "replace").strip()
    if boot_sector[54:59] in (b"FAT12", b"FAT16", b"FAT  "):
        return boot_sector[43:54].decode("ascii", "replace").strip()
    return None


def _gpt_guid(raw: bytes) -> str:
    a, b, c = struct.unpack("<IHH", raw[:8])
    return f"{a:08X}-{b:04X}-{c:04X}-{raw[8:10].hex().upper()}-{raw[10:16].hex().upper()}"


def fat_partitions(image: Path) -> list[Partition]:
    """The FAT partitions of a raw disk image (MBR or GPT), read from its partition table."""
    with open(image, "rb") as disk:
        mbr = disk.read(SECTOR)
        if len(mbr) < SECTOR or mbr[510:512] != b"\x55\xaa":
            raise TargetError(f"{image} has no partition table (not a raw disk image)")
        entries = [struct.unpack("<BBBBBBBBII", mbr[446 + 16 * i: 462 + 16 * i]) for i in range(4)]
        candidates: list[tuple[int, int, int]] = []  # (number, start sector, sectors)
        if any(entry[4] == 0xEE for entry in entries):
            disk.seek(SECTOR)
            header = disk.read(92)
            if header[:8] != b"EFI PART":
                raise TargetError(f"{image}: a protective MBR without a GPT header")
            table_lba, count, entry_size = struct.unpack("<QII", header[72:88])
            disk.seek(table_lba * SECTOR)
            table = disk.read(count * entry_size)
            for number in range(count):
                raw = table[number * entry_size:(number + 1) * entry_size]
                if _gpt_guid(raw[:16]) in (GPT_BASIC_DATA, GPT_EFI_SYSTEM):
                    first, last = struct.unpack("<QQ", raw[32:48])
                    candidates.append((number + 1, first, last - first + 1))
        else:
            candidates = [(number + 1, entry[8], entry[9]) for number, entry in enumerate(entries)
                          if entry[4] in FAT_MBR_TYPES and entry[9]]
        found = []
        for number, start, sectors in candidates:
            disk.seek(start * SECTOR)
            label = _fat_label(disk.read(SECTOR))
            if label is not None:
                found.append(Partition(number, start * SECTOR, sectors * SECTOR, label))
    return found


def boot_partition(image: Path) -> Partition:
    partitions = fat_partitions(image)
    if not partitions:
        raise TargetError(f"{image} has no FAT partition: not a Raspberry Pi image")
    labelled = [p for p in partitions if p.label.lower() == "system-boot"]
    return (labelled or partitions)[0]


class ImageFat:
    """One FAT partition inside an image file, through mtools (never mounted)."""

    def __init__(self, image: Path, partition: Partition):
        self.image, self.partition = image, partition
        self.drive = f"{image}@@{partition.start}"

    def _mtools(self, *argv: str) -> subprocess.CompletedProcess:
        # MTOOLS_SKIP_CHECK: an image's FAT geometry need not match a floppy's.
        env = {**os.environ, "MTOOLS_SKIP_CHECK": "1", "MTOOLS_NO_VFAT": "0"}
        try:
            return subprocess.run(argv, capture_output=True, env=env, check=False)
        except FileNotFoundError:
            raise TargetError("mtools is not installed (run scripts/install-host-tools as root)") from None

    def read(self, name: str) -> bytes | None:
        with tempfile.TemporaryDirectory(prefix="roslab-seed-") as scratch:
            local = Path(scratch) / "file"
            result = self._mtools("mcopy", "-n", "-i", self.drive, f"::/{name}", str(local))
            return local.read_bytes() if result.returncode == 0 and local.exists() else None

    def write(self, name: str, content: bytes) -> None:
        with tempfile.TemporaryDirectory(prefix="roslab-seed-") as scratch:
            local = Path(scratch) / "file"
            fd = os.open(local, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "wb") as out:
                out.write(content)
            result = self._mtools("mcopy", "-o", "-i", self.drive, str(local), f"::/{name}")
        if result.returncode != 0:
            raise TargetError(f"mcopy could not write {name} into {self.image}: "
                              f"{result.stderr.decode(errors='replace').strip()}")

    def has(self, name: str) -> bool:
        return self._mtools("mdir", "-b", "-i", self.drive, f"::/{name}").returncode == 0

    def names(self) -> dict[str, bool]:
        """Every file and folder in the partition, by path ("overlays/x.dtbo"): whether a folder."""
        listing = self._checked("list", "mdir", "-/", "-b", "-i", self.drive, "::/").stdout.decode(errors="replace")
        return {line[len("::/"):].rstrip("/"): line.endswith("/") for line in listing.splitlines()
                if line.startswith("::/") and line != "::/"}

    def copy_out(self, folder: Path) -> None:
        """Every file and folder of the partition into `folder` (which exists)."""
        self._checked("copy out", "mcopy", "-s", "-n", "-m", "-i", self.drive, "::/*", f"{folder}/")

    def make_folder(self, name: str) -> None:
        self._checked(f"make {name}", "mmd", "-i", self.drive, f"::/{name}")

    def remove(self, name: str, folder: bool = False) -> None:
        self._checked(f"remove {name}", "mrd" if folder else "mdel", "-i", self.drive, f"::/{name}")

    def _checked(self, what: str, *argv: str) -> subprocess.CompletedProcess:
        result = self._mtools(*argv)
        if result.returncode != 0:
            raise TargetError(f"{argv[0]} could not {what} in {self.image}: "
                              f"{result.stderr.decode(errors='replace').strip()}")
        return result


def write_image(image: Path, files: dict[str, SeedFile]) -> list[str]:
    """Write the seed into the image's boot partition; back up Ubuntu's files once."""
    if not image.is_file():
        raise TargetError(f"{image} is not a file (give a raw .img, uncompressed)")
    changed = write_fat(image, files)
    # The image now holds a private key (and maybe a WiFi password): keep it private.
    os.chmod(image, 0o600)
    return changed


def write_fat(image: Path, files: dict[str, SeedFile]) -> list[str]:
    """Write the seed into the boot partition of an image file or a card's block device (through
    mtools, nothing mounted); back up Ubuntu's files once; the names that changed."""
    fat = ImageFat(image, boot_partition(image))
    missing = [name for name in PI_BOOT_FILES if not fat.has(name)]
    if missing:
        raise TargetError(f"{image}: partition {fat.partition.number} ({fat.partition.label or 'no label'}) "
                          f"has no {', '.join(missing)}: not an Ubuntu Raspberry Pi boot partition")
    changed = []
    for name in SEED_FILES:
        old = fat.read(name)
        if old == files[name].content:
            continue
        if old is not None and fat.read(name + BACKUP_SUFFIX) is None:
            fat.write(name + BACKUP_SUFFIX, old)
        fat.write(name, files[name].content)
        changed.append(name)
    return changed
