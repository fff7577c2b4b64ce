"""The test run's cost, kept: seconds per module and the slowest tests, as a file a maintainer reads later.

tests/conftest.py feeds every test report to a `Durations` and, at the end of the session, prints
`Durations.render()` and writes it to the file named by ROSLAB_TEST_DURATIONS (`make test` names
test-durations.md in the checkout; unset: printed only). A test's time is its setup, call and
teardown together, so a module's converge in a fixture counts to the module that paid for it.
"""

from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path

ENV = "ROSLAB_TEST_DURATIONS"
SLOWEST = 25


class Durations:
    """Seconds per test (setup + call + teardown) and per module, in the order they ran."""

    def __init__(self) -> None:
        self.tests: dict[str, float] = defaultdict(float)
        self.outcomes: dict[str, str] = {}

    def add(self, nodeid: str, seconds: float, outcome: str) -> None:
        """One phase of one test (pytest's report: nodeid, duration, outcome); the first phase
        that did not pass names the test's outcome (a failed setup, a skip)."""
        self.tests[nodeid] += seconds
        if self.outcomes.get(nodeid, "passed") == "passed":
            self.outcomes[nodeid] = outcome

    def modules(self) -> dict[str, tuple[float, int]]:
        """Module path -> (seconds, number of tests), in the order the modules first ran."""
        per: dict[str, list] = {}
        for nodeid, seconds in self.tests.items():
            entry = per.setdefault(nodeid.split("::", 1)[0], [0.0, 0])
            entry[0] += seconds
            entry[1] += 1
        return {path: (seconds, count) for path, (seconds, count) in per.items()}

    def render(self, slowest: int = SLOWEST) -> str:
        """Markdown: the total, each module's seconds (slowest first), then the `slowest` tests."""
        total = sum(self.tests.values())
        modules = sorted(self.modules().items(), key=lambda item: -item[1][0])
        lines = ["# Test durations", "",
                 f"{len(self.tests)} tests, {total:.1f} s in tests (setup + call + teardown)", "",
                 "## Per module", "", "| seconds | tests | module |", "|---:|---:|---|"]
        lines += [f"| {seconds:.1f} | {count} | {path} |" for path, (seconds, count) in modules]
        ranked = sorted(self.tests.items(), key=lambda item: -item[1])[:slowest]
        lines += ["", f"## The {len(ranked)} slowest tests", "", "| seconds | outcome | test |", "|---:|---|---|"]
        lines += [f"| {seconds:.2f} | {self.outcomes.get(nodeid, '?')} | {nodeid} |" for nodeid, seconds in ranked]
        return "\n".join(lines) + "\n"

    def write(self, environ=os.environ) -> Path | None:
        """The rendering written to the file ROSLAB_TEST_DURATIONS names (None when unset or empty)."""
        target = environ.get(ENV, "")
        if not target:
            return None
        path = Path(target)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.render())
        return path


def module_seconds(text: str) -> dict[str, float]:
    """Module path -> seconds, read from a rendering's "Per module" table (a kept record such as
    bench/results/suite_durations.md); rows that are not a module's are skipped."""
    seconds: dict[str, float] = {}
    for line in text.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[2].endswith(".py"):
            try:
                seconds[cells[2]] = float(cells[0])
            except ValueError:
                continue
    return seconds

