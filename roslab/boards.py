"""One record per board a host can be (the roster's `board`): the single source of what a board means.

Like the release records (roslab.ros.distro), each `Board` holds what roslab needs to know about
one kind of computer: the roster's name for it, what a teacher calls it, whether it is a Raspberry
Pi (it has a boot partition with config.txt and cmdline.txt, which profiles change), and the first
Ubuntu LTS with a preinstalled image for it. The setting's allowed values, the profiles' `boards:`,
the roster's release check, the sandbox's boot partition stand-ins and the docs' table all read
these records; adding a board is one `Board(...)` below.
"""

from __future__ import annotations

from dataclasses import dataclass

from roslab.ros import distro as distros


@dataclass(frozen=True)
class Board:
    """A kind of computer a classroom's host can be."""

    name: str  # the roster's value: "pi4"
    title: str  # what a teacher calls it: "Raspberry Pi 4"
    raspberry_pi: bool  # a boot partition with config.txt and cmdline.txt (/boot/firmware)
    # The first Ubuntu LTS with an image for it; None: any release roslab knows.
    first_release: str | None = None


BOARDS: tuple[Board, ...] = (
    Board("pi3b+", "Raspberry Pi 3 Model B+", raspberry_pi=True),
    Board("pi4", "Raspberry Pi 4", raspberry_pi=True),
    # Ubuntu's first image for a Pi 5 is 23.10; no 22.04 image exists (field-facts.md: seed 000).
    Board("pi5", "Raspberry Pi 5", raspberry_pi=True, first_release="24.04"),
    Board("pc", "a PC (amd64 or arm64, not a Pi)", raspberry_pi=False),
)

BY_NAME: dict[str, Board] = {board.name: board for board in BOARDS}
NAMES: tuple[str, ...] = tuple(board.name for board in BOARDS)
PI_NAMES: tuple[str, ...] = tuple(board.name for board in BOARDS if board.raspberry_pi)


def in_words(names: tuple[str, ...] = NAMES) -> str:
    """"pi3b+, pi4, pi5 or pc": a list of board names as a sentence says it."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def release_problem(board: str | None, release: str) -> str | None:
    """Why an Ubuntu `release` ("22.04") cannot run on `board`, or None (also for a board not said)."""
    record = BY_NAME.get(board or "")
    if record is None or record.first_release is None or _key(release) >= _key(record.first_release):
        return None
    first = distros.BY_RELEASE.get(record.first_release)
    here = distros.BY_RELEASE.get(release)
    with_distro = f" ({first.distro})" if first else ""
    other = f"another board for {here.distro.capitalize()}" if here else "another board"
    return (f"there is no Ubuntu {release} image for a {record.title} (its first is {record.first_release}): "
            f"use ubuntu_release {record.first_release}{with_distro}, or {other}")


def _key(release: str) -> tuple[int, ...]:
    return tuple(int(part) for part in release.split("."))
