"""Taking a sandbox host's cgroup down: killed processes are waited for, bounded.

A fake cgroup tree (a directory with `cgroup.procs`) stands in for the host's; the pid in it
is never signalled for real (os.kill is replaced) and the clock runs a second per look.
"""

from __future__ import annotations

import errno
import os

import pytest

from roslab.sandbox import hosts
from roslab.sandbox.system import SandboxError

PID = 999_999_991  # above any real pid_max: never a real process


@pytest.fixture()
def cgroup(tmp_path, monkeypatch):
    tree = tmp_path / "roslab" / "class1"
    tree.mkdir(parents=True)
    (tree / "cgroup.procs").write_text(f"{PID}\n")
    killed = []
    monkeypatch.setattr(hosts.os, "kill", lambda pid, sig: killed.append(pid))
    monkeypatch.setattr(hosts.time, "sleep", lambda seconds: None)
    clock = iter(range(10_000))  # each look at the clock is a second later
    monkeypatch.setattr(hosts.time, "monotonic", lambda: next(clock))
    # rmdir of a real cgroup ignores its control files; a plain directory needs them gone first.
    real_rmdir = os.rmdir

    def rmdir(path):
        if (tree / "cgroup.procs").read_text().strip():
            raise OSError(errno.EBUSY, "Device or resource busy", str(path))
        (tree / "cgroup.procs").unlink(missing_ok=True)
        real_rmdir(path)

    monkeypatch.setattr(hosts.os, "rmdir", rmdir)
    return tree, killed


def test_a_process_that_still_runs_after_sigkill_is_an_error_naming_it(cgroup, monkeypatch):
    tree, killed = cgroup
    monkeypatch.setattr(hosts, "_is_dying", lambda pid: False)
    with pytest.raises(SandboxError, match=rf"processes \[{PID}\] in .*class1 survived SIGKILL"):
        hosts.kill_cgroup_trees([tree], timeout=3)
    assert set(killed) == {PID}


def test_a_zombie_still_freeing_its_files_is_left_to_the_kernel_with_its_cgroup(cgroup, monkeypatch, caplog):
    tree, _ = cgroup
    monkeypatch.setattr(hosts, "_is_dying", lambda pid: True)
    hosts.kill_cgroup_trees([tree], timeout=0)
    assert tree.is_dir(), "the busy cgroup stays for the kernel to empty"
    assert f"[{PID}]" in caplog.text and "zombies" in caplog.text


def test_an_emptied_cgroup_is_removed(cgroup):
    tree, killed = cgroup
    (tree / "cgroup.procs").write_text("")
    hosts.kill_cgroup_trees([tree], timeout=0)
    assert not tree.exists() and killed == []


def test_a_pid_that_is_gone_counts_as_exited():
    assert hosts._is_dying(PID)
    assert not hosts._is_dying(os.getpid())


STATUS = "Name:\tdpkg\nState:\t{state}\nSigQ:\t1/95000\nSigPnd:\t{pending}\nShdPnd:\t{shared}\n"


@pytest.mark.parametrize("state, pending, shared, dying", [
    ("Z (zombie)", "0000000000000000", "0000000000000000", True),
    ("D (disk sleep)", "0000000000000000", "0000000000000100", True),  # SIGKILL pending, waiting on the disk
    ("D (disk sleep)", "0000000000000100", "0000000000000000", True),
    ("D (disk sleep)", "0000000000000000", "0000000000004000", False),  # SIGTERM only: may still run on
    ("R (running)", "0000000000000000", "0000000000000100", False),  # on a CPU: not waiting on the kernel
    ("S (sleeping)", "0000000000000000", "0000000000000000", False),
])
def test_a_process_waiting_on_the_disk_with_sigkill_pending_counts_as_dying(state, pending, shared, dying):
    assert hosts.status_is_dying(STATUS.format(state=state, pending=pending, shared=shared)) is dying


# Removing a host's files: gone at once, deleted in the background --------------------------

def test_a_discarded_tree_is_gone_at_once_and_deleted_in_the_background(tmp_path):
    import time

    from roslab.sandbox import system

    root = tmp_path / "sandbox"
    upper = root / "class1" / "hosts" / "team1-main" / "upper"
    for index in range(2000):  # a converged host's upper dir: many files (tens of thousands)
        (upper / f"d{index % 20}").mkdir(parents=True, exist_ok=True)
        (upper / f"d{index % 20}" / f"f{index}").write_bytes(b"x" * 64)
    (upper / "locked").mkdir()
    (upper / "locked" / "file").write_text("root deletes what it cannot read")
    (upper / "locked").chmod(0o000)

    started = time.monotonic()
    system.discard(upper, root)
    assert time.monotonic() - started < 2  # one rename and a detached rm: not a delete
    assert not upper.exists() and upper.parent.is_dir()  # the host's other directories stay

    deadline = time.monotonic() + 60
    while any((root / system.DISCARDED_DIR).iterdir()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert list((root / system.DISCARDED_DIR).iterdir()) == []
    assert sorted(path.name for path in root.iterdir()) == [system.DISCARDED_DIR, "class1"]


def test_a_delete_cut_short_is_finished_by_the_next_sweep(tmp_path):
    import time

    from roslab.sandbox import system

    root = tmp_path / "sandbox"
    left = root / system.DISCARDED_DIR / "class1-123-456" / "hosts"
    left.mkdir(parents=True)
    (left / "file").write_text("x")
    system.discard(root / "nothing-here", root)  # nothing to discard: nothing happens
    system.sweep_discarded(root)
    deadline = time.monotonic() + 30
    while (root / system.DISCARDED_DIR / "class1-123-456").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not (root / system.DISCARDED_DIR / "class1-123-456").exists()

