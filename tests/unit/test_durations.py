"""tests/durations.py: the run's seconds per module and its slowest tests, printed and kept in a file.

One test runs a small pytest session in a child process (the conftest's hooks, a real run), the
others feed reports to the recorder directly.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from types import SimpleNamespace

from tests import conftest as schedule
from tests.durations import Durations, ENV, module_seconds

REPO = Path(__file__).resolve().parents[2]


def test_a_test_counts_its_setup_call_and_teardown_and_a_module_its_tests():
    record = Durations()
    for nodeid, seconds in [("tests/e2e/test_a.py::test_one", 30.0), ("tests/e2e/test_a.py::test_one", 2.0),
                            ("tests/e2e/test_a.py::test_two", 1.0), ("tests/unit/test_b.py::test_x[1]", 0.5)]:
        record.add(nodeid, seconds, "passed")
    assert record.tests["tests/e2e/test_a.py::test_one"] == 32.0
    assert record.modules() == {"tests/e2e/test_a.py": (33.0, 2), "tests/unit/test_b.py": (0.5, 1)}


def test_the_first_phase_that_did_not_pass_names_the_outcome():
    record = Durations()
    record.add("t.py::a", 1.0, "failed")
    record.add("t.py::a", 0.1, "passed")
    record.add("t.py::b", 0.1, "passed")
    record.add("t.py::b", 0.1, "skipped")
    assert record.outcomes == {"t.py::a": "failed", "t.py::b": "skipped"}


def test_the_rendering_lists_modules_slowest_first_and_only_the_slowest_tests():
    record = Durations()
    for index in range(30):
        record.add(f"tests/unit/test_m{index % 3}.py::test_{index}", float(index), "passed")
    text = record.render(slowest=25)
    modules = [line for line in text.splitlines() if line.startswith("| ") and "tests/unit/test_m" in line
               and "::" not in line]
    assert [line.rsplit("|", 2)[1].strip() for line in modules] == [
        "tests/unit/test_m2.py", "tests/unit/test_m1.py", "tests/unit/test_m0.py"]
    slow = [line for line in text.splitlines() if "::test_" in line]
    assert len(slow) == 25
    assert "::test_29 |" in slow[0] and "::test_5 |" in slow[-1]
    assert "::test_4 |" not in text
    assert "30 tests, 435.0 s" in text


def test_the_file_is_written_where_the_environment_names_it_and_nowhere_when_unset(tmp_path):
    record = Durations()
    record.add("t.py::a", 1.0, "passed")
    assert record.write({}) is None
    assert record.write({ENV: ""}) is None
    target = tmp_path / "out/test-durations.md"
    assert record.write({ENV: str(target)}) == target
    assert target.read_text() == record.render()


def test_a_pytest_run_prints_the_durations_and_leaves_the_file(tmp_path):
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "test_sample.py").write_text("import time\n\ndef test_slow():\n    time.sleep(0.2)\n\n"
                                          "def test_fast():\n    pass\n")
    (suite / "conftest.py").write_text((REPO / "tests/conftest.py").read_text())
    target = tmp_path / "test-durations.md"
    env = {**os.environ, ENV: str(target), "PYTHONPATH": str(REPO)}
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(suite)],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "durations (tests/durations.py)" in run.stdout
    assert f"durations written to {target}" in run.stdout
    text = target.read_text()
    assert "2 tests" in text
    rows = [line for line in text.splitlines() if "::test_" in line]
    assert "test_sample.py::test_slow |" in rows[0]
    assert float(rows[0].split("|")[1]) >= 0.2


def test_make_test_and_so_ci_run_leave_the_durations_in_the_checkout():
    """`.ci/run` ends in `make test`; its pytest writes test-durations.md beside the Makefile (gitignored)."""
    # Run inside `make test` too (CI): a nested make prints "make[1]: Leaving directory" last
    # unless it is told not to and forgets the outer make.
    outer = {key: value for key, value in os.environ.items() if key not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    shown = subprocess.run(["make", "--no-print-directory", "-n", "test"], cwd=REPO, capture_output=True,
                           text=True, timeout=60, env=outer)
    assert shown.returncode == 0, shown.stderr
    assert f"{ENV}={REPO}/test-durations.md " in shown.stdout.splitlines()[-1]
    assert "exec make test" in (REPO / ".ci/run").read_text()
    assert "test-durations.md" in (REPO / ".gitignore").read_text().splitlines()


def test_a_kept_record_gives_back_each_modules_seconds():
    record = Durations()
    record.add("tests/e2e/test_a.py::test_one", 30.0, "passed")
    record.add("tests/unit/test_b.py::test_x[1]", 0.5, "passed")
    assert module_seconds(record.render()) == {"tests/e2e/test_a.py": 30.0, "tests/unit/test_b.py": 0.5}
    kept = module_seconds(schedule.KEPT_DURATIONS.read_text())  # the record the schedule reads
    assert kept["tests/e2e/test_robots_e2e.py"] > 60 and len(kept) > 40


def fake_item(nodeid: str, *fixtures: str):
    return SimpleNamespace(nodeid=nodeid, fixturenames=list(fixtures))


def test_the_schedule_keeps_the_session_sandboxs_modules_together_and_sends_the_longest_group_first():
    items = [fake_item("tests/unit/test_u.py::test_1"), fake_item("tests/e2e/test_a.py::test_1", "e2e_sandbox"),
             fake_item("tests/e2e/test_a.py::test_2"), fake_item("tests/e2e/test_big.py::test_1"),
             fake_item("tests/e2e/test_new.py::test_1"), fake_item("tests/e2e/test_b.py::test_1", "e2e_sandbox")]
    groups = schedule.schedule_groups(items)
    # a module with one test on the session's sandbox is in its group whole (test_a's test_2 too)
    assert groups == {"tests/unit/test_u.py": "tests/unit/test_u.py", "tests/e2e/test_a.py": schedule.SESSION_SANDBOX_GROUP,
                      "tests/e2e/test_big.py": "tests/e2e/test_big.py", "tests/e2e/test_new.py": "tests/e2e/test_new.py",
                      "tests/e2e/test_b.py": schedule.SESSION_SANDBOX_GROUP}
    measured = {"tests/e2e/test_a.py": 200.0, "tests/e2e/test_b.py": 150.0, "tests/e2e/test_big.py": 300.0,
                "tests/unit/test_u.py": 1.0}
    order = [item.nodeid for item in schedule.scheduled(items, groups, measured)]
    # the session group (350 s) first, in the order collected, then 300 s, then the unmeasured e2e module
    assert order == ["tests/e2e/test_a.py::test_1", "tests/e2e/test_a.py::test_2", "tests/e2e/test_b.py::test_1",
                     "tests/e2e/test_big.py::test_1", "tests/e2e/test_new.py::test_1", "tests/unit/test_u.py::test_1"]


def test_two_workers_run_each_module_whole_and_the_session_sandboxs_modules_on_one(tmp_path):
    """The scheduling `make test` uses, in a real pytest-xdist run of a small suite."""
    suite = tmp_path / "tests"
    (suite / "e2e").mkdir(parents=True)
    (suite / "conftest.py").write_text((REPO / "tests/conftest.py").read_text())
    (suite / "e2e" / "conftest.py").write_text("import pytest\n\n@pytest.fixture(scope='session')\n"
                                               "def e2e_sandbox():\n    return 'class'\n")
    body = ("import os, pathlib\n\ndef note(name):\n    pathlib.Path(os.environ['RAN'], name).write_text("
            "os.environ.get('PYTEST_XDIST_WORKER', 'main'))\n\n")
    for module, uses in [("a", True), ("b", True), ("c", False), ("d", False)]:
        argument = "e2e_sandbox" if uses else ""
        (suite / "e2e" / f"test_{module}.py").write_text(body + "".join(
            f"def test_{module}{index}({argument}):\n    note('{module}{index}')\n\n" for index in range(3)))
    ran = tmp_path / "ran"
    ran.mkdir()
    target = tmp_path / "test-durations.md"
    env = {**os.environ, ENV: str(target), "PYTHONPATH": str(REPO), "RAN": str(ran)}
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist",
                          "loadgroup", "--no-loadscope-reorder", "tests"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    worker = {path.name: path.read_text() for path in ran.iterdir()}
    assert len(worker) == 12 and set(worker.values()) <= {"gw0", "gw1"}
    for module in "abcd":
        assert len({worker[f"{module}{index}"] for index in range(3)}) == 1, worker
    assert worker["a0"] == worker["b0"], worker  # the session's sandbox is set up once
    assert "tests/e2e/test_a.py::test_a0 |" in target.read_text()
