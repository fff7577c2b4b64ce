"""The robots of issue 21 end to end: a JPL Open Source Rover team and an ESP32 board.

Its own sandbox instance ($ROSLAB_ROBOTS_E2E_SANDBOX, $ROSLAB_ROBOTS_E2E_SUBNET), 3 hosts on
Ubuntu 24.04 (Jazzy):

    team1  osr              main + robot (not calibrated: the rover's service is installed, disabled)
    team2  esp32_microros   main only, the board attached to it (esp32_attached_to: main)

The robot's boot partition: a sandbox host has no /boot/firmware, so before the first run the
test writes STAND-INS of a Pi's config.txt and cmdline.txt there (Ubuntu 24.04's for a Pi,
abridged), as the Pi image has them. The rover's and the agent's sources are the sandbox's
stand-in repositories (roslab/sandbox/git_standins.py, pinned by the sandbox roster's
source_pins), built in each host's underlay; the rover's venv holds the stand-in index's
packages. The stand-in agent prints what it is and exits, as the real one does without its
board: `esp32_present: false` keeps it from starting, and the checks read the agent's unit from
systemd (its RMW_IMPLEMENTATION and its transport arguments), not a running agent.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.e2e.conftest import bring_up

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_ROBOTS_E2E_SANDBOX", "roslab-robots-e2e")
SUBNET = os.environ.get("ROSLAB_ROBOTS_E2E_SUBNET", "10.213.171.0/24")
HOSTS = 3
ROVER = "team1-robot"
BOARD_HOST = "team2-main"
RECORD = "/var/lib/roslab/reboot-needed"
# Stand-ins of a Pi's boot files (Ubuntu 24.04 preinstalled server image for the Pi, abridged).
STANDIN_CONFIG = ("# roslab e2e STAND-IN of a Pi's /boot/firmware/config.txt (Ubuntu 24.04, abridged)\n"
                  "[all]\nkernel=vmlinuz\ncmdline=cmdline.txt\ninitramfs initrd.img followkernel\n"
                  "[pi4]\nmax_framebuffers=2\narm_boost=1\n[all]\narm_64bit=1\ndtparam=audio=on\n")
STANDIN_CMDLINE = ("console=serial0,115200 multipath=off dwc_otg.lpm_enable=0 console=tty1 "
                   "root=LABEL=writable rootfstype=ext4 rootwait fixrtc\n")


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases="24.04")
    try:
        yield classroom
    finally:
        teardown()


def deploy(sandbox, roster: Path, *args):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    data = yaml.safe_load(sandbox.roster_path.read_text())
    teams = data["teams"]
    assert sorted(teams) == ["team1", "team2"], teams
    teams["team1"].update(robot_profile="osr")
    teams["team2"].update(robot_profile="esp32_microros", esp32_usb_serial="0001A2B3", esp32_attached_to="main",
                          esp32_transport="serial", esp32_present=False)
    path = tmp_path_factory.mktemp("robots") / "roster.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    sandbox.sudo(ROVER, "mkdir -p /boot/firmware", check=True)
    for name, text in (("config.txt", STANDIN_CONFIG), ("cmdline.txt", STANDIN_CMDLINE)):
        sandbox.sudo(ROVER, f"printf '%s' {shell(text)} > /boot/firmware/{name}", check=True)
    return deploy(sandbox, roster)


def shell(text: str) -> str:
    import shlex
    return shlex.quote(text)


def show(sandbox, host: str, unit: str, *properties: str) -> dict[str, str]:
    result = sandbox.ssh(host, f"systemctl show {unit} " + " ".join(f"-p {p}" for p in properties), check=True)
    return dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)


def reboot_lines(stderr: str) -> list[str]:
    return [" ".join(line.split()) for line in stderr.splitlines() if "needs a reboot" in line]


def test_the_class_converges_and_the_rover_reports_reboot_needed_once(sandbox, roster, first_run):
    assert first_run.returncode == 0, first_run.stderr[-4000:]
    assert first_run.failed_hosts == []
    lines = reboot_lines(first_run.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"{ROVER} needs a reboot: boot config changed:"), lines


def test_the_boot_config_block_is_in_place_and_the_cmdline_backed_up(sandbox, first_run):
    config = sandbox.ssh(ROVER, "cat /boot/firmware/config.txt", check=True).stdout
    assert config.startswith(STANDIN_CONFIG)  # nothing above the block changed
    assert ("# BEGIN roslab managed block (robot profile boot config)\n[all]\nenable_uart=1\n"
            "dtparam=i2c_arm=on\n# END roslab managed block (robot profile boot config)\n") in config
    cmdline = sandbox.ssh(ROVER, "cat /boot/firmware/cmdline.txt", check=True).stdout
    assert cmdline == STANDIN_CMDLINE.replace("console=serial0,115200 ", "")
    backups = sandbox.ssh(ROVER, "cat /boot/firmware/cmdline.txt.roslab-*", check=True).stdout
    assert backups == STANDIN_CMDLINE
    record = sandbox.ssh(ROVER, f"cat {RECORD}; echo now=$(cat /proc/sys/kernel/random/boot_id)", check=True)
    values = dict(line.split("=", 1) for line in record.stdout.splitlines())
    assert values["boot_id"] == values["now"] and values["reason"].startswith("boot config changed:")
    # The main (a PC here) has no boot config to change, and says nothing about rebooting.
    assert sandbox.ssh("team1-main", f"test -e {RECORD}").returncode != 0


def test_the_rover_has_its_groups_udev_rules_and_a_disabled_service(sandbox, first_run):
    groups = sandbox.ssh(ROVER, "id -nG ubuntu", check=True).stdout.split()
    assert {"tty", "dialout", "input"} <= set(groups)
    rules = sandbox.ssh(ROVER, "cat /etc/udev/rules.d/60-roslab-profile.rules", check=True).stdout
    assert 'KERNEL=="ttyS0", SYMLINK+="serial0", GROUP="tty", MODE="0660"' in rules
    props = show(sandbox, ROVER, "osr_startup.service", "LoadState", "UnitFileState", "ActiveState", "ExecStart",
                 "Restart", "User")
    assert props["LoadState"] == "loaded" and props["UnitFileState"] == "disabled", props
    assert props["ActiveState"] == "inactive" and props["Restart"] == "always" and props["User"] == "ubuntu"
    assert "source /opt/ros/jazzy/setup.bash" in props["ExecStart"]
    assert "exec ros2 launch osr_bringup osr_launch.py" in props["ExecStart"]
    installed = sandbox.ssh(ROVER, "dpkg-query -W -f '${Package}\\n' python3-serial i2c-tools ros-jazzy-joy",
                            check=True).stdout.split()
    assert sorted(installed) == ["i2c-tools", "python3-serial", "ros-jazzy-joy"]


def test_the_agent_unit_runs_the_serial_transport_with_fast_dds(sandbox, first_run):
    props = show(sandbox, BOARD_HOST, "micro_ros_agent.service", "LoadState", "UnitFileState", "ActiveState",
                 "ExecStart", "Environment", "Restart")
    assert props["LoadState"] == "loaded" and props["Restart"] == "always", props
    assert "RMW_IMPLEMENTATION=rmw_fastrtps_cpp" in props["Environment"].split()
    assert "exec ros2 run micro_ros_agent micro_ros_agent serial --dev /dev/esp32 -b 115200" in props["ExecStart"]
    # esp32_present: false: installed, not started (the agent binary is the underlay's, not built here).
    assert props["UnitFileState"] == "disabled" and props["ActiveState"] == "inactive", props
    rules = sandbox.ssh(BOARD_HOST, "cat /etc/udev/rules.d/60-roslab-profile.rules", check=True).stdout
    assert 'ATTRS{serial}=="0001A2B3"' in rules and 'SYMLINK+="esp32"' in rules
    assert "dialout" in sandbox.ssh(BOARD_HOST, "id -nG ubuntu", check=True).stdout.split()
    assert sandbox.ssh(BOARD_HOST, "dpkg-query -W brltty 2>/dev/null | grep -q .").returncode != 0


def test_the_rover_and_the_boards_host_build_their_pinned_sources_and_the_rover_has_its_venv(sandbox, first_run):
    """osr.repos on the rover, esp32_microros.repos only on the host the board is plugged into
    (the sandbox's stand-in repositories, pinned by the sandbox roster's source_pins)."""
    underlay = "/home/ubuntu/roslab_underlay/install"
    built = {host: sandbox.ssh(host, f"ls {underlay} 2>/dev/null").stdout.split()
             for host in (ROVER, "team1-main", "team2-main")}
    assert "osr_bringup" in built[ROVER], built
    assert {"micro_ros_agent", "microxrcedds_agent"} <= set(built["team2-main"]), built
    assert built["team1-main"] == [], built
    agent = sandbox.ssh("team2-main", f"bash -c 'source {underlay}/setup.bash && "
                                      f"{underlay}/micro_ros_agent/lib/micro_ros_agent/micro_ros_agent'", check=True)
    assert "roslab sandbox stand-in: micro_ros_agent" in agent.stdout
    imports = sandbox.ssh(ROVER, "~/osr_venv/bin/python -c 'import adafruit_servokit, ina260, RPi.GPIO, smbus'")
    assert imports.returncode == 0, imports.stderr
    assert sandbox.ssh(ROVER, "test -f ~/osr_venv/COLCON_IGNORE").returncode == 0


def test_a_rerun_changes_nothing_and_still_says_the_rover_waits_for_a_reboot(sandbox, roster, first_run):
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed
    lines = reboot_lines(again.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"{ROVER} needs a reboot:"), lines


def test_status_shows_reboot_needed_until_the_boot_changes(sandbox, roster, first_run):
    def status():
        result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster)], env=sandbox.env,
                                capture_output=True, text=True, timeout=120)
        return {line.split()[1]: line for line in result.stdout.splitlines() if line.startswith("team")}

    rows = status()
    assert "reboot needed: boot config changed:" in rows[ROVER]
    assert "reboot" not in rows["team1-main"] and "reboot" not in rows[BOARD_HOST]
    # A reboot gives the host a new boot id: the record (kept as it was) then names an old boot.
    sandbox.sudo(ROVER, f"sed -i 's/^boot_id=.*/boot_id=00000000-0000-0000-0000-000000000000/' {RECORD}",
                 check=True)
    assert "reboot" not in status()[ROVER]
