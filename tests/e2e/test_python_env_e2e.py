"""A profile's Python requirements end to end: a 3-host sandbox class installs them once per class.

The roster adds a profile (`rover`, extending demo) whose sides declare the OSR rover's
requirements (adafruit-circuitpython-servokit, ina260, RPi.GPIO, smbus, pinned), served by the
sandbox upstream's stand-in index (roslab/sandbox/pypi.py: stand-in wheels, and stand-in sdists
for RPi.GPIO and smbus, which PyPI has only as sdists). The test checks what a teacher notices:

- the first run converges; each file was fetched from the index once for the class (the
  controller's `pip download`, never a host), and every host's venv imports the packages, with
  ROS's own Python (rclpy) beside them where the sandbox serves real ROS 2;
- the venv has the system's site packages and a COLCON_IGNORE, and belongs to the login user;
- a second run changes nothing and fetches nothing from the index;
- with `offline: true`, a freshly imaged host converges from the controller's wheelhouse alone.

Runs on its own sandbox instance (ROSLAB_WHEELS_E2E_SANDBOX=wheels-e2e, subnet
ROSLAB_WHEELS_E2E_SUBNET=10.213.191.0/24), taken down even when a test fails.
"""

from __future__ import annotations

import ipaddress
import os
import signal
from collections import Counter

import pytest
import yaml

from roslab.sandbox import pypi, upstream
from tests.e2e.conftest import _interrupt, bring_up

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_WHEELS_E2E_SANDBOX", "wheels-e2e")
SUBNET = os.environ.get("ROSLAB_WHEELS_E2E_SUBNET", "10.213.191.0/24")
HOSTS = 3
VENV = "osr_venv"
IMPORTS = "adafruit_servokit, ina260, RPi.GPIO, smbus"


@pytest.fixture(scope="module")
def classroom(sandbox_support, tmp_path_factory):
    previous = signal.signal(signal.SIGTERM, _interrupt)
    classroom, teardown = bring_up(INSTANCE, str(ipaddress.IPv4Network(SUBNET)), HOSTS)
    try:
        roster = yaml.safe_load(classroom.roster_path.read_text())
        side = {"python_packages": list(pypi.EXTRA_REQUIREMENTS), "python_venv": VENV}
        roster["profiles"] = {"rover": {"extends": "demo", "main": dict(side), "robot": dict(side)}}
        roster["classroom"]["robot_profile"] = "rover"
        # The controller's wheelhouse for this class only (a teacher's default is ~/.cache/roslab).
        roster["classroom"]["python_wheelhouse_dir"] = str(tmp_path_factory.mktemp("wheelhouse"))
        classroom.roster_path.write_text(yaml.safe_dump(roster, sort_keys=False))
        yield classroom
    finally:
        teardown()
        signal.signal(signal.SIGTERM, previous)


def index_requests(classroom, start: int) -> list[upstream.Request]:
    log = classroom.instance.state_dir / upstream.REQUEST_LOG
    return [r for r in upstream.read_requests(log)[start:] if r.path.startswith("/pypi/")]


def log_length(classroom) -> int:
    return len(upstream.read_requests(classroom.instance.state_dir / upstream.REQUEST_LOG))


def test_the_class_downloads_each_file_once_and_every_venv_imports_them(classroom):
    start = log_length(classroom)
    run = classroom.pyinfra()
    assert run.returncode == 0, run.stderr[-3000:]
    assert not run.failed_hosts

    fetched = index_requests(classroom, start)
    files = Counter(r.path for r in fetched if r.path.startswith("/pypi/files/"))
    assert files, "nothing was downloaded from the index"
    assert set(files.values()) == {1}, f"a file was fetched more than once: {files}"
    assert {r.client for r in fetched} == {classroom.instance.bridge_address}, "a host used the index itself"
    assert {"/pypi/files/RPi.GPIO-0.7.1.tar.gz", "/pypi/files/smbus-1.1.post2.tar.gz"} <= set(files)

    ros = "rclpy, " if classroom.real_ros else ""  # stand-in ROS has no rclpy to import
    for host in classroom.hosts:
        shown = classroom.ssh(host.name, (
            "bash -c '. /opt/ros/\"$(ls /opt/ros | head -n 1)\"/setup.bash && "
            f"~/{VENV}/bin/python -c \"import sys, {ros}{IMPORTS}; print(sys.prefix, RPi.GPIO.STANDIN)\"'"))
        assert shown.returncode == 0, f"{host.name}: {shown.stderr}"
        assert shown.stdout.strip() == f"/home/ubuntu/{VENV} True"
        state = classroom.ssh(host.name, f"stat -c %U ~/{VENV}/COLCON_IGNORE && "
                                         f"grep -x 'include-system-site-packages = true' ~/{VENV}/pyvenv.cfg")
        assert state.returncode == 0 and state.stdout.splitlines()[0] == "ubuntu", state


def test_a_second_run_changes_nothing_and_fetches_nothing(classroom):
    start = log_length(classroom)
    run = classroom.pyinfra()
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.changed == {}, run.changed
    assert index_requests(classroom, start) == []


def test_offline_a_fresh_host_converges_from_the_controllers_wheelhouse(classroom):
    name = classroom.hosts[-1].name
    roster = yaml.safe_load(classroom.roster_path.read_text())
    roster["classroom"]["offline"] = True
    classroom.roster_path.write_text(yaml.safe_dump(roster, sort_keys=False))
    classroom.reset(name)
    start = log_length(classroom)
    run = classroom.pyinfra("--limit", name)
    assert run.returncode == 0, run.stderr[-3000:]
    assert index_requests(classroom, start) == []
    shown = classroom.ssh(name, f"~/{VENV}/bin/python -c 'import {IMPORTS}'")
    assert shown.returncode == 0, shown.stderr
