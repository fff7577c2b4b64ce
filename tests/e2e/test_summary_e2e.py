"""The run summary (roslab/summary.py) at the end of a real run on sandbox hosts.

One run on freshly imaged hosts, with two hosts made to fail for real, each in its own
way: one is stopped by roslab while planning (the roster expects Ubuntu 22.04, the host
runs 24.04), one fails while executing (apt cannot find an extra package). The summary
names each with the step and the reason; the other two hosts carry on and are `changed`.
"""

from __future__ import annotations

import pytest
import yaml

from tests.e2e.conftest import summary_lines

pytestmark = pytest.mark.e2e

STOPPED = "team1-robot"  # runs 24.04; the roster will say 22.04
BROKEN = "team2-main"  # gets an extra package that no archive has
MISSING = "roslab-e2e-no-such-package"


def test_a_failed_host_is_named_with_its_step_and_reason_and_the_others_carry_on(fresh_hosts, tmp_path):
    data = yaml.safe_load(fresh_hosts.roster_path.read_text())
    data["teams"]["team1"]["hosts"][STOPPED]["ubuntu_release"] = "22.04"
    data["teams"]["team2"]["hosts"][BROKEN]["ros_extra_packages"] = [MISSING]
    roster = tmp_path / "roster.yaml"
    roster.write_text(yaml.safe_dump(data, sort_keys=False))

    run = fresh_hosts.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})

    assert run.returncode == 1, run.stderr[-6000:]
    header, *rows, last = summary_lines(run.stderr)
    assert header == "--> roslab summary", run.stderr[-4000:]
    by_host = {row.split()[0]: row for row in rows}
    assert sorted(by_host) == sorted(host.name for host in fresh_hosts.hosts), rows

    stopped = by_host[STOPPED]
    assert stopped.startswith(f'{STOPPED} failed in "The host runs an Ubuntu release'), stopped
    assert ('": ubuntu_release is 22.04 (jammy) in the roster but the host runs Ubuntu noble; '
            "nothing was changed on it") in stopped, stopped

    broken = by_host[BROKEN]
    assert broken.startswith(f'{BROKEN} failed in "'), broken
    assert "Ensure ROS 2 humble is installed" in broken, broken
    assert broken.endswith(f'": E: Unable to locate package {MISSING}'), broken

    for host in set(by_host) - {STOPPED, BROKEN}:
        assert by_host[host] == f"{host} changed", by_host[host]  # fresh hosts: provisioned
    assert last == "exit code 1: 2 failed, 2 changed, 0 ok (4 hosts)", last
    assert "executed 0 commands" not in "\n".join(rows)
