"""The robot profiles' devices against the robots' own upstream files (issue 36).

From the bundles of the robots' real repositories (ROSLAB_SANDBOX_SOURCES, else ../shared/sources
beside the clone; see its README), each test reads what the robot's software opens or what its
maker's udev rules give, and runs the rules roslab writes for the profile through real udev on
emulated devices (tests/udev_harness.py): a device name, mode or group that differs from
upstream, or a new pin that opens another device, fails here.

    TurtleBot3      turtlebot3_bringup/script/99-turtlebot3-cdc.rules and launch/robot.launch.py
                    (humble, jazzy, 2.3.6), coin_d4_driver's params/single_lidar_node.yaml,
                    hls_lfcd_lds_driver's hlds_laser.launch.py, ld08_driver's src/main.cpp
    TurtleBot 4     turtlebot4_setup's udev/*.rules, turtlebot4_robot's turtlebot4_base (the I2C bus
                    and GPIO chip it opens) and rplidar.launch.py (humble, jazzy)
    OSR             osr_bringup/config/roboclaw_params.yaml at the tag osr.repos pins
"""

from __future__ import annotations

import functools
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host
from tests import udev_harness as harness
from tests import upstream_bundles

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "roslab" / "profiles" / "data"
BUNDLES = ("turtlebot3", "coin_d4_driver", "ld08_driver", "hls_lfcd_lds_driver", "turtlebot4_setup",
           "turtlebot4_robot", "osr-rover-code")
# The emulated device of each USB id and kernel name an upstream rule names.
EMULATED_BY_ID = {"10c4:ea60": "cp2102_a", "0483:5740": "opencr", "0483:df11": "opencr_dfu", "03e7:*": "oakd"}
# USB ids upstream's rules name for boards no built-in profile drives: ROBOTIS's rules carry
# fff1:ff48, the older OpenCM 9.04 board's id, which a TurtleBot3 does not have.
NOT_A_PROFILES_DEVICE = ("fff1:ff48",)


def sources_folder() -> Path | None:
    return upstream_bundles.all_present(*BUNDLES)


@pytest.fixture(scope="module")
def upstream(tmp_path_factory):
    """show(bundle, ref, path): a file of a bundle at a ref, or None where it is absent."""
    folder = sources_folder()
    if folder is None:
        pytest.skip("the robots' upstream bundles are absent (set ROSLAB_SANDBOX_SOURCES, or put "
                    "../shared/sources beside the clone): nothing to compare the profiles with")
    why = harness.unavailable()
    if why:
        pytest.skip(why)
    clones = tmp_path_factory.mktemp("upstream")
    for name in BUNDLES:
        subprocess.run(["git", "clone", "-q", "--bare", str(folder / f"{name}.bundle"), str(clones / name)],
                       check=True, capture_output=True)

    def show(bundle: str, ref: str, path: str) -> str | None:
        result = subprocess.run(["git", "--git-dir", str(clones / bundle), "show", f"{ref}:{path}"],
                                capture_output=True, text=True)
        return result.stdout if result.returncode == 0 else None
    return show


def rules(profile: str, **given) -> str:
    data, problems = resolve_host(builtin_profiles()[profile], given, distro="jazzy", role="robot")
    assert not problems, problems
    return data["udev_rules"]


def upstream_rules(text: str) -> list[dict]:
    """Each rule of an upstream rules file as {id or kernel, symlink, mode, group}."""
    found = []
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        value = {key: (match.group(1) if match else None) for key, match in (
            ("vendor", re.search(r'ATTRS\{idVendor\}=="([0-9a-f]{4})"', line)),
            ("product", re.search(r'ATTRS\{idProduct\}=="([0-9a-f]{4})"', line)),
            ("kernel", re.search(r'KERNEL=="([^"]+)"', line)),
            ("symlink", re.search(r'SYMLINK\+?="([^"]+)"', line)),
            ("mode", re.search(r'MODE:?="([0-7]+)"', line)),
            ("group", re.search(r'GROUP:?="([^"]+)"', line)),
            ("modemmanager", re.search(r'ENV\{ID_MM_DEVICE_IGNORE\}="(1)"', line)))}
        if value["vendor"]:
            value["id"] = f"{value['vendor']}:{value['product'] or '*'}"
        found.append(value)
    return found


def check_against(outcome: harness.Outcome, expected: dict, where: str) -> None:
    assert outcome.roslab_device, f"{where}: roslab's rules give the device nothing"
    if expected["symlink"]:
        assert expected["symlink"] in outcome.links, (where, outcome.links)
    if expected["mode"]:
        assert outcome.mode == expected["mode"], (where, outcome.mode)
    if expected["modemmanager"]:
        assert outcome.properties.get("ID_MM_DEVICE_IGNORE") == "1", where


@pytest.mark.parametrize("ref", ["humble", "jazzy", "2.3.6"])
def test_turtlebot3_gives_each_device_what_robotis_rules_give(upstream, ref):
    text = upstream("turtlebot3", ref, "turtlebot3_bringup/script/99-turtlebot3-cdc.rules")
    assert text, f"turtlebot3 {ref} has no turtlebot3_bringup/script/99-turtlebot3-cdc.rules"
    expected = [rule for rule in upstream_rules(text) if rule.get("id") not in NOT_A_PROFILES_DEVICE]
    assert {rule.get("id") for rule in expected} == {"0483:5740", "0483:df11", "10c4:ea60"}
    for lds in ("LDS-01", "LDS-02", "LDS-03"):  # ROBOTIS's rule is for every CP2102, every model
        configuration = rules("turtlebot3", turtlebot3_model="burger", lds_model=lds)
        result = harness_result(configuration, [EMULATED_BY_ID[rule["id"]] for rule in expected])
        for rule in expected:
            check_against(result[EMULATED_BY_ID[rule["id"]]], rule, f"turtlebot3 {ref} {rule['id']} ({lds})")


@pytest.mark.parametrize("ref", ["humble", "jazzy"])
def test_every_lidar_driver_opens_a_name_the_turtlebot3_profile_gives(upstream, ref):
    coin = yaml.safe_load(upstream("coin_d4_driver", ref, "params/single_lidar_node.yaml"))
    port = next(iter(coin.values()))["ros__parameters"]["port"]  # LDS-03
    launch = upstream("turtlebot3", ref, "turtlebot3_bringup/launch/robot.launch.py")
    handed = re.findall(r"launch_arguments=\{'port': '(/dev/[^']+)'", launch)  # LDS-01's hlds_laser port
    ld08 = upstream("ld08_driver", ref, "src/main.cpp")
    hlds = upstream("hls_lfcd_lds_driver", ref, "launch/hlds_laser.launch.py")
    assert port == "/dev/tb3_lidar" and handed == ["/dev/ttyUSB0"], (port, handed)
    assert "'/dev/ttyUSB0'" in hlds and 'strstr(n.second.c_str(), "CP2102")' in ld08  # LDS-02: the first CP2102
    result = harness_result(rules("turtlebot3", turtlebot3_model="burger", lds_model="LDS-03"), ["cp2102_a"])
    cp2102 = result["cp2102_a"]
    assert port.removeprefix("/dev/") in cp2102.links
    assert cp2102.properties["DEVNAME"] == handed[0]  # the emulated adapter is the Pi's first ttyUSB
    assert cp2102.mode == "0666"


@pytest.mark.parametrize("ref", ["humble", "jazzy"])
def test_turtlebot4_gives_what_turtlebot4_setup_gives_for_the_devices_its_software_opens(upstream, ref):
    texts = {name: upstream("turtlebot4_setup", ref, f"udev/{name}")
             for name in ("50-turtlebot4.rules", "80-movidius.rules", "99-gpio.rules")}
    assert all(texts.values()), texts
    base = upstream("turtlebot4_robot", ref, "turtlebot4_base/src/turtlebot4.cpp")
    buses = re.findall(r"I2cInterface>\((\d+)\)", base)
    chips = re.findall(r"GpioInterface>\((\d+)\)", base)
    assert buses == ["3"] and chips == ["0"], (buses, chips)
    rplidar = upstream("turtlebot4_robot", ref, "turtlebot4_bringup/launch/rplidar.launch.py")
    assert "'serial_port': '/dev/RPLIDAR'" in rplidar
    expected = [*upstream_rules(texts["50-turtlebot4.rules"]), *upstream_rules(texts["80-movidius.rules"])]
    kernel_rules = {rule["kernel"]: rule for rule in upstream_rules(texts["99-gpio.rules"])}
    wanted = {EMULATED_BY_ID[rule["id"]]: rule for rule in expected}
    wanted[f"i2c-{buses[0]}"] = kernel_rules["i2c*"]
    wanted[f"gpiochip{chips[0]}"] = kernel_rules["gpiochip*"]
    for model in ("standard", "lite"):
        result = harness_result(rules("turtlebot4", turtlebot4_model=model), list(wanted))
        for name, rule in wanted.items():
            check_against(result[name], rule, f"turtlebot4_setup {ref} {name} ({model})")
            if rule["group"]:
                assert result[name].group == rule["group"], (name, result[name].group)
    assert "RPLIDAR" in harness_result(rules("turtlebot4", turtlebot4_model="lite"), ["cp2102_a"])["cp2102_a"].links


def test_osr_opens_the_uart_its_pinned_tag_opens_with_bluetooth_off_where_that_needs_it(upstream):
    pin = yaml.safe_load((DATA / "osr.repos").read_text())["repositories"]["osr-rover-code"]["version"]
    params = upstream("osr-rover-code", pin, "ROS/osr_bringup/config/roboclaw_params.yaml")
    assert params, f"osr-rover-code {pin} (osr.repos's pin) has no ROS/osr_bringup/config/roboclaw_params.yaml"
    device = re.search(r'device:\s*"(/dev/serial\d)"', params).group(1)
    data, problems = resolve_host(builtin_profiles()["osr"], {}, distro="jazzy", role="robot", board="pi4")
    assert not problems
    uart = {"/dev/serial0": "ttyS0", "/dev/serial1": "ttyAMA0"}[device]
    result = harness_result(data["udev_rules"], [uart])
    assert device.removeprefix("/dev/") in result[uart].links, (pin, device, result[uart].links)
    serial_info = upstream("osr-rover-code", pin, "setup/serial_config_info.md") or ""
    if device == "/dev/serial1":  # the PL011 is on GPIO 14/15 only with Bluetooth off
        assert "dtoverlay=disable-bt" in serial_info
        assert "dtoverlay=disable-bt" in data["boot_config"]["config_txt"]


def harness_result(configuration: str, names: list[str]) -> dict[str, harness.Outcome]:
    return _evaluated(configuration, tuple(dict.fromkeys(names)))


@functools.cache
def _evaluated(configuration: str, names: tuple[str, ...]) -> dict[str, harness.Outcome]:
    return harness.evaluate({"profile": configuration}, names)["profile"]
