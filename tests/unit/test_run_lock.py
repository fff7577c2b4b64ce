"""The host's run lock (roslab/ssh/run_lock.py): its shell script run here, on this machine's
sh and flock, in a temporary folder instead of /run/roslab (no sudo: the test owns the folder)."""

from __future__ import annotations

import fcntl
import shutil
import subprocess
import threading
import time

from roslab.ssh.run_lock import hold_command, outcome, this_run

OTHER = "a roslab run from controller teacher-2 (user anna, pid 4242, started 2026-11-28 17:00:00 UTC)"


def run(tmp_path, wait: int, shell: str = "sh") -> subprocess.CompletedProcess:
    return subprocess.run([shell, "-c", hold_command(wait, this_run(), str(tmp_path))],
                          capture_output=True, text=True, timeout=30)


def held_by_other(tmp_path):
    (tmp_path / "run.owner").write_text(OTHER + "\n")
    handle = open(tmp_path / "run.lock", "a")
    fcntl.flock(handle, fcntl.LOCK_EX)
    return handle


def test_a_free_host_is_locked_and_records_who_when_where(tmp_path):
    done = run(tmp_path, 5)
    assert outcome(done.stdout.splitlines(), 5) == (True, None), done
    owner = (tmp_path / "run.owner").read_text()
    assert owner.startswith("a roslab run from controller ") and " pid " in owner and "started 20" in owner


def test_a_second_run_waits_then_stops_that_host_naming_the_other_run(tmp_path):
    handle = held_by_other(tmp_path)
    try:
        done = run(tmp_path, 1)
    finally:
        handle.close()
    assert done.returncode == 4
    locked, said = outcome(done.stdout.splitlines(), 1)
    assert not locked
    assert said == (f"another roslab run holds this host: {OTHER}; waited 1 s (run_lock_wait), nothing was "
                    "changed on it; run again when it has ended")


def test_a_second_run_that_waits_long_enough_goes_on_and_says_whom_it_waited_for(tmp_path):
    handle = held_by_other(tmp_path)
    threading.Timer(0.5, handle.close).start()
    done = run(tmp_path, 10)
    assert outcome(done.stdout.splitlines(), 10) == (True, f"waited for {OTHER} to end")


def test_a_second_session_of_the_same_run_goes_on_at_once(tmp_path):
    who = this_run()
    (tmp_path / "run.owner").write_text(who + "\n")
    handle = open(tmp_path / "run.lock", "a")
    fcntl.flock(handle, fcntl.LOCK_EX)  # this run's first session, still open
    try:
        done = subprocess.run(["sh", "-c", hold_command(600, who, str(tmp_path))], capture_output=True, text=True,
                              timeout=10)
    finally:
        handle.close()
    assert outcome(done.stdout.splitlines(), 600) == (True, None), done


def test_the_lock_lives_as_long_as_the_ssh_session_and_no_longer(tmp_path):
    # A stand-in for sshd's session process: a copy of sh named sshd, the ancestor the holder looks for.
    session = tmp_path / "bin" / "sshd"
    session.parent.mkdir()
    shutil.copy(shutil.which("sh"), session)
    folder = tmp_path / "lock"
    started = subprocess.Popen([str(session), "-c", hold_command(5, this_run(), str(folder)) + "; sleep 1.5"],
                               stdout=subprocess.PIPE, text=True)
    assert started.stdout.readline().strip() == "locked"
    with open(folder / "run.lock", "a") as probe:
        try:
            fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
            raise AssertionError("the lock was free while its session lived")
        except BlockingIOError:
            pass
        started.wait(timeout=10)  # the session ends (a killed controller's connection)
        deadline = time.monotonic() + 4
        while True:
            try:
                fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                assert time.monotonic() < deadline, "the lock outlived its session"
                time.sleep(0.1)


def test_two_runs_write_a_record_through_different_temporary_names():
    import sys

    from roslab.ops.files import RUN_MARK, run_temporary

    other = subprocess.run([sys.executable, "-c", "from roslab.ops.files import RUN_MARK; print(RUN_MARK)"],
                           capture_output=True, text=True, check=True).stdout.strip()
    assert other and other != RUN_MARK
    assert run_temporary("/var/lib/roslab/profile.json") == f"/var/lib/roslab/profile.json.roslab-new-{RUN_MARK}"


def test_a_killed_runs_session_that_outlived_it_is_ended_and_the_lock_taken(tmp_path):
    import socket
    import sys

    from roslab.ssh.run_lock import gone

    dead = subprocess.Popen(["true"])
    dead.wait()
    owner = (f"a roslab run from controller {socket.gethostname()} (user anna, pid {dead.pid}, "
             "started 2026-11-28 17:00:00 UTC)")
    assert gone(owner) and not gone(OTHER) and not gone(owner.replace(f"pid {dead.pid}", "pid 1"))
    (tmp_path / "run.owner").write_text(owner + "\n")
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'a'); "
                               "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
                               str(tmp_path / "run.lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        (tmp_path / "run.holder").write_text(f"{holder.pid}\n")
        done = subprocess.run(["sh", "-c", hold_command(10, this_run(), str(tmp_path), stale=owner)],
                              capture_output=True, text=True, timeout=20)
    finally:
        holder.kill()
        holder.wait()
    # the run it waited for has ended already: nothing to tell the teacher (a run straight after
    # another of this controller meets its session still ending, the same way)
    assert outcome(done.stdout.splitlines(), 10) == (True, None), done


class SudoRefusingConnector:
    """A connection whose sudo refuses the roster's password: the run lock is its first root command."""

    def __init__(self, secret: str | None):
        from pyinfra.api.host import HostData

        data = {"sudo_password_secret": secret, "_sudo_password": "Wrong-Pass-19"} if secret else {}
        self.host = type("Host", (), {"data": HostData("team1-main", data), "print_prefix": ""})()

    def run_shell_command(self, command, **arguments):
        from pyinfra.connectors.util import CommandOutput, OutputLine

        assert arguments.get("_sudo") is True
        return False, CommandOutput([OutputLine("stderr", "Sorry, try again."),
                                     OutputLine("stderr", "sudo: 3 incorrect password attempts")])


def test_a_wrong_sudo_password_is_named_as_such_not_as_a_lock_problem():
    from roslab.ssh.run_lock import lock_problem

    assert lock_problem(SudoRefusingConnector("lab_sudo"), this_run(), 600) == (
        "sudo refused the password from the roster's sudo_password_secret: the secret it names does not hold "
        "this host's sudo password (sudo: 3 incorrect password attempts)")
    assert lock_problem(SudoRefusingConnector(None), this_run(), 600) == (
        "sudo asks for a password and the roster sets no sudo_password_secret for this host "
        "(sudo: 3 incorrect password attempts)")
