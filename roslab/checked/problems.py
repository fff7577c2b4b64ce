"""Problems found in a roster, each located by file:line, team, host and field."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path


def display_path(path: Path | str) -> str:
    """A path as the user would type it: relative to the working directory if inside it."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError, RuntimeError):  # RuntimeError: a symlink loop (Python < 3.13)
        return str(path)


@dataclass(frozen=True)
class Problem:
    """One error or warning, located as precisely as the roster allows."""

    path: str
    message: str
    line: int | None = None
    team: str | None = None
    host: str | None = None
    field: str | None = None

    def __str__(self) -> str:
        where = f"{self.path}:{self.line}" if self.line else self.path
        context = []
        if self.team is not None:
            context.append(f"team {self.team!r}")
        if self.host is not None:
            context.append(f"host {self.host!r}")
        if self.field is not None:
            context.append(f"field {self.field!r}")
        if not context:
            return f"{where}: {self.message}"
        return f"{where}: {', '.join(context)}: {self.message}"


def team_wide(problems: list[Problem], team_hosts: dict[str, set[str]]) -> list[Problem]:
    """`problems` with one that every host of a team has (the same file, line, field and
    message: a value the team or the classroom sets) said once for the team, where its
    first host's was; one that only some of the team's hosts have still names each host.

    `team_hosts`: each team's hosts (those the roster could read)."""
    hosts_of: dict[Problem, set[str]] = {}
    for problem in problems:
        if problem.team is not None and problem.host is not None:
            hosts_of.setdefault(replace(problem, host=None), set()).add(problem.host)
    shown: list[Problem] = []
    said: set[Problem] = set()
    for problem in problems:
        team_problem = replace(problem, host=None)
        hosts = hosts_of.get(team_problem, set()) if problem.host is not None else set()
        every = team_hosts.get(problem.team) if problem.team is not None else None
        if len(hosts) > 1 and every is not None and hosts >= every:
            if team_problem not in said:
                said.add(team_problem)
                shown.append(team_problem)
        else:
            shown.append(problem)
    return shown


class RosterError(Exception):
    """A roster that must not be deployed; `problems` lists every error found."""

    def __init__(self, problems: list[Problem]):
        self.problems = problems
        super().__init__("\n".join(str(problem) for problem in problems))


class Report:
    """Collects problems so that a roster's errors are all reported together, once each."""

    def __init__(self, path: Path | str):
        self.path = display_path(path)
        self.errors: list[Problem] = []
        self.warnings: list[Problem] = []
        self._seen: set[Problem] = set()  # a set: a 5,000-host roster stays linear

    def _add(self, problems: list[Problem], message: str, where: dict) -> None:
        problem = Problem(self.path, message, **where)
        if problem not in self._seen:
            self._seen.add(problem)
            problems.append(problem)

    def error(self, message: str, **where) -> None:
        self._add(self.errors, message, where)

    def add(self, problem: Problem) -> None:
        """An error found in another file the roster names (a .repos file), with its own path."""
        if problem not in self._seen:
            self._seen.add(problem)
            self.errors.append(problem)

    def warning(self, message: str, **where) -> None:
        self._add(self.warnings, message, where)

    def extend(self, other: "Report") -> None:
        for problem in other.errors:
            if problem not in self._seen:
                self._seen.add(problem)
                self.errors.append(problem)
