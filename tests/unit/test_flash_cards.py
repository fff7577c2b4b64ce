"""Which devices `roslab flash` writes, from recorded `lsblk --json --bytes` records: never the
disk of `/`, never a mounted or partitioned target, never a fixed disk, a large one only when
asked, never a card smaller than the image."""

from __future__ import annotations

import pytest

from roslab.seed import cards

GB = 10**9
# lsblk --json --bytes -o NAME,PATH,TYPE,RM,HOTPLUG,SIZE,MOUNTPOINTS,TRAN,SERIAL,MODEL,MAJ:MIN, as recorded
# on a laptop with a USB card reader, its own SD slot and a loop device.
TREE = [
    {"name": "nvme0n1", "path": "/dev/nvme0n1", "type": "disk", "rm": False, "hotplug": False, "size": 512 * GB,
     "mountpoints": [None], "tran": "nvme", "serial": "S4X", "model": "Samsung SSD", "maj:min": "259:0",
     "children": [{"name": "nvme0n1p2", "path": "/dev/nvme0n1p2", "type": "part", "rm": False, "hotplug": False,
                   "size": 500 * GB, "mountpoints": ["/", "/home"], "maj:min": "259:2"}]},
    {"name": "sdb", "path": "/dev/sdb", "type": "disk", "rm": True, "hotplug": True, "size": 32 * GB,
     "mountpoints": [None], "tran": "usb", "serial": "000000001206", "model": "SD/MMC Reader", "maj:min": "8:16",
     "children": [{"name": "sdb1", "path": "/dev/sdb1", "type": "part", "size": 512 * 10**6,
                   "mountpoints": [None], "maj:min": "8:17"}]},
    {"name": "sdc", "path": "/dev/sdc", "type": "disk", "rm": True, "hotplug": True, "size": 64 * GB,
     "mountpoints": [None], "tran": "usb", "serial": "X2", "model": "Reader", "maj:min": "8:32",
     "children": [{"name": "sdc1", "path": "/dev/sdc1", "type": "part", "size": 512 * 10**6,
                   "mountpoints": ["/media/teacher/system-boot"], "maj:min": "8:33"}]},
    {"name": "mmcblk0", "path": "/dev/mmcblk0", "type": "disk", "rm": False, "hotplug": False, "size": 16 * GB,
     "mountpoints": [None], "tran": None, "serial": None, "model": None, "maj:min": "179:0"},
    {"name": "sdd", "path": "/dev/sdd", "type": "disk", "rm": False, "hotplug": False, "size": 2000 * GB,
     "mountpoints": [None], "tran": "sata", "serial": "WD", "model": "WD Blue", "maj:min": "8:48"},
    {"name": "sde", "path": "/dev/sde", "type": "disk", "rm": True, "hotplug": True, "size": 1000 * GB,
     "mountpoints": [None], "tran": "usb", "serial": "T7", "model": "Portable SSD", "maj:min": "8:64"},
    {"name": "sdf", "path": "/dev/sdf", "type": "disk", "rm": True, "hotplug": True, "size": 0,
     "mountpoints": [None], "tran": "usb", "serial": "E", "model": "Empty Reader", "maj:min": "8:80"},
    {"name": "loop3", "path": "/dev/loop3", "type": "loop", "rm": False, "hotplug": False, "size": 8 * GB,
     "mountpoints": [None], "tran": None, "serial": None, "model": None, "maj:min": "7:3"},
]
DEVICES = {device["path"]: device for device in TREE}
for _device in TREE:
    for _child in _device.get("children", []):
        DEVICES[_child["path"]] = _child
IMAGE = 4 * GB


def card(path, allow_large=False, image=IMAGE):
    return cards.card_of(DEVICES[path], cards.root_devices(TREE), image, allow_large)


def test_the_disk_holding_root_is_found_through_its_partitions():
    assert cards.root_devices(TREE) == {"/dev/nvme0n1"}


@pytest.mark.parametrize(("path", "kind"), [("/dev/sdb", "usb"), ("/dev/mmcblk0", "mmc"), ("/dev/loop3", "loop")])
def test_a_card_readers_whole_device_and_a_named_loop_device_are_cards(path, kind):
    found = card(path)
    assert (found.path, found.kind, found.majmin) == (path, kind, DEVICES[path]["maj:min"])


@pytest.mark.parametrize(("path", "allow_large", "image", "why"), [
    ("/dev/nvme0n1", False, IMAGE, "is not a removable USB or MMC card reader's card"),
    ("/dev/sdb1", False, IMAGE, "is a partition: give the whole card"),
    ("/dev/sdc", False, IMAGE, "has a mounted filesystem (/media/teacher/system-boot): unmount it first"),
    ("/dev/sdd", True, IMAGE, "is not a removable USB or MMC card reader's card (transport sata"),
    ("/dev/sde", False, IMAGE, "is 1000 GB, larger than 256 GB: a disk, not an SD card? (--allow-large"),
    ("/dev/sdf", False, IMAGE, "has no medium (no card in the reader)"),
    ("/dev/sdb", False, 40 * GB, "is 32.0 GB, smaller than the image (40.0 GB)"),
])
def test_what_is_not_a_card_is_refused_naming_the_device_and_why(path, allow_large, image, why):
    with pytest.raises(cards.CardError) as refused:
        card(path, allow_large, image)
    assert str(refused.value).startswith(path) and why in str(refused.value)


def test_a_large_usb_disk_is_written_only_when_asked():
    assert card("/dev/sde", allow_large=True).size == 1000 * GB


def test_the_root_disk_is_refused_even_if_it_looked_removable():
    removable_root = {**DEVICES["/dev/nvme0n1"], "rm": True, "tran": "usb"}
    with pytest.raises(cards.CardError, match="holds / "):
        cards.card_of(removable_root, {"/dev/nvme0n1"}, IMAGE, False)


# -- a card in use though nothing is mounted on it -----------------------------------------------

def test_a_card_with_a_loop_device_over_it_is_in_use(tmp_path):
    """A partition of a whole card mounted with `mount -o loop,offset=` (or a sandbox host running
    on the card) leaves lsblk's record of the card without a mount point: the loop over it says so."""
    backing = tmp_path / "card.bin"
    backing.write_bytes(bytes(4096))
    loops = {str(backing.resolve()): ["/dev/loop7"]}
    why = cards.in_use(str(backing), loops)
    assert why and str(backing) in why and "/dev/loop7 is a loop device over it" in why
    assert cards.in_use(str(backing), {}) is None


def test_the_loop_devices_over_each_file_are_read_from_losetup(monkeypatch):
    listed = ('{"loopdevices": [{"name": "/dev/loop0", "back-file": "/tmp/card0.bin"},'
              ' {"name": "/dev/loop1", "back-file": "/dev/loop0"}, {"name": "/dev/loop2", "back-file": null}]}')
    monkeypatch.setattr(cards.subprocess, "run",
                        lambda argv, **kwargs: __import__("subprocess").CompletedProcess(argv, 0, listed, ""))
    assert cards.loops_over() == {"/tmp/card0.bin": ["/dev/loop0"], "/dev/loop0": ["/dev/loop1"]}
