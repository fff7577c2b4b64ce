"""`roslab status` on the sandbox classroom, end to end, over real SSH.

One deploy converges the freshly imaged class (team1 on an emulated Ubuntu 24.04, team2 on
22.04) and records its run beside the roster; then status shows every host reachable with
its release, distro, domain and running nodes, and the run's time. A --dry run records
nothing. With one host powered off, that host is a row that says unreachable (bounded,
never a hang) while the others are shown as before, on the terminal and on the page,
which a real browser opens. `--listen` reports the sandbox's stand-in ROS for what it is.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time

import pytest

from roslab.reporting import runs
from roslab.sandbox import lifecycle
from tests.unit.fixtures.browser import chromium_missing, dump_dom

pytestmark = pytest.mark.e2e

STOPPED = "team1-robot"
EXPECTED = {
    "team1-main": ("24.04 noble", "jazzy", "11"),
    "team1-robot": ("24.04 noble", "jazzy", "11"),
    "team2-main": ("22.04 jammy", "humble", "12"),
    "team2-robot": ("22.04 jammy", "humble", "12"),
}
COLUMNS = ("TEAM", "HOST", "ROLE", "ADDRESS", "SSH", "UBUNTU", "ROS", "DOMAIN", "DISCOVERY", "NODES",
           "UNDERLAY", "LAST RUN", "LAST SUCCESS", "NOTE")


@pytest.fixture(scope="module")
def class_converged(default_class, default_class_saved):
    """The session's classroom converged (the session's converge from fresh hosts, restored for
    this module with its run records); fresh hosts after it (and the stopped one back)."""
    assert sorted(host.name for host in default_class.hosts) == sorted(EXPECTED)
    return default_class, default_class_saved.started


def status(sandbox, *args: str, timeout: float = 120) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "roslab", "status", str(sandbox.roster_path), *args],
                            env=sandbox.env, capture_output=True, text=True, timeout=timeout)
    return result, time.monotonic() - started


def table(stdout: str) -> dict[str, dict[str, str]]:
    """The status table's rows by host, cut at the header's column offsets."""
    lines = stdout.splitlines()
    header_index = next(i for i, line in enumerate(lines) if line.startswith("TEAM "))
    header = lines[header_index]
    offsets = [header.index(column) for column in COLUMNS]
    rows = {}
    for line in lines[header_index + 2:]:
        if not line.strip():
            break
        cells = [line[start:end].strip() for start, end in zip(offsets, offsets[1:] + [None])]
        rows[cells[1]] = dict(zip(COLUMNS, cells))
    return rows


def test_status_shows_the_converged_class_and_its_last_run(class_converged, tmp_path):
    sandbox, started = class_converged
    recorded = runs.read_runs(sandbox.roster_path)
    for name in EXPECTED:
        assert recorded[name].result == "changed", recorded[name]
        assert recorded[name].last_run >= started and recorded[name].last_success == recorded[name].last_run

    result, elapsed = status(sandbox, "--html", str(tmp_path / "status.html"))

    assert result.returncode == 0, result.stdout + result.stderr
    assert elapsed < 30, elapsed
    rows = table(result.stdout)
    assert sorted(rows) == sorted(EXPECTED)
    for name, (ubuntu, distro, domain) in EXPECTED.items():
        row = rows[name]
        assert row["ADDRESS"] == sandbox.host(name).address
        assert (row["SSH"], row["UBUNTU"], row["ROS"], row["DOMAIN"], row["DISCOVERY"], row["NODES"]) == (
            "ok", ubuntu, distro, domain, "multicast", "active (running)"), row
        assert row["LAST RUN"].startswith("changed ") and "never" not in row["LAST SUCCESS"], row
        assert row["NOTE"] == "", row
    page = (tmp_path / "status.html").read_text()
    assert page.count('data-level="ok"') == 4


def test_a_dry_run_records_nothing(class_converged):
    sandbox, _ = class_converged
    path = runs.runs_path(sandbox.roster_path)
    before = path.read_bytes()

    dry = sandbox.pyinfra("--dry")

    assert dry.returncode == 0, dry.stderr[-4000:]
    assert path.read_bytes() == before


def test_a_stopped_host_is_a_row_that_says_unreachable_and_the_page_shows_it(class_converged, tmp_path):
    sandbox, _ = class_converged
    lifecycle.power_cut(STOPPED, sandbox.instance)
    try:
        page = tmp_path / "status.html"
        result, elapsed = status(sandbox, "--html", str(page))
    finally:
        # back on, from its converged disk, for the next tests (a fresh image would make the
        # next run of team1 a whole converge of it: minutes)
        lifecycle.power_on(STOPPED, sandbox.instance)
        sandbox.ssh(STOPPED, "systemctl is-system-running --wait", timeout=180)

    assert result.returncode == 1, result.stdout + result.stderr
    assert elapsed < 40, elapsed
    assert f"1 of 4 hosts unreachable: {STOPPED}" in result.stderr
    rows = table(result.stdout)
    assert rows[STOPPED]["SSH"] == "unreachable" and rows[STOPPED]["NODES"] == "?"
    assert rows[STOPPED]["NOTE"], rows[STOPPED]
    assert rows[STOPPED]["DOMAIN"] == "11 (roster)"
    for name in set(EXPECTED) - {STOPPED}:
        assert (rows[name]["SSH"], rows[name]["NODES"]) == ("ok", "active (running)"), rows[name]

    if chromium_missing():
        pytest.skip(chromium_missing())
    dom = dump_dom(page)
    boxes = dict(re.findall(r'<g class="host" data-host="([^"]*)" data-level="([^"]*)"', dom))
    assert boxes == {**dict.fromkeys(EXPECTED, "ok"), STOPPED: "bad"}
    assert re.findall(r'<section class="team" data-team="([^"]*)"', dom) == ["team1", "team2"]


def test_listen_says_the_stand_in_ros_has_no_runtime_and_stays_bounded(class_converged):
    sandbox, _ = class_converged
    if sandbox.real_ros:
        pytest.skip("the sandbox serves real ROS 2: test_ros_runtime_e2e checks what --listen hears")

    result, elapsed = status(sandbox, "--listen", "--listen-timeout", "3", "--limit", "team2")

    assert result.returncode == 0, result.stdout + result.stderr
    assert elapsed < 60, elapsed
    assert "team team2: no ROS runtime on team2-main: not verified" in result.stdout
    page = runs.runs_path(sandbox.roster_path).parent / "status.html"
    assert "topics seen: no ROS 2 runtime on the main host" in page.read_text()


def test_a_stopped_discovery_server_is_named_by_status_and_verify(class_converged, tmp_path):
    """team1 on a Fast DDS discovery server (a class on Fast DDS, as test_discovery_e2e runs it):
    with the server stopped, both nodes services still run and the main hears nothing; status
    and verify name the server, not the topic."""
    import yaml

    sandbox, _ = class_converged
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"]["ros_middleware"] = "rmw_fastrtps_cpp"
    data["teams"]["team1"]["ros_discovery_mode"] = "discovery_server"
    roster = tmp_path / "roster.yaml"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))
    run = sandbox.pyinfra("--limit", "team1", inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})
    assert run.returncode == 0, run.stderr[-6000:]
    sandbox.sudo("team1-main", "systemctl stop roslab-discovery-server; systemctl reset-failed roslab-discovery-server",
                 check=True)
    stopped = "roslab-discovery-server.service on team1-main is inactive (dead)"

    result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster), "--limit", "team1",
                             "--html", str(tmp_path / "status.html")],
                            env=sandbox.env, capture_output=True, text=True, timeout=120)
    rows = table(result.stdout)
    assert rows["team1-main"]["NODES"] == "active (running)", rows["team1-main"]
    assert rows["team1-main"]["NOTE"].startswith(stopped), rows["team1-main"]
    assert rows["team1-robot"]["NOTE"] == "", rows["team1-robot"]

    verified = subprocess.run([sys.executable, "-m", "roslab", "verify", str(roster), "--limit", "team1"],
                              env=sandbox.env, capture_output=True, text=True, timeout=300)
    assert verified.returncode == 1, verified.stdout + verified.stderr
    assert f"FAIL {stopped}" in verified.stdout, verified.stdout
