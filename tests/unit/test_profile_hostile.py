"""Roster profiles, sources and OS tweaks that must not reach a Pi (issue 28): refused before any host
is touched, each in one line naming file:line (team and host where the value is a host's) and field.

Each case writes a real roster and runs `roslab check` on it (or loads it through
inventories/lab.py, as pyinfra does, for `--data`), with every outgoing connection made to
fail the test. The classes: environment names (an allow-list: a form plus refused families
naming the setting that governs them), the login user's groups, the units a tweak may mask,
devices as data (no udev rule text), setting patterns that could backtrack, file:// rewrites
and caches outside their purpose, system unit names, `extends` loops, .repos files that are
not regular files. Good values still pass: the built-in profiles load, and so do a lab's own.
"""

from __future__ import annotations

import json
import os
import runpy
import sys
import time
from pathlib import Path

import pytest

from roslab.cli.main import main
from roslab.profiles import library
from roslab.roster import RosterError, load_roster

REPO = Path(__file__).resolve().parents[2]
LAB_INVENTORY = REPO / "inventories" / "lab.py"

ROSTER = """\
classroom:
  ssh_user: ubuntu{classroom}
profiles:
  mine:
    extends: demo
    robot:
      {part}
teams:
  team1:
    hosts:
      team1-robot:
        role: robot
        robot_profile: mine{host}
"""
PART_LINE = 7
HOST_LINE = 14  # the first key added under the host
HOST = "team 'team1', host 'team1-robot'"
CLASSROOM_LINE = 3  # the first key added under the classroom


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ROSLAB_ROSTER", raising=False)
    monkeypatch.setattr(sys, "argv", ["pytest"])


def roster(tmp_path: Path, part: str = "launch: roslab_bringup robot.launch.py", host: str = "",
           classroom: str = "") -> Path:
    path = tmp_path / "lab.yaml"
    path.write_text(template(part=part, host="".join(f"\n        {line}" for line in host.splitlines()),
                             classroom="".join(f"\n  {line}" for line in classroom.splitlines())))
    return path


def template(part: str, host: str = "", classroom: str = "") -> str:
    return ROSTER.format(part=part, host=host, classroom=classroom)


def checked_errors(path: Path, capsys, no_connections) -> list[str]:
    """`roslab check` on the roster: exit 1, quickly, no host contacted; its error lines."""
    started = time.monotonic()
    assert main(["check", str(path)]) == 1
    assert time.monotonic() - started < 10  # a pattern or a file never hangs the check
    assert no_connections == []
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no host was touched" in err
    return [line for line in err.splitlines() if line.startswith("lab.yaml") or line.startswith("pyinfra's")]


def one_error(errors: list[str], prefix: str, *words: str) -> str:
    matching = [line for line in errors if line.startswith(prefix)]
    assert len(matching) == 1, errors
    for word in words:
        assert word in matching[0], matching[0]
    return matching[0]


# --- environment names: an allow-list ---------------------------------------------------------

GOVERNED = {
    "RMW_IMPLEMENTATION": "set by the class's `ros_middleware` setting",
    "ROS_DOMAIN_ID": "`ros_domain_id`",
    "ROS_LOCALHOST_ONLY": "`ros_discovery_mode`",
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "`ros_discovery_mode`",
    "ROS_STATIC_PEERS": "`ros_static_peers`",
    "ROS_DISCOVERY_SERVER": "`ros_discovery_mode`",
    "ROS_LOG_DIR": "ROS 2's own variables",
    "RMW_FASTRTPS_USE_QOS_FROM_XML": "`ros_middleware`",
    "CYCLONEDDS_URI": "`ros_discovery_mode`",
    "ZENOH_CONFIG_OVERRIDE": "`ros_discovery_mode`",
    "FASTDDS_DEFAULT_PROFILES_FILE": "`ros_discovery_mode`",
    "AMENT_PREFIX_PATH": "the ROS setup roslab sources",
    "PS1": "prompt", "PS2": "prompt", "PS4": "prompt", "PROMPT_COMMAND": "prompt", "PROMPT_DIRTRIM": "prompt",
    "LD_AUDIT": "loader", "LD_PRELOAD": "loader", "LD_LIBRARY_PATH": "loader", "GLIBC_TUNABLES": "loader",
    "MALLOC_CHECK_": "loader", "GCONV_PATH": "loader",
    "PYTHONHOME": "Python", "PYTHONPATH": "Python", "PYTHONSTARTUP": "Python", "PYTHON_BASIC_REPL": "Python",
    "PIP_INDEX_URL": "`python_packages`",
    "PERL5OPT": "interpreter", "PERL5LIB": "interpreter", "RUBYOPT": "interpreter", "NODE_OPTIONS": "interpreter",
    "JAVA_TOOL_OPTIONS": "interpreter",
    "BASH_ENV": "shell", "ENV": "shell", "IFS": "shell", "BASH_FUNC_ls%%": "shell", "HISTFILE": "shell",
    "PATH": "account", "HOME": "account", "EDITOR": "account",
    "GIT_SSH_COMMAND": "git", "SSH_ASKPASS": "tools", "SYSTEMD_PAGER": "tools", "LESSOPEN": "tools",
    "LANG": "`locale`", "LC_ALL": "`locale`", "TZ": "`timezone`",
}
BAD_FORM = ["DEBUG", "lowercase_name", "Mixed_Case", "_LEADING", "TRAILING_", "DOUBLE__UNDERSCORE", "1ST_NAME",
            "A" * 40 + "_" + "B" * 40, "WITH-DASH", "WITH SPACE", "TURTLEBOT3_MODEL\u0131"]
GOOD_NAMES = ["TURTLEBOT3_MODEL", "LDS_MODEL", "GAZEBO_MODEL_PATH", "GZ_SIM_RESOURCE_PATH", "FOO_BAR",
              "LAB_ROBOT_COLOUR", "RCUTILS_COLORIZED_OUTPUT", "RCUTILS_CONSOLE_OUTPUT_FORMAT", "MANIPULATOR_TYPE",
              "OPENCR_PORT", "ROBOT_2_NAME"]


@pytest.mark.parametrize("name, governs", GOVERNED.items())
def test_a_governed_variable_in_ros_environment_names_what_governs_it(name, governs, tmp_path, capsys,
                                                                       no_connections):
    path = roster(tmp_path, host=f"ros_environment: {json.dumps({name: '$(touch /tmp/x) $ '})}")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{HOST_LINE}: {HOST}, field 'ros_environment': ",
              f"{name} is not set through an environment mapping", governs)


@pytest.mark.parametrize("name", [*GOVERNED, *BAD_FORM])
def test_a_profile_environment_takes_only_allowed_names(name, tmp_path, capsys, no_connections):
    path = roster(tmp_path, part=f"environment: {json.dumps({name: 'x'})}")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.environment.")


@pytest.mark.parametrize("name", ["PS1", "LD_AUDIT", "RMW_IMPLEMENTATION", "lower_case"])
def test_a_profile_service_and_a_when_block_take_only_allowed_names(name, tmp_path, capsys, no_connections):
    services = (f"services: [{{name: lab_driver, command: /bin/true, environment: {json.dumps({name: 'x'})}}}]")
    when = f"when: [{{if: {{distro: jazzy}}, environment: {json.dumps({name: 'x'})}}}]"
    for part, field in ((services, "profiles.mine.robot.services[1].environment"),
                        (when, "profiles.mine.robot.when[1].environment")):
        errors = checked_errors(roster(tmp_path, part=part), capsys, no_connections)
        assert any(f"field '{field}." in line for line in errors), errors


def test_a_service_may_name_its_own_middleware_and_nothing_else(tmp_path, capsys, no_connections):
    ok = "services: [{name: lab_agent, command: /bin/true, environment: {RMW_IMPLEMENTATION: rmw_fastrtps_cpp}}]"
    load_roster(roster(tmp_path, part=ok))
    bad = ok.replace("rmw_fastrtps_cpp", "librmw_evil.so")
    errors = checked_errors(roster(tmp_path, part=bad), capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.services[1].environment.",
              "RMW_IMPLEMENTATION of a service is one of")


@pytest.mark.parametrize("name", ["PS1", "RMW_IMPLEMENTATION", "LD_AUDIT", "PYTHONHOME", "lower"])
def test_ros_environment_from_the_command_line_is_blamed_on_it(name, tmp_path, monkeypatch, capsys, no_connections):
    err = inventory_refused(tmp_path, monkeypatch, capsys, ["--data", f"ros_environment={json.dumps({name: 'x'})}"])
    lines = [line for line in err.splitlines() if line.startswith("pyinfra's command line: field 'ros_environment': ")]
    assert len(lines) == 1 and f"--data ros_environment=" in lines[0], err
    assert "lab.yaml" not in err
    assert no_connections == []


def test_a_classs_own_variable_names_pass_everywhere(tmp_path):
    variables = {name: "burger" for name in GOOD_NAMES}
    host = load_roster(roster(tmp_path, part=f"environment: {json.dumps(variables)}",
                              host=f"ros_environment: {json.dumps(variables)}")).hosts[0]
    assert host.data["ros_environment"] == variables
    assert host.data["roslab_profile"]["environment"] == variables


# --- groups, masked units, swap, service names -------------------------------------------------

@pytest.mark.parametrize("group", ["sudo", "root", "shadow", "disk", "adm", "docker", "lxd", "wheel", "kmem",
                                   "systemd-journal", "netdev", "staff", "lpadmin"])
def test_a_group_that_is_not_hardware_access_is_refused(group, tmp_path, capsys, no_connections):
    errors = checked_errors(roster(tmp_path, part=f"groups: [dialout, {group}]"), capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.groups': ",
              f"{group!r} is not a hardware-access group")
    errors = checked_errors(roster(tmp_path, part=f"when: [{{if: {{distro: jazzy}}, groups: [{group}]}}]"),
                            capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.when[1].groups': ", "hardware-access")


def test_hardware_groups_are_given(tmp_path):
    part = "groups: [dialout, tty, input, video, i2c, gpio, spi, plugdev, audio, render, bluetooth]"
    host = load_roster(roster(tmp_path, part=part)).hosts[0]
    assert host.data["roslab_profile"]["groups"] == ["dialout", "tty", "input", "video", "i2c", "gpio", "spi",
                                                     "plugdev", "audio", "render", "bluetooth"]


@pytest.mark.parametrize("unit", ["ssh.service", "ssh.socket", "sshd.service", "systemd-journald.service",
                                  "systemd-logind.service", "dbus.service", "dbus.socket", "local-fs.target",
                                  "multi-user.target", "network.target", "network-online.target",
                                  "systemd-networkd.service", "NetworkManager.service", "getty@tty1.service",
                                  "serial-getty@ttyS0.service", "cron.service", "systemd-udevd.service",
                                  "ssh", "default.target", "sysinit.target"])
def test_a_tweak_never_masks_what_reaching_the_host_needs(unit, tmp_path, capsys, no_connections):
    path = roster(tmp_path, part=f"os_tweaks: {{mask_units: [{unit}]}}", host="profile_os_tweaks: true")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.os_tweaks.mask_units': ",
              f"{unit!r} is not a unit an OS tweak may mask")


def test_a_tweak_masks_what_the_allow_list_holds(tmp_path):
    units = ["unattended-upgrades.service", "apt-daily.timer", "ModemManager.service", "cups.service",
             "systemd-networkd-wait-online.service", "sleep.target"]
    path = roster(tmp_path, part=f"os_tweaks: {{mask_units: {json.dumps(units)}, swap_mb: 8192}}",
                  host="profile_os_tweaks: true")
    tweaks = load_roster(path).hosts[0].data["roslab_profile"]["os_tweaks"]
    assert tweaks == {"mask_units": units, "swap_mb": 8192}


@pytest.mark.parametrize("swap", [65536, 8193, 63, 0, -1, "2G", True])
def test_a_swap_file_is_bounded(swap, tmp_path, capsys, no_connections):
    errors = checked_errors(roster(tmp_path, part=f"os_tweaks: {{swap_mb: {json.dumps(swap)}}}"), capsys,
                            no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.os_tweaks.swap_mb': ", "64 to 8192")


@pytest.mark.parametrize("name", ["systemd-journald", "systemd-resolved", "ssh", "sshd", "ssh-agent", "dbus",
                                  "dbus-broker", "getty", "cron", "roslab-nodes", "networking", "cloud-init",
                                  "snapd", "apt-daily", "udev", "polkit"])
def test_a_service_named_like_a_system_unit_is_refused_before_connecting(name, tmp_path, capsys, no_connections):
    errors = checked_errors(roster(tmp_path, part=f"services: [{{name: {name}, command: /bin/true}}]"), capsys,
                            no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.services[1].name': ",
              "a unit roslab or the system owns")


# --- devices as data: no rule text, each field allow-listed ---------------------------------------

# Rule text a profile may no longer write, whatever it says (issue 36's held-out values among them:
# every virtual console, /dev/console, every keyboard).
HOSTILE_RULES = [
    'SUBSYSTEM=="tty", ATTR{dev}=="4:*", MODE="0666"',
    'SUBSYSTEM=="tty", ATTR{dev}=="5:1", MODE="0666"',
    'SUBSYSTEM=="input", KERNEL=="*e*", MODE="0666"',
    'SUBSYSTEM=="tty", ATTRS{idVendor}=="10c4", SYMLINK+="esp32"',
    'KERNEL=="ttyUSB0", RU\\\\',
]


@pytest.mark.parametrize("rule", HOSTILE_RULES)
def test_rule_text_is_refused_pointing_to_devices(rule, tmp_path, capsys, no_connections):
    part = f"udev_rules: [{{rule: {json.dumps(rule)}}}]"
    errors = checked_errors(roster(tmp_path, part=part), capsys, no_connections)
    one_error(errors, f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.udev_rules': ", "write each device under "
              "`devices:`")


GOOD_DEVICE = {"name": "board", "kind": "usb_serial", "usb_ids": ["0483:5740"], "symlink": "lab_board",
               "group": "dialout", "mode": "0660", "modemmanager": "ignore"}
HOSTILE_DEVICES = [
    ({"kind": "block"}, "kind", "not a device kind"),
    ({"kind": "input"}, "kind", "not a device kind"),
    ({"usb_ids": ["*:*"]}, "usb_ids", "not a USB vendor:product id"),
    ({"usb_ids": ["10c4"]}, "usb_ids", "not a USB vendor:product id"),
    ({"usb_ids": ["10C4:EA60"]}, "usb_ids", "not a USB vendor:product id"),
    ({"usb_ids": ['10c4:ea60", RUN+="/bin/sh']}, "usb_ids", "not a USB vendor:product id"),
    ({"usb_ids": ["10c4:*"]}, "usb_ids", "names its product"),
    ({"usb_ids": []}, "usb_ids", "must be a list"),
    ({"group": "input"}, "group", "not a group a device may be given"),
    ({"group": "tty"}, "group", "not a group a device may be given"),
    ({"group": "disk"}, "group", "not a group a device may be given"),
    ({"group": "root"}, "group", "not a group a device may be given"),
    ({"mode": "4777"}, "mode", "not a mode a device may be given"),
    ({"mode": "0777"}, "mode", "not a mode a device may be given"),
    ({"symlink": "disk/by-uuid/1"}, "symlink", "no folders"),
    ({"symlink": "../sda"}, "symlink", "no folders"),
    ({"symlink": "%k"}, "symlink", "no folders"),
    ({"symlink": "console"}, "symlink", "the system's own devices"),
    ({"symlink": "tty1"}, "symlink", "the system's own devices"),
    ({"symlink": "sda"}, "symlink", "the system's own devices"),
    ({"symlink": "stdin"}, "symlink", "the system's own devices"),
    ({"identify_by": "serial"}, "serial", "needs serial"),
    ({"identify_by": "port"}, "port_path", "needs port_path"),
    ({"identify_by": "serial", "serial": 'A1", RUN+="x'}, "serial", "is not a value"),
    ({"identify_by": "serial", "serial": "${nope}"}, "serial", "not a setting of this profile"),
    ({"identify_by": "port", "port_path": "1-1*"}, "port_path", "is not a value"),
    ({"identify_by": "guess"}, "identify_by", "not one of"),
    ({"serial": "A1"}, "serial", "only with identify_by serial"),
    ({"kernel": "ttyUSB0"}, "kernel", "has no kernel"),
    ({"modemmanager": "probe"}, "modemmanager", "ignore"),
    ({"comment": "two\nlines"}, "comment", "line"),
    ({"name": "Bad Name"}, "name", "lower-case"),
    ({"run": "/bin/sh"}, "run", "unknown key"),
    ({"kind": "i2c", "usb_ids": None, "kernel": "i2c-*"}, "kernel", "not the kernel's name"),
    ({"kind": "uart", "usb_ids": None, "kernel": "tty1"}, "kernel", "not the kernel's name"),
    ({"kind": "uart", "usb_ids": None, "kernel": "console"}, "kernel", "not the kernel's name"),
    ({"kind": "gpio", "usb_ids": None, "kernel": "gpiomem"}, "kernel", "not the kernel's name"),
    ({"kind": "spi", "usb_ids": None, "kernel": "mem"}, "kernel", "not the kernel's name"),
]


@pytest.mark.parametrize("change, key, words", HOSTILE_DEVICES)
def test_a_hostile_device_field_is_refused(change, key, words, tmp_path, capsys, no_connections):
    device = {name: value for name, value in {**GOOD_DEVICE, **change}.items() if value is not None}
    part = f"devices: [{json.dumps(device)}]"
    errors = checked_errors(roster(tmp_path, part=part), capsys, no_connections)
    own = [line for line in errors if line.startswith(f"lab.yaml:{PART_LINE}: field 'profiles.mine.robot.devices[1]")]
    assert own and any(f"devices[1].{key}'" in line and words in line for line in own), errors


def test_a_good_device_passes_and_roslab_writes_its_rule(tmp_path):
    device = {**GOOD_DEVICE, "identify_by": "serial", "serial": "${serial}", "comment": "the lab's board"}
    text = template(part=f"devices: [{json.dumps(device)}]", host="\n        serial: A1B2").replace(
        "    robot:\n", "    settings: {serial: {pattern: '[A-Z0-9]+'}}\n    robot:\n")
    (tmp_path / "lab.yaml").write_text(text)
    written = load_roster(tmp_path / "lab.yaml").hosts[0].data["roslab_profile"]["udev_rules"]
    assert ('SUBSYSTEM=="tty", ATTRS{idVendor}=="0483", ATTRS{idProduct}=="5740", ATTRS{serial}=="A1B2", '
            'ENV{ID_MM_DEVICE_IGNORE}="1", ENV{ROSLAB_DEVICE}="board", GROUP="dialout", MODE="0660", '
            'SYMLINK+="lab_board"') in written.splitlines()
    assert "# board (usb_serial): the lab's board" in written


def test_the_built_in_profiles_declare_devices_only():
    profiles = library.builtin_profiles()
    devices = [device for profile in profiles.values() for side in profile.sides.values()
               for part in [side, *(block["side"] for block in side.when)] for device in part.devices]
    assert len(devices) >= 10
    assert {"demo", "turtlebot3", "turtlebot4", "sim", "osr", "esp32_microros"} <= set(profiles)


# --- a setting's pattern runs in bounded time -----------------------------------------------------

def test_a_nested_quantifier_cannot_hang_the_check(tmp_path, capsys, no_connections):
    text = template(part="launch: roslab_bringup robot.launch.py", host="\n        arm: " + "a" * 41 + "-").replace(
        "    robot:\n", "    settings: {arm: {pattern: '(a+)+'}}\n    robot:\n")
    (tmp_path / "lab.yaml").write_text(text)
    errors = checked_errors(tmp_path / "lab.yaml", capsys, no_connections)
    one_error(errors, f"lab.yaml:{HOST_LINE + 1}: {HOST}, field 'arm': ", "is not a value of arm (see its doc in the profile)")
    assert "(a+)+" not in "\n".join(errors)
    (tmp_path / "lab.yaml").write_text(text.replace("a" * 41 + "-", "a" * 41))
    assert load_roster(tmp_path / "lab.yaml").hosts[0].data["roslab_profile"]["settings"] == {"arm": "a" * 41}


@pytest.mark.parametrize("pattern, words", [
    ("(a)\\1", "backreferences"), ("(?=a)a", "lookaround"), ("a{1001}", "not a regular expression"),
    ("[", "not a regular expression"), ("x" * 501, "at most 500"),
])
def test_a_pattern_roslab_cannot_run_in_linear_time_is_refused_at_load(pattern, words, tmp_path, capsys,
                                                                          no_connections):
    text = template(part="launch: roslab_bringup robot.launch.py", host="").replace(
        "    robot:\n", f"    settings: {{arm: {{pattern: {json.dumps(pattern)}}}}}\n    robot:\n")
    (tmp_path / "lab.yaml").write_text(text)
    errors = checked_errors(tmp_path / "lab.yaml", capsys, no_connections)
    one_error(errors, "lab.yaml:6: field 'profiles.mine.settings.arm.pattern': ", words)


# --- --data blamed on itself; extends loops; .repos that are not regular files ----------------------

def inventory_refused(tmp_path: Path, monkeypatch, capsys, argv: list[str], text: str | None = None) -> str:
    path = tmp_path / "lab.yaml"
    path.write_text(text or template(part="launch: roslab_bringup robot.launch.py", host=""))
    monkeypatch.setenv("ROSLAB_ROSTER", str(path))
    monkeypatch.setattr(sys, "argv", ["pyinfra", "inventories/lab.py", "deploy.py", *argv])
    with pytest.raises(SystemExit) as exited:
        runpy.run_path(str(LAB_INVENTORY))
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "no host was touched" in err and "Traceback" not in err
    return err


@pytest.mark.parametrize("value", ["LDS-99", "x" * 200, "a b"])
def test_a_hostile_profile_setting_from_data_is_blamed_on_data(value, tmp_path, monkeypatch, capsys, no_connections):
    text = ("classroom:\n  ssh_user: ubuntu\nteams:\n  team1:\n    robot_profile: turtlebot3\n"
            "    turtlebot3_model: burger\n    lds_model: LDS-02\n    hosts:\n"
            "      team1-robot:\n        role: robot\n")
    err = inventory_refused(tmp_path, monkeypatch, capsys, ["--data", f"lds_model={value}"], text)
    lines = [line for line in err.splitlines() if "lds_model" in line and "roslab" not in line[:6]]
    assert lines and all(line.startswith("pyinfra's command line: team 'team1', host 'team1-robot', "
                                         f"field 'lds_model': --data lds_model={value}: ") for line in lines), err
    assert "lab.yaml:" not in err
    assert no_connections == []


def test_an_extends_loop_is_named_as_a_loop(tmp_path, capsys, no_connections):
    text = ("classroom:\n  ssh_user: ubuntu\nprofiles:\n  first:\n    extends: second\n  second:\n"
            "    extends: third\n  third:\n    extends: first\nteams:\n  team1:\n    hosts:\n"
            "      team1-robot: {role: robot, robot_profile: first}\n")
    (tmp_path / "lab.yaml").write_text(text)
    errors = checked_errors(tmp_path / "lab.yaml", capsys, no_connections)
    loop = one_error(errors, "lab.yaml:9: field 'profiles.third.extends': ",
                     "a loop (first -> second -> third -> first)")
    assert "not a profile" not in loop


def test_a_profile_extending_itself_or_a_later_one(tmp_path, capsys, no_connections):
    later = ("classroom:\n  ssh_user: ubuntu\nprofiles:\n  first:\n    extends: second\n  second:\n"
             "    extends: demo\n    robot: {environment: {LAB_NAME: x}}\nteams:\n  team1:\n    hosts:\n"
             "      team1-robot: {role: robot, robot_profile: first}\n")
    (tmp_path / "lab.yaml").write_text(later)
    host = load_roster(tmp_path / "lab.yaml").hosts[0]
    assert host.data["roslab_profile"]["environment"] == {"LAB_NAME": "x"}
    (tmp_path / "lab.yaml").write_text(later.replace("extends: demo", "extends: second"))
    errors = checked_errors(tmp_path / "lab.yaml", capsys, no_connections)
    assert any("a loop" in line for line in errors), errors


def test_a_built_in_profiles_extends_works_or_is_refused_clearly(tmp_path, monkeypatch):
    source = Path(library.__file__).parent / "data" / "demo.yaml"
    (tmp_path / "base.yaml").write_text(source.read_text().replace("profile: demo", "profile: base"))
    (tmp_path / "child.yaml").write_text("profile: child\nextends: base\nrobot: {environment: {LAB_NAME: x}}\n")
    monkeypatch.setattr(library, "data_folder", lambda: tmp_path)
    library._builtin.cache_clear()
    try:
        child = library.builtin_profiles()["child"]
        assert child.sides["robot"].environment == {"LAB_NAME": "x"} and child.sides["robot"].launch
        # a bad file is left out and listed (file:line), never raised: the others still work
        (tmp_path / "child.yaml").write_text("profile: child\nextends: nowhere\n")
        library._builtin.cache_clear()
        assert "child" not in library.builtin_profiles() and "base" in library.builtin_profiles()
        assert "field 'extends': extends 'nowhere', which is not a profile" in \
            "\n".join(str(problem) for problem in library.builtin_problems())
        (tmp_path / "child.yaml").write_text("profile: child\nextends: child\n")
        library._builtin.cache_clear()
        assert "a loop (child -> child)" in "\n".join(str(problem) for problem in library.builtin_problems())
    finally:
        library._builtin.cache_clear()


@pytest.mark.parametrize("kind, words", [("fifo", "is a FIFO (named pipe), not a regular file"),
                                         ("dir", "is a directory, not a regular file"),
                                         ("missing", "no such file")])
def test_a_repos_file_that_is_not_a_regular_file_says_so(kind, words, tmp_path, capsys, no_connections):
    target = tmp_path / "lab.repos"
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "dir":
        target.mkdir()
    path = roster(tmp_path, host="workspace_sources: [lab.repos]")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{HOST_LINE}: {HOST}, field 'workspace_sources': ", words)


# --- controller paths stay inside their purpose ----------------------------------------------------

REPOS = "repositories:\n  lab_driver:\n    type: git\n    url: {url}\n    version: v1.0.0\n"


def test_a_file_rewrite_outside_the_rosters_folder_is_refused(tmp_path, capsys, no_connections):
    elsewhere = tmp_path.parent / "elsewhere"
    path = roster(tmp_path, classroom=f"source_url_rewrites: {{'https://github.com/': 'file://{elsewhere}/'}}")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{CLASSROOM_LINE}: field 'source_url_rewrites': ", "leads outside the roster's folder")
    for bad in ("file:///etc/", f"file://{tmp_path}/../", f"file://{tmp_path}/.roslab-state/",
                f"file://otherhost{tmp_path}/"):
        path = roster(tmp_path, classroom=f"source_url_rewrites: {{'https://github.com/': '{bad}'}}")
        one_error(checked_errors(path, capsys, no_connections),
                  f"lab.yaml:{CLASSROOM_LINE}: field 'source_url_rewrites': ")


def test_a_rewritten_url_that_climbs_out_of_the_rosters_folder_is_refused(tmp_path, capsys, no_connections):
    (tmp_path / "mirror").mkdir()
    (tmp_path / "lab.repos").write_text(REPOS.format(url="https://github.com/lab/../../../../etc/driver.git"))
    path = roster(tmp_path, host="workspace_sources: [lab.repos]",
                  classroom=f"source_url_rewrites: {{'https://github.com/': 'file://{tmp_path}/mirror/'}}")
    errors = checked_errors(path, capsys, no_connections)
    one_error(errors, f"lab.yaml:{CLASSROOM_LINE}: {HOST}, field 'source_url_rewrites': ", "'lab_driver'",
              "without '..'")


def test_a_file_rewrite_into_the_rosters_folder_is_taken(tmp_path):
    (tmp_path / "mirror").mkdir()
    (tmp_path / "lab.repos").write_text(REPOS.format(url="https://github.com/lab/driver.git"))
    path = roster(tmp_path, host="workspace_sources: [lab.repos]",
                  classroom=f"source_url_rewrites: {{'https://github.com/': 'file://{tmp_path}/mirror/'}}")
    rewrites = load_roster(path).hosts[0].data["source_url_rewrites"]
    assert rewrites == {"https://github.com/": f"file://{tmp_path}/mirror/"}


@pytest.mark.parametrize("settings, line, field, words", [
    ("sources_cache_dir: cache\nrosdep_cache_dir: cache", 3, "sources_cache_dir", "share a folder"),
    ("sources_cache_dir: cache\npython_wheelhouse_dir: cache/wheels", 4, "python_wheelhouse_dir", "share a folder"),
    ("sources_cache_dir: nodes/cache\nworkspace_nodes_dir: nodes", 3, "sources_cache_dir", "copied to every Pi"),
    ("sources_cache_dir: cache\nclass_lock_debs_dir: cache/debs", 4, "class_lock_debs_dir", "share a folder"),
    ("class_lock_debs_dir: nodes/debs\nworkspace_nodes_dir: nodes", 3, "class_lock_debs_dir", "copied to every Pi"),
])
def test_caches_keep_to_folders_of_their_own(settings, line, field, words, tmp_path, capsys, no_connections):
    (tmp_path / "nodes" / "pkg").mkdir(parents=True)
    (tmp_path / "nodes" / "pkg" / "package.xml").write_text("<package/>\n")
    errors = checked_errors(roster(tmp_path, classroom=settings), capsys, no_connections)
    one_error(errors, f"lab.yaml:{line}: {HOST}, field '{field}': ", words)


def test_a_cache_that_holds_the_rosters_folder_is_refused(tmp_path, monkeypatch, capsys, no_connections):
    classroom = tmp_path / "class"
    classroom.mkdir()
    monkeypatch.chdir(classroom)
    errors = checked_errors(roster(classroom, classroom=f"sources_cache_dir: {tmp_path}"), capsys, no_connections)
    one_error(errors, f"lab.yaml:{CLASSROOM_LINE}: field 'sources_cache_dir': ", "holds the roster's folder")
