"""How a `roslab` command takes a roster and reaches its hosts: one way for every command.

    roslab COMMAND [ROSTER] [--limit NAME ...]

`add_roster_argument` registers ROSTER (and `--limit`) the same way on every subcommand;
`load_classroom` loads it (the default roster found as `inventories/lab.py` finds it) and
turns a mistake into lines on stderr and an exit status, never a traceback;
`roster_state` makes the pyinfra State of the roster's hosts as deploy.py's inventory makes
them (the same groups and connection data), through pyinfra's public API only, and
`connected_state` connects it. `--limit` selects as pyinfra's does, through one matcher
(`limit_selection`) for pyinfra's runs and every command: a group (team, role, distro) or
host names, with shell-style wildcards; a pattern that selects nothing is one line, exit 2.
A command that once named its hosts first refuses that older form in one line giving this
one (`stale_host_form`).
"""

from __future__ import annotations

import argparse
import difflib
import fnmatch
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from roslab.roster import Classroom, RosterError, default_roster_path, display_path, load_roster

ROSTER_HELP = ("roster file (default: $ROSLAB_ROSTER, else classroom.yaml or inventories/classroom.yaml "
               "in this folder if present, else inventories/lab.yaml)")
LIMIT_HELP = ("a team (`-` written `_`), role or distro group, or host names with wildcards, as pyinfra's "
              "--limit (repeatable)")


def add_roster_argument(parser: argparse.ArgumentParser, limit: bool = True, what: str = "") -> None:
    """ROSTER (optional, positional) and, with `limit`, --limit NAME (repeatable; `what`: more help)."""
    parser.add_argument("roster", nargs="?", metavar="ROSTER", help=ROSTER_HELP)
    if limit:
        add_limit_argument(parser, what)


def add_limit_argument(parser: argparse.ArgumentParser, what: str = "") -> None:
    """--limit NAME (repeatable), as every roslab command that reaches hosts takes it. `--host`,
    the same option's older name, is still read (not shown in the help)."""
    parser.add_argument("--limit", action="append", metavar="NAME", help=LIMIT_HELP + what)
    parser.add_argument("--host", dest="limit", action="append", help=argparse.SUPPRESS)


def add_stale_host_form(parser: argparse.ArgumentParser) -> None:
    """Read (and `stale_host_form` refuses) a command's older shape, which named its hosts first:
    `roslab COMMAND HOST... [ROSTER]` or `HOST... --roster ROSTER`."""
    parser.add_argument("stale_words", nargs="*", help=argparse.SUPPRESS)
    parser.add_argument("--roster", dest="stale_roster", help=argparse.SUPPRESS)


def _names_a_roster(word: str) -> bool:
    return Path(word).suffix in (".yaml", ".yml") or Path(word).is_file()


def stale_host_form(args: argparse.Namespace, command: str) -> str | None:
    """One line giving the command's shape, when it was given hosts the older way (names
    before or instead of the roster, or `--roster`), else None."""
    words = [word for word in (args.roster, *args.stale_words) if word]
    if args.stale_roster is None and len(words) <= 1 and all(_names_a_roster(word) for word in words):
        return None
    rosters = [word for word in words if _names_a_roster(word)]
    roster = args.stale_roster or (rosters[0] if rosters else None)
    hosts = [word for word in words if word != roster] + list(args.limit or ())
    shown = " ".join([f"roslab {command}", *([roster] if roster else []),
                      *(f"--limit {host}" for host in hosts or ["HOST"])])
    return (f"roslab {command}: hosts are named by --limit, after the roster, as in every roslab "
            f"command: {shown}")


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


def limit_selection(groups: Mapping[str, Sequence[str]], patterns) -> tuple[list[str], list[str]]:
    """(the host names `--limit` patterns select, in the order `groups` lists them, every host
    without patterns; the patterns that select none). The one matcher of every roslab command,
    as pyinfra's own --limit (pyinfra_cli `_get_inventory_pattern_matches`): a pattern that names
    a group (a team, role or distro) selects its hosts, any other pattern the host names
    it matches with shell-style wildcards. `groups`: group name -> host names
    (`roslab.roster.group_names`)."""
    every = list(dict.fromkeys(name for names in groups.values() for name in names))
    if not patterns:
        return every, []
    chosen: set[str] = set()
    unmatched = []
    for pattern in patterns:
        if pattern in groups:
            matched = list(groups[pattern])
        else:
            matched = [name for name in every if fnmatch.fnmatch(name, pattern)]
        chosen.update(matched)
        if not matched:
            unmatched.append(pattern)
    return [name for name in every if name in chosen], unmatched


def names_of(groups: dict) -> dict[str, list[str]]:
    """`roslab.roster.inventory_groups(...)` as group name -> host names."""
    return {group: [name for name, _ in entries] for group, entries in groups.items()}


def limit_problem(groups: Mapping[str, Sequence[str]], patterns, command: str = "roslab") -> str | None:
    """One line naming each `--limit` pattern that selects no host of the roster, or None.
    `groups`: group name -> host names (`roslab.roster.group_names`, or `names_of`).

    pyinfra only warns about such a pattern and goes on with the others (with none left it
    does nothing and exits 0): a typo in a team's name, or `--limit a,b` (one pattern with a
    comma, which pyinfra does not split), would leave hosts out of a run that says it worked."""
    _, unmatched = limit_selection(groups, patterns)
    if not unmatched:
        return None
    names = sorted({*groups, *(name for members in groups.values() for name in members)})
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


def limited_hosts(classroom: Classroom, patterns, command: str) -> tuple[list, str | None]:
    """(the roster's hosts `--limit` patterns select, in roster order; None, or the one line
    `limit_problem` gives when a pattern selects none) for a command that works from the
    roster alone, before any host is reached or any file beside the roster is read."""
    from roslab.roster.inventory import group_names

    groups = group_names(classroom)
    problem = limit_problem(groups, patterns, command)
    if problem:
        return [], problem
    chosen = set(limit_selection(groups, patterns)[0])
    return [host for host in classroom.hosts if host.name in chosen], None


def refuse_unmatched_limit(groups: dict) -> None:
    """In a pyinfra run's inventory file: stop with exit 2 when a --limit pattern selects no host."""
    from roslab.reporting.summary import cli_option

    problem = limit_problem(names_of(groups), cli_option("limit") or ())
    if problem:
        print(problem, file=sys.stderr)
        sys.exit(2)




def roster_state(groups: dict, limit: list[str] | None = None, **config):
    """A pyinfra State over the roster's hosts that `limit` selects (not connected), set as
    pyinfra's current state, config and inventory. `config`: pyinfra Config options."""
    from pyinfra.api import Config, State
    from pyinfra.context import ctx_config, ctx_inventory, ctx_state

    from roslab.ssh import keepalive as ssh_keepalive
    from roslab.ssh import sudo
    from roslab.ssh.quiet import quiet_paramiko

    quiet_paramiko()
    sudo.install()  # no sudo password on a host's command line, whatever the command
    ssh_keepalive.install()  # a host that goes silent is lost in seconds, not waited for forever
    inventory = roster_inventory(groups)
    names, _ = limit_selection(names_of(groups), limit)
    chosen = [inventory.get_host(name) for name in names]
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
