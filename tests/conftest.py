"""Checks that hold for the whole test session (unit and end-to-end tests share one process)."""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

from tests.durations import Durations, module_seconds


def _gevent_patched() -> bool:
    monkey = sys.modules.get("gevent.monkey")
    return bool(monkey and monkey.is_module_patched("subprocess"))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    """Fail the test that imports pyinfra_cli (or anything that gevent-patches) in-process.

    pyinfra_cli monkey-patches the process with gevent on import: every later test would
    then run subprocesses and threads through gevent's hub, and the long end-to-end runs
    leaked file descriptors until the session died with EMFILE. Run pyinfra's CLI code in
    a child process instead.
    """
    patched_before = _gevent_patched()
    yield
    if not patched_before and _gevent_patched():
        pytest.fail(f"{item.nodeid} gevent-patched the test process (imported pyinfra_cli?): "
                    "run that code in a child process", pytrace=False)


def pytest_collection_finish(session):
    """The same check for imports at collection time (a test module importing pyinfra_cli)."""
    if _gevent_patched():
        raise pytest.UsageError("a test module gevent-patched the test process at import "
                                "(imported pyinfra_cli?): run that code in a child process")


# The run's cost, kept (tests/durations.py): every module's seconds and the 25 slowest tests,
# printed at the end and written to the file ROSLAB_TEST_DURATIONS names (`make test`).
_DURATIONS = Durations()


def pytest_runtest_logreport(report):
    _DURATIONS.add(report.nodeid, report.duration, report.outcome)


def pytest_terminal_summary(terminalreporter):
    if not _DURATIONS.tests:
        return
    terminalreporter.section("durations (tests/durations.py)")
    terminalreporter.write(_DURATIONS.render())
    written = _DURATIONS.write()
    if written:
        terminalreporter.write_line(f"durations written to {written}")


# Two modules at a time (`make test`: pytest-xdist's `-n 2 --dist loadgroup`, with the scheduler
# below). A module's tests stay together on one worker (its sandbox class is set up once), and
# every module that uses the session's sandbox (`e2e_sandbox`: the saved default class) is one
# group, so that class is converged once per run, not once per worker. The groups go out longest
# first, by the durations the last kept record measured (the longest-processing-time rule): the
# long end-to-end modules start at once and the unit modules fill the gaps at the end.
# xdist's own loadgroup reads `xdist_group` marks through the test ids, which pytest 9.2 no longer
# lets a plugin change (pytest-xdist#1386): the workers, which collect, write each module's group
# to a file the controller names, and the controller's scheduler reads it.
SESSION_SANDBOX_GROUP = "e2e-session-sandbox"
KEPT_DURATIONS = Path(__file__).resolve().parent.parent / "bench" / "results" / "suite_durations.md"
UNMEASURED_E2E_SECONDS = 120.0  # a new end-to-end module, until a record measures it
GROUPS_INPUT = "roslab_test_groups"  # the workers' input naming the groups file


def module_of(item) -> str:
    return item.nodeid.split("::", 1)[0]


def schedule_groups(items: list) -> dict[str, str]:
    """Module -> its group: the session sandbox's when any of its tests uses it, else its own."""
    groups = {module_of(item): module_of(item) for item in items}
    for item in items:
        if "e2e_sandbox" in item.fixturenames:
            groups[module_of(item)] = SESSION_SANDBOX_GROUP
    return groups


def scheduled(items: list, groups: dict[str, str], measured: dict[str, float]) -> list:
    """`items` with their groups longest first (ties and the order inside a group as collected)."""
    seconds: dict[str, float] = {}
    for module, group in groups.items():
        default = UNMEASURED_E2E_SECONDS if module.startswith("tests/e2e/") else 0.0
        seconds[group] = seconds.get(group, 0.0) + measured.get(module, default)
    return sorted(items, key=lambda item: -seconds[groups[module_of(item)]])


def pytest_configure(config):
    if config.getoption("dist", "no") == "loadgroup" and not hasattr(config, "workerinput"):
        config.roslab_groups_file = Path(tempfile.mkdtemp(prefix="roslab-test-groups-")) / "groups.json"


def pytest_unconfigure(config):
    groups_file = getattr(config, "roslab_groups_file", None)
    if groups_file is not None:
        shutil.rmtree(groups_file.parent, ignore_errors=True)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """Controller: tell each worker where to write the groups."""
    node.workerinput[GROUPS_INPUT] = str(node.config.roslab_groups_file)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    groups_file = getattr(config, "roslab_groups_file", None)
    if groups_file is None:
        return None  # another --dist: xdist's own scheduler
    from xdist.scheduler import LoadScopeScheduling

    class ModuleGroupScheduling(LoadScopeScheduling):
        """xdist's per-scope scheduling with the workers' groups as scopes, in collection order."""

        def __init__(self, config, log=None) -> None:
            super().__init__(config, log)
            config.option.loadscopereorder = False  # the workers' order is the schedule
            self.groups: dict[str, str] | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self.groups is None:
                self.groups = json.loads(groups_file.read_text())
            module = nodeid.split("::", 1)[0]
            return self.groups.get(module, module)

    return ModuleGroupScheduling(config, log)


def pytest_collection_modifyitems(config, items):
    target = getattr(config, "workerinput", {}).get(GROUPS_INPUT)
    if target is None:
        return  # one process: the order as collected
    measured = module_seconds(KEPT_DURATIONS.read_text()) if KEPT_DURATIONS.is_file() else {}
    groups = schedule_groups(items)
    items[:] = scheduled(items, groups, measured)
    written = Path(f"{target}.{os.getpid()}")  # every worker writes the same groups; renamed into place
    written.write_text(json.dumps(groups))
    os.replace(written, target)
