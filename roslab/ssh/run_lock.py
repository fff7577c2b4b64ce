"""One roslab run at a time on a host: two teachers (or a cron run and a hand run) never interleave.

`install()` makes every SSH connection pyinfra opens for a run (deploy.py) take the host's run
lock before anything is read or changed: as root, `flock` on LOCK_FILE under /run/roslab (a
tmpfs: no lock survives a reboot). The lock is held by a small process on the host that lives
as long as the SSH session of the connection (it waits for that session's sshd process to
end), so a controller that is killed, or loses the network, never leaves a stale lock: its
session ends and the lock goes with it within seconds.

A run that finds the lock taken says who holds it (the other run's controller host, user, pid
and start time, from OWNER_FILE) and waits up to `run_lock_wait` seconds; then it stops that
host with the same words (the other hosts carry on). A session can outlive its run when the host
moved address mid-change (the end of the connection never reaches it): a run of the same
controller whose pid is gone has its holder (run.holder) ended instead of waited for, and so
has the previous run of this controller whose session is still ending (a run straight after
another): neither is another run, so neither is announced as one.
"""

from __future__ import annotations

import getpass
import os
import re
import shlex
import socket
from datetime import datetime, timezone

LOCK_DIR = "/run/roslab"
LOCK_FILE = "run.lock"
OWNER_FILE = "run.owner"
# How often the holder looks whether its SSH session still exists (s).
HOLDER_POLL = 2

# $1 the folder, $2 the seconds to wait, $3 this run's who/when/where. Prints `waiting <owner>`
# when the lock is taken, then `locked`, or `held <owner>` and exits 4 when the wait ran out.
# The holder finds the session's sshd (sshd, or sshd-session on newer OpenSSH) among its
# ancestors and keeps the lock (fd 9) until that process is gone.
HOLD_SCRIPT = r"""
dir=$1; wait=$2; who=$3; stale=$4
mkdir -p "$dir" && chmod 755 "$dir" || exit 3
exec 9>>"$dir/run.lock" || exit 3
owner() { tr -d '\n' < "$dir/run.owner" 2>/dev/null || echo 'an unknown run'; }
pid=$$; session=
while [ "$pid" -gt 1 ] 2>/dev/null; do
  case "$(cat /proc/$pid/comm 2>/dev/null)" in sshd*) session=$pid; break;; esac
  pid=$(awk '/^PPid:/ {print $2}' /proc/$pid/status 2>/dev/null)
done
hold() { [ -z "$session" ] || { (trap '' HUP; "$@" && while kill -0 "$session" 2>/dev/null; do sleep POLL; done) \
  </dev/null >/dev/null 2>&1 & echo $! > "$dir/run.holder"; }; }
if ! flock -n 9; then
  if [ "$(owner)" = "$who" ]; then
    # this run's earlier session (the network step reconnects before it closes the old one):
    # this session takes the lock over as soon as that one ends
    hold flock 9; echo locked; exit 0
  fi
  # a run its controller knows is gone (killed) whose session outlived it (its host moved address)
  # (not another run: nothing to say while its holder lets go)
  if [ -n "$stale" ] && [ "$(owner)" = "$stale" ]; then kill "$(cat "$dir/run.holder")" 2>/dev/null
  else echo "waiting $(owner)"; fi
  flock -w "$wait" 9 || { echo "held $(owner)"; exit 4; }
fi
printf '%s\n' "$who" > "$dir/run.owner.$$" && mv -f "$dir/run.owner.$$" "$dir/run.owner"
hold true
echo locked
""".replace("POLL", str(HOLDER_POLL))


class RunLockHeld(Exception):
    """Another run held the host's lock for longer than this run would wait."""


def this_run() -> str:
    """Who/when/where of this run, as the other run's message names it."""
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    return (f"a roslab run from controller {socket.gethostname()} (user {getpass.getuser()}, pid {os.getpid()}, "
            f"started {started})")


def hold_command(wait: int, who: str, directory: str = LOCK_DIR, stale: str = "") -> str:
    """The shell command that takes the run lock in `directory` (run as root) and keeps it for
    the SSH session it runs in; `stale`: an owner known gone, whose holder it ends first."""
    return (f"sh -c {shlex.quote(HOLD_SCRIPT)} roslab-run-lock {shlex.quote(directory)} {int(wait)} "
            f"{shlex.quote(who)} {shlex.quote(stale)}")


_OWNER = re.compile(r"a roslab run from controller (\S+) \(user .*, pid ([0-9]+), started ")


def gone(owner: str, controller: str | None = None, alive=None) -> bool:
    """Whether `owner` (the run.owner line) names a run of this controller whose process has
    ended (killed): its session may outlive it when its host moved address mid-change."""
    match = _OWNER.match(owner)
    if match is None or match.group(1) != (controller or socket.gethostname()):
        return False
    pid = int(match.group(2))
    if alive is not None:
        return not alive(pid)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def outcome(lines: list[str], wait: int) -> tuple[bool, str | None]:
    """(locked, the line to say) from the command's output: the other run while waiting, or why
    this host stops."""
    waited = next((line.removeprefix("waiting ") for line in lines if line.startswith("waiting ")), None)
    if any(line.strip() == "locked" for line in lines):
        return True, (f"waited for {waited} to end" if waited else None)
    held = next((line.removeprefix("held ") for line in lines if line.startswith("held ")), None)
    if held:
        return False, (f"another roslab run holds this host: {held}; waited {wait} s (run_lock_wait), "
                       "nothing was changed on it; run again when it has ended")
    return False, "could not take the host's run lock in /run/roslab (sudo, flock): nothing was changed on it"


def lock_problem(connector, who: str, wait: int) -> str | None:
    """Take the run lock of `connector`'s host over its connection, waiting up to `wait` seconds
    (its run_lock_wait); why the host must stop (another run held it longer), else None."""
    from pyinfra import logger
    from pyinfra.api import StringCommand

    host = connector.host
    arguments = {"_sudo": True}
    if host.data.get("_sudo_password"):
        arguments["_sudo_password"] = host.data.get("_sudo_password")
    _, output = connector.run_shell_command(StringCommand(hold_command(0, who)), **arguments)
    lines = list(output.stdout_lines)
    held = next((line.removeprefix("held ") for line in lines if line.startswith("held ")), None)
    if held is not None and wait > 0:  # busy: end a gone run's holder, else wait for the other run
        stale = held if gone(held) else ""
        _, output = connector.run_shell_command(StringCommand(hold_command(wait, who, stale=stale)), **arguments)
        lines = list(output.stdout_lines)
    locked, said = outcome(lines, wait)
    if not locked:
        # the lock is the first thing a run does as root: a wrong sudo password shows here first
        from roslab.ssh.sudo import sudo_refusal
        return sudo_refusal(host, output.stderr_lines) or said
    connector.roslab_run_locked = wait  # its reconnections take the lock again
    if said:
        logger.warning(f"{host.print_prefix}roslab: {said}")
    return None


_WHO: list[str] = []


def run_lock_problem(host, wait: int) -> str | None:
    """Take `host`'s run lock for this run (deploy/common.py's supported_host, before anything
    is read), waiting up to `wait` seconds (its run_lock_wait): why the host stops, or None.
    Only SSH connections have a session to hold it."""
    from pyinfra.connectors.ssh import SSHConnector

    connector = host.connector
    if not isinstance(connector, SSHConnector) or getattr(connector, "client", None) is None:
        return None  # no SSH session (another connector, or none open) to hold it
    if not _WHO:
        _WHO.append(this_run())
    return lock_problem(connector, _WHO[0], wait)


def install() -> None:
    """Make every later connection of a host whose run lock this run holds (the network step
    reconnects at the new address) take it again on the new SSH session. Idempotent."""
    from pyinfra.api.exceptions import ConnectError
    from pyinfra.connectors.ssh import SSHConnector

    if getattr(SSHConnector.connect, "roslab_run_lock", False):
        return
    connect = SSHConnector.connect

    def connect_locked(self, *args, **kwargs):
        result = connect(self, *args, **kwargs)
        wait = getattr(self, "roslab_run_locked", None)
        if wait is not None:
            problem = lock_problem(self, _WHO[0] if _WHO else this_run(), wait)
            if problem:
                self.disconnect()
                raise ConnectError(f"roslab stops this host: {problem}")
        return result

    connect_locked.roslab_run_lock = True  # type: ignore[attr-defined]  # the patch's marker (getattr above)
    SSHConnector.connect = connect_locked  # type: ignore[method-assign]  # roslab patches pyinfra here on purpose
