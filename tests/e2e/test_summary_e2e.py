"""The run summary (roslab/reporting/summary.py) at the end of a real run on sandbox hosts.

On the session's converged default class (restored): a no-op and a converged `--dry` fit one
screen; then a run that moves both teams to new domains, with two hosts made to fail for real,
each in its own way: one is stopped by roslab while planning (the roster expects Ubuntu 22.04,
the host runs 24.04), one fails while executing (apt cannot find an extra package). The summary
names each with the step and the reason; the other two hosts carry on and are `changed`.
(The failed-host run used to start from freshly imaged hosts: a whole converge, minutes, for
a summary that a converged class shows the same way.)
"""

from __future__ import annotations

import subprocess

import pytest
import yaml

from tests.e2e.conftest import BIN, REPO, summary_lines

pytestmark = pytest.mark.e2e

STOPPED = "team1-robot"  # runs 24.04; the roster will say 22.04
BROKEN = "team2-main"  # gets an extra package that no archive has
MISSING = "roslab-e2e-no-such-package"


SCREEN = 30  # lines: a no-op and a converged --dry of the 4-host class fit one terminal screen


def plain_pyinfra(sandbox, *args: str) -> subprocess.CompletedProcess:
    """pyinfra as a teacher runs it (no --json): the compact output and roslab's summary."""
    return subprocess.run([str(BIN / "pyinfra"), *args, "inventories/sandbox.py", "deploy.py"], cwd=REPO,
                          env={**sandbox.env, "COLUMNS": "120"}, capture_output=True, text=True, timeout=1800)


def test_a_no_op_and_a_converged_dry_run_fit_one_screen(default_class):
    # The session's converge, restored: its "0 changed" below also says restored is converged.
    sandbox = default_class
    no_op = plain_pyinfra(sandbox, "-y")
    shown = (no_op.stdout + no_op.stderr).splitlines()
    print("\n".join(["--- the no-op, as a teacher sees it:", *shown]))  # pytest -s shows it
    assert no_op.returncode == 0, "\n".join(shown[-60:])
    assert len(shown) <= SCREEN, "\n".join(shown)
    assert "Grand total" not in no_op.stderr and "No Change" not in no_op.stderr  # pyinfra's results table
    assert "exit code 0: 0 failed, 0 changed, 4 ok (4 hosts)" in no_op.stderr, no_op.stderr

    dry = plain_pyinfra(sandbox, "--dry")
    shown = (dry.stdout + dry.stderr).splitlines()
    print("\n".join(["--- the converged --dry:", *shown]))
    assert dry.returncode == 0, "\n".join(shown[-60:])
    assert len(shown) <= SCREEN, "\n".join(shown)
    assert "Conditional Change" not in dry.stderr, dry.stderr  # "4 (...)" rows for restarts that will not run
    assert any(line.strip() == "nothing would change on any host" for line in shown), dry.stderr
    assert "Ready: deploy.py" not in dry.stderr  # one line per host that says nothing
    assert "exit code 0: 0 failed, 0 changed, 4 ok (4 hosts)" in dry.stderr, dry.stderr


def test_a_failed_host_is_named_with_its_step_and_reason_and_the_others_carry_on(default_class, tmp_path):
    # After the no-op above (it needs the class as the sandbox's roster left it): the teacher moved
    # both teams to new domains, so the hosts that carry on have something to change, and made
    # two mistakes.
    sandbox = default_class
    data = yaml.safe_load(sandbox.roster_path.read_text())
    for team in data["teams"].values():
        team["ros_domain_id"] = team["ros_domain_id"] + 50
    data["teams"]["team1"]["hosts"][STOPPED]["ubuntu_release"] = "22.04"
    data["teams"]["team2"]["hosts"][BROKEN]["ros_extra_packages"] = [MISSING]
    roster = tmp_path / "roster.yaml"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))

    run = sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})

    assert run.returncode == 1, run.stderr[-6000:]
    header, *rows, last = summary_lines(run.stderr)
    assert header == "--> roslab summary", run.stderr[-4000:]
    by_host = {row.split()[0]: row for row in rows}
    assert sorted(by_host) == sorted(host.name for host in sandbox.hosts), rows

    stopped = by_host[STOPPED]
    assert stopped.startswith(f'{STOPPED} failed in "The host runs an Ubuntu release'), stopped
    assert ('": ubuntu_release is 22.04 (jammy) in the roster but the host runs Ubuntu noble; '
            "nothing was changed on it") in stopped, stopped

    broken = by_host[BROKEN]
    assert broken.startswith(f'{BROKEN} failed in "'), broken
    assert "Ensure ROS 2 humble is installed" in broken, broken
    assert broken.endswith(f'": E: Unable to locate package {MISSING}'), broken

    for host in set(by_host) - {STOPPED, BROKEN}:
        assert by_host[host] == f"{host} changed", by_host[host]  # on their new domain
    assert last == "exit code 1: 2 failed, 2 changed, 0 ok (4 hosts)", last
    assert "executed 0 commands" not in "\n".join(rows)
