"""The robots that need more than apt, end to end: a JPL Open Source Rover team and an ESP32 board.

Its own sandbox instance ($ROSLAB_ROBOTS_E2E_SANDBOX, $ROSLAB_ROBOTS_E2E_SUBNET), 4 hosts, Jazzy:

    team1  osr              24.04, main + robot (calibrated: the rover's service runs its launch)
    team2  esp32_microros   24.04, main + robot, the board attached to the robot, over UDP

With the robots' REAL repositories (ROSLAB_SANDBOX_SOURCES: git bundles, `.ci/run` names
../shared/sources) and the real ROS runtime (ROSLAB_SANDBOX_ROS_RUNTIME), the rover builds
osr-rover-code v4.1.0's osr_interfaces, osr_control and osr_bringup and its launch starts, the
board's host builds the real micro-ROS agent (micro-ROS-Agent 5.0.2 on Micro-XRCE-DDS-Agent
v2.4.3) and its service listens on UDP, and a STAND-IN board (roslab/sandbox/esp32_board.py: a
Linux DDS-XRCE client from the bundles' Micro-XRCE-DDS-Client, on this machine), started by
`roslab sandbox board team2 start` with the firmware's values (the team's domain, node
esp32_board_team2), publishes through that agent, so `roslab verify` hears the board on team2's
main, hears it again after the agent is killed (the board reconnects, as the firmware does), and
fails naming the board when `roslab sandbox board team2 stop` stops it. What stays a stand-in and why: the rover's joy and teleop_twist_joy (the
shared runtime lacks them: the sandbox's stand-in executables), its RoboClaws and servo board
(serial and I2C hardware: those nodes fail, each in its own line of the launch's journal) until
`roslab sandbox board team1 start` runs STAND-IN RoboClaws in the rover
(roslab/sandbox/roboclaw_board.py): then the real roboclaw_wrapper publishes /drive_state.
Moved to `osr_calibrated: false` by a run, the rover team is NOT CHECKED by verify (exit 3, never
PASS) and status says its service is not started; the calibrated rover is back after.
Without bundles or a real runtime, every robot repository is a stand-in (git_standins.py): the
same class converges and the real-only tests skip, saying so.

The profiles' repositories go the whole way a classroom's do: fetched once per class by the
controller, a changed pin rebuilding only the workspace that uses it, a moved tag or an
unreachable repository failing only the hosts that need it, offline mode converging from the
controller's cache (`sources_cache_dir`: the test's folder), a failing build keeping the last
good install (last: it is the one case that leaves a host unconverged).

The robot's boot partition: the sandbox's robots are Raspberry Pi 4s (their roster `board`), so
they boot with STAND-INS of Ubuntu 24.04's config.txt and cmdline.txt for the Pi
(roslab/sandbox/pi_boot.py); the rover's boot config goes there, the run says the rover needs a
reboot, and after a real reboot of the sandbox host the next run changes nothing and says no more.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from roslab.reporting.summary import LONG_STEP, STILL_RUNNING_VARIABLE
from roslab.sandbox import git_standins, pi_boot, upstream
from tests.e2e.conftest import bring_up, summary_lines

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_ROBOTS_E2E_SANDBOX", "roslab-robots-e2e")
SUBNET = os.environ.get("ROSLAB_ROBOTS_E2E_SUBNET", "10.213.171.0/24")
HOSTS = 4
ROVER = "team1-robot"
BOARD_HOST = "team2-robot"
AGENT_PORT = 8888
RECORD = "/run/roslab/reboot-needed"
UNDERLAY = "/home/ubuntu/roslab_underlay"
OSR_URL = "https://github.com/nasa-jpl/osr-rover-code.git"
AGENT_URL = "https://github.com/micro-ROS/micro-ROS-Agent.git"
XRCE_URL = "https://github.com/eProsima/Micro-XRCE-DDS-Agent.git"
OSR_PIN = "v4.1.0"  # osr.repos
STILL_RUNNING_EVERY = 2  # seconds between the first run's "still running" lines (ROSLAB_STILL_RUNNING_SECONDS)
# the class's own tools (the roster's workspace_sources, a stand-in made by this test): every host
LAB_TOOLS_URL = "https://github.com/roslab-standin/lab_tools.git"
# every repository of the class, and the hosts that build it
REPOSITORIES = {LAB_TOOLS_URL: {ROVER, BOARD_HOST, "team1-main", "team2-main"}, OSR_URL: {ROVER},
                AGENT_URL: {BOARD_HOST}, XRCE_URL: {BOARD_HOST}}
# The rover's boot partition as the sandbox boots a Pi 4 on 24.04 (stand-ins of Ubuntu's files).
PI_BOOT = pi_boot.boot_files("pi4", "24.04")
STANDIN_CONFIG = PI_BOOT["/boot/firmware/config.txt"][0]
STANDIN_CMDLINE = PI_BOOT["/boot/firmware/cmdline.txt"][0]


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases="24.04,24.04")
    try:
        yield classroom
    finally:
        teardown()


def is_real(sandbox) -> bool:
    """The robots' code is real here: bundles served and a real Jazzy to build them on."""
    return sandbox.real_ros and {OSR_URL, AGENT_URL, XRCE_URL} <= set(sandbox.real_repositories)


def needs_real(sandbox) -> None:
    if not is_real(sandbox):
        pytest.skip("the sandbox serves STAND-IN robot repositories (set ROSLAB_SANDBOX_SOURCES to a folder of "
                    "the robots' git bundles and ROSLAB_SANDBOX_ROS_RUNTIME to the real ROS runtime)")


def deploy(sandbox, roster: Path, *args, json_output: bool = True, env: dict[str, str] | None = None):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster), **(env or {})},
                           json_output=json_output)


def write_roster(sandbox, path: Path, rover_pin: str | None = None, offline: bool = False) -> Path:
    """The sandbox roster with the two robots; `rover_pin`: team1's source_pins for the rover's
    repository (a teacher moving one team's pin), `offline`: the class's offline mode."""
    data = yaml.safe_load(sandbox.roster_path.read_text())
    data["classroom"]["sources_cache_dir"] = str(path.parent / "sources-cache")
    data["classroom"]["workspace_sources"] = ["class.repos"]
    if offline:
        data["classroom"]["offline"] = True
    teams = data["teams"]
    assert sorted(teams) == ["team1", "team2"], teams
    real = is_real(sandbox)
    # calibrated only where the rover's code is real: a stand-in has no launch file to start
    teams["team1"].update(robot_profile="osr", osr_calibrated=real)
    if rover_pin:
        teams["team1"]["source_pins"] = {"osr-rover-code": rover_pin}
    # present only where the agent is real: the stand-in agent prints what it is and exits
    teams["team2"].update(robot_profile="esp32_microros", esp32_usb_serial="0001A2B3", esp32_attached_to="robot",
                          esp32_transport="udp", esp32_udp_port=str(AGENT_PORT), esp32_present=real)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def roster(sandbox, tmp_path_factory):
    folder = tmp_path_factory.mktemp("robots")
    git_standins.standin_repository(sandbox.instance.state_dir / "upstream", LAB_TOOLS_URL, "lab_tools",
                                    tags=["v1.0.0"])
    (folder / "class.repos").write_text(yaml.safe_dump({"repositories": {
        "lab_tools": {"type": "git", "url": LAB_TOOLS_URL, "version": "v1.0.0"}}}))
    return write_roster(sandbox, folder / "roster.yaml")


def request_count(sandbox) -> int:
    return len(upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG))


def requests_since(sandbox, start: int) -> list:
    return upstream.read_requests(sandbox.instance.state_dir / upstream.REQUEST_LOG)[start:]


def git_requests(requests, url: str) -> list:
    prefix = "/" + git_standins.served_path(url) + "/"
    return [request for request in requests if request.path.startswith(prefix)]


def bare(sandbox, url: str) -> Path:
    """The upstream's stand-in repository for `url` (roslab/sandbox/git_standins.py)."""
    return sandbox.instance.state_dir / "upstream" / git_standins.served_path(url)


def underlay_packages(sandbox, host: str) -> list[str]:
    return sandbox.ssh(host, f"ls {UNDERLAY}/install 2>/dev/null").stdout.split()


def rover_marker(sandbox) -> str:
    """What the rover's installed code says of its version: the stand-in's marker, or the real
    osr_bringup's params file (which the changed-pin test marks)."""
    if is_real(sandbox):
        return sandbox.ssh(ROVER, f"cat {UNDERLAY}/install/osr_bringup/share/osr_bringup/config/osr_params.yaml",
                           check=True).stdout
    return sandbox.ssh(ROVER, f"bash -c 'source {UNDERLAY}/install/setup.bash && "
                              f"{UNDERLAY}/install/osr_bringup/lib/osr_bringup/osr_bringup'", check=True).stdout


def commit_rover(sandbox, tag: str, change: str, move: bool = False) -> None:
    """A new commit of the rover's repository on top of its pin, tagged `tag` (moved if `move`),
    as upstream would publish one. `change`: "v2" (a marked params file) or "broken" (a package
    that fails to build)."""
    repository = bare(sandbox, OSR_URL)
    if not is_real(sandbox):
        files = git_standins.package_files("osr_bringup", ["osr_bringup"], marker=f"roslab-e2e-{change}")
        if change == "broken":  # setuptools' "error: can't copy 'missing.yaml'" in colcon's log
            files["osr_bringup/setup.py"] = files["osr_bringup/setup.py"].replace(
                "['package.xml']", "['package.xml', 'missing.yaml']")
        git_standins.commit(repository, files, f"the rover's code, {change}", [tag], move_tags=move)
        return
    with tempfile.TemporaryDirectory(prefix="roslab-e2e-osr-") as work:
        def git(*args):
            subprocess.run(["git", "-c", "user.name=roslab e2e", "-c", "user.email=e2e@roslab.invalid", *args],
                           cwd=work, check=True, capture_output=True)
        git("clone", "--quiet", str(repository), ".")
        git("checkout", "--quiet", OSR_PIN)
        if change == "broken":
            path = Path(work, "ROS/osr_interfaces/CMakeLists.txt")
            path.write_text(path.read_text() + '\nmessage(FATAL_ERROR "roslab e2e: a broken commit")\n')
        else:
            path = Path(work, "ROS/osr_bringup/config/osr_params.yaml")
            path.write_text(path.read_text() + f"\n# roslab-e2e-{change}\n")
        git("commit", "--quiet", "-am", f"roslab e2e: {change}")
        git("tag", "-f", tag)
        git("push", "--quiet", "--force", "origin", f"refs/tags/{tag}")
    subprocess.run(["git", "--git-dir", str(repository), "update-server-info"], check=True)


def domain_id(sandbox, host: str) -> int:
    return int(sandbox.ssh(host, "bash -ic 'echo $ROS_DOMAIN_ID' 2>/dev/null", check=True).stdout.split()[-1])


def verify(sandbox, roster: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "roslab", "verify", *args, str(roster)], env=sandbox.env,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    start = request_count(sandbox)
    # As a teacher runs it, the output they read; a "still running" line every 2 s (rather than
    # every 20), so the agent's build (13 s with the machine's compiler cache warm) is seen in it.
    run = deploy(sandbox, roster, json_output=False, env={STILL_RUNNING_VARIABLE: str(STILL_RUNNING_EVERY)})
    run.requests = requests_since(sandbox, start)
    return run


def show(sandbox, host: str, unit: str, *properties: str) -> dict[str, str]:
    result = sandbox.ssh(host, f"systemctl show {unit} " + " ".join(f"-p {p}" for p in properties), check=True)
    return dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)


def reboot_lines(stderr: str) -> list[str]:
    return [" ".join(line.split()) for line in stderr.splitlines() if "needs a reboot" in line]


def test_the_class_converges_and_the_rover_reports_reboot_needed_once(sandbox, roster, first_run):
    assert first_run.returncode == 0, first_run.stderr[-4000:]
    assert first_run.failed_hosts == []
    # roslab's summary: a line per host, each ok or changed
    statuses: dict[str, str] = {}
    for words in map(str.split, summary_lines(first_run.stderr)[1:]):  # a host's first line: its status
        if len(words) > 1 and words[0] in {host.name for host in sandbox.hosts}:
            statuses.setdefault(words[0], words[1])
    assert set(statuses) == {host.name for host in sandbox.hosts}, summary_lines(first_run.stderr)
    assert set(statuses.values()) <= {"ok", "changed"}, summary_lines(first_run.stderr)
    lines = reboot_lines(first_run.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"{ROVER} needs a reboot: boot config changed:"), lines


def test_each_repository_was_fetched_once_for_the_class_by_the_controller_alone(sandbox, first_run):
    # lab_tools is built on all three hosts, yet downloaded once: the controller fetched it
    for url in REPOSITORIES:
        # dumb HTTP: one request per object, so a repeat would be a second download
        fetched = [r.path for r in git_requests(first_run.requests, url) if "/objects/" in r.path and r.status == 200]
        assert fetched and len(fetched) == len(set(fetched)), (url, fetched)
        refs = [r for r in git_requests(first_run.requests, url) if "/info/refs" in r.path]
        assert 1 <= len(refs) <= 2, (url, refs)  # ls-remote of the tag, then the fetch
    hosts = {host.address for host in sandbox.hosts}
    assert not [r for r in first_run.requests if r.path.startswith("/git/") and r.client in hosts]


def test_the_boot_config_block_is_in_place_and_the_cmdline_backed_up(sandbox, first_run):
    config = sandbox.ssh(ROVER, "cat /boot/firmware/config.txt", check=True).stdout
    assert config.startswith(STANDIN_CONFIG)  # nothing above the block changed
    assert ("# BEGIN roslab managed block (robot profile boot config)\n[all]\nenable_uart=1\n"
            "dtoverlay=disable-bt\ndtparam=i2c_arm=on\n# END roslab managed block (robot profile boot config)\n") in config
    cmdline = sandbox.ssh(ROVER, "cat /boot/firmware/cmdline.txt", check=True).stdout
    assert cmdline == STANDIN_CMDLINE.replace("console=serial0,115200 ", "")
    backups = sandbox.ssh(ROVER, "cat /boot/firmware/cmdline.txt.roslab-*", check=True).stdout
    assert backups == STANDIN_CMDLINE
    record = sandbox.ssh(ROVER, f"cat {RECORD}; echo now=$(cat /proc/sys/kernel/random/boot_id)", check=True)
    values = dict(line.split("=", 1) for line in record.stdout.splitlines())
    assert values["boot_id"] == values["now"] and values["reason"].startswith("boot config changed:")
    # The main (a PC here: no boot partition) has no boot config to change, and says nothing about rebooting.
    assert sandbox.ssh("team1-main", f"test -e {RECORD} || test -e /boot/firmware/config.txt").returncode != 0
    # The board's host is a Pi too, whose profile has no boot config: its files are Ubuntu's still.
    assert sandbox.ssh(BOARD_HOST, "cat /boot/firmware/config.txt", check=True).stdout == STANDIN_CONFIG


def test_the_rover_has_its_groups_udev_rules_and_its_service(sandbox, first_run):
    groups = sandbox.ssh(ROVER, "id -nG ubuntu", check=True).stdout.split()
    assert {"tty", "dialout", "input"} <= set(groups)
    rules = sandbox.ssh(ROVER, "cat /etc/udev/rules.d/60-roslab-profile.rules", check=True).stdout
    # the RoboClaws' UART as /dev/serial1, which roboclaw_params.yaml opens at the pinned v4.1.0
    assert 'KERNEL=="ttyAMA0", ENV{ROSLAB_DEVICE}="roboclaw_uart", GROUP="dialout", MODE="0660", SYMLINK+="serial1"' in rules
    props = show(sandbox, ROVER, "osr_startup.service", "LoadState", "UnitFileState", "ActiveState", "ExecStart",
                 "Restart", "User")
    assert props["LoadState"] == "loaded" and props["Restart"] == "always" and props["User"] == "ubuntu", props
    # calibrated (osr_calibrated: true) where the rover's code is real: enabled and running
    expected = ("enabled", "active") if is_real(sandbox) else ("disabled", "inactive")
    assert (props["UnitFileState"], props["ActiveState"]) == expected, props
    assert "source /opt/ros/jazzy/setup.bash" in props["ExecStart"]
    assert "exec ros2 launch osr_bringup osr_launch.py" in props["ExecStart"]
    # the rover's nodes run with /usr/bin/python3: the venv reaches them through PYTHONPATH
    assert "/home/ubuntu/osr_venv/lib/python3*/site-packages" in props["ExecStart"]
    shell = sandbox.ssh(ROVER, "bash -ic 'python3 -c \"import adafruit_servokit, ina260\" && echo imported' "
                               "2>/dev/null", check=True).stdout
    assert "imported" in shell
    installed = sandbox.ssh(ROVER, "dpkg-query -W -f '${Package}\\n' python3-serial i2c-tools ros-jazzy-joy "
                                   "ros-jazzy-tf2-ros ros-jazzy-nav-msgs", check=True).stdout.split()
    assert sorted(installed) == ["i2c-tools", "python3-serial", "ros-jazzy-joy", "ros-jazzy-nav-msgs",
                                 "ros-jazzy-tf2-ros"]


def test_the_agent_unit_runs_the_udp_transport_with_fast_dds(sandbox, first_run):
    props = show(sandbox, BOARD_HOST, "micro_ros_agent.service", "LoadState", "UnitFileState", "ActiveState",
                 "ExecStart", "Environment", "Restart")
    assert props["LoadState"] == "loaded" and props["Restart"] == "always", props
    assert "RMW_IMPLEMENTATION=rmw_fastrtps_cpp" in props["Environment"].split()
    # for a board that asks for domain 255 only (the firmware sets the team's domain itself)
    assert f"XRCE_DOMAIN_ID_OVERRIDE={domain_id(sandbox, BOARD_HOST)}" in props["Environment"].split()
    assert f"exec ros2 run micro_ros_agent micro_ros_agent udp4 --port {AGENT_PORT}" in props["ExecStart"]
    assert "source /opt/ros/jazzy/setup.bash" in props["ExecStart"]
    # esp32_present where the agent is real; the stand-in agent is installed, not started
    expected = ("enabled", "active") if is_real(sandbox) else ("disabled", "inactive")
    assert (props["UnitFileState"], props["ActiveState"]) == expected, props
    # a board on UDP (WiFi) has no USB link to its host: no device, no rules file
    assert sandbox.ssh(BOARD_HOST, "test -e /etc/udev/rules.d/60-roslab-profile.rules").returncode == 1
    assert "dialout" in sandbox.ssh(BOARD_HOST, "id -nG ubuntu", check=True).stdout.split()
    assert sandbox.ssh(BOARD_HOST, "dpkg-query -W brltty 2>/dev/null | grep -q .").returncode != 0
    assert sandbox.ssh("team2-main", "test -e /etc/systemd/system/micro_ros_agent.service").returncode != 0


def test_the_rover_and_the_boards_host_build_their_pinned_sources_and_the_rover_has_its_venv(sandbox, first_run):
    """osr.repos on the rover (without its ROS 1 and Gazebo packages), the agent's .repos only on
    the host the board is plugged into, the class's lab_tools everywhere."""
    built = {host.name: set(underlay_packages(sandbox, host.name)) for host in sandbox.hosts}
    rover = {"osr_bringup", "osr_control", "osr_interfaces"} if is_real(sandbox) else {"osr_bringup"}
    assert rover | {"lab_tools"} <= built[ROVER], built
    assert not {"led_screen", "osr_gazebo"} & built[ROVER], built
    if is_real(sandbox):  # never copied: the ROS 1 leftover (skip_packages)
        assert sandbox.ssh(ROVER, f"test -e {UNDERLAY}/src/osr-rover-code/ROS/led_screen").returncode != 0
    assert {"micro_ros_agent", "microxrcedds_agent", "lab_tools"} <= built[BOARD_HOST], built
    for host in ("team1-main", "team2-main"):
        assert "lab_tools" in built[host] and not {"osr_bringup", "micro_ros_agent"} & built[host], built
    imports = sandbox.ssh(ROVER, "~/osr_venv/bin/python -c 'import adafruit_servokit, ina260, RPi.GPIO, smbus'")
    assert imports.returncode == 0, imports.stderr
    assert sandbox.ssh(ROVER, "test -f ~/osr_venv/COLCON_IGNORE").returncode == 0
    # the agent's superbuild is off and its build-order edge given: colcon read the profile's meta
    meta = yaml.safe_load(sandbox.ssh(BOARD_HOST, f"cat {UNDERLAY}/.roslab/colcon.meta", check=True).stdout)
    assert meta["names"]["micro_ros_agent"]["dependencies"] == ["microxrcedds_agent"], meta
    assert "-DMICROROSAGENT_SUPERBUILD=OFF" in meta["names"]["micro_ros_agent"]["cmake-args"], meta
    colcon_log = sandbox.ssh(BOARD_HOST, f"grep -h 'Command line arguments' {UNDERLAY}/log/latest_build/logger_all.log",
                             check=True).stdout
    assert "'--metas', '.roslab/colcon.meta'" in colcon_log, colcon_log
    assert sandbox.ssh(ROVER, f"test -e {UNDERLAY}/.roslab/colcon.meta").returncode != 0  # the rover has none


def test_the_real_agent_is_an_elf_binary_built_after_the_xrce_agent_and_listens_on_udp(sandbox, first_run):
    needs_real(sandbox)
    agent = f"{UNDERLAY}/install/micro_ros_agent/lib/micro_ros_agent/micro_ros_agent"
    magic = sandbox.ssh(BOARD_HOST, f"head -c 4 {agent} | od -An -c", check=True).stdout.split()
    assert magic == ["177", "E", "L", "F"], magic
    libraries = sandbox.ssh(BOARD_HOST, f"bash -c 'source {UNDERLAY}/install/setup.bash && ldd {agent}'",
                            check=True).stdout
    assert "libmicroxrcedds_agent" in libraries and "not found" not in libraries, libraries
    # colcon's own record of the build: the XRCE-DDS agent finished before micro_ros_agent started
    events = sandbox.ssh(BOARD_HOST, f"grep -hE '(JobStarted|JobEnded).*(micro_ros_agent|microxrcedds_agent)' "
                                     f"{UNDERLAY}/log/latest_build/events.log", check=True).stdout.splitlines()
    order = [("end" if "JobEnded" in line else "start",
              "micro_ros_agent" if "micro_ros_agent" in line else "microxrcedds_agent") for line in events]
    assert order.index(("end", "microxrcedds_agent")) < order.index(("start", "micro_ros_agent")), order
    listening = ""
    for _ in range(30):  # the service starts the agent with the host; it listens within a second
        listening = sandbox.ssh(BOARD_HOST, "ss -ulnpH", check=True).stdout
        if f":{AGENT_PORT} " in listening:
            break
        time.sleep(1)
    assert f":{AGENT_PORT} " in listening and "micro_ros_agent" in listening, listening


def test_the_agents_long_build_names_its_package_in_the_runs_still_running_lines(sandbox, first_run):
    """While colcon builds the board host's underlay, the run's "still running" lines say which
    package it is at and how many of how many are built (roslab/ros/colcon_progress.py)."""
    events = sandbox.ssh(BOARD_HOST, f"grep -hE '(JobStarted|JobEnded)' {UNDERLAY}/log/latest_build/events.log",
                         check=True).stdout.splitlines()
    # colcon's events.log: "[12.345] (package) JobStarted: {...}", seconds since colcon started
    times = [float(line[1:line.index("]")]) for line in events]
    packages = {line.split("(", 1)[1].split(")", 1)[0] for line in events}
    took = max(times) - min(times)
    # the first line comes LONG_STEP + STILL_RUNNING_EVERY seconds into the step, then one per
    # STILL_RUNNING_EVERY: a build longer than both is under way at one of them, wherever it starts
    assert took > LONG_STEP + STILL_RUNNING_EVERY + 1, f"colcon built {sorted(packages)} in {took:.1f} s"
    said = [line for line in first_run.stderr.splitlines()
            if "still running on" in line and f"{BOARD_HOST}: building " in line]
    assert said, [line for line in first_run.stderr.splitlines() if "still running on" in line]
    named = [re.search(rf"{BOARD_HOST}: building ([\w, ]+) \((\d+) of (\d+) built\)", line) for line in said]
    assert None not in named, said
    # the underlay's build (the workspace's, a later step, names its own packages)
    underlay = [match for match in named if set(match.group(1).split(", ")) <= packages]
    assert underlay and all(int(match.group(3)) == len(packages) for match in underlay), (said, packages)


def test_the_rovers_real_packages_have_their_generated_code_and_its_launch_starts(sandbox, roster, first_run):
    needs_real(sandbox)
    interfaces = sandbox.ssh(ROVER, f"ls {UNDERLAY}/install/osr_interfaces/lib", check=True).stdout.split()
    assert {"libosr_interfaces__rosidl_typesupport_c.so", "libosr_interfaces__rosidl_generator_py.so"} <= set(
        interfaces), interfaces
    imported = sandbox.ssh(ROVER, f"bash -c 'source {UNDERLAY}/install/setup.bash && python3 -c "
                                  "\"from osr_interfaces.msg import CommandDrive; print(CommandDrive())\"'")
    assert imported.returncode == 0 and "CommandDrive" in imported.stdout, imported.stderr
    # The launch runs the rover's nodes; what fails is what this machine lacks: the RoboClaws'
    # serial port, the servo board's I2C, the packages the shared runtime has no code of.
    journal = ""
    for _ in range(60):
        journal = sandbox.sudo(ROVER, "journalctl -u osr_startup --no-pager -o cat", check=True).stdout
        if "roboclaw_wrapper" in journal and "stand-in: joy joy_node" in journal:
            break
        time.sleep(1)
    assert "[roboclaw_wrapper-1]" in journal or "roboclaw_wrapper" in journal, journal[-3000:]
    assert "roslab sandbox stand-in: joy joy_node" in journal, journal[-3000:]
    assert "roslab sandbox stand-in: teleop_twist_joy teleop_node" in journal, journal[-3000:]
    assert show(sandbox, ROVER, "osr_startup.service", "ActiveState")["ActiveState"] == "active"
    # roslab status says so truly, one line per node that died (systemd sees the launch running)
    result = subprocess.run([sys.executable, "-m", "roslab", "status", "--limit", ROVER, str(roster)],
                            env=sandbox.env, capture_output=True, text=True, timeout=120)
    text = " ".join(result.stdout.split())
    assert "osr_startup: roboclaw_wrapper died" in text and "Unable to connect to serial port" in text, text
    assert "osr_startup: rover died" in text and "No module named 'tf2_ros'" in text, text


def board(sandbox, roster: Path, action: str) -> subprocess.CompletedProcess:
    """`roslab sandbox board team2 ACTION --roster ROSTER`, as a teacher runs it."""
    return subprocess.run([sys.executable, "-m", "roslab", "sandbox", "board", "team2", action, "--roster",
                           str(roster)], env=sandbox.env, capture_output=True, text=True, timeout=900)


def board_pid(status: str) -> str:
    return status.rsplit("(pid ", 1)[1].split(")")[0]


def test_the_board_on_its_teams_domain_is_heard_reconnects_after_the_agent_is_killed_and_fails_when_stopped(
        sandbox, roster, first_run):
    """The emulated board, started by `roslab sandbox board` with the values the firmware is
    flashed with (the team's domain, esp32_board_team2), is heard by verify through the real
    agent; after a kill -9 of the agent (systemd restarts it 5 s later) the same board process
    reconnects and verify passes again; `board stop` makes verify fail naming the board."""
    needs_real(sandbox)
    domain = domain_id(sandbox, BOARD_HOST)
    started = board(sandbox, roster, "start")
    try:
        assert started.returncode == 0, started.stdout + started.stderr
        address = sandbox.host(BOARD_HOST).address
        assert (f"team2: board esp32_board_team2 (domain {domain}) publishes /esp32/potentiometer "
                f"(std_msgs/msg/Int32) through the micro-ROS agent on {BOARD_HOST} at {address}:{AGENT_PORT}/udp: "
                "publishing") in started.stdout, started.stdout
        heard = verify(sandbox, roster, "--limit", "team2")
        assert heard.returncode == 0, heard.stdout + heard.stderr
        # its publisher is the board's node, named as the firmware is flashed (verify_publisher)
        assert "/esp32/potentiometer from esp32_board_team2" in heard.stdout, heard.stdout
        before = board(sandbox, roster, "status").stdout
        assert before.rstrip().endswith(")") and ": publishing (pid " in before, before
        sandbox.sudo(BOARD_HOST, "systemctl kill -s KILL micro_ros_agent", check=True)
        status = ""
        for _ in range(10):  # the board's ping fails within 0.2 s; the agent is back after 5 s
            status = board(sandbox, roster, "status").stdout
            if "waiting for the agent" in status:
                break
            time.sleep(0.5)
        assert "waiting for the agent" in status, status
        for _ in range(60):
            status = board(sandbox, roster, "status").stdout
            if ": publishing (pid " in status:
                break
            time.sleep(1)
        assert ": publishing (pid " in status and board_pid(status) == board_pid(before), (before, status)
        again = verify(sandbox, roster, "--limit", "team2")
        assert again.returncode == 0, again.stdout + again.stderr
        assert "/esp32/potentiometer from esp32_board_team2" in again.stdout, again.stdout
    finally:
        stopped = board(sandbox, roster, "stop")
    assert stopped.returncode == 0 and "team2: board esp32_board_team2 stopped" in stopped.stdout, stopped
    assert "stopped" in board(sandbox, roster, "status").stdout
    silent = verify(sandbox, roster, "--limit", "team2")
    assert silent.returncode == 1, silent.stdout + silent.stderr
    assert "ESP32 board" in silent.stdout and BOARD_HOST in silent.stdout, silent.stdout


def test_verify_and_status_never_pass_an_uncalibrated_rover_and_say_what_starts_it(sandbox, roster, first_run):
    """The rover before its calibration (issue 40): with osr_calibrated: false a run stops the
    rover's service; verify then says NOT CHECKED and why, never PASS, and exits 3 (nothing failed,
    not every team verified); status's row for the robot says its service is not started. The
    roster's calibrated rover is back after (with stand-in rover code it is never calibrated)."""
    uncalibrated = roster.parent / "uncalibrated.yaml"  # beside the roster: its class.repos
    data = yaml.safe_load(roster.read_text())
    data["teams"]["team1"]["osr_calibrated"] = False
    uncalibrated.write_text(yaml.safe_dump(data, sort_keys=False))
    try:
        run = deploy(sandbox, uncalibrated, "--limit", "team1")
        assert run.returncode == 0 and not run.failed_hosts, run.stderr[-4000:]
        checked = verify(sandbox, uncalibrated, "--limit", "team1")
        assert checked.returncode == 3, checked.stdout + checked.stderr
        (row,) = [line for line in checked.stdout.splitlines() if line.split()[:1] == ["team1"]]
        assert "NOT CHECKED not checked, nothing to hear: robot profile osr names no topic" in row, row
        assert f"osr_startup on {ROVER} not started: osr_calibrated is false" in row and "PASS" not in row, row
        status = subprocess.run([sys.executable, "-m", "roslab", "status", str(uncalibrated), "--limit", "team1"],
                                env=sandbox.env, capture_output=True, text=True, timeout=300)
        assert status.returncode == 0, status.stdout + status.stderr
        (rover,) = [line for line in status.stdout.splitlines() if line.split()[:2] == ["team1", ROVER]]  # its row
        assert "none: osr_startup not started" in rover, status.stdout
    finally:
        if is_real(sandbox):
            again = deploy(sandbox, roster, "--limit", "team1")
            assert again.returncode == 0 and not again.failed_hosts, again.stderr[-4000:]


def test_the_stand_in_roboclaws_let_the_rovers_real_wrapper_publish_drive_state(sandbox, roster, first_run):
    """`roslab sandbox board team1 start` runs the STAND-IN RoboClaws (roslab/sandbox/roboclaw_board.py)
    inside the rover on /dev/serial1: osr-rover-code's real roboclaw_wrapper, respawned by the
    rover's launch, connects to addresses 128-130 and publishes /drive_state; `stop` ends it."""
    needs_real(sandbox)

    def rover_board(action: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "roslab", "sandbox", "board", "team1", action, "--roster",
                               str(roster)], env=sandbox.env, capture_output=True, text=True, timeout=120)

    started = rover_board("start")
    try:
        assert started.returncode == 0, started.stdout + started.stderr
        assert f"on /dev/serial1 of {ROVER}" in started.stdout and ": answering (pid " in started.stdout, started.stdout
        echoed = sandbox.ssh(ROVER, "timeout -k 5 90 bash -ic 'ros2 topic echo --once /drive_state "
                                    "sensor_msgs/msg/JointState' 2>/dev/null", timeout=120)
        assert "drive_left_front" in echoed.stdout and "drive_right_back" in echoed.stdout, echoed
    finally:
        stopped = rover_board("stop")
    assert stopped.returncode == 0 and stopped.stdout.rstrip().endswith(": stopped"), stopped
    assert sandbox.ssh(ROVER, "test -e /dev/serial1").returncode != 0


def test_the_students_shell_and_the_rovers_service_overlay_the_underlay(sandbox, first_run):
    bashrc = sandbox.ssh(ROVER, "cat ~/.bashrc", check=True).stdout
    assert bashrc.index("roslab_underlay/install/setup.bash") < bashrc.index("ros2_ws/install/setup.bash")
    shell = sandbox.ssh(ROVER, "bash -ic 'echo $AMENT_PREFIX_PATH' 2>/dev/null", check=True).stdout
    assert f"{UNDERLAY}/install/osr_bringup" in shell, shell
    # the rover's service sources the workspace, whose setup brings the underlay along (the
    # workspace was built on top of it)
    chained = sandbox.ssh(ROVER, "bash -c 'source /opt/ros/jazzy/setup.bash && "
                                 "source ~/ros2_ws/install/setup.bash && echo $AMENT_PREFIX_PATH'", check=True).stdout
    assert f"{UNDERLAY}/install/osr_bringup" in chained, chained


def test_a_rerun_changes_nothing_and_still_says_the_rover_waits_for_a_reboot(sandbox, roster, first_run):
    start = request_count(sandbox)
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed
    # a converged class asks the git upstream nothing (tags are checked when the pins change)
    git = [r.path for r in requests_since(sandbox, start) if r.path.startswith("/git/")]
    assert git == [], git
    lines = reboot_lines(again.stderr)
    assert len(lines) == 1 and lines[0].startswith(f"{ROVER} needs a reboot:"), lines


def test_status_shows_reboot_needed_until_a_reboot_after_which_a_run_changes_nothing(sandbox, roster, first_run):
    def status():
        result = subprocess.run([sys.executable, "-m", "roslab", "status", str(roster)], env=sandbox.env,
                                capture_output=True, text=True, timeout=120)
        return {line.split()[1]: line for line in result.stdout.splitlines() if line.startswith("team")}

    rows = status()
    assert "reboot needed: boot config changed:" in rows[ROVER]
    assert "reboot" not in rows["team1-main"] and "reboot" not in rows[BOARD_HOST]
    # A real reboot of the sandbox host: /run is a fresh tmpfs, the boot partition is kept.
    sandbox.reboot(ROVER)
    assert "reboot" not in status()[ROVER]
    assert "enable_uart=1" in sandbox.ssh(ROVER, "cat /boot/firmware/config.txt", check=True).stdout
    again = deploy(sandbox, roster)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.changed == {}, again.changed
    assert reboot_lines(again.stderr) == [], again.stderr[-3000:]


# --- the sources' ways of going wrong, each healed before the next test -----------------------


def test_a_changed_pin_rebuilds_only_the_rovers_underlay(sandbox, roster, first_run):
    commit_rover(sandbox, "roslab-e2e-v2", "v2")
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v2"))
    assert run.returncode == 0, run.stderr[-3000:]
    assert set(run.changes_per_host()) == {ROVER}, run.changed
    assert any("underlay" in name and "colcon" in name for name in run.changed), run.changed
    assert "roslab-e2e-v2" in rover_marker(sandbox)


def test_a_moved_tag_fails_only_the_rover_naming_the_repository_and_nothing_is_copied(sandbox, roster, first_run):
    """A tag is checked against upstream when the class's pins change (source_fetch.py): the
    teacher moves the rover back to its profile's pin, a tag locked in the first run, which
    someone moved upstream since."""
    repository = bare(sandbox, OSR_URL)
    recorded = subprocess.run(["git", "--git-dir", str(repository), "rev-parse", f"refs/tags/{OSR_PIN}"],
                              capture_output=True, text=True, check=True).stdout.strip()
    commit_rover(sandbox, OSR_PIN, "moved", move=True)
    try:
        run = deploy(sandbox, write_roster(sandbox, roster))
        assert run.failed_hosts == [ROVER], (run.failed_hosts, run.stderr[-3000:])
        assert "repository 'osr-rover-code'" in run.stderr and "now resolves to" in run.stderr, run.stderr[-3000:]
        assert "roslab-e2e-v2" in rover_marker(sandbox)  # nothing of the moved tag was copied
    finally:
        subprocess.run(["git", "--git-dir", str(repository), "tag", "-f", OSR_PIN, recorded], check=True,
                       capture_output=True)
        subprocess.run(["git", "--git-dir", str(repository), "update-server-info"], check=True)


def test_an_unreachable_repository_whose_pin_is_locked_is_named_in_one_warning_and_the_class_goes_on(
        sandbox, roster, first_run):
    repository = bare(sandbox, OSR_URL)
    # a new pin for the rover (a tag on the commit it runs: nothing to rebuild), so every tag of
    # the class is checked upstream, where the agent's repository is gone
    subprocess.run(["git", "--git-dir", str(repository), "tag", "-f", "roslab-e2e-v3", "roslab-e2e-v2"], check=True,
                   capture_output=True)
    subprocess.run(["git", "--git-dir", str(repository), "update-server-info"], check=True)
    agent = bare(sandbox, AGENT_URL)
    hidden = agent.with_name("hidden.git")
    agent.rename(hidden)
    try:
        run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v3"))
        # the lock and the controller's mirror hold the agent's pins: one warning, no failure
        assert run.returncode == 0, run.stderr[-3000:]
        assert set(run.changes_per_host()) <= {ROVER}, run.changed  # its workspace names the new pin
        warnings = [line for line in run.stderr.splitlines() if "cannot be reached" in line]
        assert len(warnings) == 1 and AGENT_URL in warnings[0], run.stderr[-3000:]
    finally:
        hidden.rename(agent)


def test_offline_the_class_converges_from_the_controllers_cache(sandbox, roster, first_run):
    start = request_count(sandbox)
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v3", offline=True))
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.changed == {}, run.changed
    assert not [r for r in requests_since(sandbox, start) if r.path.startswith("/git/")]
    cache = roster.parent / "sources-cache" / "git"
    kept = cache.with_name("git-kept")
    shutil.move(cache, kept)  # what offline cannot do without
    try:
        run = deploy(sandbox, roster)  # still offline (the roster as last written)
        # every host stopped while planning, saying why (each builds lab_tools)
        assert run.returncode != 0
        assert "offline, and the controller's cache" in run.stderr, run.stderr[-3000:]
        lines = summary_lines(run.stderr)
        for host in (ROVER, BOARD_HOST, "team1-main", "team2-main"):
            assert any(line.startswith(host + " ") and "failed" in line for line in lines), lines
    finally:
        shutil.move(kept, cache)


def test_a_failing_build_fails_the_rover_naming_the_package_and_keeps_the_last_good_install(
        sandbox, roster, first_run):
    """Last: the rover is left with a failed build (healing it would build the rover again)."""
    commit_rover(sandbox, "roslab-e2e-broken", "broken")
    before = sandbox.ssh(ROVER, f"readlink {UNDERLAY}/install", check=True).stdout.strip()
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-broken"))
    assert run.returncode != 0
    assert run.failed_hosts == [ROVER], run.failed_hosts
    if is_real(sandbox):
        assert "package osr_interfaces failed to build: CMake Error" in run.stderr, run.stderr[-3000:]
    else:
        assert "package osr_bringup failed to build: error: can't copy 'missing.yaml'" in run.stderr, \
            run.stderr[-3000:]
    assert sandbox.ssh(ROVER, f"readlink {UNDERLAY}/install", check=True).stdout.strip() == before
    assert "roslab-e2e-v2" in rover_marker(sandbox)  # the last good build, still in use
