"""The sandbox host that runs on a card (roslab/sandbox/card.py): the card's writable grown to
its end as cloud-init's growpart does, and its system-boot's files written back to the card's FAT
when the card is let go. On image files (tests/pi_image.py), through mtools: no root, no mount."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from roslab.sandbox import card

sys.path.insert(0, str(Path(__file__).parent.parent))
import pi_image  # noqa: E402  (the tests' stand-in image)

MIB = 1 << 20
ENV = {**os.environ, "MTOOLS_SKIP_CHECK": "1"}


def fat_files(image: Path) -> dict[str, bytes]:
    drive = f"{image}@@{MIB}"
    listing = subprocess.run(["mdir", "-/", "-b", "-i", drive, "::/"], capture_output=True, text=True,
                             env=ENV, check=True).stdout.split()
    return {line[3:].rstrip("/"): subprocess.run(["mtype", "-i", drive, line], capture_output=True, env=ENV,
                                     check=True).stdout if not line.endswith("/") else b"(folder)"
            for line in listing if line.startswith("::/")}


@pytest.fixture
def image(tmp_path) -> Path:
    return pi_image.write(tmp_path / "card.img")


def test_the_boot_folder_is_written_back_to_the_cards_fat_changes_new_folders_and_deletions(image, tmp_path):
    folder = tmp_path / "boot"
    folder.mkdir()
    subprocess.run(["mcopy", "-s", "-n", "-m", "-i", f"{image}@@{MIB}", "::/*", f"{folder}/"], env=ENV, check=True)
    assert (folder / "config.txt").is_file() and (folder / "user-data").is_file()
    # What a host did to its /boot/firmware: a deploy's config.txt, a new overlay, a file removed.
    (folder / "config.txt").write_text((folder / "config.txt").read_text() + "dtoverlay=i2c-rtc\n")
    (folder / "overlays").mkdir()
    (folder / "overlays/i2c-rtc.dtbo").write_bytes(b"\xd0\x0d\xfe\xed")
    (folder / "network-config").unlink()
    card.write_back(folder, card._fat(image, MIB))
    files = fat_files(image)
    assert files["config.txt"].endswith(b"dtoverlay=i2c-rtc\n")
    assert files["overlays"] == b"(folder)" and files["overlays/i2c-rtc.dtbo"] == b"\xd0\x0d\xfe\xed"
    assert "network-config" not in files
    assert files["user-data"] == (folder / "user-data").read_bytes()  # unchanged, still there
    # The folder emptied of the overlay: the card's folder goes too.
    (folder / "overlays/i2c-rtc.dtbo").unlink()
    (folder / "overlays").rmdir()
    card.write_back(folder, card._fat(image, MIB))
    assert not any(name.startswith("overlays") for name in fat_files(image))


def test_the_writable_partition_grows_to_the_cards_end_once(image):
    (_, fat_size), (start, size) = card._partitions(image)
    with open(image, "r+b") as disk:
        disk.truncate(image.stat().st_size + 64 * MIB)  # a card larger than the image
    assert card._grow_writable(image, start)
    (_, fat_after), (start_after, size_after) = card._partitions(image)
    assert (start_after, start_after + size_after) == (start, image.stat().st_size)
    assert fat_after == fat_size  # system-boot as it was
    assert not card._grow_writable(image, start)  # it ends at the card's end: nothing more to do
    with open(image, "rb") as disk:
        assert disk.read(512)[510:] == b"\x55\xaa"


def test_a_card_without_a_writable_partition_is_refused_naming_it(tmp_path):
    image = tmp_path / "blank.img"
    image.write_bytes(bytes(440) + bytes(6) + struct.pack("<BBBBBBBBII", 0, 0, 0, 0, 0x0C, 0, 0, 0, 2048, 2048)
                      + bytes(48) + b"\x55\xaa")
    with pytest.raises(card.SandboxError, match=rf"--card {image}: no FAT system-boot and Linux writable"):
        card._partitions(image)


def test_a_host_on_no_card_has_nothing_to_let_go(tmp_path):
    card.release(tmp_path)  # no record: nothing unmounted, nothing written
    assert not (tmp_path / card.RECORD).exists()


@pytest.fixture
def card_read(monkeypatch, tmp_path):
    """The card's system as debugfs would read it, and the loop devices over each file."""
    from roslab.seed import cards

    device = tmp_path / "card.bin"
    device.write_bytes(b"")
    seen = {"system": ("24.04", "amd64"), "loops": {}}
    monkeypatch.setattr(cards, "writable_system", lambda path: seen["system"])
    monkeypatch.setattr(cards, "loops_over", lambda: seen["loops"])
    return device, seen


def test_a_card_is_refused_before_anything_is_stopped_when_in_use_or_of_another_release(card_read, tmp_path):
    device, seen = card_read
    host_dir = tmp_path / "hosts" / "team1-robot"
    host_dir.mkdir(parents=True)
    card.check(host_dir, device, "24.04", "team1-robot")  # a free card of the host's release
    seen["loops"] = {str(device.resolve()): ["/dev/loop4"]}  # another host runs on it
    with pytest.raises(card.SandboxError, match=r"--card .*card\.bin is in use: /dev/loop4"):
        card.check(host_dir, device, "24.04", "team1-robot")
    # The card this host runs on is its own: booting from it again is not refused.
    (host_dir / card.RECORD).write_text(f'{{"card": "{device}", "fat_offset": 1048576}}\n')
    card.check(host_dir, device, "24.04", "team1-robot")
    seen["system"] = ("22.04", "amd64")
    with pytest.raises(card.SandboxError, match=r"its system is Ubuntu 22\.04, but team1-robot is on Ubuntu 24\.04: "
                                                r"write a card image of 24\.04 \(`roslab sandbox card-image FILE "
                                                r"--release 24\.04`\)"):
        card.check(host_dir, device, "24.04", "team1-robot")
