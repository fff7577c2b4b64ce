"""`roslab flash ROSTER --image IMG --device DEV ...`: a tray of SD cards written at once,
each with its own host's seed, each verified by reading it back.

    roslab flash classroom.yaml --image ubuntu-24.04.3-preinstalled-server-arm64+raspi.img.xz \\
        --limit team1 --device /dev/sdb --device /dev/sdc

The hosts `--limit` selects (in roster order) are matched to the `--device` cards in the order
given: the first host's card is the first device; or, with `--interactive`, to the card put in
when asked ("insert the card for team3-robot"); or, with `--by-slot`, to the card readers' slots
in order (roslab.seed.matching). Before any byte is written, the whole run is
checked: the roster and every host's seed (as `roslab seed` checks them), every card
(roslab.seed.cards: whole removable USB/MMC devices, or loop devices named explicitly; never
`/`'s disk, never mounted, never over 256 GB without --allow-large), and the image (a Pi
preinstalled Ubuntu image of the hosts' release and architecture; with --image-sha256, its
digest). The list of hosts and cards is shown and confirmed unless `-y`.

Then the image is read once and written to every card at once (one writer per card, each
card's progress, rate and time left shown), each card is read back and its bytes compared with
the image's digest (the kernel's cache of the card dropped first), its host's seed (the files
`roslab seed` writes: identity, host key, address, WiFi, users) written into its
`system-boot` partition and read back, and last a record (`roslab-flash.json`: host, image
digest, time) that says the card is done. A card that fails says so in one line and the others
finish. A card whose record names the same host and image, with the seed in place, is skipped
(`--force` writes it again): a re-run after an interruption finishes only the unfinished cards.
The table at the end (host, device, card, result) is what goes on each card's label.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import os
import queue
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from roslab.reach import add_roster_argument
from roslab.roster.model import Host
from roslab.seed import cards, matching, targets
from roslab.seed.command import _checked_seeds, _record_key, _refuse_what_the_roster_cannot_say, _selected, _Stop
from roslab.seed.documents import SEED_FILES

CHUNK = 4 << 20
MARKER = "roslab-flash.json"
BLKFLSBUF = 0x1261  # linux/fs.h: drop the block device's buffers, so a read-back reads the card
PROGRESS_EVERY = 5.0  # seconds between progress lines


@dataclass
class Job:
    host: Host  # the roster's
    card: cards.Card
    slot: str = ""  # the reader's /dev/disk/by-path name, with --by-slot
    written: int = 0
    result: str = "waiting"  # writing, verified, skipped, FAILED
    reason: str = ""

    def fail(self, reason: str) -> None:
        if self.result != "FAILED":
            self.result, self.reason = "FAILED", reason


# -- writing --------------------------------------------------------------------------------------


def _writer(job: Job, chunks: queue.Queue) -> None:
    """Write the chunks to the job's card; a failure is the job's, the queue is still drained."""
    fd = None
    try:
        # O_EXCL on a block device: refused while it is mounted, even if it was mounted after the check.
        fd = os.open(job.card.path, os.O_WRONLY | os.O_EXCL)
    except OSError as error:
        job.fail(f"cannot open {job.card.path}: {error.strerror}")
    while (chunk := chunks.get()) is not None:
        if fd is None or job.result == "FAILED":
            continue
        try:
            view = memoryview(chunk)
            while view:
                done = os.write(fd, view)
                view = view[done:]
                job.written += done
        except OSError as error:
            job.fail(f"the write stopped after {job.written / 1e6:.0f} MB: {error.strerror}")
    if fd is not None:
        try:
            os.fsync(fd)
        except OSError as error:
            job.fail(f"the card did not take the last writes: {error.strerror}")
        os.close(fd)


def write_all(image: cards.Image, jobs: list[Job], say=print) -> None:
    """Read the image once and write it to every job's card at once (its digest was taken with
    the image: `cards.raw_image`)."""
    queues: list[queue.Queue] = [queue.Queue(maxsize=4) for _ in jobs]
    writers = [threading.Thread(target=_writer, args=(job, chunks), daemon=True) for job, chunks in zip(jobs, queues)]
    for job, writer in zip(jobs, writers):
        job.result = "writing"
        writer.start()
    started = shown = time.monotonic()
    with open(image.path, "rb") as source:
        while chunk := source.read(CHUNK):
            for chunks in queues:
                chunks.put(chunk)
            if time.monotonic() - shown >= PROGRESS_EVERY:
                shown = time.monotonic()
                say_progress(jobs, image.size, shown - started, say)
    for chunks in queues:
        chunks.put(None)
    for writer in writers:
        writer.join()
    say_progress(jobs, image.size, time.monotonic() - started, say)


def say_progress(jobs: list[Job], total: int, seconds: float, say=print) -> None:
    for job in jobs:
        if job.result == "FAILED":
            continue
        rate = job.written / seconds if seconds > 0 else 0
        left = f", {(total - job.written) / rate:.0f} s left" if rate and job.written < total else ""
        say(f"  {job.host.name} ({job.card.path}): {job.written / 1e6:.0f} of {total / 1e6:.0f} MB, "
            f"{rate / 1e6:.1f} MB/s{left}")


def read_back(job: Job, size: int, expected: str) -> None:
    """Read the card's first `size` bytes from the card itself and compare them with the image."""
    changed = cards.still_the_same(job.card)
    if changed:
        return job.fail(changed)
    try:
        fd = os.open(job.card.path, os.O_RDONLY)
    except OSError as error:
        return job.fail(f"cannot read {job.card.path} back: {error.strerror}")
    try:
        fcntl.ioctl(fd, BLKFLSBUF)  # the kernel's cached pages would be read instead of the card
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        digest, left = hashlib.sha256(), size
        while left and (chunk := os.read(fd, min(CHUNK, left))):
            digest.update(chunk)
            left -= len(chunk)
    except OSError as error:
        return job.fail(f"reading {job.card.path} back failed: {error.strerror}")
    finally:
        os.close(fd)
    if left or digest.hexdigest() != expected:
        job.fail("read back, its bytes differ from the image's: the card or its reader is faulty")


# -- the seed and the record -----------------------------------------------------------------------


def card_fat(job: Job) -> targets.ImageFat:
    return targets.ImageFat(Path(job.card.path), targets.boot_partition(Path(job.card.path)))


def record_of(job: Job) -> dict | None:
    """The card's flash record, or None (never flashed by roslab, or not finished)."""
    try:
        text = card_fat(job).read(MARKER)
        return json.loads(text) if text else None
    except (targets.TargetError, OSError, ValueError):
        return None


def already_done(job: Job, image_sha256: str, files: dict) -> bool:
    """The card holds this image for this host with its seed: its record and seed say so."""
    record = record_of(job)
    if not record or record.get("host") != job.host.name or record.get("image_sha256") != image_sha256:
        return False
    fat = card_fat(job)
    return all(fat.read(name) == files[name].content for name in SEED_FILES)


def seed_card(job: Job, files: dict, image_sha256: str) -> None:
    """Write the host's seed into the card's system-boot, read it back, then the record."""
    try:
        targets.write_fat(Path(job.card.path), files)
        fat = card_fat(job)
        wrong = [name for name in SEED_FILES if fat.read(name) != files[name].content]
        if wrong:
            return job.fail(f"its seed read back wrong ({', '.join(wrong)})")
        record = {"host": job.host.name, "image_sha256": image_sha256,
                  "flashed": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        fat.write(MARKER, json.dumps(record).encode() + b"\n")
    except (targets.TargetError, OSError) as error:
        job.fail(f"its seed could not be written: {error}")


# -- the command ------------------------------------------------------------------------------------


def _plan(args: argparse.Namespace, image: cards.Image) -> tuple[list[Job], dict, Path]:
    """The jobs (host -> card), their seeds and the roster's path, all checked; _Stop otherwise."""
    classroom, hosts = _selected(args, "flash")
    wrong = [f"{host.name} is on Ubuntu {host.ubuntu_release}" for host in hosts
             if host.ubuntu_release and host.ubuntu_release != image.release]
    if wrong:
        raise _Stop(1, f"roslab flash: the image is Ubuntu {image.release} ({image.architecture}), but "
                       f"{'; '.join(wrong)}: nothing was written")
    allowed = (args.architecture,) if args.architecture else cards.PI_ARCHITECTURES
    if image.architecture not in allowed:
        what = "not a Raspberry Pi" if not args.architecture else f"not {args.architecture} (--architecture)"
        raise _Stop(1, f"roslab flash: the image is for {image.architecture}, {what}: nothing was written")
    _refuse_what_the_roster_cannot_say(hosts, classroom.path)
    seeds = _checked_seeds(hosts, classroom.path)  # before a teacher is asked for any card
    matched = _matched(args, hosts, image)
    found, problems = cards.cards([device for _, _, device in matched], image.size, args.allow_large)
    if problems:
        raise _Stop(1, *(f"roslab flash: {problem}" for problem in problems), "roslab flash: nothing was written")
    return [Job(host, card, slot=slot) for (host, slot, _), card in zip(matched, found)], seeds, classroom.path


def _matched(args: argparse.Namespace, hosts: list[Host], image: cards.Image) -> list[tuple[Host, str, str]]:
    """(host, reader slot or "", device) for each host to flash, as --device, --interactive or
    --by-slot match them (roslab.seed.matching); _Stop when they do not."""
    if args.by_slot:
        if args.device:
            raise _Stop(2, "roslab flash: --by-slot takes the cards from the reader slots: no --device with it")
        slots = matching.reader_slots(matching.by_path_links(), cards.lsblk(empty=True))
        return matching.by_slot(hosts, slots)
    if args.interactive:
        prompter = matching.Prompter(image.size, args.allow_large, set(args.device or []),
                                     ask=input, say=lambda line: print(line, flush=True), lsblk=cards.lsblk)
        try:
            matched = matching.interactive(hosts, prompter)
        except KeyboardInterrupt:
            raise _Stop(1, "\nroslab flash: stopped while asking for the cards: nothing was written") from None
        if not matched:
            raise _Stop(1, "roslab flash: no card was put in for any host: nothing was written")
        return [(host, "", device) for host, device in matched]
    if len(args.device or []) != len(hosts):
        raise _Stop(2, f"roslab flash: {len(hosts)} hosts ({', '.join(h.name for h in hosts)}) and "
                       f"{len(args.device or [])} --device cards: give one card per host, in the hosts' order "
                       "(or --interactive, or --by-slot)")
    return [(host, "", device) for host, device in zip(hosts, args.device)]


def _confirmed(jobs: list[Job], image: cards.Image, args: argparse.Namespace) -> bool:
    print(f"roslab flash: Ubuntu {image.release} {image.architecture} ({image.size / 1e6:,.0f} MB) to "
          f"{len(jobs)} cards; everything on them is lost:")
    for job in jobs:
        slot = f"  slot {job.slot}" if job.slot else ""
        print(f"  {job.host.name:<20} {job.card.path:<14} {job.card.label} ({job.card.size / 1e6:,.0f} MB){slot}")
    if args.yes:
        return True
    return input("Write these cards? [y/N] ").strip().lower() in ("y", "yes")


def table(jobs: list[Job]) -> str:
    """The final label table: host, device, card, result; with the reader's slot after the
    device when cards were matched by slot, so each card is labelled by where it sat."""
    slots = any(job.slot for job in jobs)
    rows = [("host", "device", *(("slot",) if slots else ()), "card", "result")] + [
        (job.host.name, job.card.path, *((job.slot,) if slots else ()), job.card.label,
         job.result + (f": {job.reason}" if job.reason else "")) for job in jobs]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join([*(cell.ljust(width) for cell, width in zip(row[:-1], widths)), row[-1]]).rstrip()
                     for row in rows)


def run_flash(args: argparse.Namespace) -> int:
    work = Path(tempfile.mkdtemp(prefix="roslab-flash-", dir=args.work_dir))
    try:
        return _flash(args, work)
    except _Stop as stop:
        print(stop, file=sys.stderr)
        return stop.status
    except cards.CardError as error:
        print(f"roslab flash: {error}; nothing was written", file=sys.stderr)
        return 1
    finally:
        for path in work.iterdir():
            path.unlink()
        work.rmdir()


def _flash(args: argparse.Namespace, work: Path) -> int:
    if args.image_sha256 and cards.file_sha256(Path(args.image)) != args.image_sha256.lower():
        raise _Stop(1, f"roslab flash: {args.image} is not the image --image-sha256 names: nothing was written")
    raw, image_sha256 = cards.raw_image(Path(args.image), work)
    image = cards.image_of(raw)
    jobs, seeds, roster = _plan(args, image)
    todo = []
    for job in jobs:
        if not args.force and already_done(job, image_sha256, seeds[job.host.name]):
            job.result, job.reason = "skipped", "already flashed for it with this image (--force writes it again)"
        else:
            todo.append(job)
    if todo and not _confirmed(todo, image, args):
        raise _Stop(1, "roslab flash: nothing was written")
    started = time.monotonic()
    if todo:
        write_all(image, todo, say=lambda line: print(line, file=sys.stderr, flush=True))
    for job in todo:
        if job.result != "FAILED":
            read_back(job, image.size, image_sha256)
        if job.result != "FAILED":
            seed_card(job, seeds[job.host.name], image_sha256)
        if job.result != "FAILED":
            job.result = "verified"
            _record_key(job.host, roster)
    print(table(jobs))
    failed = [job for job in jobs if job.result == "FAILED"]
    print(f"roslab flash: {len(jobs) - len(failed)} of {len(jobs)} cards ready "
          f"({len(todo)} written and verified in {time.monotonic() - started:.0f} s)")
    return 1 if failed else 0


def register(commands) -> None:
    flash = commands.add_parser(
        "flash", help="write a tray of SD cards at once: the image, each card's own seed, verified",
        description=__doc__.split("\n\n")[2].replace("\n", " "))
    add_roster_argument(flash, what=" (one card per selected host)")
    flash.add_argument("--image", required=True, metavar="IMG",
                       help="the Raspberry Pi preinstalled Ubuntu image (.img or .img.xz)")
    flash.add_argument("--image-sha256", metavar="HEX", help="the image file's sha256 (Ubuntu's SHA256SUMS)")
    flash.add_argument("--device", action="append", metavar="DEV",
                       help="a card: the whole device of a USB or MMC card reader (/dev/sdb), or a loop device; "
                            "repeat it, one per host, in the hosts' order (with --interactive: the only devices "
                            "a card may be found on)")
    how = flash.add_mutually_exclusive_group()
    how.add_argument("--interactive", action="store_true",
                     help="ask for each host's card in turn (\"insert the card for HOST\"): the one card put in "
                          "since the previous one is that host's")
    how.add_argument("--by-slot", action="store_true",
                     help="the card readers' slots (/dev/disk/by-path, in order) get the hosts in roster order")
    flash.add_argument("--architecture", choices=sorted(set(cards.ARCHITECTURES.values())),
                       help="the image's architecture, when it is not a Pi's (arm64, armhf): the sandbox's own "
                            "card image is amd64, as its hosts are (`roslab sandbox card-image`)")
    flash.add_argument("--allow-large", action="store_true",
                       help=f"write a device larger than {cards.MAX_CARD_BYTES / 1e9:.0f} GB")
    flash.add_argument("--force", action="store_true", help="write cards already flashed for their host")
    flash.add_argument("-y", "--yes", action="store_true", help="do not ask before writing")
    flash.add_argument("--work-dir", default=tempfile.gettempdir(), metavar="DIR",
                       help="where a .xz image is decompressed once (default: %(default)s)")
    flash.set_defaults(run=run_flash)
