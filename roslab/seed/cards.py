"""The cards `roslab flash` may write, and the image it writes: checked before any byte is.

A card is a whole block device of a removable USB or MMC card reader (lsblk's `rm` or
`hotplug`, transport `usb` or `mmc`), or a loop device, accepted only because it is named
explicitly (`--device`; the tests' cards). Never a partition, never the disk that holds `/`,
never a device with a mounted filesystem, never one larger than MAX_CARD_BYTES without
`--allow-large`, never one smaller than the image. Each card's identity (major:minor, size,
serial, model) is taken before the first write and compared again before it is verified: a
card that vanished and came back under another name is not read as if it were the same.

The image is a Raspberry Pi preinstalled Ubuntu image: an MBR or GPT partition table with a
FAT partition labelled `system-boot` holding `config.txt` and `cmdline.txt`, and an ext4
partition (`writable`) whose /usr/lib/os-release names the Ubuntu release and whose
/usr/lib/<triplet> names the architecture (read with e2fsprogs' `debugfs`, nothing mounted).
A `.img.xz` is decompressed once, into a private temporary file beside the other work, and
every card is written from that one stream of bytes.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import lzma
import os
import struct
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from roslab.seed import targets

CHUNK = 4 << 20
MAX_CARD_BYTES = 256 * 10**9  # larger: a disk, not an SD card, unless --allow-large says so
LSBLK_COLUMNS = "NAME,PATH,TYPE,RM,HOTPLUG,SIZE,MOUNTPOINTS,TRAN,SERIAL,MODEL,MAJ:MIN"
CARD_TRANSPORTS = ("usb", "mmc")
EXT4_MAGIC = 0xEF53
ARCHITECTURES = {"aarch64-linux-gnu": "arm64", "arm-linux-gnueabihf": "armhf", "x86_64-linux-gnu": "amd64"}
PI_ARCHITECTURES = ("arm64", "armhf")  # what a Raspberry Pi's Ubuntu image is for


class CardError(ValueError):
    """A device or image `roslab flash` will not write (one line: what and why)."""


@dataclass(frozen=True)
class Card:
    path: str  # /dev/sdb, /dev/mmcblk0, /dev/loop3
    size: int  # bytes
    kind: str  # usb, mmc or loop
    serial: str  # the reader's serial number ("" when it has none)
    model: str
    majmin: str  # the device number: the same card keeps it while it stays plugged

    @property
    def label(self) -> str:
        return " ".join(part for part in (self.model, self.serial) if part) or self.path


def lsblk(paths: list[str] | None = None, empty: bool = False) -> list[dict]:
    """lsblk's tree (`--json --bytes`) of `paths`, or of every block device (an empty card
    reader only with `empty`: lsblk skips a device of size 0 unless `--all`)."""
    done = subprocess.run(["lsblk", "--json", "--bytes", *(["--all"] if empty else []), "-o", LSBLK_COLUMNS,
                           *(paths or [])],
                          capture_output=True, text=True)
    if done.returncode:
        raise CardError(f"lsblk {' '.join(paths or [])}: {done.stderr.strip() or 'failed'}")
    return json.loads(done.stdout)["blockdevices"]


def _mountpoints(device: dict) -> list[str]:
    """Every mounted filesystem on the device or any of its partitions."""
    points = [point for point in device.get("mountpoints") or [] if point]
    for child in device.get("children") or []:
        points += _mountpoints(child)
    return points


def root_devices(tree: list[dict]) -> set[str]:
    """The whole devices (by path) that hold `/` somewhere in their tree."""
    return {device["path"] for device in tree if "/" in _mountpoints(device)}


def transport_of(device: dict) -> str:
    """A whole disk's transport as lsblk gives it (usb, ...), mmc for an MMC slot (whose lsblk
    record has none), "" when lsblk names none."""
    return device.get("tran") or ("mmc" if device.get("name", "").startswith("mmcblk") else "")


def card_of(device: dict, roots: set[str], image_size: int, allow_large: bool) -> Card:
    """The Card a device (lsblk's record of a path given with --device) is, or CardError saying
    why roslab will not write it."""
    path, kind = device["path"], device.get("type")
    if kind == "part":
        raise CardError(f"{path} is a partition: give the whole card (its disk, e.g. /dev/sdb)")
    if kind == "loop":
        transport = "loop"
    elif kind == "disk":
        transport = transport_of(device)
        # A laptop's own SD slot (mmcblk) says it is not removable; a USB disk must say it is.
        if transport not in CARD_TRANSPORTS or (transport == "usb" and not (device.get("rm") or device.get("hotplug"))):
            raise CardError(f"{path} is not a removable USB or MMC card reader's card "
                            f"(transport {transport or 'none'}, removable {bool(device.get('rm'))})")
    else:
        raise CardError(f"{path} is a {kind or 'unknown'} device, not a card")
    if path in roots:
        raise CardError(f"{path} holds / (this machine's own system)")
    mounted = _mountpoints(device)
    if mounted:
        raise CardError(f"{path} has a mounted filesystem ({', '.join(mounted[:3])}): unmount it first")
    size = int(device.get("size") or 0)
    if size == 0:
        raise CardError(f"{path} has no medium (no card in the reader)")
    if size > MAX_CARD_BYTES and not allow_large:
        raise CardError(f"{path} is {size / 1e9:.0f} GB, larger than {MAX_CARD_BYTES / 1e9:.0f} GB: "
                        "a disk, not an SD card? (--allow-large writes it anyway)")
    if size < image_size:
        raise CardError(f"{path} is {size / 1e9:.1f} GB, smaller than the image ({image_size / 1e9:.1f} GB)")
    return Card(path, size, transport, (device.get("serial") or "").strip(), (device.get("model") or "").strip(),
                device.get("maj:min") or "")


def cards(paths: list[str], image_size: int, allow_large: bool = False) -> tuple[list[Card], list[str]]:
    """(the cards among `paths`, one problem line for each that is refused)."""
    roots = root_devices(lsblk())
    found, problems = [], []
    if len(set(map(os.path.realpath, paths))) != len(paths):
        problems.append("a device is named twice")
    loops = loops_over()
    for path in paths:
        try:
            (device,) = lsblk([path])
            card = card_of(device, roots, image_size, allow_large)
            busy = in_use(card.path, loops)
            if busy:
                raise CardError(busy)
            found.append(card)
        except CardError as error:
            problems.append(str(error))
    return found, problems


def loops_over() -> dict[str, list[str]]:
    """The loop devices over each backing file or device (realpath -> loop devices)."""
    done = subprocess.run(["losetup", "--list", "--json", "--output", "NAME,BACK-FILE"],
                          capture_output=True, text=True)
    over: dict[str, list[str]] = {}
    for loop in (json.loads(done.stdout or "{}").get("loopdevices") or []) if done.returncode == 0 else []:
        back = (loop.get("back-file") or "").strip()
        if back:
            over.setdefault(os.path.realpath(back), []).append(loop["name"])
    return over


def in_use(path: str, loops: dict[str, list[str]]) -> str | None:
    """Why a device is in use though lsblk shows nothing mounted on it, or None: a loop device
    over it (how a partition of a whole card is mounted: `mount -o loop,offset=`, a sandbox host
    running on it), or the kernel's exclusive claim (a mount, swap, RAID or device mapper)."""
    over = loops.get(os.path.realpath(path))
    if over:
        return (f"{path} is in use: {', '.join(over)} is a loop device over it (a partition of it mounted, "
                "or a sandbox host running on it): unmount or detach it first")
    try:
        os.close(os.open(path, os.O_RDONLY | os.O_EXCL))
    except OSError as error:
        if error.errno == errno.EBUSY:
            return f"{path} is in use (the kernel holds it: a mount, swap, RAID or device mapper): free it first"
    return None


def still_the_same(card: Card) -> str | None:
    """None while the device at `card.path` is the card that was checked; else why not."""
    try:
        (device,) = lsblk([card.path])
    except (CardError, ValueError):
        return f"{card.path} is gone (the card was removed)"
    now = (device.get("maj:min") or "", int(device.get("size") or 0), (device.get("serial") or "").strip())
    if now != (card.majmin, card.size, card.serial):
        return f"{card.path} is another device now (the card was removed and another took its name)"
    return None


# -- the image ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Image:
    path: Path  # the raw image the cards are written from (a .xz's decompressed copy)
    size: int
    release: str  # VERSION_ID of its writable partition: "24.04"
    architecture: str  # arm64, armhf (amd64: the sandbox's card image)
    boot: targets.Partition


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def raw_image(source: Path, work_dir: Path) -> tuple[Path, str]:
    """(the raw image, its sha256): `source` itself, or a .xz decompressed once into `work_dir`
    (0600), its digest taken as it is written."""
    if source.suffix != ".xz":
        return source, file_sha256(source)
    fd, name = tempfile.mkstemp(prefix="roslab-flash-", suffix=".img", dir=work_dir)
    digest = hashlib.sha256()
    try:
        with os.fdopen(fd, "wb") as out, lzma.open(source) as stream:
            while chunk := stream.read(CHUNK):
                digest.update(chunk)
                out.write(chunk)
    except (lzma.LZMAError, EOFError) as error:
        os.unlink(name)
        raise CardError(f"{source}: not a readable .xz image ({error})") from None
    return Path(name), digest.hexdigest()


def _partitions(image: Path) -> list[tuple[int, int, int]]:
    """(type, start byte, size in bytes) of an MBR image's primary partitions (Ubuntu's Pi
    images have an MBR)."""
    with open(image, "rb") as disk:
        mbr = disk.read(targets.SECTOR)
    if len(mbr) < targets.SECTOR or mbr[510:512] != b"\x55\xaa":
        raise CardError(f"{image} has no partition table: not a Raspberry Pi preinstalled image")
    entries = [struct.unpack("<BBBBBBBBII", mbr[446 + 16 * i: 462 + 16 * i]) for i in range(4)]
    return [(entry[4], entry[8] * targets.SECTOR, entry[9] * targets.SECTOR) for entry in entries if entry[9]]


def _writable(image: Path) -> tuple[int, int]:
    """(start, size) of the image's ext4 partition (its superblock's magic at 1080)."""
    for _, start, size in _partitions(image):
        with open(image, "rb") as disk:
            disk.seek(start + 1080)
            magic = disk.read(2)
        if len(magic) == 2 and struct.unpack("<H", magic)[0] == EXT4_MAGIC:
            return start, size
    raise CardError(f"{image} has no ext4 partition (writable): not a Raspberry Pi preinstalled image")


@contextlib.contextmanager
def _partition_device(image: Path, start: int, size: int):
    """A read-only loop device over exactly the partition at `start` of `image` (nothing is
    mounted), detached afterwards."""
    loop = subprocess.run(["losetup", "--read-only", "--find", "--show", "--offset", str(start),
                           "--sizelimit", str(size), str(image)], capture_output=True, text=True)
    if loop.returncode:
        raise CardError(f"{image}: cannot read its writable partition: {loop.stderr.strip()}")
    device = loop.stdout.strip()
    try:
        yield device
    finally:
        subprocess.run(["losetup", "--detach", device], capture_output=True)


def _debugfs(device: str, request: str) -> str:
    """debugfs's answer about the ext4 filesystem on `device`."""
    return subprocess.run(["debugfs", "-R", request, device], capture_output=True, text=True).stdout


def writable_system(card: Path) -> tuple[str, str]:
    """(Ubuntu release, architecture) of the system in the ext4 `writable` partition of an image
    file or a card; CardError in one line when it is not Ubuntu or its architecture is unclear."""
    with _partition_device(card, *_writable(card)) as device:
        os_release = _debugfs(device, "cat /usr/lib/os-release") or _debugfs(device, "cat /etc/os-release")
        listing = _debugfs(device, "ls -l /usr/lib")
    fields = dict(line.split("=", 1) for line in os_release.splitlines() if "=" in line)
    release = fields.get("VERSION_ID", "").strip('"')
    if fields.get("ID", "").strip('"') != "ubuntu" or not release:
        raise CardError(f"{card}: its writable partition is not Ubuntu (no ID=ubuntu in os-release)")
    found = [arch for triplet, arch in ARCHITECTURES.items() if f" {triplet}" in listing]
    if len(found) != 1:
        raise CardError(f"{card}: cannot tell its architecture from /usr/lib")
    return release, found[0]


def image_of(raw: Path) -> Image:
    """The checked Image: a FAT system-boot with config.txt and cmdline.txt, an ext4 writable
    with its release and architecture; CardError in one line otherwise."""
    try:
        boot = targets.boot_partition(raw)
    except targets.TargetError as error:
        raise CardError(str(error)) from None
    fat = targets.ImageFat(raw, boot)
    missing = [name for name in targets.PI_BOOT_FILES if not fat.has(name)]
    if missing:
        raise CardError(f"{raw}: its boot partition has no {', '.join(missing)}: not a Raspberry Pi image")
    release, architecture = writable_system(raw)
    return Image(raw, raw.stat().st_size, release, architecture, boot)
