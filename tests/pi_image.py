"""A stand-in for Ubuntu's Raspberry Pi preinstalled image, for the tests of `roslab flash`.

Ubuntu's download (ubuntu-24.04.x-preinstalled-server-arm64+raspi.img.xz) is out of reach here.
This writes an image with its layout: an MBR with a FAT partition (FAT16 here: small; Ubuntu's is FAT32) labelled `system-boot` at
1 MiB (config.txt, cmdline.txt and cloud-init's NoCloud files, as Ubuntu ships them) and an ext4
partition labelled `writable` holding /usr/lib/os-release (ID=ubuntu, the release) and an empty
/usr/lib/<triplet> that names its architecture. It holds no system: nothing boots from it.
"""

from __future__ import annotations

import os
import struct
import subprocess
import tempfile
from pathlib import Path

MIB = 1 << 20
STANDIN = "roslab test stand-in for Ubuntu's Raspberry Pi preinstalled image"
TRIPLETS = {"arm64": "aarch64-linux-gnu", "armhf": "arm-linux-gnueabihf", "amd64": "x86_64-linux-gnu"}
CODENAMES = {"22.04": "jammy", "24.04": "noble"}


def _mbr(partitions: list[tuple[int, int, int]]) -> bytes:
    """An MBR with (type, start sector, sectors) primary partitions."""
    table = b"".join(struct.pack("<BBBBBBBBII", 0, 0, 0, 0, kind, 0, 0, 0, start, sectors)
                     for kind, start, sectors in partitions)
    return bytes(446) + table + bytes(16 * (4 - len(partitions))) + b"\x55\xaa"


def write(path: Path, release: str = "24.04", architecture: str = "arm64", boot_mib: int = 16,
          root_mib: int = 24) -> Path:
    boot_start, root_start = 1 * MIB, (1 + boot_mib) * MIB
    size = root_start + root_mib * MIB
    with open(path, "wb") as image:
        image.truncate(size)
        image.write(_mbr([(0x0E, boot_start // 512, boot_mib * MIB // 512),
                          (0x83, root_start // 512, root_mib * MIB // 512)]))
    subprocess.run(["mkfs.vfat", "-F", "16", "-n", "system-boot", "--offset", str(boot_start // 512),
                    str(path), str(boot_mib * 1024)], check=True, capture_output=True)
    env = {**os.environ, "MTOOLS_SKIP_CHECK": "1"}
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        files = {"config.txt": f"# {STANDIN}\n[all]\narm_64bit=1\nkernel=vmlinuz\n",
                 "cmdline.txt": "console=serial0,115200 console=tty1 root=LABEL=writable rootfstype=ext4 rootwait\n",
                 "user-data": "#cloud-config\n# Ubuntu's default user-data\n",
                 "meta-data": "instance-id: cloud-image\n", "network-config": "version: 2\n"}
        for name, text in files.items():
            (scratch / name).write_text(text)
            subprocess.run(["mcopy", "-i", f"{path}@@{boot_start}", str(scratch / name), f"::/{name}"],
                           check=True, capture_output=True, env=env)
        root = scratch / "root"
        (root / "usr/lib" / TRIPLETS[architecture]).mkdir(parents=True)
        (root / "usr/lib/os-release").write_text(
            f'NAME="Ubuntu"\nVERSION_ID="{release}"\nID=ubuntu\nVERSION_CODENAME={CODENAMES.get(release, "x")}\n'
            f'# {STANDIN}\n')
        (root / "etc").mkdir()
        (root / "etc/os-release").symlink_to("../usr/lib/os-release")
        subprocess.run(["mkfs.ext4", "-q", "-F", "-L", "writable", "-d", str(root), "-E", f"offset={root_start}",
                        str(path), f"{root_mib * 1024}k"], check=True, capture_output=True)
    return path
