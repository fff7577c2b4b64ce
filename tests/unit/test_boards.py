"""The board records (roslab/boards.py): every consumer reads them, so a new board is one record."""

from __future__ import annotations

import dataclasses

import pytest

from roslab import boards, settings
from roslab.profiles import schema
from roslab.ros import distro as distros


def test_a_release_before_a_boards_first_image_is_refused_naming_what_to_use():
    assert boards.release_problem("pi5", "22.04") == (
        "there is no Ubuntu 22.04 image for a Raspberry Pi 5 (its first is 24.04): use ubuntu_release 24.04 "
        "(jazzy), or another board for Humble")


@pytest.mark.parametrize("board", [None, "pc", "pi4", "pi3b+", "pi5"])
def test_every_release_from_a_boards_first_image_on_is_accepted(board):
    first = boards.BY_NAME[board].first_release if board else None
    for platform in distros.PLATFORMS:
        if first is None or tuple(map(int, platform.release.split("."))) >= tuple(map(int, first.split("."))):
            assert boards.release_problem(board, platform.release) is None, (board, platform.release)


def test_a_new_board_record_needs_no_other_code(monkeypatch):
    """A made-up board whose first image is 26.04: refused on 24.04 by the same check, no code edit."""
    made_up = boards.Board("pi6", "Raspberry Pi 6", raspberry_pi=True, first_release="26.04")
    monkeypatch.setitem(boards.BY_NAME, "pi6", made_up)
    assert boards.release_problem("pi6", "24.04").startswith(
        "there is no Ubuntu 24.04 image for a Raspberry Pi 6 (its first is 26.04)")
    assert boards.release_problem("pi6", "26.04") is None


def test_the_setting_the_profiles_and_the_docs_take_their_boards_from_the_records():
    assert settings.SETTINGS["board"].check("pi4") is None and settings.SETTINGS["board"].check("pi6")
    assert schema.BOARDS == boards.NAMES == tuple(board.name for board in boards.BOARDS)
    assert boards.in_words() in settings.SETTINGS["board"].doc
    assert all(dataclasses.is_dataclass(board) for board in boards.BOARDS)
