"""Robot profiles end to end: a TurtleBot3 class (Jazzy and Humble), a sim team and a 26.04/Lyrical team.

Its own sandbox instance ($ROSLAB_PROFILES_E2E_SANDBOX, $ROSLAB_PROFILES_E2E_SUBNET), 7 hosts on
the releases 24.04, 22.04, 26.04, 24.04 in turn (ROSLAB_SANDBOX_RELEASES):

    team1  24.04  turtlebot3 (burger, LDS-02)     main + robot, profile_os_tweaks (units masked)
    team2  22.04  turtlebot3 (waffle, LDS-01)     main + robot
    team3  26.04  demo on Lyrical                  main + robot
    team4  24.04  sim                              main only

The ROS packages are the sandbox's stand-ins (one per name the built-in profiles install; the
simulators' stand-ins conflict like the real ones), so the checks stop where ROS code would
run: the packages are installed, the robot's service runs `ros2 launch turtlebot3_bringup
robot.launch.py` with the profile's variables (systemd says so; the stand-in `ros2 launch`
stays up like a healthy launch), the udev rules are in place, the login user is in dialout.
systemd-udevd does not run in a container, so the reload step says the rules apply at the
next boot (on a Pi it reloads udev and replays the devices' add events).

With ROSLAB_SANDBOX_ROS_RUNTIME (CI), `ros2` on the Jazzy and Humble hosts is real: the bringup's
stand-in package then carries a real robot.launch.py (roslab/sandbox/upstream.py,
standin_launch_files) that the real `ros2 launch` runs, and its labelled process reports the
variables it got in the service's journal (checked only there).
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import real_sources
from tests.e2e.conftest import bring_up

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
INSTANCE = os.environ.get("ROSLAB_PROFILES_E2E_SANDBOX", "roslab-profiles-e2e")
SUBNET = os.environ.get("ROSLAB_PROFILES_E2E_SUBNET", "10.213.121.0/24")
RELEASES = "24.04,22.04,26.04,24.04"
HOSTS = 7
RULES = "/etc/udev/rules.d/60-roslab-profile.rules"
SERVICE = "roslab-nodes.service"
# A value that means something to a shell and to systemd: each destination must carry it as text.
NOTE = "it's $HOME; 100% \\ \"quoted\""


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases=RELEASES)
    try:
        yield classroom
    finally:
        teardown()


def class_roster(sandbox, path: Path, team1_lds: str = "LDS-02") -> Path:
    """The sandbox's roster with the class's profiles, as a teacher writes it."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"]["ros_environment"] = {"ROSLAB_E2E_NOTE": NOTE}
    teams = data["teams"]
    teams["team1"].update(robot_profile="turtlebot3", turtlebot3_model="burger", lds_model=team1_lds,
                          profile_os_tweaks=True)
    teams["team2"].update(robot_profile="turtlebot3", turtlebot3_model="waffle", lds_model="LDS-01")
    teams["team4"].update(robot_profile="sim")
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deploy(sandbox, roster: Path, *args):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    return class_roster(sandbox, tmp_path_factory.mktemp("profiles") / "roster.yaml")


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    assert [h.release for h in sandbox.hosts] == ["24.04", "24.04", "22.04", "22.04", "26.04", "26.04", "24.04"]
    return deploy(sandbox, roster)


def show(sandbox, host: str, unit: str, *properties: str) -> dict[str, str]:
    result = sandbox.ssh(host, f"systemctl show {unit} " + " ".join(f"-p {p}" for p in properties), check=True)
    return dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)


def login_shell(sandbox, host: str, command: str) -> str:
    return sandbox.ssh(host, f"bash -ic {command!r} 2>/dev/null", check=True).stdout


def test_the_class_converges_and_a_rerun_changes_nothing(sandbox, roster, first_run):
    assert first_run.returncode == 0, first_run.stderr[-3000:]
    assert first_run.failed_hosts == []
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed


def test_each_side_has_its_profiles_packages(sandbox, first_run):
    expected = {
        "team1-robot": ["ros-jazzy-ros-base", "ros-jazzy-turtlebot3-bringup", "ros-jazzy-ld08-driver",
                        "ros-jazzy-coin-d4-driver", "ros-jazzy-dynamixel-sdk"],
        "team1-main": ["ros-jazzy-desktop", "ros-jazzy-turtlebot3-teleop"],
        "team2-robot": ["ros-humble-ros-base", "ros-humble-turtlebot3-bringup", "ros-humble-hls-lfcd-lds-driver"],
        "team2-main": ["ros-humble-desktop", "ros-humble-turtlebot3-teleop"],
        "team3-robot": ["ros-lyrical-ros-base"],
        "team4-main": ["ros-jazzy-desktop", "ros-jazzy-turtlebot3-gazebo", "ros-jazzy-ros-gz", "gz-harmonic"],
    }
    for host, names in expected.items():
        result = sandbox.ssh(host, "dpkg-query -W -f '${Package} ${Status}\\n' " + " ".join(names))
        installed = {line.split()[0] for line in result.stdout.splitlines() if line.endswith("installed")}
        assert installed == set(names), (host, result.stdout, result.stderr)
    assert sandbox.ssh("team1-main", "dpkg-query -W ros-jazzy-turtlebot3-bringup").returncode != 0


def test_humbles_gazebo_classic_conflicts_with_harmonic_like_the_real_one(sandbox, first_run):
    result = sandbox.sudo("team2-robot", "apt-get install -s -y ros-humble-gazebo-ros-pkgs gz-harmonic")
    assert result.returncode != 0
    assert "gazebo11" in result.stdout + result.stderr


def test_the_robots_service_runs_the_bringup_with_the_profiles_variables(sandbox, first_run):
    for host, model, lds in (("team1-robot", "burger", "LDS-02"), ("team2-robot", "waffle", "LDS-01")):
        props = show(sandbox, host, SERVICE, "ActiveState", "ExecStart", "Environment")
        assert props["ActiveState"] == "active", (host, props)
        assert "ros2 launch turtlebot3_bringup robot.launch.py" in props["ExecStart"]
        environment = props["Environment"]
        assert f"TURTLEBOT3_MODEL={model}" in environment and f"LDS_MODEL={lds}" in environment
        assert "ROSLAB_E2E_NOTE=" in environment
        # What the service's process really has, byte for byte (systemd's own quoting undone).
        pid = show(sandbox, host, SERVICE, "MainPID")["MainPID"]
        env = sandbox.sudo(host, f"cat /proc/{pid}/environ", check=True).stdout.split("\0")
        assert f"ROSLAB_E2E_NOTE={NOTE}" in env and f"LDS_MODEL={lds}" in env
    # The main drives and watches: no bringup there, the model in the students' shell.
    assert login_shell(sandbox, "team1-main", "echo $TURTLEBOT3_MODEL/${LDS_MODEL:-unset}").strip() == "burger/unset"
    assert login_shell(sandbox, "team2-robot", 'printf %s "$ROSLAB_E2E_NOTE"') == NOTE


def test_on_real_ros_the_bringups_launch_runs_with_the_profiles_variables(sandbox, first_run):
    served = sandbox.ros_served
    robots = [(host, model, lds) for host, distro, model, lds in (
        ("team1-robot", "jazzy", "burger", "LDS-02"), ("team2-robot", "humble", "waffle", "LDS-01"))
        if served.get(distro, "").startswith("real")]
    if not robots:
        pytest.skip("no real ROS runtime for Jazzy or Humble (ROSLAB_SANDBOX_ROS_RUNTIME): the stand-in ros2 "
                    "does not read launch files")
    label = "roslab-standin-turtlebot3_bringup-robot"
    for host, model, lds in robots:
        expected = f"{label}: stand-in, no robot code; got LDS_MODEL={lds} TURTLEBOT3_MODEL={model}"
        deadline = time.monotonic() + 60  # the launch's first start after the deploy
        while True:
            journal = sandbox.sudo(host, f"journalctl -u {SERVICE} --no-pager -o cat", check=True).stdout
            if expected in journal or time.monotonic() > deadline:
                break
            time.sleep(2)
        assert expected in journal, (host, journal[-3000:])
        assert show(sandbox, host, SERVICE, "ActiveState")["ActiveState"] == "active"
        assert sandbox.ssh(host, f"pgrep -f '^{label} '").returncode == 0, host


def test_on_real_ros_verify_passes_each_turtlebot3_team_whose_main_hears_its_scans(sandbox, roster, first_run):
    teams = [team for team, distro in (("team1", "jazzy"), ("team2", "humble"))
             if sandbox.ros_served.get(distro, "").startswith("real")]
    if not teams:
        pytest.skip("no real ROS runtime for Jazzy or Humble (ROSLAB_SANDBOX_ROS_RUNTIME): the stand-in ros2 "
                    "publishes nothing")
    # The stand-in bringup publishes /scan with the real `ros2 topic pub` (roslab/sandbox/upstream.py).
    deadline = time.monotonic() + 90
    while True:
        result = subprocess.run([sys.executable, "-m", "roslab", "verify", str(roster),
                                 *(word for team in teams for word in ("--limit", team))],
                                cwd=REPO, env=sandbox.env, capture_output=True, text=True, timeout=600)
        if result.returncode == 0 or time.monotonic() > deadline:
            break
        time.sleep(5)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = {line.split()[0]: " ".join(line.split()) for line in result.stdout.splitlines()[2:] if line.strip()}
    for team in teams:
        assert "PASS heard a sensor_msgs/msg/LaserScan on /scan" in rows[team], rows


def test_the_lyrical_team_runs_the_demo_and_the_sim_main_keeps_discovery_on_the_host(sandbox, first_run):
    props = show(sandbox, "team3-robot", SERVICE, "ActiveState", "ExecStart")
    assert props["ActiveState"] == "active" and "roslab_bringup robot.launch.py" in props["ExecStart"]
    assert "/opt/ros/lyrical/setup.bash" in props["ExecStart"]
    assert login_shell(sandbox, "team4-main", "echo $ROS_AUTOMATIC_DISCOVERY_RANGE $TURTLEBOT3_MODEL").split() == [
        "LOCALHOST", "burger"]
    assert show(sandbox, "team4-main", SERVICE, "LoadState")["LoadState"] == "not-found"


def test_udev_rules_and_the_dialout_group_are_in_place(sandbox, first_run):
    team1 = sandbox.ssh("team1-robot", f"cat {RULES}", check=True).stdout
    team2 = sandbox.ssh("team2-robot", f"cat {RULES}", check=True).stdout
    for rules in (team1, team2):
        assert 'ATTRS{idVendor}=="0483", ATTRS{idProduct}=="5740", ENV{ID_MM_DEVICE_IGNORE}="1"' in rules
        assert 'ATTR{idProduct}=="df11"' in rules  # the USB device itself, in DFU mode
        # every LDS model's CP2102 is /dev/tb3_lidar, as ROBOTIS's 99-turtlebot3-cdc.rules names it
        assert 'ENV{ROSLAB_DEVICE}="lidar", GROUP="dialout", MODE="0666", SYMLINK+="tb3_lidar"' in rules
    assert sandbox.ssh("team1-main", f"test -e {RULES}").returncode == 1
    reloaded = {host for name, hosts in first_run.changed.items() if "udev has read" in name for host in hosts}
    assert reloaded == {"team1-robot", "team2-robot"}
    for host in ("team1-robot", "team2-robot"):
        assert "dialout" in sandbox.ssh(host, "id -nG ubuntu", check=True).stdout.split()


def test_the_opted_in_robot_has_the_e_manuals_units_masked_and_no_swap_above_2_gib(sandbox, first_run):
    units = "systemd-networkd-wait-online.service sleep.target suspend.target hibernate.target hybrid-sleep.target"
    opted_in = sandbox.ssh("team1-robot", f"systemctl is-enabled {units}").stdout.split()
    assert opted_in == ["masked"] * 5, opted_in
    # team2 did not opt in: its robot's units are as Ubuntu ships them.
    assert "masked" not in sandbox.ssh("team2-robot", f"systemctl is-enabled {units}").stdout.split()
    # A sandbox host has the machine's memory (far above 2 GiB): no swap file (unit tests cover a 2 GB Pi).
    memory_kib = int(sandbox.ssh("team1-robot", "awk '/^MemTotal:/ {print $2}' /proc/meminfo", check=True).stdout)
    assert memory_kib > 2048 * 1024
    assert sandbox.ssh("team1-robot", "test -e /swapfile").returncode == 1


def test_another_lidar_changes_only_the_variable_in_the_shell_block_and_the_unit(sandbox, roster, first_run, tmp_path):
    changed = class_roster(sandbox, tmp_path / "roster.yaml", team1_lds="LDS-03")
    dry = sandbox.pyinfra("--dry", "--diff", inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(changed)})
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert {host for hosts in dry.changed.values() for host in hosts} == {"team1-robot"}
    # pyinfra names an operation once for all hosts (here after the first host: "the main's").
    names = {re.sub(r"runs the \w+'s launch", "runs the role's launch", name.split(" | ")[-1]) for name in dry.changed}
    bashrc = "Ensure ubuntu's ~/.bashrc sets up the ROS 2 environment"
    unit = f"Ensure {SERVICE} runs the role's launch as ubuntu"
    assert names >= {bashrc, unit}, names
    # Nothing else: at most the steps that follow a changed unit.
    assert names <= {bashrc, unit, "Ensure systemd has read the changed unit",
                     f"Ensure {SERVICE} runs the current build and unit"}, names
    output = dry.stdout + dry.stderr
    diff_lines = [line.strip() for line in output.splitlines() if line.strip()[:2] in ("+ ", "- ")]
    assert "- export LDS_MODEL=LDS-02" in diff_lines and "+ export LDS_MODEL=LDS-03" in diff_lines, diff_lines
    assert any("LDS_MODEL=LDS-03" in line and line.startswith("+") and "Environment" in line for line in diff_lines)
    assert all("LDS" in line for line in diff_lines), diff_lines
    # --dry changed nothing.
    assert show(sandbox, "team1-robot", SERVICE, "Environment")["Environment"].count("LDS_MODEL=LDS-02") == 1


def test_status_shows_each_robots_hardware_checklist(sandbox, roster, first_run):
    result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster)], cwd=REPO, env=sandbox.env,
                            capture_output=True, text=True, timeout=300)
    assert "Hardware checklist" in result.stdout, result.stdout + result.stderr
    assert "team1-robot (turtlebot3):" in result.stdout and "burger.opencr" in result.stdout
    assert "team2-robot (turtlebot3):" in result.stdout and "waffle.opencr" in result.stdout
    page = (roster.parent / ".roslab-state" / "status.html").read_text()
    assert "Hardware checklist" in page and "waffle.opencr" in page


def opencr_update(sandbox, roster: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "roslab", "opencr-update", str(roster), "--limit", "team1-robot",
                           *args], cwd=REPO, env=sandbox.env, capture_output=True, text=True, timeout=300)


def test_opencr_update_refuses_where_no_board_is_attached(sandbox, roster, first_run, tmp_path):
    archive = tmp_path / "opencr_update.tar.bz2"  # any archive: the port is refused before it is used
    archive.write_bytes(b"an archive")
    result = opencr_update(sandbox, roster, "--url", archive.as_uri(),
                           "--sha256", hashlib.sha256(b"an archive").hexdigest())
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        "no OpenCR board on team1-robot: /dev/ttyACM0 does not exist (attach the OpenCR to the Pi by USB "
        "and run this again)")


# Stands in for the OpenCR: a pseudo-terminal on the robot that never answers, recording what it is sent.
PTY_HOLDER = ("import os, time; m, s = os.openpty(); open('/run/roslab-e2e-opencr.port', 'w').write(os.ttyname(s)); "
              "sent = open('/run/roslab-e2e-opencr.sent', 'wb', 0); "
              "[sent.write(os.read(m, 4096)) for _ in iter(int, 1)]")


def test_opencr_update_runs_robotis_flasher_from_the_real_archive_until_no_board_answers(
        sandbox, roster, first_run):
    served = sandbox.instance.state_dir / "upstream" / real_sources.OPENCR_SERVED
    if not served.is_file():
        pytest.skip("no OpenCR-Binaries.bundle in ROSLAB_SANDBOX_SOURCES: the upstream serves no OpenCR archive")
    url = f"{sandbox.instance.upstream_url}/{real_sources.OPENCR_SERVED}"
    sandbox.sudo("team1-robot", "systemctl stop roslab-e2e-opencr-pty 2>/dev/null; rm -f /run/roslab-e2e-opencr.*")
    sandbox.sudo("team1-robot", "systemd-run --unit roslab-e2e-opencr-pty -p RuntimeMaxSec=300 "
                 f"python3 -c {shlex.quote(PTY_HOLDER)}", check=True)
    try:
        deadline = time.monotonic() + 30
        while (found := sandbox.sudo("team1-robot", "cat /run/roslab-e2e-opencr.port")).returncode != 0:
            assert time.monotonic() < deadline, found.stderr
            time.sleep(0.5)
        port = found.stdout.strip()
        # A port udev cannot name is refused unless the teacher says so.
        refused = opencr_update(sandbox, roster, "--url", url, "--port", port)
        assert refused.returncode == 1 and refused.stderr.strip().splitlines()[-1] == (
            f"{port} on team1-robot is a device udev cannot identify, not an OpenCR (0483:5740): nothing was "
            "flashed (--allow-unidentified-port flashes through it all the same)"), refused.stdout + refused.stderr
        result = opencr_update(sandbox, roster, "--url", url, "--port", port, "--allow-unidentified-port")
        sent = sandbox.sudo("team1-robot", "tr -c 'A-Za-z0-9 ' . < /run/roslab-e2e-opencr.sent", check=True).stdout
    finally:
        sandbox.sudo("team1-robot", "systemctl stop roslab-e2e-opencr-pty")
    assert result.returncode == 1, result.stdout + result.stderr
    assert "team1-robot: x86_64: update.sh runs the x86 flasher natively" in result.stdout, result.stdout
    assert result.stderr.strip().splitlines()[-1] == (
        f"team1-robot: no OpenCR answered on {port}: nothing was flashed"), result.stdout + result.stderr
    # ROBOTIS's flasher wrote to the port: the jump-to-bootloader word, then its board-name requests.
    assert sent.startswith("OpenCR 5555AAAA"), sent
    unpacked = sandbox.sudo("team1-robot", "stat -c '%U %a' /var/lib/roslab/opencr-update; "
                            "ls /var/lib/roslab/opencr-update/opencr_update", check=True).stdout.split()
    assert unpacked[:2] == ["root", "700"], unpacked
    assert {"update.sh", "opencr_ld_shell_x86", "burger.opencr", "waffle.opencr"} <= set(unpacked), unpacked
