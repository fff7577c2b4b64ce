"""Which card is which host, for `roslab flash`: a teacher with a tray of identical cards can
follow each of the three ways (issue 38).

- `--device DEV ...`: the hosts (roster order, after --limit) get the devices in the order given.
- `--interactive`: for each host in turn, "insert the card for HOST": the one whole device that
  appeared or whose reader got a card since the previous card (lsblk's size goes from 0) is
  that host's. None or two new: it says so and asks again; `s` skips the host.
  With `--device`, only the devices named may be picked (loop devices only so, as everywhere).
- `--by-slot`: the card readers' ports (their /dev/disk/by-path names, which name the USB port
  and the reader's slot and stay the same from one run to the next) in natural order get the
  hosts in roster order: the first host is always in the first slot, whatever device name the
  kernel gives its card. (lsblk cannot say it: Debian 12's util-linux 2.38 has no by-path
  column, and its HCTL's SCSI host number follows the order the readers were plugged in.)

Every device picked here is then checked as a `--device` is (roslab.seed.cards.card_of).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from roslab.roster.model import Host
from roslab.seed import cards

BY_PATH = Path("/dev/disk/by-path")
PROMPT = "insert the card for {host} (ENTER when it is in, s to skip) "


class Skipped(Exception):
    """The teacher skipped the host (answered `s`)."""


def snapshot(tree: list[dict]) -> dict[str, str]:
    """The whole devices lsblk lists, path -> "major:minor size": a card put into a reader
    changes its reader's size from 0 (a USB reader) or adds the device (an MMC slot, a loop)."""
    return {device["path"]: _state(device) for device in tree}


def _state(device: dict) -> str:
    return f"{device.get('maj:min') or ''} {int(device.get('size') or 0)}"


def new_card(before: dict[str, str], tree: list[dict], allowed: set[str],
             image_size: int, allow_large: bool) -> tuple[str | None, str]:
    """(the path of the one card that appeared since `before`, "") or (None, why none was picked).

    Only whole disks and, when named in `allowed`, loop devices count; with `allowed`, only those.
    A new device that is refused as a card (mounted, too large...) is named with the reason."""
    roots = cards.root_devices(tree)
    new = [device for device in tree
           if before.get(device["path"]) != _state(device) and int(device.get("size") or 0)
           and device.get("type") in ("disk", "loop")
           and (device["path"] in allowed if allowed else device.get("type") == "disk")]
    if not new:
        return None, "no new card appeared"
    if len(new) > 1:
        return None, f"{len(new)} new devices appeared ({', '.join(d['path'] for d in new)}): leave only one in"
    try:
        cards.card_of(new[0], roots, image_size, allow_large)
    except cards.CardError as error:
        return None, str(error)
    return new[0]["path"], ""


@dataclass
class Prompter:
    """Asks for each host's card in turn; `ask` reads the teacher's answer, `say` tells them."""
    image_size: int
    allow_large: bool
    allowed: set[str]
    ask: Callable[[str], str] = input
    say: Callable[[str], None] = print
    lsblk: Callable[[], list[dict]] = cards.lsblk

    def card_for(self, host: Host, before: dict[str, str], taken: dict[str, str]) -> tuple[str, dict[str, str]]:
        """(the card's path, the snapshot with it); Skipped when the teacher skips the host.
        `taken`: device -> the host whose card it already is (a reader is not used twice)."""
        while True:
            answer = self.ask(PROMPT.format(host=host.name)).strip().lower()
            if answer == "s":
                raise Skipped(host.name)
            if answer:
                self.say(f"  {answer!r}: press ENTER once the card is in, or type s to skip {host.name}")
                continue
            tree = self.lsblk()
            path, why = new_card(before, tree, self.allowed, self.image_size, self.allow_large)
            owner = taken.get(path or "")
            if owner:
                why = f"{path} was {owner}'s card: put this one in another reader"
            elif path:
                self.say(f"  {host.name}: {path}")
                return path, snapshot(tree)
            self.say(f"  {why}; try again")


def interactive(hosts: list[Host], prompter: Prompter) -> list[tuple[Host, str]]:
    """Each host (in order) with the card the teacher put in for it; skipped hosts left out."""
    before, matched = snapshot(prompter.lsblk()), []
    taken: dict[str, str] = {}
    for host in hosts:
        try:
            path, before = prompter.card_for(host, before, taken)
        except Skipped:
            prompter.say(f"  {host.name}: skipped")
            continue
        except EOFError:
            prompter.say("  no more answers: the hosts left are not flashed")
            break
        taken[path] = host.name
        matched.append((host, path))
    return matched


def _natural(name: str) -> list:
    """usb-0:2 before usb-0:10: the ports' numbers compared as numbers."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def reader_slots(links: dict[str, str], tree: list[dict]) -> list[tuple[str, str]]:
    """The card readers' slots: (by-path name, device path) for each whole USB or MMC device
    (with or without a card: lsblk -a), in natural order of the name. `links` is by-path
    name -> the device it points to."""
    readers = {device["path"] for device in tree
               if device.get("type") == "disk" and cards.transport_of(device) in cards.CARD_TRANSPORTS}
    slots = [(name, target) for name, target in links.items() if "-part" not in name and target in readers]
    return sorted(slots, key=lambda slot: _natural(slot[0]))


def by_path_links(folder: Path = BY_PATH) -> dict[str, str]:
    """/dev/disk/by-path: name -> the device node it points to (udev's; none without udev)."""
    if not folder.is_dir():
        return {}
    return {link.name: os.path.realpath(link) for link in folder.iterdir()}


def by_slot(hosts: list[Host], slots: list[tuple[str, str]]) -> list[tuple[Host, str, str]]:
    """(host, slot name, device) for each host in order in the slots in order; CardError when
    there are fewer slots than hosts."""
    if len(slots) < len(hosts):
        raise cards.CardError(f"{len(hosts)} hosts but {len(slots)} card reader slots "
                              f"({', '.join(name for name, _ in slots) or 'none in /dev/disk/by-path'})")
    return [(host, name, device) for host, (name, device) in zip(hosts, slots)]
