"""`roslab flash` on loop devices standing in for a tray of SD cards (root; no sandbox needed).

Three cards are written at once from a `.img.xz` (a stand-in for Ubuntu's Pi image,
tests/pi_image.py); each card holds the image's bytes and its own host's seed; a re-run skips
them; a byte changed on a card behind the writer's back is caught by the read-back; a card
pulled out mid-write fails alone while the others finish, and the re-run writes only it; a mounted
card, a card named twice and an image of another release are refused without a byte written;
with --interactive, each host gets the card put in when its card is asked for.
"""

from __future__ import annotations

import errno
import hashlib
import json
import lzma
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent.parent))
import pi_image  # noqa: E402  (the tests' stand-in image)

from roslab.cli.main import main  # noqa: E402
from roslab.seed import cards, flash, targets  # noqa: E402

pytestmark = pytest.mark.e2e
TEACHER = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFlMtlfltx2Ordc++JZrFF/P0U8EAhdPijdaM3K81dM9 teacher"
HOSTS = ["team1-main", "team1-robot", "team2-main"]


@pytest.fixture
def roster(tmp_path):
    path = tmp_path / "classroom.yaml"
    path.write_text(textwrap.dedent(f"""\
        classroom:
          teacher_ssh_keys: [{yaml.safe_dump(TEACHER, width=4096).splitlines()[0]}]
          ubuntu_release: "24.04"
          network_prefix: 24
          network_gateway: 192.168.50.1
          network_nameservers: [192.168.50.1]
        teams:
          team1:
            hosts:
              team1-main: {{role: main, address: 192.168.50.11, network_address: 192.168.50.11}}
              team1-robot: {{role: robot, address: 192.168.50.12, network_address: 192.168.50.12}}
          team2:
            hosts:
              team2-main: {{role: main, address: 192.168.50.21, network_address: 192.168.50.21}}
        """))
    return path


@pytest.fixture
def image_xz(tmp_path):
    raw = pi_image.write(tmp_path / "ubuntu-24.04-preinstalled-server-arm64+raspi.img")
    packed = raw.with_suffix(".img.xz")
    packed.write_bytes(lzma.compress(raw.read_bytes(), preset=0))
    return raw, packed


@pytest.fixture
def loop_cards(tmp_path):
    """Three 64 MB "cards": loop devices over sparse files, detached whatever happens."""
    devices, files = [], []
    try:
        for index in range(3):
            backing = tmp_path / f"card{index}.bin"
            with open(backing, "wb") as card:
                card.truncate(64 << 20)
            done = subprocess.run(["losetup", "--find", "--show", str(backing)], capture_output=True, text=True,
                                  check=True)
            devices.append(done.stdout.strip())
            files.append(backing)
        yield devices, files
    finally:
        for device in devices:
            subprocess.run(["umount", device], capture_output=True)
            subprocess.run(["losetup", "--detach", device], capture_output=True)


def flash_cli(roster, image, devices, *extra) -> int:
    return main(["flash", str(roster), "--image", str(image), "-y",
                 *(word for device in devices for word in ("--device", device)), *extra])


def card_seed(device: str, name: str) -> bytes | None:
    return targets.ImageFat(Path(device), targets.boot_partition(Path(device))).read(name)


def test_three_cards_are_flashed_at_once_each_with_its_own_seed_and_verified(roster, image_xz, loop_cards, capsys):
    raw, packed = image_xz
    devices, backing = loop_cards
    assert flash_cli(roster, packed, devices) == 0, capsys.readouterr()
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines()[1:] if line.split() and line.split()[0] in HOSTS}
    assert [rows[host].split()[1] for host in HOSTS] == devices, out
    assert all(rows[host].endswith("verified") for host in HOSTS), out
    size = raw.stat().st_size
    for host, device, file in zip(HOSTS, devices, backing):
        meta = card_seed(device, "meta-data").decode()
        assert f"local-hostname: {host}" in meta, meta
        record = json.loads(card_seed(device, flash.MARKER))
        assert record["host"] == host and record["image_sha256"] == hashlib.sha256(raw.read_bytes()).hexdigest()
        # outside the boot partition, the card is the image byte for byte
        start = targets.boot_partition(raw).start + targets.boot_partition(raw).size
        assert file.read_bytes()[start:size] == raw.read_bytes()[start:]
    assert card_seed(devices[0], "user-data.before-roslab") is not None  # Ubuntu's own, kept

    # A second run: every card is already flashed for its host with this image.
    assert flash_cli(roster, packed, devices) == 0
    again = capsys.readouterr().out
    assert again.count("skipped: already flashed for it") == 3, again


def test_a_card_changed_behind_the_writers_back_fails_its_read_back_and_the_others_finish(
        roster, image_xz, loop_cards, capsys, monkeypatch):
    raw, _ = image_xz
    devices, backing = loop_cards
    real_write_all = flash.write_all

    def corrupt_after_writing(image, jobs, say=print):
        digest = real_write_all(image, jobs, say)
        with open(backing[1], "r+b") as card:  # a byte of team1-robot's card, past the boot partition
            card.seek(raw.stat().st_size - 4096)
            old = card.read(1)
            card.seek(-1, os.SEEK_CUR)
            card.write(bytes([old[0] ^ 0xFF]))
        return digest

    monkeypatch.setattr(flash, "write_all", corrupt_after_writing)
    assert flash_cli(roster, raw, devices) == 1
    out = capsys.readouterr().out
    assert "team1-robot" in out and "FAILED: read back, its bytes differ from the image's" in out, out
    assert [line.split()[0] for line in out.splitlines() if line.endswith("  verified")] == [
        "team1-main", "team2-main"], out
    assert card_seed(devices[1], flash.MARKER) is None  # never marked done: a re-run writes it again
    # The re-run (as after an interruption) writes only the card that is not done.
    monkeypatch.setattr(flash, "write_all", real_write_all)
    assert flash_cli(roster, raw, devices) == 0
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line[:4] == "team"}
    assert rows["team1-robot"].endswith("  verified"), rows
    assert "skipped" in rows["team1-main"] and "skipped" in rows["team2-main"], rows


def test_a_card_pulled_out_mid_write_fails_alone_the_others_finish_and_the_rerun_writes_only_it(
        roster, image_xz, loop_cards, capsys, monkeypatch):
    """A card pulled from its reader mid-write: the kernel fails the writes on the gone device
    with ENODEV (a loop device cannot be pulled: `losetup -d` waits for the last close, so the
    writes on team1-robot's card fail here as the kernel's would, after its first 4 MB)."""
    raw, _ = image_xz
    devices, _ = loop_cards
    real_write = os.write

    def write(fd, data):
        if os.readlink(f"/proc/self/fd/{fd}") == devices[1] and os.lseek(fd, 0, os.SEEK_CUR) >= flash.CHUNK:
            raise OSError(errno.ENODEV, os.strerror(errno.ENODEV))
        return real_write(fd, data)

    monkeypatch.setattr(flash.os, "write", write)
    assert flash_cli(roster, raw, devices) == 1
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines() if line[:4] == "team"}
    assert "FAILED: the write stopped after 4 MB: No such device" in rows["team1-robot"], out
    assert rows["team1-main"].endswith("  verified") and rows["team2-main"].endswith("  verified"), out
    monkeypatch.setattr(flash.os, "write", real_write)  # the card is back in its reader
    assert flash_cli(roster, raw, devices) == 0
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines() if line[:4] == "team"}
    assert rows["team1-robot"].endswith("  verified"), rows
    assert "skipped" in rows["team1-main"] and "skipped" in rows["team2-main"], rows


def test_refused_before_a_byte_is_written(roster, tmp_path, image_xz, loop_cards, capsys):
    raw, _ = image_xz
    devices, backing = loop_cards
    old = pi_image.write(tmp_path / "ubuntu-22.04.img", release="22.04")
    assert flash_cli(roster, old, devices) == 1
    assert "the image is Ubuntu 22.04 (arm64), but team1-main is on Ubuntu 24.04" in capsys.readouterr().err
    assert flash_cli(roster, raw, [devices[0], devices[0], devices[1]]) == 1
    assert "a device is named twice" in capsys.readouterr().err
    # A mounted card: its filesystem would be written under the feet of whoever mounted it.
    subprocess.run(["mkfs.ext4", "-q", "-F", devices[2]], check=True)
    mount_dir = tmp_path / "mnt"
    mount_dir.mkdir()
    subprocess.run(["mount", devices[2], str(mount_dir)], check=True)
    try:
        assert flash_cli(roster, raw, devices) == 1
        err = capsys.readouterr().err
        assert f"{devices[2]} has a mounted filesystem ({mount_dir})" in err and "nothing was written" in err
    finally:
        subprocess.run(["umount", str(mount_dir)], check=True)
    for file in backing[:2]:
        assert file.read_bytes()[:512] == bytes(512)  # not a byte: the cards are still blank
    assert flash_cli(roster, raw, devices[:2]) == 2
    assert "3 hosts" in capsys.readouterr().err


def test_a_card_that_was_swapped_for_another_is_not_read_as_the_same():
    card = cards.Card("/dev/loop99999", 1 << 26, "loop", "", "", "7:99999")
    assert "is gone" in cards.still_the_same(card)


class CardTray:
    """The teacher at the keyboard, as `roslab flash --interactive` reads them (sys.stdin): each
    answer first does what the teacher did at the tray (put card N in: its loop device is
    attached; None: nothing), then types the answer."""

    def __init__(self, devices, files, steps):
        self.devices, self.files, self.steps, self.asked = devices, files, list(steps), 0

    def readline(self):
        if not self.steps:
            return ""
        card, answer = self.steps.pop(0)
        self.asked += 1
        if card is not None:
            subprocess.run(["losetup", self.devices[card], str(self.files[card])], check=True)
        return answer


def unused_loop_devices(count):
    """Loop device names nothing is attached to, far above those `losetup --find` hands out."""
    free = [f"/dev/loop{n}" for n in range(200, 1000) if not Path(f"/sys/block/loop{n}/loop").exists()]
    return free[:count]


def test_interactive_each_host_gets_the_card_put_in_when_asked(roster, image_xz, tmp_path, capsys, monkeypatch):
    """--interactive: no card is in when the command starts; the card put in when a host's card
    is asked for is that host's (loop devices, named with --device: the only ones it may pick)."""
    raw, _ = image_xz
    devices = unused_loop_devices(2)
    files = []
    for index in range(2):
        files.append(tmp_path / f"card{index}.bin")
        with open(files[-1], "wb") as card:
            card.truncate(64 << 20)
    tray = CardTray(devices, files, [(None, "\n"), (0, "\n"), (None, "s\n"), (1, "\n")])
    monkeypatch.setattr(sys, "stdin", tray)
    try:
        assert flash_cli(roster, raw, devices, "--interactive") == 0, capsys.readouterr()
        out = capsys.readouterr().out
        assert tray.asked == 4, out
        assert "insert the card for team1-main (ENTER when it is in, s to skip)   no new card appeared; try again" \
            in out, out
        assert "team1-robot: skipped" in out, out
        rows = {line.split()[0]: line.split() for line in out.splitlines() if line.endswith("  verified")}
        assert {host: row[1] for host, row in rows.items()} == {"team1-main": devices[0], "team2-main": devices[1]}
        for host, device in zip(["team1-main", "team2-main"], devices):
            assert f"local-hostname: {host}" in card_seed(device, "meta-data").decode()
    finally:
        for device in devices:
            subprocess.run(["losetup", "--detach", device], capture_output=True)
