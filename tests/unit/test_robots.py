"""Robot profiles osr and esp32_microros, and the profile features they brought: side boards,
middlewares, boot config ("reboot needed"), services gated by a setting, apt packages to
remove. Refusals from a roster (before connecting, naming file, host and field), then
operations and deploys on fake hosts (facts in, commands out, no-op paths)."""

from __future__ import annotations

import shlex

import pytest
from fixtures.fake_host import plan
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import Directory, File, FileContents
from pyinfra.facts.systemd import SystemdEnabled, SystemdStatus
from test_profiles import _in_tmp, errors_of, rosdistro_url, write  # noqa: F401  (fixtures)

from deploy.profile_services import profile_services_in_place, unit_text
from roslab.profiles.resolve import ResolvedService
from deploy.robot_profile import robot_profile
from roslab.ops.boot_config import (
    CMDLINE_TXT,
    CONFIG_TXT,
    CmdlineText,
    REBOOT_RECORD,
    RebootRecord,
    cmdline_without,
    parse_reboot_record,
    reboot_pending,
)
from roslab.ops.files import RUN_MARK
from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host
from roslab.roster import load_roster
from roslab.checked.problems import Report
from roslab.profiles.schema import read_profile

UBUNTU_CMDLINE = ("console=serial0,115200 multipath=off dwc_otg.lpm_enable=0 console=tty1 root=LABEL=writable "
                  "rootfstype=ext4 rootwait fixrtc")


def roster(tmp_path, url, profile, team_extra="", robot_extra="", main_extra="", classroom_extra=""):
    team_extra = team_extra.replace("\n", "\n" + " " * 12)
    return write(tmp_path, f"""\
        classroom:
          ssh_user: ubuntu
          rosdistro_index_url: {url}
          rosdep_cache_dir: cache
          {classroom_extra}
        teams:
          t1:
            ubuntu_release: "24.04"
            robot_profile: {profile}
            {team_extra}
            hosts:
              t1-main: {{role: main{main_extra}}}
              t1-robot: {{role: robot{robot_extra}}}
        """)


def resolved(name, role="robot", distro="jazzy", board=None, **given):
    data, problems = resolve_host(builtin_profiles()[name], given, distro=distro, role=role, board=board)
    assert not problems, problems
    return data


# --- refused before connecting ----------------------------------------------------------------

def test_an_osr_robot_on_a_pi_5_is_refused_naming_file_host_and_field(tmp_path, rosdistro_url):
    errors = errors_of(roster(tmp_path, rosdistro_url, "osr", robot_extra=", board: pi5"))
    assert errors == ["lab.yaml:13: team 't1', host 't1-robot', field 'board': the robot of profile 'osr' does "
                      "not run on a pi5 (it runs on: pi3b+, pi4)"]


def test_an_osr_main_on_a_pi_5_is_fine_only_the_rovers_pi_needs_rpi_gpio(tmp_path, rosdistro_url):
    classroom = load_roster(roster(tmp_path, rosdistro_url, "osr", main_extra=", board: pi5",
                                   robot_extra=", board: pi4"))
    assert [host.data["roslab_profile"]["name"] for host in classroom.hosts] == ["osr", "osr"]


@pytest.mark.parametrize("transport", ["tcp", "udp6", "serial;reboot", "SERIAL"])
def test_an_esp32_transport_other_than_serial_or_udp_is_refused(tmp_path, rosdistro_url, transport):
    errors = errors_of(roster(tmp_path, rosdistro_url, "esp32_microros",
                              f"esp32_usb_serial: A1B2C3\nesp32_transport: {shlex.quote(transport)}"))
    assert errors and all("field 'esp32_transport'" in error and ("serial, udp" in error or "not a word" in error)
                          for error in errors)
    assert all(error.startswith("lab.yaml:") and "team 't1'" in error for error in errors)


def test_an_esp32_team_on_rmw_zenoh_is_refused(tmp_path, rosdistro_url):
    errors = errors_of(roster(tmp_path, rosdistro_url, "esp32_microros", "esp32_usb_serial: A1B2C3",
                              classroom_extra="ros_middleware: rmw_zenoh_cpp"))
    assert len(errors) == 1  # the classroom's value, the team's profile: said once, for the team
    assert "team 't1', field 'ros_middleware': profile 'esp32_microros' does not work with rmw_zenoh_cpp" \
        in errors[0]


@pytest.mark.parametrize("serial", ['A1"; RUN+="/bin/sh', "a b", "x" * 65, "$(reboot)"])
def test_a_hostile_usb_serial_number_is_refused(tmp_path, rosdistro_url, serial):
    errors = errors_of(roster(tmp_path, rosdistro_url, "esp32_microros", f"esp32_usb_serial: {shlex.quote(serial)}"))
    assert errors and all("field 'esp32_usb_serial'" in error for error in errors)


def test_the_esp32_board_is_the_only_chip_its_port_or_its_serial_and_on_udp_no_device(tmp_path, rosdistro_url):
    def rules(settings: str) -> str:
        return load_roster(roster(tmp_path, rosdistro_url, "esp32_microros", settings)).hosts[1].data[
            "roslab_profile"]["udev_rules"]

    only = rules("esp32_transport: serial")
    assert 'SYMLINK+="esp32"' in only and "ATTRS{serial}" not in only and "KERNELS" not in only
    by_port = rules("esp32_usb_port: 1-1.3")  # a CH340 has no serial number
    assert by_port.count('KERNELS=="1-1.3"') == 3 and "ATTRS{serial}" not in by_port
    assert rules("esp32_usb_port: 1-1.3\nesp32_usb_serial: A1").count('ATTRS{serial}=="A1"') == 3
    assert rules("esp32_transport: udp") == ""  # a board on WiFi has no USB link to the host
    errors = errors_of(roster(tmp_path, rosdistro_url, "esp32_microros", "esp32_usb_port: '1-1*'"))
    assert errors and all("field 'esp32_usb_port'" in error for error in errors)


@pytest.mark.parametrize("port", ["80", "65536", "8888x", "0"])
def test_a_udp_port_outside_1024_65535_is_refused(tmp_path, rosdistro_url, port):
    errors = errors_of(roster(tmp_path, rosdistro_url, "esp32_microros",
                              f"esp32_usb_serial: A1\nesp32_transport: udp\nesp32_udp_port: '{port}'"))
    assert errors and all("field 'esp32_udp_port'" in error for error in errors)


def test_yaml_true_and_a_port_number_are_the_settings_words(tmp_path, rosdistro_url):
    classroom = load_roster(roster(tmp_path, rosdistro_url, "esp32_microros",
                                   "esp32_usb_serial: A1\nesp32_transport: udp\nesp32_udp_port: 9999\n"
                                   "esp32_present: false"))
    robot = classroom.hosts[1].data["roslab_profile"]
    (agent,) = robot["services"]
    assert agent["command"].endswith("udp4 --port 9999") and agent["enabled"] is False
    assert robot["verify_topic"] is None  # no board: `roslab verify` expects nothing from it


def test_osr_calibrated_true_in_yaml_enables_the_rovers_service(tmp_path, rosdistro_url):
    classroom = load_roster(roster(tmp_path, rosdistro_url, "osr", "osr_calibrated: true"))
    (service,) = classroom.hosts[1].data["roslab_profile"]["services"]
    assert service["name"] == "osr_startup" and service["enabled"] is True
    assert classroom.hosts[0].data["roslab_profile"]["services"] == []


# --- the profile schema --------------------------------------------------------------------

def problems_of(mapping) -> list[str]:
    report = Report("lab.yaml")
    profile = read_profile(mapping, report, "profiles.bot", "the roster")
    assert profile is None
    return [str(problem) for problem in report.errors]


BASE = {"profile": "bot", "distros": ["jazzy"], "settings": {"on": {"allowed": ["true", "false"]}}}


@pytest.mark.parametrize("robot, words", [
    ({"boot_config": {"config_txt": ["enable_uart=1 # comment"]}}, "not a config.txt line"),
    ({"boot_config": {"config_txt": ["dtoverlay=x\ninitramfs evil"]}}, "not a config.txt line"),
    ({"boot_config": {"cmdline_remove": ["console=serial0 root=/dev/sda"]}}, "not one word of cmdline.txt"),
    ({"boot_config": {"kernel": ["x"]}}, "unknown key 'kernel'"),
    ({"services": [{"name": "roslab-nodes", "command": "true"}]}, "a unit roslab or the system owns"),
    ({"services": [{"name": "ssh", "command": "true"}]}, "a unit roslab or the system owns"),
    ({"services": [{"name": "../evil", "command": "true"}]}, "a service's name"),
    ({"services": [{"name": "agent", "command": "run ${nope}"}]}, "names ${nope}"),
    ({"services": [{"name": "agent", "command": "run\nreboot"}]}, "command"),
    ({"services": [{"name": "agent", "command": "run", "enabled_if": {"calibrated": "true"}}]},
     "tests 'calibrated'"),
    ({"services": [{"name": "agent", "command": "a"}, {"name": "agent", "command": "b"}]}, "a second service"),
    ({"services": [{"name": "agent", "command": "a", "environment": {"X": "a\nb"}}]}, "environment"),
    ({"remove_apt_packages": ["brltty"], "apt_packages": ["brltty"]}, "both installed and removed"),
    ({"remove_apt_packages": ["brltty; rm -rf /"]}, "Debian package name"),
    ({"boards": ["pi6"]}, "must be a list of boards"),
])
def test_a_profile_side_with_a_bad_new_key_is_refused(robot, words):
    problems = problems_of({**BASE, "robot": robot})
    assert any(words in problem for problem in problems), problems


def test_a_profile_naming_an_unknown_middleware_is_refused():
    problems = problems_of({**BASE, "middlewares": ["rmw_connext_cpp"], "robot": {}})
    assert any("middlewares" in problem for problem in problems)


# --- what the built-in profiles resolve to --------------------------------------------------

def test_osr_robot_gets_serial_and_i2c_on_and_its_service_disabled_until_calibrated():
    robot = resolved("osr", board="pi4")
    # At the pinned v4.1.0 the RoboClaws are on /dev/serial1 (the PL011), on GPIO 14/15 only with
    # Bluetooth off (setup/serial_config_info.md; tests/unit/test_devices_upstream.py reads the pin).
    assert robot["boot_config"] == {"config_txt": ["enable_uart=1", "dtoverlay=disable-bt", "dtparam=i2c_arm=on"],
                                    "cmdline_remove": ["console=serial0,115200"]}
    assert robot["groups"] == ["tty", "dialout", "input"]
    assert ('SUBSYSTEM=="tty", KERNEL=="ttyAMA0", ENV{ROSLAB_DEVICE}="roboclaw_uart", GROUP="dialout", '
            'MODE="0660", SYMLINK+="serial1"') in robot["udev_rules"]
    (service,) = robot["services"]
    assert service["command"] == "ros2 launch osr_bringup osr_launch.py"
    assert service["enabled"] is False and "osr_calibrated is false" in service["disabled_because"]
    assert any("128, 129 and 130" in item or "128, 129, 130" in item for item in robot["checklist"])
    assert any("osr_calibrated: true" in item for item in robot["checklist"])
    main = resolved("osr", role="main")
    assert main["packages"] == ["ros-jazzy-joy", "ros-jazzy-teleop-twist-joy"] and not main["boot_config"]


def test_esp32_agent_runs_on_the_side_the_board_is_attached_to():
    robot = resolved("esp32_microros", esp32_usb_serial="A1B2")
    main = resolved("esp32_microros", role="main", esp32_usb_serial="A1B2")
    (agent,) = robot["services"]
    assert agent["command"] == "ros2 run micro_ros_agent micro_ros_agent serial --dev /dev/esp32 -b 115200"
    assert agent["environment"] == {"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
                                    "XRCE_DOMAIN_ID_OVERRIDE": "${ros_domain_id}"}
    assert robot["remove_apt_packages"] == ["brltty"] and robot["groups"] == ["dialout"]
    assert 'ATTRS{serial}=="A1B2"' in robot["udev_rules"] and 'SYMLINK+="esp32"' in robot["udev_rules"]
    # CP2102, CH340 and CH9102 boards, each by the serial number
    assert [line.split(", ")[1:4] for line in robot["udev_rules"].splitlines() if not line.startswith("#")] == [
        ['ATTRS{idVendor}=="10c4"', 'ATTRS{idProduct}=="ea60"', 'ATTRS{serial}=="A1B2"'],
        ['ATTRS{idVendor}=="1a86"', 'ATTRS{idProduct}=="7523"', 'ATTRS{serial}=="A1B2"'],
        ['ATTRS{idVendor}=="1a86"', 'ATTRS{idProduct}=="55d4"', 'ATTRS{serial}=="A1B2"']]
    assert main["services"] == [] and main["udev_rules"] == "" and main["remove_apt_packages"] == []
    on_main = resolved("esp32_microros", role="main", esp32_usb_serial="A1B2", esp32_attached_to="main",
                       esp32_transport="udp", esp32_udp_port="9000")
    assert on_main["services"][0]["command"].endswith("udp4 --port 9000")
    assert on_main["services"][0]["description"] == "micro-ROS agent for the ESP32 board (UDP port 9000)"


def test_esp32_checklist_flashes_and_plugs_in_the_board_before_it_is_tried():
    robot = resolved("esp32_microros", esp32_usb_serial="A1", esp32_transport="udp")
    steps = [item.split()[0] for item in robot["checklist"]]
    assert steps == ["Flash", "UDP:", "Turn"], robot["checklist"]


def test_esp32_verify_expects_the_boards_reading_only_with_a_board_present_and_names_the_board():
    # the board's own topic: the robot's servo angle goes on after the board stops (the demo
    # node repeats its last angle), so only the potentiometer proves the board is there
    present = resolved("esp32_microros", esp32_usb_serial="A1", esp32_transport="udp")
    assert present["verify_topic"] == "/esp32/potentiometer"
    assert present["verify_source"] == "the ESP32 board (through micro_ros_agent on the team's robot, udp)"
    assert resolved("esp32_microros", esp32_usb_serial="A1", esp32_present="false")["verify_topic"] is None


def test_verify_names_what_publishes_the_topic_when_the_main_hears_nothing():
    from roslab.cli.verify import TeamResult, parse_check_output

    team = TeamResult("team2", main="team2-main", robots=["team2-robot"], topic="/esp32/potentiometer",
                      timeout=20, message_type="std_msgs/msg/Int32",
                      services={"team2-main": "not installed", "team2-robot": "active (running)"},
                      without_service={"team2-main"},
                      source="the ESP32 board (through micro_ros_agent on the team's robot, udp)")
    team.heard = {**parse_check_output([]), "ros": True, "finished": True, "topics": []}
    assert not team.passed
    assert team.verdict() == ("team2-main does not see /esp32/potentiometer: the ESP32 board (through "
                              "micro_ros_agent on the team's robot, udp) publishes nothing")


# --- boot config and the reboot record (operations, facts in, commands out) -------------------

def record(boot_id="b1", current="b1", reasons=("x",)):
    lines = [f"current_boot={current}"]
    if boot_id is not None:
        lines += ["#record", f"boot_id={boot_id}", *(f"reason={r}" for r in reasons)]
    return parse_reboot_record(lines)


def boot_facts(config=None, cmdline=UBUNTU_CMDLINE, reboot=None, boot=True):
    config = ["[pi4]", "max_framebuffers=2", "[all]", "arm_64bit=1"] if config is None else config
    return {
        File: lambda path: {"user": "root", "group": "root", "mode": 755} if boot and path == CONFIG_TXT else None,
        FileContents: lambda path: config if boot and path == CONFIG_TXT else None,
        CmdlineText: lambda path: cmdline if boot else None,
        RebootRecord: reboot or record(boot_id=None),
    }


def osr_plan(facts):
    profile = resolved("osr", board="pi4")
    profile.update(udev_rules="", groups=[])  # this test is about the boot config
    return plan(robot_profile, facts, data={"roslab_profile": profile, "robot_profile_enabled": True})


def test_the_cmdline_loses_only_the_serial_console():
    assert cmdline_without(UBUNTU_CMDLINE, ["console=serial0,115200"]) == UBUNTU_CMDLINE.replace(
        "console=serial0,115200 ", "")
    assert cmdline_without("console=serial0,1152000 quiet", ["console=serial0,115200"]) == \
        "console=serial0,1152000 quiet"


def test_a_pi_gets_the_block_the_cmdline_backed_up_and_a_reboot_recorded():
    result = osr_plan(boot_facts())
    changes = result.changing()
    block = result.uploads()[CONFIG_TXT]
    assert block.startswith("[pi4]\nmax_framebuffers=2\n[all]\narm_64bit=1\n")
    assert ("# BEGIN roslab managed block (robot profile boot config)\n[all]\nenable_uart=1\n"
            "dtoverlay=disable-bt\ndtparam=i2c_arm=on\n# END roslab managed block (robot profile boot config)\n") in block
    (cmdline,) = [commands for name, commands in changes.items() if CMDLINE_TXT in name]
    assert cmdline[0].startswith(f"cp -p -- {CMDLINE_TXT} {CMDLINE_TXT}.roslab-")
    assert "multipath=off" in cmdline[0] and "console=serial0" not in cmdline[0].split("printf")[1]
    (reboot,) = [commands for name, commands in changes.items() if "reboot" in name]
    assert "boot_id=%s" in reboot[0] and REBOOT_RECORD in reboot[0] and "chmod 644" in reboot[0]
    assert "reason=%s" in reboot[0] and "'boot config changed: /boot/firmware/config.txt" in reboot[0]


def test_config_txt_is_backed_up_before_its_block_changes():
    changes = osr_plan(boot_facts()).changing()
    (config,) = [commands for name, commands in changes.items() if CONFIG_TXT in name and "boot config" in name]
    assert config[0].startswith(f"cp -p -- {CONFIG_TXT} {CONFIG_TXT}.roslab-") and "&& sync -- " in config[0]
    assert config[1].startswith("upload ")  # the block's upload (fsynced file and folder: remote_files)


def test_boot_files_and_the_reboot_record_are_renamed_durably(tmp_path):
    """The cmdline's command, run here with `sync` a stand-in that logs: the new file and the
    backup reach the disk before the rename, the folder after it."""
    import os
    import subprocess

    from fixtures.fake_host import plan as plan_op

    from roslab.ops.boot_config import cmdline_words_absent

    boot = tmp_path / "firmware"
    boot.mkdir()
    cmdline = boot / "cmdline.txt"
    cmdline.write_text(UBUNTU_CMDLINE)
    stubs = tmp_path / "bin"
    stubs.mkdir()
    (stubs / "sync").write_text(f"#!/bin/sh\necho \"sync $* $(ls {boot} | tr '\\n' ' ')\" >> {tmp_path}/log\n")
    (stubs / "sync").chmod(0o755)
    result = plan_op(lambda: cmdline_words_absent(name="cmdline", path=str(cmdline),
                                                  words=["console=serial0,115200"], backup_suffix=".roslab-x"),
                     {CmdlineText: lambda path: UBUNTU_CMDLINE}, {})
    (command,) = [line for op in result.operations for line in op.text()]
    subprocess.run(["sh", "-c", command], check=True, env={**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}"})
    assert (tmp_path / "log").read_text().splitlines() == [
        # before the rename: the new file and the backup, both beside the old one
        f"sync -- {cmdline}.roslab-new-{RUN_MARK} {cmdline}.roslab-x cmdline.txt cmdline.txt.roslab-new-{RUN_MARK} "
        "cmdline.txt.roslab-x ",
        f"sync -- {boot} cmdline.txt cmdline.txt.roslab-x ",  # after it: the folder
    ]
    assert cmdline.read_text() == UBUNTU_CMDLINE.replace("console=serial0,115200 ", "").strip() + "\n"
    (reboot,) = [commands for name, commands in osr_plan(boot_facts()).changing().items() if "reboot" in name]
    assert reboot[0].endswith(f"&& sync -- {REBOOT_RECORD}.roslab-new-{RUN_MARK} && mv -f -- "
                              f"{REBOOT_RECORD}.roslab-new-{RUN_MARK} "
                              f"{REBOOT_RECORD} && {{ sync -- /run/roslab 2>/dev/null || true; }}")


def test_a_converged_pi_changes_nothing_and_records_no_reboot():
    block = ["[all]", "# BEGIN roslab managed block (robot profile boot config)", "[all]", "enable_uart=1",
             "dtoverlay=disable-bt", "dtparam=i2c_arm=on", "# END roslab managed block (robot profile boot config)"]
    result = osr_plan(boot_facts(config=block, cmdline=UBUNTU_CMDLINE.replace("console=serial0,115200 ", "")))
    assert result.changing() == {}
    assert any("holds none of console=serial0,115200" in noop for noop in result.noops)


def test_a_host_without_a_boot_partition_gets_nothing_and_says_why():
    result = osr_plan(boot_facts(boot=False))
    assert result.changing() == {}
    assert any("/boot/firmware/config.txt does not exist" in noop for noop in result.noops)


def test_a_record_from_an_earlier_boot_is_removed_and_a_pending_one_kept():
    stale = osr_plan(boot_facts(config=[], reboot=record(boot_id="old", current="new")))
    assert [f"rm -f -- {REBOOT_RECORD}"] in stale.changing().values()
    pending = record(boot_id="b1", current="b1", reasons=["boot config changed: earlier"])
    kept = osr_plan(boot_facts(reboot=pending)).changing()
    (reboot,) = [commands for name, commands in kept.items() if "reboot" in name]
    assert "'boot config changed: earlier'" in reboot[0]  # the earlier reason stays
    assert not [commands for commands in kept.values() if commands == [f"rm -f -- {REBOOT_RECORD}"]]


def test_reboot_pending_needs_the_same_boot():
    assert reboot_pending(record("b1", "b1")) and not reboot_pending(record("b0", "b1"))
    assert not reboot_pending(record(None, "b1"))


def test_brltty_is_removed_where_installed_and_left_alone_where_not():
    profile = resolved("esp32_microros", esp32_usb_serial="A1")
    profile.update(udev_rules="", groups=[])
    data = {"roslab_profile": profile, "robot_profile_enabled": True}
    installed = plan(robot_profile, {DebPackages: {"brltty": ["6.6-4ubuntu5"]}, File: None}, data=data).changing()
    assert any("apt-get" in command and "remove" in command and "brltty" in command
               for commands in installed.values() for command in commands)
    assert plan(robot_profile, {DebPackages: {}, File: None}, data=data).changing() == {}


# --- profile services --------------------------------------------------------------------------

def service_data(profile):
    return {"roslab_profile": profile, "profile_services_enabled": True, "workspace_dir": "~/ros2_ws",
            "login_user": "ubuntu", "ros_distro": "jazzy", "roslab_role": "robot", "ros_domain_id": 7,
            "ros_middleware": "rmw_fastrtps_cpp", "discovery_enabled": False}


def service_facts(unit=None, running=False, enabled=False, foreign=None, contents=None):
    from pyinfra.facts.server import Home, LinuxDistribution
    return {
        Home: "/home/ubuntu",
        File: lambda path: ({"user": "root", "group": "root", "mode": 644}
                            if (unit and path.startswith("/etc/")) or path in (foreign or ()) else None),
        Directory: lambda path: None,
        FileContents: lambda path: (contents if contents is not None else
                                    ["# managed by roslab (deploy/profile_services.py) for robot profile osr"]
                                    if unit else None),
        SystemdStatus: lambda services, **_: {name: running for name in services},
        SystemdEnabled: lambda services, **_: {name: enabled for name in services},
        LinuxDistribution: {"name": "Ubuntu", "major": 24, "minor": 4, "release_meta": {"VERSION_CODENAME": "noble"}},
    }


def test_the_agent_unit_runs_its_transport_with_fast_dds_as_the_login_user():
    profile = resolved("esp32_microros", esp32_usb_serial="A1")
    text = unit_text(service=ResolvedService.from_data(profile["services"][0]), profile="esp32_microros", user="ubuntu",
                     home="/home/ubuntu", workspace_dir="/home/ubuntu/ros2_ws", distro="jazzy",
                     environment={"ROS_DOMAIN_ID": "7", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"})
    assert 'Environment="RMW_IMPLEMENTATION=rmw_fastrtps_cpp"' in text  # the service's own wins
    assert 'Environment="ROS_DOMAIN_ID=7"' in text
    assert "User=ubuntu" in text and "Restart=always" in text
    (exec_start,) = [line for line in text.splitlines() if line.startswith("ExecStart=")]
    assert exec_start.startswith('ExecStart=/bin/bash -c "source /opt/ros/jazzy/setup.bash && ')
    assert "exec ros2 run micro_ros_agent micro_ros_agent serial --dev /dev/esp32 -b 115200" in exec_start


def test_a_hostile_setting_in_a_service_command_stays_one_shell_word():
    from roslab.profiles.resolve import resolved_service
    service = {"name": "s", "description": "", "command": "run --port ${port} ${distro}", "environment": {},
               "enabled_if": {}}
    out = resolved_service(service, {"port": "8888;reboot"}, "jazzy", "p")
    assert out["command"] == "run --port '8888;reboot' jazzy"


def test_an_uncalibrated_rover_gets_its_unit_installed_but_not_enabled_saying_why(monkeypatch):
    monkeypatch.setattr("deploy.profile_services.host_environment", lambda data, distro: {"ROS_DOMAIN_ID": "7"})
    monkeypatch.setattr("deploy.profile_services.host_distro", lambda: "jazzy")
    result = plan(profile_services_in_place, service_facts(), data=service_data(resolved("osr", board="pi4")))
    changes = result.changing()
    assert "/etc/systemd/system/osr_startup.service" in result.uploads()
    assert not [name for name, commands in changes.items() if any("enable" in c and "disable" not in c
                                                                   for c in commands)]
    assert any("installed but not enabled because osr_calibrated is false" in noop for noop in result.noops)


def test_a_rover_whose_calibration_was_withdrawn_gets_its_service_stopped_and_disabled(monkeypatch):
    monkeypatch.setattr("deploy.profile_services.host_environment", lambda data, distro: {})
    monkeypatch.setattr("deploy.profile_services.host_distro", lambda: "jazzy")
    changes = plan(profile_services_in_place, service_facts(running=True, enabled=True),
                   data=service_data(resolved("osr", board="pi4"))).changing()
    (stop,) = [commands for name, commands in changes.items() if "stopped and disabled" in name]
    assert stop == ["systemctl stop osr_startup.service", "systemctl disable osr_startup.service"]


@pytest.mark.parametrize("facts", [
    {"foreign": ["/usr/lib/systemd/system/osr_startup.service"]},  # a package's unit of that name
    {"unit": True, "contents": ["[Unit]", "Description=someone's own"]},  # a unit roslab did not write
])
def test_a_unit_roslab_did_not_write_is_never_replaced_and_stops_the_host(monkeypatch, facts):
    monkeypatch.setattr("deploy.profile_services.host_environment", lambda data, distro: {})
    monkeypatch.setattr("deploy.profile_services.host_distro", lambda: "jazzy")
    result = plan(profile_services_in_place, service_facts(**facts), data=service_data(resolved("osr", board="pi4")))
    assert result.failed and result.changing() == {}
    assert any("osr_startup.service is a unit of this host that roslab did not write" in e for e in result.errors)


def test_a_calibrated_rover_gets_its_service_enabled_and_started(monkeypatch):
    monkeypatch.setattr("deploy.profile_services.host_environment", lambda data, distro: {})
    monkeypatch.setattr("deploy.profile_services.host_distro", lambda: "jazzy")
    profile = resolved("osr", board="pi4", osr_calibrated="true")
    changes = plan(profile_services_in_place, service_facts(), data=service_data(profile)).changing()
    commands = [command for commands in changes.values() for command in commands]
    assert any("systemctl start osr_startup.service" in command for command in commands)
    assert any("systemctl enable osr_startup.service" in command for command in commands)


# --- "reboot needed" in the run summary and in `roslab status` -------------------------------

def test_the_summary_says_reboot_needed_once_per_host_that_changed_or_still_waits():
    from test_summary import classroom, executed, finished_run, operation_on, printed

    state, handler = classroom("osr-robot", "esp-robot", "waiting-robot")
    changed = operation_on(state, "osr-robot", "op-boot", "Ensure config.txt", changed=True)
    second = operation_on(state, "osr-robot", "op-cmdline", "Ensure cmdline.txt", changed=True)
    unchanged = operation_on(state, "esp-robot", "op-boot", "Ensure config.txt", changed=False)
    pending = operation_on(state, "waiting-robot", "op-boot", "Ensure config.txt", changed=False)
    handler.record_reboot("osr-robot", ["boot config changed: a", "boot config changed: b"], [], [changed, second])
    handler.record_reboot("esp-robot", ["boot config changed: a"], [], [unchanged])
    handler.record_reboot("waiting-robot", ["boot config changed: a"], ["boot config changed: earlier"], [pending])
    finished_run(state)
    executed(state, handler, "osr-robot", "op-boot", success=True)
    for name in ("esp-robot", "waiting-robot"):
        executed(state, handler, name, "op-boot", success=True, commands=0)
    executed(state, handler, "osr-robot", "op-cmdline", success=True)
    lines = printed(state, handler)
    reboot = lines[lines.index("--> reboot needed") + 1:]
    assert reboot == [
        "    osr-robot needs a reboot: boot config changed: a; boot config changed: b (roslab never reboots during "
        "a run: reboot it when the class allows, e.g. `sudo reboot`)",
        "    waiting-robot needs a reboot: boot config changed: earlier (roslab never reboots during a run: "
        "reboot it when the class allows, e.g. `sudo reboot`)",
    ]


def test_status_shows_reboot_needed_until_the_host_has_rebooted():
    from fixtures.status_hosts import NOW, PROBE_OUTPUT, reachable_host

    from roslab.cli.status import format_table, host_cells, parse_probe

    def with_record(boot_id, current):
        lines = [line for line in PROBE_OUTPUT if line != "## end"]
        lines += ["## reboot", f"current_boot={current}", "#record", f"boot_id={boot_id}",
                  "reason=boot config changed: /boot/firmware/config.txt (enable_uart=1)", "## end"]
        return parse_probe(lines)

    waiting = reachable_host(probe=with_record("b1", "b1"))
    note = host_cells(waiting, NOW)["NOTE"]
    assert note.text == "reboot needed: boot config changed: /boot/firmware/config.txt (enable_uart=1)"
    assert note.level == "warn"
    assert "reboot needed" in format_table([waiting], NOW)
    rebooted = reachable_host(probe=with_record("b1", "b2"))
    assert "reboot" not in host_cells(rebooted, NOW)["NOTE"].text
    assert "reboot" not in host_cells(reachable_host(), NOW)["NOTE"].text  # no record at all


def test_the_status_probe_reads_the_record_without_sudo():
    from roslab.cli.status import probe_script

    script = probe_script()
    assert "## reboot" in script and REBOOT_RECORD in script and "sudo" not in script


def test_the_rovers_service_sees_its_venvs_packages_through_pythonpath(tmp_path):
    """ROS starts the rover's Python nodes with /usr/bin/python3 (their shebang), not the venv's
    interpreter: the unit puts the venv's site-packages first on PYTHONPATH, as the student's
    ~/.bashrc block does, once however often it is sourced."""
    import subprocess

    from deploy.profile_services import exec_script
    from deploy.shell_env import render_ros_environment

    home = tmp_path / "home"
    site = home / "osr_venv/lib/python3.12/site-packages"
    site.mkdir(parents=True)
    (site / "adafruit_servokit.py").write_text("NAME = 'from the venv'\n")
    ros = tmp_path / "opt/ros/jazzy"
    ros.mkdir(parents=True)
    (ros / "setup.bash").write_text("export PYTHONPATH=/opt/ros/jazzy/lib/python3.12/site-packages\n")
    command = "python3 -c \"import adafruit_servokit, os; print(adafruit_servokit.NAME, os.environ['PYTHONPATH'])\""
    script = exec_script(distro="jazzy", workspace_dir=str(home / "ros2_ws"), command=command,
                         venv_dir=str(home / "osr_venv")).replace("/opt/ros/", f"{tmp_path}/opt/ros/")
    done = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert done.stdout.split() == ["from", "the", "venv", f"{site}:/opt/ros/jazzy/lib/python3.12/site-packages"], \
        done.stderr

    block = render_ros_environment("jazzy", {"ROS_DOMAIN_ID": "7"}, venv_dir="~/osr_venv").replace("/opt/ros/", f"{tmp_path}/opt/ros/")
    twice = subprocess.run(["bash", "-c", f"{block}\n{block}\necho $PYTHONPATH"], capture_output=True, text=True,
                           env={"PATH": "/usr/bin:/bin", "HOME": str(home)})
    assert twice.stdout.strip() == f"{site}:/opt/ros/jazzy/lib/python3.12/site-packages", twice.stderr
    assert "osr_venv" not in render_ros_environment("jazzy", {"ROS_DOMAIN_ID": "7"})


def test_the_rovers_unit_names_its_venv_only_when_the_python_step_fills_it(monkeypatch):
    monkeypatch.setattr("deploy.profile_services.host_environment", lambda data, distro: {})
    monkeypatch.setattr("deploy.profile_services.host_distro", lambda: "jazzy")
    for enabled in (True, False):
        data = {**service_data(resolved("osr", board="pi4")), "python_env_enabled": enabled}
        unit = plan(profile_services_in_place, service_facts(), data=data).uploads()[
            "/etc/systemd/system/osr_startup.service"]
        assert ("/home/ubuntu/osr_venv/lib/python3*/site-packages" in unit) is enabled, unit


def test_a_profile_with_a_venv_and_a_launch_gives_its_nodes_unit_the_venv_too():
    from deploy.workspace import exec_script

    script = exec_script(distro="jazzy", workspace_dir="/home/u/ros2_ws", launch="roslab_bringup robot.launch.py",
                         venv_dir="/home/u/mybot_venv")
    assert script.index("ros2_ws/install/setup.bash") < script.index("/home/u/mybot_venv/lib/python3*")
    assert script.index("/home/u/mybot_venv/lib/python3*") < script.index("exec ros2 launch")
    assert "venv" not in exec_script(distro="jazzy", workspace_dir="/home/u/ros2_ws",
                                     launch="roslab_bringup robot.launch.py")
