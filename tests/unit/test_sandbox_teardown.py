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
    monkeypatch.setattr(hosts, "_is_zombie", lambda pid: False)
    with pytest.raises(SandboxError, match=rf"processes \[{PID}\] in .*class1 survived SIGKILL"):
        hosts.kill_cgroup_trees([tree], timeout=3)
    assert set(killed) == {PID}


def test_a_zombie_still_freeing_its_files_is_left_to_the_kernel_with_its_cgroup(cgroup, monkeypatch, caplog):
    tree, _ = cgroup
    monkeypatch.setattr(hosts, "_is_zombie", lambda pid: True)
    hosts.kill_cgroup_trees([tree], timeout=0)
    assert tree.is_dir(), "the busy cgroup stays for the kernel to empty"
    assert f"[{PID}]" in caplog.text and "zombies" in caplog.text


def test_an_emptied_cgroup_is_removed(cgroup):
    tree, killed = cgroup
    (tree / "cgroup.procs").write_text("")
    hosts.kill_cgroup_trees([tree], timeout=0)
    assert not tree.exists() and killed == []


def test_a_pid_that_is_gone_counts_as_exited():
    assert hosts._is_zombie(PID)
    assert not hosts._is_zombie(os.getpid())
