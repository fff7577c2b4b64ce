"""A TurtleBot 4 team end to end: the robot's link to its Create 3, and the Create 3 configured.

Its own sandbox instance ($ROSLAB_TB4_E2E_SANDBOX, $ROSLAB_TB4_E2E_SUBNET), one Jazzy team of two
hosts, the robot a Raspberry Pi 4 (its roster `board`). The Create 3 is a STAND-IN
(`roslab sandbox create3`, roslab/sandbox/create3.py: an emulation of its web server, not the
robot): plugged into the robot, usb0 appears there, and the base answers at 192.168.186.2 on the
link's other end, reachable from the robot only, recording what it is posted.

As a teacher meets it (the cable plugged in): the first run writes the boot config (the USB
gadget that makes usb0 on a Pi), usb0's netplan file and chrony's drop-in, gives usb0 its address
(it exists: on a Pi, only after the reboot the run asks for), and configures the Create 3 (the
team's domain, /_do_not_use namespace on Jazzy, the class's middleware, the Pi as its NTP server,
then a reboot of the base); after the reboot usb0 holds its address from the netplan file, and a
run changes nothing and posts nothing.
chrony does not run in a sandbox host (a container has no CAP_SYS_TIME): that it serves time is
unproven here.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import create3_link
from roslab.sandbox.create3 import recorded_posts
from tests.e2e.conftest import bring_up

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_TB4_E2E_SANDBOX", "roslab-tb4-e2e")
SUBNET = os.environ.get("ROSLAB_TB4_E2E_SUBNET", "10.213.181.0/24")
ROBOT = "team1-robot"
CONFIGURE = "Ensure the create3 has domain"


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, 2, releases="24.04")
    try:
        yield classroom
    finally:
        teardown()


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory) -> Path:
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["teams"]["team1"].update(robot_profile="turtlebot4", turtlebot4_model="standard")
    path = tmp_path_factory.mktemp("tb4") / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy(sandbox, roster: Path):
    return sandbox.pyinfra(inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


def posts(sandbox) -> list[dict]:
    return recorded_posts(create3_link.files(sandbox.instance, sandbox.host(ROBOT))[1])


def usb0(sandbox) -> str:
    return sandbox.ssh(ROBOT, "ip -4 -br addr show dev usb0", check=True).stdout


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    create3_link.plug(sandbox.instance, sandbox.host(ROBOT))
    return deploy(sandbox, roster)


def test_the_first_run_links_the_robot_to_its_base_configures_it_and_asks_for_the_reboot(sandbox, roster, first_run):
    assert first_run.returncode == 0, first_run.stderr[-4000:]
    reboot = [line for line in first_run.stderr.splitlines() if "needs a reboot" in line]
    assert len(reboot) == 1 and "dtoverlay=dwc2,dr_mode=peripheral" in reboot[0], reboot
    assert "modules-load=dwc2,g_ether" in sandbox.ssh(ROBOT, "cat /boot/firmware/cmdline.txt", check=True).stdout
    netplan = sandbox.sudo(ROBOT, "stat -c '%a %U' /etc/netplan/61-roslab-usb0.yaml && "
                                  "cat /etc/netplan/61-roslab-usb0.yaml", check=True).stdout
    assert netplan.startswith("600 root") and "usb0" in netplan and "192.168.186.3/24" in netplan, netplan
    chrony = sandbox.ssh(ROBOT, "cat /etc/chrony/conf.d/roslab-robot-base.conf", check=True).stdout
    assert "allow 192.168.186.0/24" in chrony, chrony
    assert "192.168.186.3/24" in usb0(sandbox)  # usb0 was there: its address now, not only at boot
    # usb0 up, the base answered within the same run: it has the team's settings, then reboots
    data = yaml.safe_load(roster.read_text())
    assert posts(sandbox) == [
        {"path": "/ros-config-save-main",
         "form": {"ros_domain_id": team_domain(roster), "ros_namespace": "/_do_not_use",
                  "rmw_implementation": data["classroom"]["ros_middleware"]}},
        {"path": "/beta-ntp-conf-save", "form": {"config": "server 192.168.186.3 prefer iburst minpoll 4 maxpoll 6"}},
        {"path": "/api/reboot", "form": {}},
    ]
    changed = {name.split(" | ")[-1].split(",")[0]: hosts for name, hosts in first_run.changed.items()}
    assert changed[f"{CONFIGURE} {team_domain(roster)}"] == {ROBOT}, first_run.changed


def test_after_the_reboot_usb0_comes_from_the_netplan_file_and_a_run_changes_nothing_and_posts_nothing(
        sandbox, roster, first_run):
    # the address goes, as on a Pi's power cycle: after the reboot only the netplan file gives it back
    sandbox.sudo(ROBOT, "ip addr flush dev usb0", check=True)
    sandbox.reboot(ROBOT)
    assert "192.168.186.3/24" in usb0(sandbox)
    before = len(posts(sandbox))
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-4000:]
    assert again.changed == {}, again.changed
    assert len(posts(sandbox)) == before  # the base has the team's settings: nothing posted


def test_status_names_the_create3s_firmware(sandbox, roster, first_run):
    result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster)], env=sandbox.env,
                            capture_output=True, text=True, timeout=120)
    (row,) = [line for line in result.stdout.splitlines() if line.startswith("team1") and f" {ROBOT} " in line]
    assert "create3 firmware I.0.0.FastDDS" in row, row


def team_domain(roster: Path) -> str:
    data = yaml.safe_load(roster.read_text())
    return str(data["teams"]["team1"]["ros_domain_id"])
