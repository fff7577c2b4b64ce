"""Checks that hold for the whole test session (unit and end-to-end tests share one process)."""

from __future__ import annotations

import sys

import pytest

from tests.durations import Durations


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
