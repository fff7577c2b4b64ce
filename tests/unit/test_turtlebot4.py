"""TurtleBot 4: its boot config (config.txt overlays from an allow-list, cmdline.txt words a
profile adds), checked against turtlebot4_setup's boot/firmware files, and written as the other
boot config is (facts in, commands out)."""

from __future__ import annotations

import shlex
import subprocess

import pytest
from fixtures.fake_host import plan
from test_robots import BASE, UBUNTU_CMDLINE, boot_facts, problems_of, resolved  # noqa: F401

from deploy.robot_profile import robot_profile
from roslab.ops.boot_config import CMDLINE_TXT, CONFIG_TXT, cmdline_with
from roslab.profiles.schema import cmdline_add_problem, config_line_problem
from tests import upstream_bundles

USB0_OVERLAY = "dtoverlay=dwc2,dr_mode=peripheral"
I2C3_OVERLAY = "dtoverlay=i2c-gpio,bus=3,i2c_gpio_delay_us=1,i2c_gpio_sda=4,i2c_gpio_scl=5"
GADGET_MODULES = "modules-load=dwc2,g_ether"


# --- the allow-lists ---------------------------------------------------------------------------

@pytest.mark.parametrize("line", [USB0_OVERLAY, I2C3_OVERLAY, "dtparam=i2c_arm=on", "enable_uart=1", "[pi4]",
                                  "dtoverlay=disable-bt", "dtparam=i2c_arm=on,spi=on"])
def test_config_lines_a_robot_needs_are_accepted(line):
    assert config_line_problem(line) is None


@pytest.mark.parametrize("line, words", [
    ("kernel=evil.img", "config.txt key"),
    ("initramfs=evil", "config.txt key"),
    ("cmdline=other.txt", "config.txt key"),
    ("os_prefix=evil/", "not a config.txt line"),
    ("include=extra.txt", "config.txt key"),
    ("[board-serial]", "not a config.txt line"),
    ("[tryboot]", "section"),
    ("dtoverlay=../../evil", "not a config.txt line"),
    ("dtoverlay=sneaky-overlay", "the overlay 'sneaky-overlay'"),
    ("dtoverlay=dwc2,dr_mode=peri/pheral", "not a config.txt line"),
    ("dtoverlay=dwc2,Dr_Mode=host", "not a parameter"),
    ("dtparam=watchdog=on", "'watchdog' is not a parameter"),
    ("dtoverlay=dwc2,dr_mode=peripheral # usb0", "not a config.txt line"),
    ("enable_uart=1\ninitramfs evil", "not a config.txt line"),
])
def test_hostile_config_lines_are_refused(line, words):
    assert words in (config_line_problem(line) or ""), config_line_problem(line)


@pytest.mark.parametrize("word, words", [
    ("init=/bin/sh", "modules-load=<modules>"),
    ("root=/dev/sda1", "modules-load=<modules>"),
    ("console=ttyAMA0", "modules-load=<modules>"),
    ("modules-load=dwc2,evil", "(not 'evil')"),
    ("modules-load=", "kernel modules"),
    ("modules-load", "modules-load=<modules>"),
])
def test_hostile_cmdline_words_are_refused(word, words):
    assert words in (cmdline_add_problem(word) or ""), cmdline_add_problem(word)


def test_a_profile_with_a_hostile_boot_word_is_refused_naming_the_field():
    problems = problems_of({**BASE, "robot": {"boot_config": {"cmdline_add": ["init=/bin/sh"]}}})
    assert any("boot_config.cmdline_add" in problem and "init=/bin/sh" in problem for problem in problems), problems
    both = {"cmdline_add": [GADGET_MODULES], "cmdline_remove": [GADGET_MODULES]}
    problems = problems_of({**BASE, "robot": {"boot_config": both}})
    assert any("both added to and removed from" in problem for problem in problems), problems
    problems = problems_of({**BASE, "robot": {"boot_config": {"config_txt": ["kernel=x"]}}})
    assert any("boot_config.config_txt" in problem for problem in problems), problems


# --- the cmdline word ---------------------------------------------------------------------------

def test_a_word_is_added_once_and_the_line_keeps_its_other_words():
    added = cmdline_with(UBUNTU_CMDLINE, [GADGET_MODULES], [])
    assert added == UBUNTU_CMDLINE + " " + GADGET_MODULES
    assert cmdline_with(added, [GADGET_MODULES], []) == added
    assert cmdline_with("quiet  modules-load=dwc2,g_ether\n", [GADGET_MODULES], []) == "quiet " + GADGET_MODULES
    assert cmdline_with("a b", ["c"], ["a"]) == "b c"


# --- the profile against turtlebot4_setup's boot files -----------------------------------------

@pytest.mark.parametrize("model", ["standard", "lite"])
@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_both_models_get_usb0_and_i2c3_at_boot(model, distro):
    robot = resolved("turtlebot4", distro=distro, board="pi4", turtlebot4_model=model)
    assert robot["boot_config"] == {"config_txt": [USB0_OVERLAY, I2C3_OVERLAY], "cmdline_add": [GADGET_MODULES]}


@pytest.fixture(scope="module")
def setup_repo(tmp_path_factory):
    """turtlebot4_setup from its bundle (ROSLAB_SANDBOX_SOURCES or ../shared/sources), bare."""
    bundle = upstream_bundles.bundle("turtlebot4_setup")
    if bundle is None:
        pytest.skip("no turtlebot4_setup.bundle (set ROSLAB_SANDBOX_SOURCES, or ../shared/sources)")
    repo = tmp_path_factory.mktemp("tb4") / "turtlebot4_setup.git"
    subprocess.run(["git", "clone", "--quiet", "--bare", str(bundle), str(repo)],
                   check=True, capture_output=True)
    return repo


def upstream(repo, branch: str, path: str) -> str:
    return subprocess.run(["git", "show", f"{branch}:{path}"], cwd=repo, capture_output=True, text=True,
                          check=True).stdout


@pytest.mark.parametrize("branch", ["humble", "jazzy"])
def test_the_boot_config_is_turtlebot4_setups_own(setup_repo, branch):
    """Each config.txt line and cmdline word the profile writes is in turtlebot4_setup's
    boot/firmware files of the distro's branch."""
    boot = resolved("turtlebot4", distro=branch, board="pi4", turtlebot4_model="standard")["boot_config"]
    config_lines = upstream(setup_repo, branch, "boot/firmware/config.txt").splitlines()
    cmdline_words = upstream(setup_repo, branch, "boot/firmware/cmdline.txt").split()
    assert set(boot["config_txt"]) <= set(config_lines)
    assert set(boot["cmdline_add"]) <= set(cmdline_words)


# --- written on a Pi ----------------------------------------------------------------------------

def tb4_plan(facts, distro="jazzy"):
    profile = resolved("turtlebot4", distro=distro, board="pi4", turtlebot4_model="standard")
    profile.update(udev_rules="", groups=[])  # this test is about the boot config
    return plan(robot_profile, facts, data={"roslab_profile": profile, "robot_profile_enabled": True})


def test_a_pi_gets_the_overlays_the_gadget_modules_and_a_reboot_recorded():
    result = tb4_plan(boot_facts())
    block = result.uploads()[CONFIG_TXT]
    assert (f"# BEGIN roslab managed block (robot profile boot config)\n[all]\n{USB0_OVERLAY}\n{I2C3_OVERLAY}\n"
            "# END roslab managed block (robot profile boot config)\n") in block
    changes = result.changing()
    (cmdline,) = [commands for name, commands in changes.items() if CMDLINE_TXT in name]
    assert cmdline[0].startswith(f"cp -p -- {CMDLINE_TXT} {CMDLINE_TXT}.roslab-")
    written = shlex.split(cmdline[0].split("printf")[1])[1]
    assert written == UBUNTU_CMDLINE + " " + GADGET_MODULES
    (reboot,) = [commands for name, commands in changes.items() if "reboot" in name]
    assert "with modules-load=dwc2,g_ether" in reboot[0] and "i2c-gpio" in reboot[0]


def test_a_converged_turtlebot4_pi_changes_nothing():
    block = ["[all]", "# BEGIN roslab managed block (robot profile boot config)", "[all]", USB0_OVERLAY,
             I2C3_OVERLAY, "# END roslab managed block (robot profile boot config)"]
    result = tb4_plan(boot_facts(config=block, cmdline=UBUNTU_CMDLINE + " " + GADGET_MODULES))
    assert result.changing() == {}
    assert any(f"holds {GADGET_MODULES}" in noop for noop in result.noops)


# --- the Create 3 (profile base:, roslab/profiles/robot_base.py, deploy/robot_base.py) ------------------

from pyinfra.facts.deb import DebPackages  # noqa: E402
from pyinfra.facts.files import Directory, File, Sha1File  # noqa: E402
from pyinfra.facts.server import LinuxDistribution  # noqa: E402
from pyinfra.facts.systemd import SystemdStatus  # noqa: E402

from deploy.robot_base import CHRONY_DROP_IN, BaseAnswer, robot_base  # noqa: E402
from roslab.profiles.robot_base import (  # noqa: E402
    POSTED_RECORD,
    RobotBase,
    base_problems,
    chrony_text,
    create3_posts,
    create3_wanted,
    firmware_generation,
    firmware_problem,
    netplan_text,
    record_text,
)

TB4_BASE = RobotBase.from_data(resolved("turtlebot4", board="pi4", turtlebot4_model="lite")["base"])
TEAM = {"ROS_DOMAIN_ID": "7", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


def test_the_base_block_is_turtlebot4_setups_link():
    assert (TB4_BASE.interface, TB4_BASE.pi_address, TB4_BASE.base_address, TB4_BASE.ntp_allow) == (
        "usb0", "192.168.186.3/24", "192.168.186.2", "192.168.186.0/24")
    assert resolved("turtlebot4", role="main", board="pi4")["base"] is None


@pytest.mark.parametrize("change, key", [
    ({"kind": "roomba"}, "kind"),
    ({"interface": "eth0; reboot"}, "interface"),
    ({"pi_address": "192.168.186.3"}, "pi_address"),
    ({"pi_address": "8.8.8.8/24"}, "pi_address"),
    ({"base_address": "192.168.187.2"}, "base_address"),
    ({"base_address": "http://evil/"}, "base_address"),
    ({"ntp_allow": "0.0.0.0/0"}, "ntp_allow"),
    ({"firmware": {"jazzy": "I.*"}}, "firmware"),
    ({"namespace_suffix": {"jazzy": "/x y"}}, "namespace_suffix"),
    ({"url": "http://elsewhere"}, "url"),
])
def test_a_hostile_base_block_is_refused(change, key):
    base = {**resolved("turtlebot4", board="pi4", turtlebot4_model="lite")["base"], **change}
    assert key in dict(base_problems(base)), base_problems(base)
    problems = problems_of({**BASE, "base": base, "robot": {}})
    assert any(f"base.{key}" in problem for problem in problems), problems


def test_netplan_and_chrony_files():
    assert netplan_text(TB4_BASE).endswith(
        "network:\n  version: 2\n  ethernets:\n    usb0:\n      addresses: [192.168.186.3/24]\n"
        "      dhcp4: false\n      optional: true\n")
    assert chrony_text(TB4_BASE).splitlines()[-1] == "allow 192.168.186.0/24"


@pytest.mark.parametrize("distro, namespace, team_ns", [
    ("jazzy", "/_do_not_use", None), ("jazzy", "/team3/_do_not_use", "/team3"), ("humble", "", None),
    ("humble", "/team3", "/team3/")])
def test_the_posts_carry_the_teams_settings_per_distro(distro, namespace, team_ns):
    environment = {**TEAM, **({"ROBOT_NAMESPACE": team_ns} if team_ns else {})}
    wanted = create3_wanted(TB4_BASE, distro, environment)
    posts = create3_posts(wanted, None)
    from urllib.parse import parse_qs

    assert [path for path, _ in posts] == ["/ros-config-save-main", "/beta-ntp-conf-save", "/api/reboot"]
    assert parse_qs(posts[0][1]) == {"ros_domain_id": ["7"], "rmw_implementation": ["rmw_fastrtps_cpp"],
                                     **({"ros_namespace": [namespace]} if namespace else {})}
    assert parse_qs(posts[1][1]) == {"config": ["server 192.168.186.3 prefer iburst minpoll 4 maxpoll 6"]}


def test_only_what_differs_is_posted_and_a_zenoh_team_is_told():
    wanted = create3_wanted(TB4_BASE, "jazzy", TEAM)
    assert create3_posts(wanted, dict(wanted)) == []
    assert [path for path, _ in create3_posts(wanted, {**wanted, "ros_domain_id": "3"})] == [
        "/ros-config-save-main", "/api/reboot"]
    with pytest.raises(ValueError, match="not the team's rmw_zenoh_cpp"):
        create3_wanted(TB4_BASE, "jazzy", {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"})
    for hostile in ("team 3", "/team3&ros_domain_id=0", "/../x", "team3"):
        with pytest.raises(ValueError, match="not a ROS namespace"):
            create3_wanted(TB4_BASE, "jazzy", {**TEAM, "ROBOT_NAMESPACE": hostile})


def test_the_firmware_generation_is_checked_against_the_distro():
    assert firmware_generation('{"version": "I.0.0.FastDDS", "model": "Create 3"}') == "I.0.0.FastDDS"
    assert firmware_generation("no version here") is None
    assert firmware_problem("I.0.0.FastDDS", "jazzy", TB4_BASE) is None
    assert firmware_problem("H.2.6.CycloneDDS", "humble", TB4_BASE) is None
    assert firmware_problem("H.2.6.FastDDS", "jazzy", TB4_BASE) == (
        "Create 3 firmware H.2.6.FastDDS on a Jazzy class: update it to I.* (iRobot's Create 3 firmware page; "
        "turtlebot4_setup's scripts/create_update.sh)")


def base_facts(about="{\"version\": \"I.0.0.FastDDS\"}", posted=None, installed=True, converged=False):
    digests = {}
    if converged:
        digests = {"/etc/netplan/61-roslab-usb0.yaml": netplan_text(TB4_BASE), CHRONY_DROP_IN: chrony_text(TB4_BASE)}
    import hashlib

    return {
        BaseAnswer: lambda url, record: {"about": about, "posted": posted},
        SystemdStatus: {"chrony.service": True},
        LinuxDistribution: {"release_meta": {"ID": "ubuntu", "UBUNTU_CODENAME": "noble"}},
        DebPackages: {"chrony": ["4.5-1"]} if installed else {},
        File: lambda path: {"user": "root", "group": "root", "mode": 600 if "netplan" in path else 644}
        if path in digests else None,
        Directory: lambda path: {"mode": 755} if path in ("/etc/netplan", "/etc/chrony/conf.d") else None,
        Sha1File: lambda path: hashlib.sha1(digests[path].encode()).hexdigest() if path in digests else None,
    }


def base_plan(facts, distro="jazzy", environment=None):
    profile = resolved("turtlebot4", distro=distro, board="pi4", turtlebot4_model="standard")
    data = {"roslab_profile": profile, "robot_base_enabled": True, "ros_distro": distro, "ros_domain_id": 7,
            "ros_environment": environment or {}}
    return plan(robot_base, facts, data=data)


def test_a_fresh_pi_gets_usb0_chrony_and_the_create3_configured():
    result = base_plan(base_facts(installed=False))
    uploads = result.uploads()
    assert uploads["/etc/netplan/61-roslab-usb0.yaml"] == netplan_text(TB4_BASE)
    assert uploads[CHRONY_DROP_IN] == chrony_text(TB4_BASE)
    changes = result.changing()
    (now,) = [commands for name, commands in changes.items() if "holds 192.168.186.3/24 now" in name]
    assert "ip addr replace 192.168.186.3/24 dev usb0" in now[0]
    assert any("chrony" in name and "restart" in " ".join(commands) for name, commands in changes.items())
    (posts,) = [commands for name, commands in changes.items() if "posted, then it reboots" in name]
    command = posts[0]
    assert "http://192.168.186.2/ros-config-save-main" in command
    assert "ros_domain_id=7" in command and "ros_namespace=%2F_do_not_use" in command
    assert "http://192.168.186.2/beta-ntp-conf-save" in command and "http://192.168.186.2/api/reboot" in command
    assert command.index("/api/reboot") < command.index(POSTED_RECORD) and "umask 077" in command


def test_a_converged_robot_posts_nothing_and_says_why():
    wanted = create3_wanted(TB4_BASE, "jazzy", {"ROS_DOMAIN_ID": "7", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"})
    result = base_plan(base_facts(posted=wanted, converged=True))
    assert result.changing() == {}
    assert any("already has domain 7" in noop for noop in result.noops), result.noops
    assert record_text(wanted) == record_text(dict(reversed(list(wanted.items()))))


def test_a_silent_create3_is_one_line_and_the_rest_converges(caplog):
    result = base_plan(base_facts(about=None, converged=True))
    assert result.changing() == {}
    assert any("192.168.186.2 does not answer on usb0" in noop for noop in result.noops), result.noops
    # a warning of the run, which roslab's compact output shows (a no-op reason it does not)
    warned = [record.getMessage() for record in caplog.records if record.levelname == "WARNING"]
    assert len(warned) == 1 and "roslab: robot base: the create3 at 192.168.186.2 does not answer" in warned[0], warned


def test_a_humble_firmware_on_a_jazzy_class_is_said(caplog):
    wanted = create3_wanted(TB4_BASE, "jazzy", {"ROS_DOMAIN_ID": "7", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"})
    result = base_plan(base_facts(about='{"version": "H.2.6.FastDDS"}', posted=wanted, converged=True))
    assert any("Create 3 firmware H.2.6.FastDDS on a Jazzy class: update it to I.*" in n for n in result.noops)
    warned = [record.getMessage() for record in caplog.records if record.levelname == "WARNING"]
    assert len(warned) == 1 and "firmware H.2.6.FastDDS on a Jazzy class" in warned[0], warned


# --- the deploy's own commands against the Create 3 stand-in (roslab/sandbox/create3.py) ---------

@pytest.fixture
def create3(tmp_path):
    """The stand-in on loopback; the deploy's curl reaches it through http_proxy, as if it were
    192.168.186.2 (its request line carries the real URL)."""
    import os

    from roslab.sandbox.create3 import serve

    record = tmp_path / "posts.jsonl"
    server = serve("127.0.0.1", 0, "I.0.0.FastDDS", record)
    env = {**{k: v for k, v in os.environ.items() if k.lower() not in ("no_proxy", "all_proxy")},
           "http_proxy": f"http://127.0.0.1:{server.server_address[1]}"}
    yield record, env
    server.shutdown()


def test_the_deploys_requests_reach_a_create3_stand_in_and_a_second_run_posts_nothing(create3, tmp_path):
    from deploy.robot_base import base_settings_kept
    from roslab.sandbox.create3 import recorded_posts

    record, env = create3
    posted = tmp_path / "lib" / "create3-posted.json"
    fact = BaseAnswer()
    output = subprocess.run(["sh", "-c", fact.command(url="http://192.168.186.2", record=str(posted))],
                            env=env, capture_output=True, text=True, timeout=20).stdout.splitlines()
    answer = fact.process(output)
    assert firmware_generation(answer["about"]) == "I.0.0.FastDDS" and answer["posted"] is None
    wanted = create3_wanted(TB4_BASE, "jazzy", {**TEAM, "ROBOT_NAMESPACE": "/team3"})
    result = plan(lambda: base_settings_kept(name="create3", base=TB4_BASE.__dict__, distro="jazzy", wanted=wanted,
                                             record=str(posted)), {BaseAnswer: answer})
    (command,) = [line for op in result.operations for line in op.text()]
    subprocess.run(["sh", "-c", command], env=env, check=True, timeout=30)
    assert recorded_posts(record) == [
        {"path": "/ros-config-save-main", "form": {"ros_domain_id": "7", "ros_namespace": "/team3/_do_not_use",
                                                   "rmw_implementation": "rmw_fastrtps_cpp"}},
        {"path": "/beta-ntp-conf-save", "form": {"config": "server 192.168.186.3 prefer iburst minpoll 4 maxpoll 6"}},
        {"path": "/api/reboot", "form": {}},
    ]
    assert oct(posted.stat().st_mode & 0o777) == "0o600"
    output = subprocess.run(["sh", "-c", fact.command(url="http://192.168.186.2", record=str(posted))],
                            env=env, capture_output=True, text=True, timeout=20).stdout.splitlines()
    again = plan(lambda: base_settings_kept(name="create3", base=TB4_BASE.__dict__, distro="jazzy", wanted=wanted,
                                            record=str(posted)), {BaseAnswer: fact.process(output)})
    assert again.changing() == {} and len(recorded_posts(record)) == 3


# --- roslab status ------------------------------------------------------------------------------

@pytest.mark.parametrize("answer, distro, note", [
    (['{"version": "I.0.0.FastDDS"}'], "jazzy", "create3 firmware I.0.0.FastDDS"),
    (['{"version": "H.2.6.FastDDS"}'], "jazzy", "Create 3 firmware H.2.6.FastDDS on a Jazzy class: update it to I.*"),
    (["#no-answer"], "jazzy", "create3 at 192.168.186.2: no answer"),
])
def test_status_shows_the_create3_firmware(answer, distro, note):
    from roslab.cli.status import HostStatus, base_note, parse_probe, probe_script

    assert "curl -fsS -m 3 http://192.168.186.2/api/about" in probe_script(base_url="http://192.168.186.2")
    assert "## base" not in probe_script()
    probe = parse_probe(["## base", *answer, "## end"])
    status = HostStatus(name="t1-robot", team="t1", role="robot", address="10.0.0.2", expected_distro=distro,
                        reachable=True, probe=probe, base=TB4_BASE.__dict__)
    assert base_note(status).startswith(note)
    assert parse_probe(["## end"])["base"] is None


# --- the sandbox's Create 3 link (roslab/sandbox/create3_link.py): names and values, no boots -----

def test_the_sandbox_create3_link_names_fit_the_kernel_and_go_with_the_sandbox():
    from roslab.sandbox import create3_link
    from roslab.sandbox.instance import Instance, SandboxHost
    import ipaddress

    instance = Instance("a-very-long-sandbox-name-for-a-class", ipaddress.IPv4Network("10.213.181.0/24"))
    host = SandboxHost(name="team12-robot", team="team12", role="robot", release="24.04", index=23,
                       address="10.213.181.34")
    assert len(create3_link.veth(instance, host)) <= 15  # IFNAMSIZ - 1
    assert create3_link.netns(instance, host).startswith(instance.netns_prefix)  # `down` deletes it
    pid_file, record = create3_link.files(instance, host)
    assert pid_file.parent == record.parent == instance.state_dir / "create3"


@pytest.mark.parametrize("firmware", ["I.0.0.FastDDS", "H.2.6", "G.5.3.CycloneDDS"])
def test_a_create3_firmware_version_is_taken(firmware):
    from roslab.sandbox.create3_link import FIRMWARE

    assert FIRMWARE.fullmatch(firmware)


@pytest.mark.parametrize("firmware", ["", "I", "i.0.0", "I.0.0.Fast DDS", "I.0.0;reboot", "I.0.0.FastDDS\n"])
def test_a_create3_firmware_that_is_no_version_is_refused(firmware):
    from roslab.sandbox.create3_link import FIRMWARE, plug
    from roslab.sandbox.instance import Instance, SandboxHost
    from roslab.sandbox.system import SandboxError
    import ipaddress

    assert not FIRMWARE.fullmatch(firmware)
    instance = Instance("unit", ipaddress.IPv4Network("10.213.181.0/24"))
    host = SandboxHost(name="team1-robot", team="team1", role="robot", release="24.04", index=1, address="10.213.181.12")
    with pytest.raises(SandboxError, match="firmware version"):
        plug(instance, host, firmware)
