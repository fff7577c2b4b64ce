"""How a `roslab` command takes a roster and reaches its hosts: one way for every command.

    roslab COMMAND [ROSTER] [--limit NAME ...]

`add_roster_argument` registers ROSTER (and `--limit`) the same way on every subcommand;
`load_classroom` loads it (the default roster found as `inventories/lab.py` finds it) and
turns a mistake into lines on stderr and an exit status, never a traceback;
`roster_state` makes the pyinfra State of the roster's hosts as deploy.py's inventory makes
them (the same groups and connection data), through pyinfra's public API only, and
`connected_state` connects it. `--limit` selects as pyinfra's does: a group (team, role,
distro) or a host name, with shell-style wildcards.
"""

from __future__ import annotations

import argparse
import difflib
import fnmatch
import os
import sys
from pathlib import Path

from roslab.roster import Classroom, RosterError, default_roster_path, display_path, load_roster

ROSTER_HELP = ("roster file (default: $ROSLAB_ROSTER, else classroom.yaml or inventories/classroom.yaml "
               "in this folder if present, else inventories/lab.yaml)")
LIMIT_HELP = "a team, role, distro or host name, wildcards allowed (pyinfra's --limit; repeatable)"


def add_roster_argument(parser: argparse.ArgumentParser, limit: bool = True) -> None:
    """ROSTER (optional, positional) and, with `limit`, --limit NAME (repeatable)."""
    parser.add_argument("roster", nargs="?", metavar="ROSTER", help=ROSTER_HELP)
    if limit:
        parser.add_argument("--limit", action="append", metavar="NAME", help=LIMIT_HELP)


class RosterProblem(Exception):
    """A roster that cannot be used, said in lines for stderr (no traceback)."""


def roster_path(argument: str | None) -> Path:
    return Path(argument) if argument else default_roster_path()


def load_classroom(argument: str | None, command: str) -> Classroom:
    """The roster ROSTER names (or the default one), checked; RosterProblem says what is wrong."""
    path = roster_path(argument)
    if path.suffix == ".py":
        raise RosterProblem(
            f"roslab {command}: {display_path(path)} is a pyinfra inventory; roslab {command} takes the "
            f"roster itself (a .yaml file), as every roslab command does: roslab {command} [ROSTER]")
    try:
        return load_roster(path)
    except RosterError as error:
        count = len(error.problems)
        raise RosterProblem(f"{error}\nroslab {command}: {count} error{'s' if count != 1 else ''} "
                            f"in the roster; no host was touched, nothing was written") from None


def load_classroom_groups(argument: str | None, command: str) -> tuple[Classroom, dict]:
    """`load_classroom` and its `roslab.roster.inventory_groups`; RosterProblem also for a broken
    addresses.yaml or known_hosts beside the roster."""
    from roslab.roster import inventory_groups

    classroom = load_classroom(argument, command)
    try:
        return classroom, inventory_groups(classroom)
    except RosterError as error:
        raise RosterProblem(str(error)) from None


def roster_inventory(groups: dict):
    """pyinfra's Inventory of `roslab.roster.inventory_groups(...)`, as inventories/lab.py makes it."""
    from pyinfra.api import Inventory

    everyone: dict[str, dict] = {}
    for entries in groups.values():
        for name, data in entries:
            everyone[name] = data
    return Inventory((list(everyone.items()), {}),
                     **{group: (entries, {}) for group, entries in groups.items()})


def select_hosts(inventory, patterns: list[str] | None) -> list:
    """The hosts `--limit` patterns select (all without patterns), as pyinfra's --limit: each
    pattern a group's name (team, role, distro), else host names with shell-style wildcards."""
    hosts = list(inventory)
    if not patterns:
        return hosts
    selected: set = set()
    for pattern in patterns:
        group = inventory.get_group(pattern, None)
        selected.update(group if group else [host for host in hosts if fnmatch.fnmatch(host.name, pattern)])
    return [host for host in hosts if host in selected]


def limit_problem(groups: dict, patterns, command: str = "roslab") -> str | None:
    """One line naming each `--limit` pattern that selects no host of the roster, or None.

    pyinfra only warns about such a pattern and goes on with the others (with none left it
    does nothing and exits 0): a typo in a team's name, or `--limit a,b` (one pattern with a
    comma, which pyinfra does not split), would leave hosts out of a run that says it worked."""
    inventory = roster_inventory(groups)
    unmatched = [pattern for pattern in patterns or () if not select_hosts(inventory, [pattern])]
    if not unmatched:
        return None
    names = sorted({*(name for name in groups if name != "all"), *(host.name for host in inventory)})
    hints = []
    for pattern in unmatched:
        if "," in pattern:
            parts = " ".join(f"--limit {part.strip()}" for part in pattern.split(",") if part.strip())
            hints.append(f"for several, repeat the option: {parts}")
        else:
            close = difflib.get_close_matches(pattern.replace("-", "_"), names, n=1) or \
                difflib.get_close_matches(pattern, names, n=1)
            if close:
                hints.append(f"did you mean {close[0]!r}?")
    quoted = ", ".join(repr(pattern) for pattern in unmatched)
    return (f"{command}: --limit {quoted} selects no host of the roster (a team, role or distro group, "
            f"or host names with wildcards)" + (f"; {'; '.join(hints)}" if hints else "") + "; nothing was run")


def refuse_unmatched_limit(groups: dict) -> None:
    """In a pyinfra run's inventory file: stop with exit 2 when a --limit pattern selects no host."""
    from roslab.summary import cli_option

    problem = limit_problem(groups, cli_option("limit") or ())
    if problem:
        print(problem, file=sys.stderr)
        sys.exit(2)


def quiet_paramiko() -> None:
    """No paramiko traceback on stderr: a Pi whose sshd is still starting accepts the TCP
    connection and hangs up, and paramiko's transport thread logs "Error reading SSH protocol
    banner" with two tracebacks through Python's last-resort handler (paramiko's logger has
    none of its own). pyinfra reports the same failure as one line naming the host."""
    import logging

    paramiko_logger = logging.getLogger("paramiko")
    if not any(isinstance(handler, logging.NullHandler) for handler in paramiko_logger.handlers):
        paramiko_logger.addHandler(logging.NullHandler())


def select_roster_hosts(classroom: Classroom, patterns) -> tuple[list, list[str]]:
    """(the roster's hosts `--limit` patterns select, in roster order; the patterns that select
    none), without building pyinfra's inventory: as pyinfra's --limit, a pattern is a team (its
    name or its group's, `team-1` or `team_1`), a role, a distro, or host names with wildcards."""
    hosts = list(classroom.hosts)
    chosen: set[str] = set()
    unmatched = []
    for pattern in patterns or ():
        matched = [host.name for host in hosts if fnmatch.fnmatch(host.name, pattern)
                   or pattern in (host.team, host.team.replace("-", "_"), host.role, host.distro)]
        chosen.update(matched)
        if not matched:
            unmatched.append(pattern)
    return ([host for host in hosts if host.name in chosen] if patterns else hosts), unmatched


def add_limit_argument(parser: argparse.ArgumentParser, what: str = "") -> None:
    """--limit NAME (repeatable), as every roslab command that reaches hosts takes it; --host
    is the same option's older name."""
    parser.add_argument("--limit", "--host", dest="limit", action="append", metavar="NAME",
                        help=LIMIT_HELP + what)


def roster_state(groups: dict, limit: list[str] | None = None, **config):
    """A pyinfra State over the roster's hosts that `limit` selects (not connected), set as
    pyinfra's current state, config and inventory. `config`: pyinfra Config options."""
    from pyinfra.api import Config, State
    from pyinfra.context import ctx_config, ctx_inventory, ctx_state

    from roslab import ssh_keepalive, sudo

    quiet_paramiko()
    sudo.install()  # no sudo password on a host's command line, whatever the command
    ssh_keepalive.install()  # a host that goes silent is lost in seconds, not waited for forever
    inventory = roster_inventory(groups)
    chosen = select_hosts(inventory, limit)
    state = State(check_for_changes=False)
    state.cwd = os.getcwd()
    settings = Config(**config)
    ctx_state.set(state)
    ctx_config.set(settings)
    ctx_inventory.set(inventory)
    state.init(inventory, settings, initial_limit=chosen)
    return state


def connected_state(groups: dict, limit: list[str] | None = None, **config):
    """`roster_state`, connected (in parallel) to the hosts it selects; the ones that cannot be
    reached are left inactive (`state.active_hosts` holds the others)."""
    from pyinfra.api.connect import connect_all
    from pyinfra.api.exceptions import PyinfraError

    state = roster_state(groups, limit, **config)
    state.config.FAIL_PERCENT = None  # an unreachable host is a row of the result, not an error
    try:
        connect_all(state)
    except PyinfraError:
        pass  # "No hosts remaining!": every host is unreachable, which the caller reports
    return state


def fail(problem: Exception) -> int:
    print(problem, file=sys.stderr)
    return 1
