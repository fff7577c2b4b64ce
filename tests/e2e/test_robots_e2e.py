"""The robots that need more than apt, end to end: a JPL Open Source Rover team and an ESP32 board.

Its own sandbox instance ($ROSLAB_ROBOTS_E2E_SANDBOX, $ROSLAB_ROBOTS_E2E_SUBNET), 3 hosts:

    team1  osr              24.04 (Jazzy), main + robot (not calibrated: the rover's service is
                            installed, disabled)
    team2  esp32_microros   22.04 (Humble), main only, the board attached to it (esp32_attached_to: main)

The profiles' repositories (osr.repos on the rover, esp32_microros_humble.repos where the board is
plugged in) go the whole way a classroom's do: fetched once per class by the controller, a
changed pin rebuilding only the workspace that uses it, a failing build keeping the last good
install, a moved tag or an unreachable repository failing only the hosts that need it, and
offline mode converging from the controller's cache (`sources_cache_dir`: the test's folder).

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
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import git_standins, upstream
from tests.e2e.conftest import bring_up, summary_lines

pytestmark = pytest.mark.e2e

INSTANCE = os.environ.get("ROSLAB_ROBOTS_E2E_SANDBOX", "roslab-robots-e2e")
SUBNET = os.environ.get("ROSLAB_ROBOTS_E2E_SUBNET", "10.213.171.0/24")
HOSTS = 3
ROVER = "team1-robot"
BOARD_HOST = "team2-main"
RECORD = "/var/lib/roslab/reboot-needed"
UNDERLAY = "/home/ubuntu/roslab_underlay"
OSR_URL = "https://github.com/nasa-jpl/osr-rover-code.git"
AGENT_URL = "https://github.com/micro-ROS/micro-ROS-Agent.git"
# the class's own tools (the roster's workspace_sources, a stand-in made by this test): every host
LAB_TOOLS_URL = "https://github.com/roslab-standin/lab_tools.git"
# every repository of the class, and the hosts that build it
REPOSITORIES = {LAB_TOOLS_URL: {ROVER, BOARD_HOST, "team1-main"}, OSR_URL: {ROVER}, AGENT_URL: {BOARD_HOST},
                "https://github.com/eProsima/Micro-XRCE-DDS-Agent.git": {BOARD_HOST}}
# Stand-ins of a Pi's boot files (Ubuntu 24.04 preinstalled server image for the Pi, abridged).
STANDIN_CONFIG = ("# roslab e2e STAND-IN of a Pi's /boot/firmware/config.txt (Ubuntu 24.04, abridged)\n"
                  "[all]\nkernel=vmlinuz\ncmdline=cmdline.txt\ninitramfs initrd.img followkernel\n"
                  "[pi4]\nmax_framebuffers=2\narm_boost=1\n[all]\narm_64bit=1\ndtparam=audio=on\n")
STANDIN_CMDLINE = ("console=serial0,115200 multipath=off dwc_otg.lpm_enable=0 console=tty1 "
                   "root=LABEL=writable rootfstype=ext4 rootwait fixrtc\n")


@pytest.fixture(scope="module")
def sandbox(sandbox_support):
    classroom, teardown = bring_up(INSTANCE, SUBNET, HOSTS, releases="24.04,22.04")
    try:
        yield classroom
    finally:
        teardown()


def deploy(sandbox, roster: Path, *args):
    return sandbox.pyinfra(*args, inventory="inventories/lab.py", env={"ROSLAB_ROSTER": str(roster)})


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
    teams["team1"].update(robot_profile="osr")
    if rover_pin:
        teams["team1"]["source_pins"] = {"osr-rover-code": rover_pin}
    teams["team2"].update(robot_profile="esp32_microros", esp32_usb_serial="0001A2B3", esp32_attached_to="main",
                          esp32_transport="serial", esp32_present=False)
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


def run_rover_standin(sandbox) -> str:
    """The rover's stand-in launch package, as a student runs it: after sourcing the underlay."""
    return sandbox.ssh(ROVER, f"bash -c 'source {UNDERLAY}/install/setup.bash && "
                              f"{UNDERLAY}/install/osr_bringup/lib/osr_bringup/osr_bringup'", check=True).stdout


@pytest.fixture(scope="module")
def first_run(sandbox, roster):
    sandbox.sudo(ROVER, "mkdir -p /boot/firmware", check=True)
    for name, text in (("config.txt", STANDIN_CONFIG), ("cmdline.txt", STANDIN_CMDLINE)):
        sandbox.sudo(ROVER, f"printf '%s' {shell(text)} > /boot/firmware/{name}", check=True)
    start = request_count(sandbox)
    run = deploy(sandbox, roster)
    run.requests = requests_since(sandbox, start)
    return run


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
    # the rover's nodes run with /usr/bin/python3: the venv reaches them through PYTHONPATH
    assert "/home/ubuntu/osr_venv/lib/python3*/site-packages" in props["ExecStart"]
    shell = sandbox.ssh(ROVER, "bash -ic 'python3 -c \"import adafruit_servokit, ina260\" && echo imported' "
                               "2>/dev/null", check=True).stdout
    assert "imported" in shell
    installed = sandbox.ssh(ROVER, "dpkg-query -W -f '${Package}\\n' python3-serial i2c-tools ros-jazzy-joy",
                            check=True).stdout.split()
    assert sorted(installed) == ["i2c-tools", "python3-serial", "ros-jazzy-joy"]


def test_the_agent_unit_runs_the_serial_transport_with_fast_dds(sandbox, first_run):
    props = show(sandbox, BOARD_HOST, "micro_ros_agent.service", "LoadState", "UnitFileState", "ActiveState",
                 "ExecStart", "Environment", "Restart")
    assert props["LoadState"] == "loaded" and props["Restart"] == "always", props
    assert "RMW_IMPLEMENTATION=rmw_fastrtps_cpp" in props["Environment"].split()
    assert "exec ros2 run micro_ros_agent micro_ros_agent serial --dev /dev/esp32 -b 115200" in props["ExecStart"]
    assert "source /opt/ros/humble/setup.bash" in props["ExecStart"]  # the board's host is on 22.04
    # esp32_present: false: installed, not started (the agent binary is the underlay's, not built here).
    assert props["UnitFileState"] == "disabled" and props["ActiveState"] == "inactive", props
    rules = sandbox.ssh(BOARD_HOST, "cat /etc/udev/rules.d/60-roslab-profile.rules", check=True).stdout
    assert 'ATTRS{serial}=="0001A2B3"' in rules and 'SYMLINK+="esp32"' in rules
    assert "dialout" in sandbox.ssh(BOARD_HOST, "id -nG ubuntu", check=True).stdout.split()
    assert sandbox.ssh(BOARD_HOST, "dpkg-query -W brltty 2>/dev/null | grep -q .").returncode != 0


def test_the_rover_and_the_boards_host_build_their_pinned_sources_and_the_rover_has_its_venv(sandbox, first_run):
    """osr.repos on the rover, esp32_microros_humble.repos only on the host the board is plugged into
    (the sandbox's stand-in repositories, pinned by the sandbox roster's source_pins)."""
    underlay = "/home/ubuntu/roslab_underlay/install"
    built = {host: sandbox.ssh(host, f"ls {underlay} 2>/dev/null").stdout.split()
             for host in (ROVER, "team1-main", "team2-main")}
    assert {"osr_bringup", "lab_tools"} <= set(built[ROVER]), built
    assert {"micro_ros_agent", "microxrcedds_agent", "lab_tools"} <= set(built["team2-main"]), built
    assert "lab_tools" in built["team1-main"] and "osr_bringup" not in built["team1-main"], built
    agent = sandbox.ssh("team2-main", f"bash -c 'source {underlay}/setup.bash && "
                                      f"{underlay}/micro_ros_agent/lib/micro_ros_agent/micro_ros_agent'", check=True)
    assert "roslab sandbox stand-in: micro_ros_agent" in agent.stdout
    imports = sandbox.ssh(ROVER, "~/osr_venv/bin/python -c 'import adafruit_servokit, ina260, RPi.GPIO, smbus'")
    assert imports.returncode == 0, imports.stderr
    assert sandbox.ssh(ROVER, "test -f ~/osr_venv/COLCON_IGNORE").returncode == 0
    # the agent's superbuild is off (the XRCE-DDS agent is in the underlay): colcon was given
    # the profile's CMake settings
    meta = sandbox.ssh(BOARD_HOST, f"cat {UNDERLAY}/.roslab/colcon.meta", check=True).stdout
    assert yaml.safe_load(meta)["names"]["micro_ros_agent"] == {"cmake-args": ["-DMICROROSAGENT_SUPERBUILD=OFF"]}
    colcon_log = sandbox.ssh(BOARD_HOST, f"grep -h 'Command line arguments' {UNDERLAY}/log/latest_build/logger_all.log",
                             check=True).stdout
    assert "'--metas', '.roslab/colcon.meta'" in colcon_log, colcon_log
    assert sandbox.ssh(ROVER, f"test -e {UNDERLAY}/.roslab/colcon.meta").returncode != 0  # the rover has none


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
    assert not [path for path in git if "/objects/" in path], git
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


# --- the sources' ways of going wrong, each healed before the next test -----------------------


def test_a_changed_pin_rebuilds_only_the_rovers_underlay(sandbox, roster, first_run):
    git_standins.commit(bare(sandbox, OSR_URL), git_standins.package_files(
        "osr_bringup", ["osr_bringup"], marker="roslab-e2e-v2"), "the rover's code, v2", ["roslab-e2e-v2"])
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v2"))
    assert run.returncode == 0, run.stderr[-3000:]
    assert set(run.changes_per_host()) == {ROVER}, run.changed
    assert any("underlay" in name and "colcon" in name for name in run.changed), run.changed
    assert "roslab-e2e-v2" in run_rover_standin(sandbox)


def test_a_failing_build_fails_the_rover_naming_the_package_and_keeps_the_last_good_install(
        sandbox, roster, first_run):
    broken = git_standins.package_files("osr_bringup", ["osr_bringup"])
    # a file the package installs is missing: setuptools' "error: can't copy ..." in colcon's log
    broken["osr_bringup/setup.py"] = broken["osr_bringup/setup.py"].replace(
        "['package.xml']", "['package.xml', 'missing.yaml']")
    git_standins.commit(bare(sandbox, OSR_URL), broken, "broken", ["roslab-e2e-broken"])
    before = sandbox.ssh(ROVER, f"readlink {UNDERLAY}/install", check=True).stdout.strip()
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-broken"))
    assert run.returncode != 0
    assert run.failed_hosts == [ROVER], run.failed_hosts
    assert "package osr_bringup failed to build: error: can't copy 'missing.yaml'" in run.stderr, run.stderr[-3000:]
    assert sandbox.ssh(ROVER, f"readlink {UNDERLAY}/install", check=True).stdout.strip() == before
    assert "roslab-e2e-v2" in run_rover_standin(sandbox)  # the last good build, still in use
    assert deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v2")).returncode == 0


def test_a_moved_tag_fails_only_the_rover_naming_the_repository_and_nothing_is_copied(sandbox, roster, first_run):
    # A tag is checked against upstream when the class's pins change (source_fetch.py): the
    # teacher moves the rover's pin back to a tag locked earlier, which someone moved since.
    repository = bare(sandbox, OSR_URL)
    recorded = subprocess.run(["git", "--git-dir", str(repository), "rev-parse", "refs/tags/roslab-e2e-broken"],
                              capture_output=True, text=True, check=True).stdout.strip()
    git_standins.commit(repository, git_standins.package_files("osr_bringup", ["osr_bringup"], marker="moved"),
                        "someone moved the tag", ["roslab-e2e-broken"], move_tags=True)
    try:
        run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-broken"))
        assert run.failed_hosts == [ROVER], (run.failed_hosts, run.stderr[-3000:])
        assert "repository 'osr-rover-code'" in run.stderr and "now resolves to" in run.stderr, run.stderr[-3000:]
        assert "roslab-e2e-v2" in run_rover_standin(sandbox)  # nothing of the moved tag was copied
    finally:
        subprocess.run(["git", "--git-dir", str(repository), "tag", "-f", "roslab-e2e-broken", recorded], check=True,
                       capture_output=True)
        subprocess.run(["git", "--git-dir", str(repository), "update-server-info"], check=True)


def test_an_unreachable_repository_whose_pin_is_locked_is_named_in_one_warning_and_the_class_goes_on(
        sandbox, roster, first_run):
    agent = bare(sandbox, AGENT_URL)
    hidden = agent.with_name("hidden.git")
    agent.rename(hidden)
    try:
        # the pins change back (the last test's): every tag is checked, the agent's upstream is gone,
        # and the lock and the controller's mirror hold its pin
        run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v2"))
        assert run.returncode == 0, run.stderr[-3000:]
        warnings = [line for line in run.stderr.splitlines() if "cannot be reached" in line]
        assert len(warnings) == 1 and AGENT_URL in warnings[0], run.stderr[-3000:]
    finally:
        hidden.rename(agent)


def test_offline_the_class_converges_from_the_controllers_cache(sandbox, roster, first_run):
    start = request_count(sandbox)
    run = deploy(sandbox, write_roster(sandbox, roster, rover_pin="roslab-e2e-v2", offline=True))
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.changed == {}, run.changed
    assert not [r for r in requests_since(sandbox, start) if r.path.startswith("/git/")]
    shutil.rmtree(roster.parent / "sources-cache" / "git")  # what offline cannot do without
    run = deploy(sandbox, roster)  # still offline (the roster as last written)
    # every host stopped while planning, saying why (each builds lab_tools)
    assert run.returncode != 0
    assert "offline, and the controller's cache" in run.stderr, run.stderr[-3000:]
    lines = summary_lines(run.stderr)
    for host in (ROVER, BOARD_HOST, "team1-main"):
        assert any(line.startswith(host + " ") and "failed" in line for line in lines), lines
