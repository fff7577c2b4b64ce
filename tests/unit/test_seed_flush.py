"""`roslab seed --boot-partition` flushes the files it wrote, not the whole machine (issue 41).

It called os.sync() (Python has no os.syncfs): every filesystem of the controller was flushed,
and on a machine busy writing elsewhere (sandbox builds) one seed waited 102 s here, 262 s in CI.
"""

from __future__ import annotations

import os

from roslab.seed import targets
from roslab.seed.documents import SeedFile


def test_the_written_files_and_their_folder_are_fsynced_and_nothing_else(tmp_path, monkeypatch):
    boot = tmp_path / "system-boot"
    boot.mkdir()
    for name, text in {"config.txt": "arm_64bit=1\n", "cmdline.txt": "console=tty1\n",
                       "user-data": "#cloud-config\nubuntu\n"}.items():
        (boot / name).write_text(text)
    flushed = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "sync", lambda: flushed.append("the whole machine"))
    monkeypatch.setattr(os, "fsync", lambda fd: flushed.append(os.readlink(f"/proc/self/fd/{fd}")) or real_fsync(fd))
    files = {name: SeedFile(name, f"{name} of team1-main\n".encode(), secret=False) for name in targets.SEED_FILES}
    assert sorted(targets.write_boot_partition(boot, files)) == sorted(targets.SEED_FILES)
    assert "the whole machine" not in flushed
    assert set(flushed) == {str(boot), *(str(boot / name) for name in targets.SEED_FILES),
                            str(boot / ("user-data" + targets.BACKUP_SUFFIX))}
    flushed.clear()
    assert targets.write_boot_partition(boot, files) == []  # unchanged: nothing to flush
    assert flushed == []
