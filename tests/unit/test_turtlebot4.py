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
from roslab.profiles.host import CMDLINE_TXT, CONFIG_TXT, cmdline_with
from roslab.profiles.schema import cmdline_add_problem, config_line_problem

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
    from test_robot_sources import bundles_dir

    folder = bundles_dir()
    if folder is None or not (folder / "turtlebot4_setup.bundle").is_file():
        pytest.skip("no turtlebot4_setup.bundle (set ROSLAB_SANDBOX_SOURCES, or ../shared/sources)")
    repo = tmp_path_factory.mktemp("tb4") / "turtlebot4_setup.git"
    subprocess.run(["git", "clone", "--quiet", "--bare", str(folder / "turtlebot4_setup.bundle"), str(repo)],
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
