"""The run summary a teacher reads at the end of `pyinfra inventories/lab.py deploy.py`.

pyinfra's own output ends with a table of operations; a host that failed shows up in it
as a count, and in the log as "Error: executed 0 commands" somewhere above. This module
prints, last of all (real run or --dry), one line per host: `ok`, `changed` or `failed`,
and for a failed host the step (the operation, or the deploy that stopped it) and one
line of why. Then the exit code pyinfra gives and the counts:

    --> roslab summary
        team1-main   changed
        team1-robot  failed   in "ROS 2 is installed ... | Ensure ROS 2 ...": E: Unable to locate package foo
        exit code 1: 1 failed, 1 changed, 0 ok (2 hosts)

How it hears about the run:

- `RunSummary` is a pyinfra state callback handler (`BaseStateCallback`). deploy.py
  registers it with `install()`, once per run although pyinfra executes deploy.py once
  per host. Its callbacks note which operation failed on which host; the operation's
  output is read at the end (pyinfra completes an operation's result only after
  `operation_host_error` has fired).
- `record_stop(host, message)` is called by `deploy.common.stop_host`: a host roslab
  stops while planning fails without any operation failing.
- A logging handler on pyinfra's logger keeps each host's warning and error lines
  (pyinfra prefixes them with `[host]`), for failures no callback carries: a command
  timeout, an SSH error, a fact that could not load, an exception in a Python step.
- The summary is printed at interpreter exit (`atexit`, CLI runs only), after pyinfra
  has disconnected and printed its own error, so it is the last thing on screen.
  The network deploy reconnects hosts mid-run, so "the last host disconnected" is no
  end-of-run signal.

A real run (not --dry) also records each host's outcome and time on the controller, in
`<roster dir>/.roslab-state/runs.yaml` (`roslab.reporting.runs`), for `roslab status`; nothing is
written onto the hosts.

It never prints host data: only host names, operation and deploy names, and lines
pyinfra already logged. Secrets (`HiddenValue`s such as `roslab.secrets.Secret`, and
password keys) are masked in every line all the same, in case a command echoed one.
"""

from __future__ import annotations

import atexit
import logging
import os
import re
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, TextIO

import gevent
import pyinfra
from pyinfra.api import HiddenValue
from pyinfra.api.state import BaseStateCallback, State, StateStage
from pyinfra.context import ctx_host, ctx_state

from roslab.ssh import identity
from roslab.ssh.sudo import sudo_refusal
from roslab.ros import colcon_progress
from roslab.connections import connection_lost
from roslab.reporting.runs import HostRun, record_runs

OK, CHANGED, FAILED, PLANNED, NOT_RUN = "ok", "changed", "failed", "planned", "not run"
INTERRUPTED = "interrupted"  # the run was stopped (Ctrl-C, SIGTERM) before the host's last step
# The exit codes of a run stopped by a signal, as a shell reports them (128 + the signal).
SIGNAL_EXITS = {signal.SIGINT: 130, signal.SIGTERM: 143}
SIGNAL_NAMES = {signal.SIGINT: "SIGINT (Ctrl-C)", signal.SIGTERM: "SIGTERM"}
NO_STDIN = ("pyinfra asked a question (a confirmation, or a password) but standard input is closed "
            "(cron, CI, no terminal): nothing more was executed; run with -y to apply without asking, "
            "or --dry to preview")
MASK = "***"
MAX_REASON = 240  # characters of a reason kept on its one line
MAX_LOG_LINES = 200  # warning/error lines kept per host (the latest)

STOP_PREFIX = "roslab stops this host: "
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
_PREFIXED = re.compile(r"^\s*\[([^\]\s]+)\]\s*(?:nested\s+)?(.*)$")
# `where()` in deploy.common and the network deploy start a stop message with the host,
# which the summary's own host column already shows.
_WHERE = re.compile(r"^host \S+(?: \(team [^)]*\))?: ")
# pyinfra's own lines that say only that something failed.
_GENERIC = re.compile(r"^Error(?: \(ignored[^)]*\))?(?::\s*(?:executed \d+ commands.*)?)?$")
_PYINFRA_ERROR = re.compile(r"^Error(?: \(ignored[^)]*\))?: ")
_ROSLAB = re.compile(r"^roslab\b")
_APT_ERROR = re.compile(r"^E: ")
_EXCEPTION = re.compile(r"^[\w.]+(?:Error|Exception)\b:?")
_ERROR_WORDS = re.compile(
    r"(?i)\b(?:error|errors|failed|failure|fatal|denied|not found|no such|unable|cannot|"
    r"can't|could not|couldn't|timed out|refused|unreachable|invalid|missing)\b"
)


def one_line(text: str) -> str:
    """`text` without colour codes, on one line with single spaces, cut to MAX_REASON."""
    text = " ".join(_ANSI.sub("", str(text)).split())
    if len(text) > MAX_REASON:
        text = text[: MAX_REASON - 3].rstrip() + "..."
    return text


def stop_reason(message: str) -> str:
    """The first line of a `stop_host` message, without the host it names."""
    lines = [line for line in _ANSI.sub("", str(message)).splitlines() if line.strip()]
    first = lines[0].strip() if lines else ""
    if first.startswith(STOP_PREFIX):
        first = first[len(STOP_PREFIX):]
    return _WHERE.sub("", first)


def most_useful_line(lines: Iterable[str]) -> str | None:
    """The line of a failure's output that says most about why, or None.

    In order: roslab's stop message, another roslab report, apt's `E:` line, an exception,
    the first line with an error word, the last line; pyinfra's own "Error: ..." lines
    only when nothing else is there, and never "Error: executed 0 commands".
    """
    cleaned = [one_line(line) for line in lines]
    cleaned = [line for line in cleaned if line and not _GENERIC.match(line)]
    for line in cleaned:
        if line.startswith(STOP_PREFIX):
            return stop_reason(line)
    own = [line for line in cleaned if not _PYINFRA_ERROR.match(line)]
    for pattern in (_ROSLAB, _APT_ERROR, _EXCEPTION, _ERROR_WORDS):
        for line in own:
            if pattern.search(line):
                return line
    if own:
        return own[-1]
    return cleaned[0] if cleaned else None


@dataclass
class LogLine:
    level: int
    text: str
    op_hash: str | None = None  # the operation executing on the host when it was logged
    step: str | None = None  # the deploy planning on the host when it was logged


NO_ERROR_PRINTED = "the operation failed without printing an error"
# pyinfra's words for a command whose connection broke (api/util.py log_host_command_error)
_SOCKET_ERROR = re.compile(r"Command socket/SSH error|Socket is closed|EOFError|Connection reset", re.ASCII)
LOST_CONNECTION = ("lost the connection to the host during this step (it stopped answering: powered off, "
                   "rebooted or off the network); run roslab again once it is back")


def connection_of(host):
    """The SSH connection (paramiko's transport) pyinfra reaches `host` over now, or None."""
    client = getattr(getattr(host, "connector", None), "client", None)
    try:
        return client.get_transport() if client is not None else None
    except Exception:  # noqa: BLE001 - a half-closed client: nothing more to learn
        return None


# How long the summary waits for a host to answer on the connection its step failed on.
ANSWER_WITHIN = 3.0


def closed_by_the_host(connection) -> bool:
    """Whether `connection` ended because its host went away. A host killed mid-command may end
    the command a moment before its connection (its processes die one by one), so the step's
    failure alone cannot tell; the summary asks again: a connection that ended keeps the end of
    file or socket error that stopped it (one the controller closed keeps none), and one still
    open must carry an answer from the host (sshd answers a keepalive request at once) within
    ANSWER_WITHIN seconds."""
    if connection is None:
        return False
    try:
        if not connection.is_active():
            return isinstance(getattr(connection, "saved_exception", None), (EOFError, OSError))
        with gevent.Timeout(ANSWER_WITHIN):
            connection.global_request("keepalive@openssh.com", wait=True)
        return not connection.is_active()
    except gevent.Timeout:
        return True  # connected, and silent: the host stopped answering
    except (EOFError, OSError):
        return True  # the keepalive met the connection's end: the host went as it was asked
    except Exception:  # noqa: BLE001 - nothing more to learn
        return False


def pending_network_change(host) -> str | None:
    """The network change the controller started on `host` and did not see end, in words, or None."""
    from roslab.network import state as network_state

    roster_path = (getattr(host, "data", None) or {}).get("roslab_roster_path")
    if not roster_path:
        return None
    entry = network_state.pending_changes(roster_path).get(host.name)
    return network_state.pending_description(entry) if entry else None


@dataclass
class HostEvents:
    error_ops: list[str] = field(default_factory=list)  # op hashes, in the order they failed
    stop: tuple[str, str] | None = None  # (step, message) from record_stop
    connect_error: str | None = None
    lost: bool = False  # the connection was found closed when a step failed
    connection: Any = None  # the connection a step failed on (closed_by_the_host, at the summary)
    log: deque = field(default_factory=lambda: deque(maxlen=MAX_LOG_LINES))


@dataclass
class Row:
    host: str
    status: str
    step: str | None = None
    reason: str | None = None

    def text(self, width: int, status_width: int = 7) -> str:
        line = f"{self.host:<{width}}  {self.status:<{status_width}}"
        if self.status in (FAILED, INTERRUPTED):
            line += f"  in \"{self.step}\": {self.reason}"
        return line.rstrip()


class RunSummary(BaseStateCallback):
    """Collects what happened to each host during one pyinfra run, and prints the table."""

    def __init__(self) -> None:
        self.events: dict[str, HostEvents] = {}
        self.planned: set[str] = set()  # hosts whose deploy.py ran to its end
        # How the process ends when roslab ends it (a signal, no answer on stdin): its exit
        # code and why, so that the summary's exit code is the process's.
        self.exit_status: int | None = None
        self.ended_by: str | None = None
        self.signal_name: str | None = None
        self._dry_changes: dict | None = None  # --dry: host name -> would change
        # host name -> (reasons of this run's changes, reasons still pending from an earlier run
        # in the same boot, the changes): the "reboot needed" lines (deploy/robot_profile.py).
        self.reboots: dict[str, tuple[list[str], list[str], list]] = {}

    def end(self, exit_status: int, why: str, signal_name: str | None = None) -> None:
        """Note that the run is ended by roslab with `exit_status` (the first end counts)."""
        if self.exit_status is None:
            self.exit_status, self.ended_by, self.signal_name = exit_status, why, signal_name

    def host(self, name: str) -> HostEvents:
        return self.events.setdefault(name, HostEvents())

    # pyinfra callbacks (pyinfra calls them as handler.<name>(state, ...))

    # pyinfra declares its callbacks static and calls them on the handler: a method's self is
    # bound by then, so these take the same arguments (mypy sees a different signature).
    def host_connect_error(self, state: State, host, error) -> None:  # type: ignore[override]
        text = error.args[0] if getattr(error, "args", None) else error
        self.host(host.name).connect_error = one_line(text)

    def operation_host_error(self, state: State, host, op_hash, retry_count: int = 0,  # type: ignore[override]
                             max_retries: int = 0) -> None:
        events = self.host(host.name)
        events.error_ops.append(op_hash)
        events.lost = events.lost or connection_lost(host)
        events.connection = events.connection or connection_of(host)

    # roslab's own events

    def record_stop(self, name: str, step: str | None, message: str) -> None:
        events = self.host(name)
        if events.stop is None:  # the first stop is the reason; later ones follow from it
            events.stop = (step or "planning", message)

    def record_log(self, name: str, line: LogLine) -> None:
        self.host(name).log.append(line)

    def mark_planned(self, name: str) -> None:
        self.planned.add(name)

    def record_reboot(self, name: str, reasons: list[str], pending: list[str], changes: list) -> None:
        self.reboots[name] = (list(reasons), list(pending), list(changes))

    def reboot_lines(self, state: State) -> list[str]:
        """One line per host that needs a reboot: a change made now, or one still waiting from an
        earlier run in the same boot. --dry: the hosts whose change would need one."""
        lines = []
        for host in state.inventory:
            entry = self.reboots.get(host.name)
            if entry is None or not state.is_host_in_limit(host) or host_failed(state, host):
                continue
            reasons, pending, changes = entry
            if state.is_executing:
                changed = any(meta.is_complete() and meta.did_change() for meta in changes)
            else:
                changed = self.would_change(state, host) and bool(changes)
            if changed or pending:
                shown = list(dict.fromkeys([*pending, *(reasons if changed else [])]))
                verb = "needs" if state.is_executing or pending else "would need"
                lines.append(f"    {host.name} {verb} a reboot: {'; '.join(shown)} (roslab never reboots "
                             "during a run: reboot it when the class allows, e.g. `sudo reboot`)")
        return lines

    # the summary

    def run_finished(self, state: State) -> bool:
        """Whether pyinfra got to the end of the run (or of the plan, for --dry) on its own."""
        if state.current_stage >= StateStage.Disconnect:
            return True
        if state.current_stage == StateStage.Prepare and not state.is_executing:
            return all(host.name in self.planned for host in state.active_hosts)
        return False

    def exit_code(self, state: State) -> int:
        """The process's exit code: the one roslab ends it with (a signal, no stdin), else
        pyinfra's (1 when a host failed or pyinfra stopped with an error before the end)."""
        if self.exit_status is not None:
            return self.exit_status
        if state.failed_hosts or not self.run_finished(state):
            return 1
        return 0

    def rows(self, state: State) -> list[Row]:
        rows = []
        finished = self.run_finished(state)
        for host in state.inventory:
            if not state.is_host_in_limit(host):
                continue
            if host_failed(state, host):
                step, reason = self.failure(state, host)
                rows.append(Row(host.name, FAILED, step, reason))
            elif state.is_executing and self.signal_name and not self.all_ops_ran(state, host):
                step = self.unfinished_op(state, host)
                rows.append(Row(host.name, INTERRUPTED, step,
                                f"the run was stopped by {self.signal_name} before this step finished here"))
            elif state.is_executing:
                if self.did_change(state, host):
                    rows.append(Row(host.name, CHANGED))
                else:
                    rows.append(Row(host.name, OK if finished or self.all_ops_ran(state, host) else NOT_RUN))
            elif not finished:
                rows.append(Row(host.name, NOT_RUN))  # the run stopped while planning
            elif self.exit_status is not None:
                rows.append(Row(host.name, NOT_RUN))  # roslab ended the run before it executed
            elif not state.should_check_for_changes():
                rows.append(Row(host.name, PLANNED))  # --dry with -y: changes were not detected
            else:
                rows.append(Row(host.name, CHANGED if self.would_change(state, host) else OK))
        return rows

    def would_change(self, state: State, host) -> bool:
        """--dry: whether the host's plan would change it (`dry_run_changes`)."""
        if self._dry_changes is None:
            self._dry_changes = dry_run_changes(state)
        return self._dry_changes.get(host.name, False)

    @staticmethod
    def unfinished_op(state: State, host) -> str:
        """The name of the host's first operation that did not complete (pyinfra runs them in order)."""
        ops = state.ops.get(host, {})
        for op_data in ops_in_order(state, host):
            if not op_data.operation_meta.is_complete():
                op_hash = next(key for key, value in ops.items() if value is op_data)
                return op_name(state, op_hash, host)
        return "the end of the run"

    @staticmethod
    def all_ops_ran(state: State, host) -> bool:
        return all(op_data.operation_meta.is_complete() for op_data in state.ops.get(host, {}).values())

    @staticmethod
    def did_change(state: State, host) -> bool:
        for op_data in state.ops.get(host, {}).values():
            meta = op_data.operation_meta
            if meta.is_complete() and meta.did_change():
                return True
        return False

    def failure(self, state: State, host) -> tuple[str, str]:
        """(step, reason) for a failed host, from the best source there is; sudo's words
        about a wrong password become a line naming the roster setting."""
        step, reason = self._failure(state, host)
        return step, sudo_refusal(host, [reason]) or reason

    def _failure(self, state: State, host) -> tuple[str, str]:
        events = self.host(host.name)
        if events.stop:
            step, message = events.stop
            return step, stop_reason(message) or "roslab stopped it"
        op_hash = self.failed_op(state, host)
        if op_hash is not None:
            reason = self.op_reason(state, host, op_hash)
            if self.host_lost(host):
                # the step's own words, when it had any beyond pyinfra's socket error
                said = "" if reason == NO_ERROR_PRINTED or _SOCKET_ERROR.search(reason) else f" ({reason})"
                return op_name(state, op_hash, host), LOST_CONNECTION + said
            return op_name(state, op_hash, host), reason
        if events.connect_error or host not in state.activated_hosts:
            # A refused host key: roslab.ssh.identity's line says what to run.
            why = identity.refusal(host.name) or events.connect_error or most_useful_line(
                line.text for line in events.log if line.level >= logging.ERROR
            ) or "pyinfra could not connect to it (its message is above)"
            pending = pending_network_change(host)
            if pending and not identity.refusal(host.name):
                tried = (getattr(host, "data", None) or {}).get("ssh_hostname") or host.name
                why = f"tried {tried}: {why}; {pending}"
            return "connect", why
        # Planning failures no callback carries: a fact that could not load, stop_host's
        # own log line (most_useful_line prefers it).
        errors = [line for line in events.log if line.level >= logging.ERROR]
        logged = most_useful_line(line.text for line in errors)
        if logged and self.host_lost(host):  # "could not load fact: ..." of a host that went away
            logged = LOST_CONNECTION
        if logged:
            failed_step = next((line.step for line in reversed(errors) if line.step), None)
            if failed_step is None:
                failed_step = next((op_name(state, line.op_hash, host) for line in reversed(errors)
                                    if line.op_hash in state.op_meta), "planning")
            return failed_step, logged
        return "unknown", "pyinfra marked it failed without saying why (see its output above)"

    def host_lost(self, host) -> bool:
        """Whether the host went away during its failed step (asked once: closed_by_the_host)."""
        events = self.host(host.name)
        if not events.lost and events.connection is not None:
            events.lost = closed_by_the_host(events.connection)
            events.connection = None
        return events.lost

    def failed_op(self, state: State, host) -> str | None:
        """The operation that failed the host: its first error that was not ignored."""
        ops = state.ops.get(host, {})
        for op_hash in self.host(host.name).error_ops:
            op_data = ops.get(op_hash)
            if op_data is None or not op_data.global_arguments.get("_ignore_errors"):
                return op_hash
        return None

    def op_reason(self, state: State, host, op_hash: str) -> str:
        """The most useful line of the operation's stderr, else its stdout, else of what
        pyinfra logged for the host while it ran (a timeout, an SSH or Python error)."""
        op_data = state.ops.get(host, {}).get(op_hash)
        sources: list[list[str]] = []
        if op_data is not None and op_data.operation_meta.is_complete():
            sources += [op_data.operation_meta.stderr_lines, op_data.operation_meta.stdout_lines]
        sources.append([line.text for line in self.host(host.name).log if line.op_hash == op_hash])
        for lines in sources:
            reason = most_useful_line(lines)
            if reason:
                return reason
        return NO_ERROR_PRINTED

    def lines(self, state: State) -> list[str]:
        rows = self.rows(state)
        secrets = secrets_in(state)
        width = max([len(row.host) for row in rows] + [4])
        status_width = max([len(row.status) for row in rows] + [7])
        header = "--> roslab summary"
        if not state.is_executing and self.run_finished(state) and self.exit_status is None:
            if state.should_check_for_changes():
                header += " (nothing was executed: changed = would change)"
            else:
                header += " (nothing was executed; with -y changes were not detected)"
        out = [header]
        if _compact is not None and _compact.hidden_steps:
            out.insert(0, f"--> {_compact.hidden_steps} steps changed nothing on any host and are not shown "
                          "above (-v shows every step)\n")
        out += [f"    {mask(row.text(width, status_width), secrets)}" for row in rows]
        counts = {status: sum(row.status == status for row in rows) for status in (FAILED, CHANGED, OK)}
        tally = ", ".join(f"{number} {status}" for status, number in counts.items())
        interrupted = sum(row.status == INTERRUPTED for row in rows)
        if interrupted:
            tally += f", {interrupted} interrupted"
        not_run = sum(row.status == NOT_RUN for row in rows)
        if not_run:
            tally += f", {not_run} not run"
        planned = sum(row.status == PLANNED for row in rows)
        if planned:
            tally += f", {planned} planned"
        code = self.exit_code(state)
        if self.ended_by:
            stopped = f"{self.ended_by}; "
        elif not self.run_finished(state):
            stopped = "pyinfra stopped before the end of the run (its error is above); "
        else:
            stopped = ""
        out.append(f"    exit code {code}: {stopped}{tally} ({len(rows)} host{'s' if len(rows) != 1 else ''})")
        reboots = self.reboot_lines(state) if self.run_finished(state) else []
        if reboots:
            out += ["--> reboot needed", *(mask(line, secrets) for line in reboots)]
        return out

    def write(self, state: State, stream: TextIO | None = None) -> None:
        stream = stream or sys.stderr
        stream.write("\n" + "\n".join(self.lines(state)) + "\n")
        stream.flush()

    def record(self, state: State, when=None) -> list:
        """Note each host's outcome in runs.yaml beside its roster (`roslab.reporting.runs`), for
        `roslab status`. Only a run that executed records: --dry (or a run not confirmed)
        records nothing. Returns the files written."""
        if not state.is_executing:
            return []
        secrets = secrets_in(state)
        by_roster: dict[str, list[HostRun]] = {}
        for row in self.rows(state):
            host = state.inventory.get_host(row.host, None)
            roster = host.data.get("roslab_roster_path") if host is not None else None
            if not roster:
                continue  # not a roslab roster's host: nowhere to record it
            by_roster.setdefault(str(roster), []).append(HostRun(
                row.host, row.status,
                mask(row.step, secrets) if row.step else None,
                mask(row.reason, secrets) if row.reason else None,
            ))
        return [record_runs(roster, runs, when) for roster, runs in by_roster.items()]

    def lock_taken(self, state: State) -> list[str]:
        """class_lock_auto: write the groups classroom.lock lacks from the hosts that converged in
        this run (ok or changed; roslab.class_lock_auto), one line per lock written. --dry
        (nothing executed) writes nothing."""
        from roslab import class_lock_auto

        if not state.is_executing:
            class_lock_auto.forget()
            return []
        rows = self.rows(state)
        converged = [row.host for row in rows if row.status in (OK, CHANGED)]
        return class_lock_auto.write_taken(converged)


def dry_run_changes(state: State) -> dict:
    """--dry: for each host, whether its plan would change it, conditions included.

    pyinfra's count of changes (`ops_change`) includes the conditional operations
    (`_if=other_op.did_change`: a reload after a changed file), which change only when
    their condition holds. The plan is walked in pyinfra's order, each operation completed
    as it would end (its commands if pyinfra found any, none otherwise) and each condition
    evaluated as pyinfra evaluates it when executing. Only after a dry run: the state is
    done with, nothing executes after it. A condition that cannot be evaluated counts as a
    change (as pyinfra's "Conditional Change" column does).
    """
    from pyinfra.api.command import StringCommand
    from pyinfra.connectors.util import CommandOutput

    changes: dict = {}
    for host in state.inventory:
        changed = False
        for op_data in ops_in_order(state, host):
            meta = op_data.operation_meta
            if meta.is_complete():
                continue
            runs = bool(meta.will_change) and condition_holds(op_data.global_arguments.get("_if"))
            changed = changed or runs
            meta.set_complete(True, [StringCommand("true")] if runs else [], CommandOutput([]))
        changes[host.name] = changed
    return changes


def planned_changes(state: State) -> dict[str, list[str]]:
    """Before executing (a real run's plan, or --dry): op hash -> the hosts it would change,
    each `_if` condition evaluated as pyinfra evaluates it when executing (as `dry_run_changes`),
    without changing the state: every operation completed for the walk is reset afterwards."""
    from pyinfra.api.command import StringCommand
    from pyinfra.connectors.util import CommandOutput

    changes: dict[str, list[str]] = {}
    for host in state.inventory:
        if host not in state.active_hosts or not state.is_host_in_limit(host):
            continue
        walked = []
        try:
            ops = state.ops.get(host, {})
            hashes = {id(op_data): op_hash for op_hash, op_data in ops.items()}
            for op_data in ops_in_order(state, host):
                meta = op_data.operation_meta
                if meta.is_complete():
                    continue
                runs = bool(meta.will_change) and condition_holds(op_data.global_arguments.get("_if"))
                if runs:
                    changes.setdefault(hashes[id(op_data)], []).append(host.name)
                meta.set_complete(True, [StringCommand("true")] if runs else [], CommandOutput([]))
                walked.append(meta)
        finally:
            for meta in walked:  # back to "not executed yet" (OperationMeta's class defaults)
                for attribute in ("_success", "_commands", "_combined_output"):
                    meta.__dict__.pop(attribute, None)
    return changes


def executed_changes(state: State) -> dict[str, dict[str, list[str]]]:
    """After executing: op hash -> {"changed": hosts, "failed": hosts}, only the operations
    that changed or failed somewhere, each host named (pyinfra's table counts them)."""
    result: dict[str, dict[str, list[str]]] = {}
    for op_hash in op_order(state):
        changed, failed = [], []
        for host in state.inventory.iter_activated_hosts():
            op_data = state.ops.get(host, {}).get(op_hash)
            if op_data is None or not state.is_host_in_limit(host):
                continue
            meta = op_data.operation_meta
            if not meta.is_complete():
                continue
            if not meta.did_succeed(_raise_if_not_complete=False):
                failed.append(host.name)
            elif meta.did_change():
                changed.append(host.name)
        if changed or failed:
            result[op_hash] = {"changed": sorted(changed), "failed": sorted(failed)}
    return result


def op_order(state: State) -> list[str]:
    """Every planned operation's hash in pyinfra's order (then any it does not order)."""
    order = list(state.get_op_order())
    return order + [op_hash for op_hash in state.op_meta if op_hash not in order]


MAX_STEP_NAME = 80  # characters of a step's name on its line of the compact tables


def own_name(name: str) -> str:
    """An operation's own name without its deploy's title ("SSH is on, ... | Ensure sshd ..."
    -> "Ensure sshd ..."): the deploy's title is the same for all its steps, the operation's
    own name is what tells them apart."""
    return name.rsplit(" | ", 1)[-1]


def clipped(text: str, limit: int = MAX_STEP_NAME) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def step_title(state: State, op_hash: str, host_name: str | None = None) -> str:
    """The step's own name as pyinfra showed it on that host (a name holding a host's value,
    such as its distro, is that host's), on one line of at most MAX_STEP_NAME characters."""
    host = state.inventory.get_host(host_name, None) if host_name else None
    return clipped(" ".join(own_name(op_name(state, op_hash, host)).split()))


MAX_START_LINE = 240  # characters of a "--> Starting operation" line that joins several names


def short_start_line(text: str, state: State | None) -> str:
    """pyinfra's "--> Starting operation: A | x, A | y, ..." (one name per host where names
    hold host values) without the deploys' titles; where several names are joined, at most
    MAX_START_LINE characters: the ROS install's start line was 1,665 characters of seven
    titles joined. One name is kept whole (it may end in a path the teacher looks for)."""
    head, _, names = text.partition("operation: ")
    if not names or state is None:
        return text
    own = {name.rsplit(" | ", 1)[-1] for meta in state.op_meta.values() for name in meta.names}
    titles = sorted({name.rsplit(" | ", 1)[0] + " | " for meta in state.op_meta.values()
                     for name in meta.names if " | " in name}, key=len, reverse=True)
    for title in titles:
        names = names.replace(title, "")
    line = f"{head}operation: {names}"
    joined = sum(1 for name in own if name and name in names) > 1
    return clipped(line, MAX_START_LINE) if joined else line


def _by_title(state: State, op_hash: str, names: list[str]) -> dict[str, list[str]]:
    titles: dict[str, list[str]] = {}
    for name in sorted(names):
        titles.setdefault(step_title(state, op_hash, name), []).append(name)
    return titles


def plan_lines(state: State) -> list[str]:
    """The compact "Detected changes": one line per step that would change a host, naming the
    hosts (a restart gated on a change that will not happen is not one)."""
    changes = planned_changes(state)
    if not changes:
        return ["nothing would change on any host"]
    return [f"{title}: {', '.join(hosts)}"
            for op_hash in op_order(state) if changes.get(op_hash)
            for title, hosts in _by_title(state, op_hash, changes[op_hash]).items()]


def result_lines(state: State) -> list[str]:
    """The compact "Results": one line per step that changed or failed on a host, naming them;
    none when nothing changed (the summary says each host's outcome)."""
    lines = []
    for op_hash, hosts in executed_changes(state).items():
        outcome = {name: "changed" for name in hosts["changed"]} | {name: "failed" for name in hosts["failed"]}
        for title, names in _by_title(state, op_hash, list(outcome)).items():
            parts = [f"{what} on {', '.join(name for name in names if outcome[name] == what)}"
                     for what in ("changed", "failed") if any(outcome[name] == what for name in names)]
            lines.append(f"{title}: {'; '.join(parts)}")
    return lines


def ops_in_order(state: State, host) -> list:
    """The host's planned operations (StateOperationHostData) in the order pyinfra runs them."""
    ops = state.ops.get(host, {})
    order = [op_hash for op_hash in state.get_op_order() if op_hash in ops]
    order += [op_hash for op_hash in ops if op_hash not in order]
    return [ops[op_hash] for op_hash in order]


def condition_holds(conditions) -> bool:
    """pyinfra's `_if`: one callable or a list of them, all true."""
    if not conditions:
        return True
    if callable(conditions):
        conditions = [conditions]
    try:
        return all(condition() for condition in conditions)
    except Exception:  # noqa: BLE001 - a condition that cannot be known before running may hold
        return True


def host_failed(state: State, host) -> bool:
    """Whether pyinfra failed `host` in this run.

    Not `host in state.failed_hosts`: a deploy that fails the current host with
    `state.fail_hosts({host})` puts pyinfra's context proxy in that set, and the proxy
    stands for no host once the run is over. `active_hosts` loses the real host.
    """
    if any(failed is host for failed in state.failed_hosts):
        return True
    if host not in state.activated_hosts:
        return True  # it never connected
    return host not in state.active_hosts


def op_name(state: State, op_hash: str, host=None) -> str:
    """The operation's name as pyinfra printed it for `host`.

    pyinfra keeps one set of names per operation for all hosts (one name per host when
    the name holds host values: "Ensure ROS 2 jazzy ...", "Ensure ROS 2 humble ...");
    the host's own `name=` argument picks its one.
    """
    meta = state.op_meta.get(op_hash)
    names = sorted(meta.names) if meta else []
    op_data = state.ops.get(host, {}).get(op_hash) if host is not None else None
    own = (op_data.global_arguments.get("name") if op_data is not None else None) or None
    if own:
        mine = [name for name in names if name == own or name.endswith(f" | {own}")]
        if mine:
            names = mine[:1]
    return one_line(", ".join(names)) or "an operation"


def secrets_in(state: State) -> list[str]:
    """Every secret value in the run's host data, longest first (only to mask them)."""
    found: set[str] = set()

    def walk(key: str, value: Any) -> None:
        if isinstance(value, HiddenValue):
            found.add(str(value.unmask()))
        elif isinstance(value, dict):
            for sub_key, sub_value in value.items():
                walk(str(sub_key), sub_value)
        elif isinstance(value, (list, tuple, set)):
            for item in value:
                walk(key, item)
        elif isinstance(value, str) and "password" in key.lower():
            found.add(value)

    for host in state.inventory:
        try:
            walk("", host.data.dict())
        except Exception:  # noqa: BLE001 - masking must never stop the summary
            continue
    return sorted((secret for secret in found if secret), key=len, reverse=True)


def mask(text: str, secrets: list[str]) -> str:
    for secret in secrets:
        text = text.replace(secret, MASK)
    return text


# --- wiring: one summary per run ----------------------------------------------------------

_current: tuple[RunSummary, State | None] | None = None
_atexit_registered = False


def summary_for(state: State | None) -> RunSummary | None:
    """The RunSummary registered on `state`, if any."""
    for handler in getattr(state, "callback_handlers", None) or []:
        if isinstance(handler, RunSummary):
            return handler
    return None


def install(state: State | None = None) -> RunSummary:
    """Register the run summary on the current pyinfra state, once per run.

    The inventories (inventories/lab.py, inventories/sandbox.py) call it before pyinfra
    connects, so a run where no host can be reached still ends with the summary; deploy.py
    calls it for every host (any inventory); only the first call registers. In the pyinfra
    CLI, for a run of deploy files, the summary is printed to stderr at exit, and roslab
    ends the run itself where pyinfra would end it with a wrong exit code or a traceback:
    SIGINT (Ctrl-C) and SIGTERM exit 130 and 143 (pyinfra exits 0 on Ctrl-C), and a
    confirmation pyinfra asks for on a closed standard input ends with one line, exit 1.
    """
    global _current, _atexit_registered
    from roslab.ssh.quiet import quiet_paramiko

    quiet_paramiko()  # a host that hangs up is pyinfra's one line, not paramiko's traceback
    state = state if isinstance(state, State) else ctx_state.get()
    summary = summary_for(state)
    if summary is None:
        pending = _current[0] if _current is not None and _current[1] is None else None
        summary = pending or RunSummary()
        if getattr(state, "initialised", False):
            state.add_callback_handler(summary)
            _current = (summary, state)
        else:
            # An inventory file: pyinfra initialises the state after loading it. The
            # callbacks are registered by the next call (deploy.py); until then the log
            # lines (a host that cannot be reached) are kept and the summary still prints.
            _current = (summary, None)
        _attach_log_capture()
        if pyinfra.is_cli and not _atexit_registered and deploying_files():
            atexit.register(_print_at_exit)
            _atexit_registered = True
            _handle_signals(summary)
            _guard_stdin(summary)
            if cli_option("verbosity") == 0 and not cli_option("json_output") and not (
                    cli_option("debug") or cli_option("debug_all")):
                _attach_compact_output()
    return summary


def cli_option(name: str):
    """A pyinfra command line option of this run (click's parameters), or None outside it."""
    try:
        import click
    except ImportError:  # pragma: no cover - pyinfra's CLI always has click
        return None
    context = click.get_current_context(silent=True)
    while context is not None:
        if name in context.params:
            return context.params[name]
        context = context.parent
    return None


def deploying_files() -> bool:
    """Whether this pyinfra run executes deploy files (`pyinfra INVENTORY deploy.py`), not
    `exec`, `fact` or `debug-inventory` (those have no per-host result to summarise).

    The command line is read where pyinfra's click context is visible (an inventory file,
    loaded in the main greenlet); deploy.py runs in a greenlet per host, where it is not, and
    is itself a deploy file."""
    operations = cli_option("operations")
    if operations is None:
        return True
    return bool(operations) and all(str(name).endswith(".py") for name in operations)


def _handle_signals(summary: RunSummary) -> None:
    """End the run on SIGINT/SIGTERM with the shell's exit code for the signal, noted for
    the summary (pyinfra's own handler exits 0 on Ctrl-C; SIGTERM would skip the summary)."""
    if threading.current_thread() is not threading.main_thread():
        return

    def stop(signum, frame) -> None:
        name = SIGNAL_NAMES.get(signum, f"signal {signum}")
        summary.end(SIGNAL_EXITS.get(signum, 128 + signum), f"stopped by {name}", name)
        sys.stderr.write(f"\n--> roslab: stopped by {name}; disconnecting\n")
        raise SystemExit(summary.exit_status)

    for signum in SIGNAL_EXITS:
        signal.signal(signum, stop)


class _ClosedStdinGuard:
    """Standard input that ends the run with one line (exit 1) when pyinfra reads its end.

    pyinfra asks for confirmation with `input()`; on a closed standard input that raises
    EOFError, which pyinfra reports as an internal error with a traceback and exit 1
    while the summary would claim success. Nothing else in a deploy run reads standard
    input (with -y nothing does); everything else is the real stream's."""

    def __init__(self, stream, summary: RunSummary) -> None:
        self._stream = stream
        self._summary = summary

    def readline(self, *args):
        line = self._stream.readline(*args)
        if line == "":
            self._summary.end(1, "no one could answer pyinfra (standard input is closed; use -y)")
            sys.stderr.write(f"\n--> roslab: {NO_STDIN}\n")
            raise SystemExit(1)
        return line

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _guard_stdin(summary: RunSummary) -> None:
    """Without a terminal (cron, CI), pyinfra's confirmation prompt reads a pipe or
    /dev/null: guard its end. A terminal has someone to answer."""
    stdin = sys.stdin
    if stdin is None or isinstance(stdin, _ClosedStdinGuard):
        return
    try:
        interactive = stdin.isatty()
    except (ValueError, OSError):  # closed
        interactive = False
    if not interactive:
        sys.stdin = _ClosedStdinGuard(stdin if not stdin.closed else open(os.devnull), summary)


def _print_at_exit() -> None:
    if _current is None:
        return
    summary, state = _current
    if state is None:  # no deploy.py ran (no host could be reached): pyinfra's state all the same
        state = ctx_state.get()
        if state is None or not getattr(state, "initialised", False):
            return  # pyinfra stopped before it had a state to report (its error says why)
    try:
        summary.write(state)
    except Exception as error:  # noqa: BLE001 - the run's result stands; say why there is no table
        sys.stderr.write(f"\n--> roslab summary unavailable: {type(error).__name__}: {error}\n")
    try:
        summary.record(state)
    except Exception as error:  # noqa: BLE001 - the run's result stands; say why it is not recorded
        sys.stderr.write(f"--> roslab could not record the run for `roslab status`: "
                         f"{type(error).__name__}: {error}\n")
    try:
        for line in summary.lock_taken(state):
            sys.stderr.write(f"--> roslab class lock: {line}\n")
    except Exception as error:  # noqa: BLE001 - the run's result stands; say why the lock is not written
        sys.stderr.write(f"--> roslab could not write the class lock: {type(error).__name__}: {error}\n")


def _host_name(host) -> str:
    return str(getattr(host, "name", host))


def record_stop(host, message: str) -> None:
    """Note that roslab stopped `host` (deploy.common.stop_host), with its message.

    The step is the deploy (or operation) the host was in. Without a summary on the run
    (a unit test calling a deploy directly) this does nothing.
    """
    state = getattr(host, "state", None) or ctx_state.get()
    summary = summary_for(state)
    if summary is None:
        return
    step = None
    op_hash = getattr(host, "executing_op_hash", None)
    if op_hash and op_hash in getattr(state, "op_meta", {}):
        step = op_name(state, op_hash, host)
    step = step or getattr(host, "current_deploy_name", None)
    summary.record_stop(_host_name(host), step, message)


def record_reboot(reasons: list[str], pending: list[str], changes: list, host=None) -> None:
    """Note that this host needs a reboot for `reasons` when one of `changes` (operation results)
    changes it, or already does (`pending`): the summary says so once per host."""
    host = host if host is not None else ctx_host.get()
    if host is None:
        return
    summary = summary_for(getattr(host, "state", None) or ctx_state.get())
    if summary is not None:
        summary.record_reboot(_host_name(host), reasons, pending, changes)


def mark_planned(host=None) -> None:
    """Note that deploy.py ran to its end for this host (the plan is complete for it)."""
    host = host if host is not None else ctx_host.get()
    if host is None:
        return
    summary = summary_for(getattr(host, "state", None) or ctx_state.get())
    if summary is not None:
        summary.mark_planned(_host_name(host))


class _LogCapture(logging.Handler):
    """Keeps pyinfra's `[host] ...` warning and error lines for the current run's summary."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if _current is None:
                return
            summary, state = _current
            match = _PREFIXED.match(_ANSI.sub("", record.getMessage()))
            if not match:
                return
            name, text = match.groups()
            if text.startswith(colcon_progress.PREFIX):
                return  # a build's progress line: no reason for the summary
            host = ctx_host.get()
            if host is None or getattr(host, "name", None) != name:
                host = None
            if record.levelno >= logging.ERROR:
                # before deploy.py's first host registers the state (no host connected), only
                # the record's own host is known
                known = host or (state.inventory.get_host(name, None) if state is not None else None)
                if known is not None:
                    events = summary.host(name)
                    events.lost = events.lost or connection_lost(known)
                    events.connection = events.connection or connection_of(known)
            summary.record_log(name, LogLine(
                record.levelno,
                text,
                op_hash=getattr(host, "executing_op_hash", None),
                step=getattr(host, "current_deploy_name", None),
            ))
        except Exception:  # noqa: BLE001 - logging must never break the run
            pass


_log_capture: _LogCapture | None = None

# --- compact output ------------------------------------------------------------------------

LONG_STEP = 5.0  # seconds after which a step that has changed nothing yet is shown anyway
STILL_RUNNING_EVERY = 15.0  # seconds between "still running on ..." lines of a long step: a teacher never
# waits over 20 s in silence, with room for a loaded controller's late tick (a tick at 20 s came 20.0 s apart)
# The controller's environment may set another interval (whole seconds, 1 to 3600): a teacher
# watching a long first build may want a line more often, a log kept for later one less often.
STILL_RUNNING_VARIABLE = "ROSLAB_STILL_RUNNING_SECONDS"


def still_running_every(environ=os.environ) -> tuple[float, str | None]:
    """(seconds between "still running" lines, None or the warning for a value not taken)."""
    value = environ.get(STILL_RUNNING_VARIABLE, "").strip()
    if not value:
        return STILL_RUNNING_EVERY, None
    if value.isascii() and value.isdigit() and 1 <= int(value) <= 3600:
        return float(value), None
    return STILL_RUNNING_EVERY, (f"{STILL_RUNNING_VARIABLE}={value[:40]!r} is not a whole number of seconds from 1 "
                                 f"to 3600: every {STILL_RUNNING_EVERY:.0f} s")
_STARTING = re.compile(r"^--> Starting\b.*\boperation:")
_QUIET_STATUSES = re.compile(r"^(?:No changes|Skipped)\b")
# pyinfra's "[host] Ready: deploy.py", one per host once its plan is made: a host that cannot
# be planned says so in a warning or an error line, which is always shown.
_READY = re.compile(r"^Ready: ")


class CompactOutput(logging.Filter):
    """pyinfra's default output without the steps that changed nothing, so that a converged
    class's run fits a screen and ends with the summary (`-v` shows pyinfra's full output).

    A "--> Starting operation" line is held back until a host reports something about it
    (a change, a warning, an error: then it is shown, with that line), or until the step
    has run `LONG_STEP` seconds (then it is shown, so a long step is never silent); a
    step every host reports "No changes" for is not shown at all. While a long step runs,
    every `STILL_RUNNING_EVERY` seconds one line says which hosts are still in it and for how
    long. Warnings and errors always pass, at once.

    pyinfra's two tables (its "Detected changes" plan and its "Results", a row per step with
    counts of hosts) become roslab's lines (`plan_lines`, `result_lines`): one per step that
    would change, changed or failed something, naming each host; a restart gated on a change
    that will not happen (`_if`) is not one; after a run that changed nothing, none at all.
    """

    def __init__(self, logger: logging.Logger, long_step: float | None = LONG_STEP,
                 hosts=None, every: float = STILL_RUNNING_EVERY) -> None:
        super().__init__("roslab-compact")
        self.logger = logger
        self.long_step = long_step
        self.every = every
        self.hosts: Callable[[], list[str]] = hosts or (lambda: [])  # the names of the hosts the run executes on
        self.pending: logging.LogRecord | None = None
        self.step: logging.LogRecord | None = None  # the step running now
        self.done: set[str] = set()  # hosts that finished it
        self.hidden_steps = 0
        self.table: str | None = None  # pyinfra's table being printed (its rows are held back)
        self.state = None  # the run's pyinfra State (else the current one)

    def show_table(self, header: str, lines_of) -> None:
        """roslab's lines in place of pyinfra's table: the steps that change (or changed, or
        failed) something, each naming its hosts; nothing after a run that changed nothing."""
        try:
            lines = lines_of(self.state or ctx_state.get())
        except Exception as error:  # noqa: BLE001 - the output must never break the run
            lines = [f"(roslab could not list the steps: {type(error).__name__}: {error}; -v shows pyinfra's table)"]
        if not lines:
            return
        for line in [header, *lines]:
            self.logger.info(line, extra={"roslab_shown": True})

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "roslab_shown", False):
            return True
        try:
            text = _ANSI.sub("", record.getMessage()).strip()
        except Exception:  # noqa: BLE001 - a line that cannot be read is shown as it is
            return True
        if text.startswith("-->"):
            self.table = None
        if self.table is not None and record.levelno <= logging.INFO:
            return False  # a row of pyinfra's table: roslab's lines stand for it
        table = _TABLES.get(text)
        if table is not None and record.levelno <= logging.INFO:
            self.drop_pending()
            self.step = None
            self.table = text
            self.show_table(text, table)
            return False
        prefixed = _PREFIXED.match(text)
        if prefixed and (_QUIET_STATUSES.match(prefixed.group(2)) or prefixed.group(2).startswith(
                ("Success", "Error"))):
            self.done.add(prefixed.group(1))  # the host is through the step
        if record.levelno > logging.INFO:
            self.show_pending()
            return True
        if colcon_progress.PREFIX in text:
            return False  # a build's progress line (a failed build's output): said while it ran
        if _STARTING.match(text):
            self.drop_pending()
            self.pending = self.step = record
            self.done = set()
            colcon_progress.BUILDS.clear()
            if self.long_step is not None:
                self._later(record)
            return False
        if prefixed:
            if _QUIET_STATUSES.match(prefixed.group(2)) or (self.step is None and _READY.match(prefixed.group(2))):
                return False
            self.show_pending()
            return True
        self.drop_pending()  # the run moved on (results, disconnecting)
        self.step = None
        return True

    def show_pending(self) -> None:
        record, self.pending = self.pending, None
        if record is not None:
            record.roslab_shown = True
            try:
                text = _ANSI.sub("", record.getMessage())
                short = short_start_line(text, self.state or ctx_state.get())
                if short != text:
                    record.msg, record.args = short, None
            except Exception:  # noqa: BLE001 - the output must never break the run
                pass
            self.logger.handle(record)

    def drop_pending(self) -> None:
        if self.pending is not None:
            self.hidden_steps += 1
        self.pending = None

    def _later(self, record: logging.LogRecord) -> None:
        long_step = self.long_step
        if long_step is None:  # no "still running" lines (handle() calls this only with one)
            return
        try:
            import gevent
        except ImportError:  # pragma: no cover - pyinfra's CLI runs on gevent
            return

        started = time.monotonic()

        def still_running(first: bool) -> None:
            if self.step is not record:
                return  # the step is over
            if first:
                self.show_pending()
            else:
                waiting = [name for name in self.hosts() if name not in self.done]
                if waiting:
                    # a colcon build's package, as its progress lines told it (roslab.ros.colcon_progress)
                    doing = "; ".join(f"{name}: {words}" for name in waiting
                                      if (words := colcon_progress.BUILDS.words(name)))
                    self.logger.info(f"    still running on {', '.join(waiting)} "
                                     f"({time.monotonic() - started:.0f} s)" + (f": {doing}" if doing else ""),
                                     extra={"roslab_shown": True})
            gevent.spawn_later(self.every, still_running, False)

        gevent.spawn_later(long_step, still_running, True)


# pyinfra's tables (pyinfra_cli.prints: print_meta, print_results), after their header line: in
# the compact output roslab's own lines stand for them (`-v` shows pyinfra's).
_TABLES = {"--> Detected changes:": plan_lines, "--> Results:": result_lines}

_compact: CompactOutput | None = None


def _attach_compact_output() -> None:
    global _compact
    if _compact is None:
        every, problem = still_running_every()
        if problem:
            pyinfra.logger.warning(f"roslab: {problem}")
        _compact = CompactOutput(pyinfra.logger, hosts=_executing_hosts, every=every)
        pyinfra.logger.addFilter(_compact)


def _executing_hosts() -> list[str]:
    state = _current[1] if _current is not None else None
    state = state or ctx_state.get()
    try:
        return sorted(host.name for host in state.active_hosts)
    except Exception:  # noqa: BLE001 - progress must never break the run
        return []


def _attach_log_capture() -> None:
    global _log_capture
    if _log_capture is None:
        _log_capture = _LogCapture(level=logging.WARNING)
        pyinfra.logger.addHandler(_log_capture)
