"""Which card is which host (issue 38), from recorded `lsblk --json --bytes` records: the card put
in when asked for a host is that host's (a USB reader's size going from 0, a new MMC or named
loop device), none or two new cards are asked again, a refused device is said why, `s` skips
a host; and the card readers' slots (a recorded /dev/disk/by-path listing) get the hosts in
the slots' order."""

from __future__ import annotations

import argparse
import copy
from types import SimpleNamespace

import pytest

from roslab.seed import cards, flash, matching
from roslab.seed.command import _Stop

GB = 10**9
IMAGE = 4 * GB
ROOT = {"name": "nvme0n1", "path": "/dev/nvme0n1", "type": "disk", "rm": False, "hotplug": False, "size": 512 * GB,
        "mountpoints": [None], "tran": "nvme", "serial": "S4X", "model": "Samsung SSD", "maj:min": "259:0",
        "children": [{"name": "nvme0n1p2", "path": "/dev/nvme0n1p2", "type": "part", "size": 500 * GB,
                      "mountpoints": ["/"], "maj:min": "259:2"}]}


def reader(name, majmin, size=0, mounted=None):
    """A USB card reader's whole device, as lsblk records it (size 0: no card in it)."""
    device = {"name": name, "path": f"/dev/{name}", "type": "disk", "rm": True, "hotplug": True, "size": size,
              "mountpoints": [None], "tran": "usb", "serial": f"R{majmin}", "model": "SD/MMC Reader",
              "maj:min": majmin}
    if mounted:
        device["children"] = [{"name": f"{name}1", "path": f"/dev/{name}1", "type": "part", "size": GB,
                               "mountpoints": [mounted], "maj:min": majmin[:-1] + "1"}]
    return device


def loop(name, majmin):
    return {"name": name, "path": f"/dev/{name}", "type": "loop", "rm": False, "hotplug": False, "size": 8 * GB,
            "mountpoints": [None], "tran": None, "serial": None, "model": None, "maj:min": majmin}


EMPTY = [ROOT, reader("sdb", "8:16"), reader("sdc", "8:32")]
ONE = [ROOT, reader("sdb", "8:16", 32 * GB), reader("sdc", "8:32")]
BOTH = [ROOT, reader("sdb", "8:16", 32 * GB), reader("sdc", "8:32", 32 * GB)]
HOSTS = [SimpleNamespace(name=name) for name in ("team1-main", "team1-robot", "team2-main")]


def run(snapshots, answers, hosts=HOSTS, allowed=()):
    """matching.interactive with lsblk answering `snapshots` in turn (the first before any
    question) and the teacher typing `answers`; (the matches, what was said, the questions)."""
    trees, typed, said, asked = iter(snapshots), iter(answers), [], []

    def ask(prompt):
        asked.append(prompt)
        try:
            return next(typed)
        except StopIteration:
            raise EOFError from None

    prompter = matching.Prompter(IMAGE, False, set(allowed), ask=ask, say=said.append,
                                 lsblk=lambda: copy.deepcopy(next(trees)))
    matched = matching.interactive(hosts, prompter)
    return [(host.name, path) for host, path in matched], said, asked


def test_each_host_gets_the_card_put_into_a_reader_when_it_was_asked_for():
    matched, said, asked = run([EMPTY, ONE, BOTH], ["", ""], hosts=HOSTS[:2])
    assert matched == [("team1-main", "/dev/sdb"), ("team1-robot", "/dev/sdc")]
    assert asked == ["insert the card for team1-main (ENTER when it is in, s to skip) ",
                     "insert the card for team1-robot (ENTER when it is in, s to skip) "]
    assert said == ["  team1-main: /dev/sdb", "  team1-robot: /dev/sdc"]


def test_no_new_card_or_two_new_cards_are_said_and_asked_again():
    matched, said, asked = run([EMPTY, EMPTY, BOTH, ONE], ["", "", ""], hosts=HOSTS[:1])
    assert matched == [("team1-main", "/dev/sdb")]
    assert said == ["  no new card appeared; try again",
                    "  2 new devices appeared (/dev/sdb, /dev/sdc): leave only one in; try again",
                    "  team1-main: /dev/sdb"]
    assert len(asked) == 3


def test_a_new_card_that_is_not_a_card_to_write_is_said_why_and_asked_again():
    automounted = [ROOT, reader("sdb", "8:16", 32 * GB, mounted="/media/teacher/system-boot"), reader("sdc", "8:32")]
    huge = [ROOT, reader("sdb", "8:16"), reader("sdc", "8:32", 1000 * GB)]
    matched, said, _ = run([EMPTY, automounted, huge, ONE], ["", "", ""], hosts=HOSTS[:1])
    assert matched == [("team1-main", "/dev/sdb")]
    assert said[0] == ("  /dev/sdb has a mounted filesystem (/media/teacher/system-boot): unmount it first; "
                       "try again")
    assert said[1].startswith("  /dev/sdc is 1000 GB, larger than 256 GB")


def test_an_answer_that_is_neither_enter_nor_s_is_asked_again_without_looking_for_a_card():
    matched, said, asked = run([EMPTY, ONE], ["y", ""], hosts=HOSTS[:1])
    assert matched == [("team1-main", "/dev/sdb")] and len(asked) == 2
    assert said[0] == "  'y': press ENTER once the card is in, or type s to skip team1-main"


def test_a_skipped_host_gets_no_card_and_the_next_one_is_asked():
    matched, said, _ = run([EMPTY, ONE], ["s", "", "S"])
    assert matched == [("team1-robot", "/dev/sdb")]
    assert said == ["  team1-main: skipped", "  team1-robot: /dev/sdb", "  team2-main: skipped"]


def test_a_card_swapped_in_the_same_reader_is_not_taken_for_two_hosts():
    swapped = [ROOT, reader("sdb", "8:16", 64 * GB), reader("sdc", "8:32")]
    matched, said, _ = run([EMPTY, ONE, swapped, BOTH], ["", "", ""], hosts=HOSTS[:2])
    assert matched == [("team1-main", "/dev/sdb"), ("team1-robot", "/dev/sdc")]
    assert said[1] == "  /dev/sdb was team1-main's card: put this one in another reader; try again"


def test_the_end_of_the_answers_stops_asking_and_keeps_the_cards_matched():
    matched, said, _ = run([EMPTY, ONE], [""])
    assert matched == [("team1-main", "/dev/sdb")]
    assert said[-1] == "  no more answers: the hosts left are not flashed"


def test_loop_devices_are_picked_only_when_named_and_with_names_only_those():
    attached = EMPTY + [loop("loop7", "7:7")]
    matched, said, _ = run([EMPTY, attached, ONE], ["", ""], hosts=HOSTS[:1])
    assert matched == [("team1-main", "/dev/sdb")] and said[0] == "  no new card appeared; try again"
    matched, _, _ = run([EMPTY, attached], [""], hosts=HOSTS[:1], allowed={"/dev/loop7"})
    assert matched == [("team1-main", "/dev/loop7")]
    matched, said, _ = run([EMPTY, ONE, attached], ["", ""], hosts=HOSTS[:1], allowed={"/dev/loop7"})
    assert matched == [("team1-main", "/dev/loop7")] and said[0] == "  no new card appeared; try again"


def test_the_root_disk_appearing_is_never_picked():
    odd_root = {**ROOT, "maj:min": "259:9", "rm": True, "tran": "usb"}  # as if it had come back
    matched, said, _ = run([[reader("sdb", "8:16")], [odd_root, reader("sdb", "8:16")], ONE[1:]], ["", ""],
                           hosts=HOSTS[:1])
    assert said[0] == "  /dev/nvme0n1 holds / (this machine's own system); try again"
    assert matched == [("team1-main", "/dev/sdb")]


# A hub with a two-slot reader (LUN 0 and 1) on port 2 and a one-slot reader on port 10, the
# laptop's own disk and a USB stick mounted, as /dev/disk/by-path lists them (-> the device).
LINKS = {
    "pci-0000:00:14.0-usb-0:10:1.0-scsi-0:0:0:0": "/dev/sdd",
    "pci-0000:00:14.0-usb-0:10:1.0-scsi-0:0:0:0-part1": "/dev/sdd1",
    "pci-0000:00:14.0-usb-0:2:1.0-scsi-0:0:0:1": "/dev/sdc",
    "pci-0000:00:14.0-usb-0:2:1.0-scsi-0:0:0:0": "/dev/sdb",
    "pci-0000:01:00.0-nvme-1": "/dev/nvme0n1",
    "pci-0000:01:00.0-nvme-1-part2": "/dev/nvme0n1p2",
}
SLOTS_TREE = [ROOT, reader("sdb", "8:16", 32 * GB), reader("sdc", "8:32"), reader("sdd", "8:48", 32 * GB)]


def test_the_reader_slots_are_the_usb_readers_in_port_order_empty_ones_included():
    slots = matching.reader_slots(LINKS, SLOTS_TREE)
    assert slots == [("pci-0000:00:14.0-usb-0:2:1.0-scsi-0:0:0:0", "/dev/sdb"),
                     ("pci-0000:00:14.0-usb-0:2:1.0-scsi-0:0:0:1", "/dev/sdc"),
                     ("pci-0000:00:14.0-usb-0:10:1.0-scsi-0:0:0:0", "/dev/sdd")]


def test_the_hosts_fill_the_slots_in_order_whatever_name_the_kernel_gave_each_card():
    renamed = {name: {"/dev/sdb": "/dev/sdf", "/dev/sdc": "/dev/sdg", "/dev/sdd": "/dev/sde"}.get(device, device)
               for name, device in LINKS.items()}
    tree = [ROOT, reader("sdf", "8:80", 32 * GB), reader("sdg", "8:96"), reader("sde", "8:64", 32 * GB)]
    first = matching.by_slot(HOSTS, matching.reader_slots(LINKS, SLOTS_TREE))
    again = matching.by_slot(HOSTS, matching.reader_slots(renamed, tree))
    assert [(host.name, slot) for host, slot, _ in first] == [(host.name, slot) for host, slot, _ in again]
    assert [device for _, _, device in again] == ["/dev/sdf", "/dev/sdg", "/dev/sde"]


def test_more_hosts_than_slots_is_refused_naming_the_slots():
    with pytest.raises(cards.CardError, match="3 hosts but 1 card reader slots \\(pci-0000:00:14.0-usb-0:2:1.0"):
        matching.by_slot(HOSTS, matching.reader_slots(LINKS, SLOTS_TREE[:2]))
    with pytest.raises(cards.CardError, match="none in /dev/disk/by-path"):
        matching.by_slot(HOSTS, [])


def test_the_by_path_listing_is_read_from_the_folder(tmp_path):
    (tmp_path / "sdb").touch()
    (tmp_path / "pci-usb-0:2:1.0-scsi-0:0:0:0").symlink_to(tmp_path / "sdb")
    assert matching.by_path_links(tmp_path) == {"pci-usb-0:2:1.0-scsi-0:0:0:0": str(tmp_path / "sdb"),
                                                "sdb": str(tmp_path / "sdb")}
    assert matching.by_path_links(tmp_path / "missing") == {}


def args(**given):
    return argparse.Namespace(**{"device": None, "interactive": False, "by_slot": False, "allow_large": False,
                                 **given})


IMAGE_OF = SimpleNamespace(size=IMAGE)


def test_flash_needs_one_way_to_match_the_cards_and_says_the_three():
    with pytest.raises(_Stop) as stop:
        flash._matched(args(), HOSTS, IMAGE_OF)
    assert stop.value.status == 2 and "0 --device cards" in str(stop.value) and "--by-slot" in str(stop.value)
    with pytest.raises(_Stop, match="no --device with it"):
        flash._matched(args(by_slot=True, device=["/dev/sdb"]), HOSTS, IMAGE_OF)


def test_flash_by_slot_names_each_hosts_slot_and_refuses_too_few(monkeypatch):
    monkeypatch.setattr(matching, "by_path_links", lambda: LINKS)
    monkeypatch.setattr(cards, "lsblk", lambda paths=None, empty=False: SLOTS_TREE if empty else [])
    matched = flash._matched(args(by_slot=True), HOSTS, IMAGE_OF)
    assert [(host.name, device) for host, _, device in matched] == [
        ("team1-main", "/dev/sdb"), ("team1-robot", "/dev/sdc"), ("team2-main", "/dev/sdd")]
    with pytest.raises(cards.CardError, match="4 hosts but 3 card reader slots"):
        flash._matched(args(by_slot=True), HOSTS + [SimpleNamespace(name="team3-main")], IMAGE_OF)


def test_flash_interactive_with_no_card_for_any_host_writes_nothing(monkeypatch):
    monkeypatch.setattr(cards, "lsblk", lambda paths=None, empty=False: copy.deepcopy(EMPTY))
    monkeypatch.setattr("builtins.input", lambda prompt: "s")
    with pytest.raises(_Stop, match="no card was put in for any host: nothing was written"):
        flash._matched(args(interactive=True), HOSTS, IMAGE_OF)


def test_flash_interactive_stopped_with_ctrl_c_writes_nothing(monkeypatch):
    monkeypatch.setattr(cards, "lsblk", lambda paths=None, empty=False: copy.deepcopy(EMPTY))

    def interrupted(prompt):
        raise KeyboardInterrupt

    monkeypatch.setattr("builtins.input", interrupted)
    with pytest.raises(_Stop, match="stopped while asking for the cards: nothing was written"):
        flash._matched(args(interactive=True), HOSTS, IMAGE_OF)


def test_flash_interactive_asks_on_the_terminal_and_takes_the_card_put_in(monkeypatch, capsys):
    trees = iter([EMPTY, ONE])
    monkeypatch.setattr(cards, "lsblk", lambda paths=None, empty=False: copy.deepcopy(next(trees)))
    monkeypatch.setattr("builtins.input", lambda prompt: print(prompt) or "")
    matched = flash._matched(args(interactive=True), HOSTS[:1], IMAGE_OF)
    assert [(host.name, slot, device) for host, slot, device in matched] == [("team1-main", "", "/dev/sdb")]
    assert capsys.readouterr().out == ("insert the card for team1-main (ENTER when it is in, s to skip) \n"
                                       "  team1-main: /dev/sdb\n")


def test_the_final_table_shows_each_cards_slot_only_when_cards_were_matched_by_slot():
    def job(name: str, path: str, slot: str = "", result: str = "verified") -> flash.Job:
        card = cards.Card(path=path, size=32_000_000_000, kind="usb", serial="000000001234", model="Reader",
                          majmin="8:16")
        return flash.Job(SimpleNamespace(name=name), card, slot=slot, result=result)

    by_slot = flash.table([job("team1-main", "/dev/sdb", "pci-0000:00:14.0-usb-0:1:1.0-scsi-0:0:0:0"),
                           job("team1-robot", "/dev/sdc", "pci-0000:00:14.0-usb-0:2:1.0-scsi-0:0:0:0")]).splitlines()
    assert by_slot[0].split() == ["host", "device", "slot", "card", "result"]
    assert "usb-0:2:1.0" in by_slot[2] and by_slot[2].startswith("team1-robot") and by_slot[2].endswith("verified")
    by_device = flash.table([job("team1-main", "/dev/sdb")]).splitlines()
    assert by_device[0].split() == ["host", "device", "card", "result"]


class _PastTheImageChecks(Exception):
    """Raised where _plan goes on to the roster's checks: the image was accepted."""


@pytest.mark.parametrize("architecture, allowed, refusal", [
    ("amd64", None, "the image is for amd64, not a Raspberry Pi: nothing was written"),
    ("arm64", "amd64", "the image is for arm64, not amd64 (--architecture): nothing was written"),
    ("arm64", None, None),
    ("armhf", None, None),
    ("amd64", "amd64", None),  # the sandbox's own card image, asked for by name
])
def test_an_image_not_for_a_pi_is_written_only_for_the_architecture_named(monkeypatch, architecture, allowed,
                                                                          refusal):
    hosts = [SimpleNamespace(name="team1-robot", ubuntu_release="24.04")]
    monkeypatch.setattr(flash, "_selected", lambda given, command: (SimpleNamespace(path="r.yaml"), hosts))

    def past(*_):
        raise _PastTheImageChecks

    monkeypatch.setattr(flash, "_refuse_what_the_roster_cannot_say", past)
    image = SimpleNamespace(release="24.04", architecture=architecture, size=IMAGE)
    if refusal:
        with pytest.raises(_Stop, match=refusal.replace("(", r"\(").replace(")", r"\)")):
            flash._plan(args(architecture=allowed), image)
    else:
        with pytest.raises(_PastTheImageChecks):
            flash._plan(args(architecture=allowed), image)
