"""controller_files.replace_file: the one atomic writer of the controller's own files (the class lock)."""

from __future__ import annotations

import os
import stat

import pytest

from roslab import controller_files


def test_a_file_is_replaced_whole_with_its_mode(tmp_path):
    path = tmp_path / "classroom.lock"
    path.write_text("old\n")
    controller_files.replace_file(path, "new\n")
    assert path.read_text() == "new\n" and stat.S_IMODE(path.stat().st_mode) == 0o644
    controller_files.replace_file(path, b"secret\n", mode=0o600)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert os.listdir(tmp_path) == ["classroom.lock"]  # no temporary file left beside it


def test_a_write_that_fails_leaves_the_old_file_whole_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "classroom.lock"
    path.write_text("groups: {}\n")

    def disk_full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(controller_files.os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        controller_files.replace_file(path, "groups: {jazzy-amd64: ...}\n")
    assert path.read_text() == "groups: {}\n" and os.listdir(tmp_path) == ["classroom.lock"]


def test_a_link_at_the_path_is_replaced_not_followed(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_text("someone else's file\n")
    path = tmp_path / "classroom.lock"
    path.symlink_to(elsewhere)
    controller_files.replace_file(path, "lock\n")
    assert not path.is_symlink() and path.read_text() == "lock\n"
    assert elsewhere.read_text() == "someone else's file\n"
