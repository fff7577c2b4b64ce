"""The udev rules roslab writes for each built-in profile's devices, run by real udev on
emulated devices (tests/udev_harness.py: Debian's `udevadm test` under umockdev, in a private
mount namespace): every symlink, mode and group the robot's software needs exists, for every
model, lidar and transport setting; two CP2102s on one host each get their own name; and no
device a profile did not declare (a keyboard, the console, a virtual terminal, a USB disk, a
webcam, another board) is matched by any of them."""

from __future__ import annotations

import functools
import os

import pytest

from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host
from tests import udev_harness as harness

USB_SERIALS = ("cp2102_a", "cp2102_b", "cp2102_no_serial", "ch340", "ch9102", "opencr")


@pytest.fixture(autouse=True, scope="module")
def _udev_here():
    why = harness.unavailable()
    if why and os.environ.get("CI"):
        pytest.fail(f"CI has the udev harness's tools (make setup): {why}")
    if why:
        pytest.skip(why)


def rules(profile: str, role: str = "robot", **given) -> str:
    data, problems = resolve_host(builtin_profiles()[profile], given, distro="jazzy", role=role)
    assert not problems, problems
    return data["udev_rules"]


@functools.cache
def _evaluated(configurations: tuple[tuple[str, str], ...], names: tuple[str, ...]):
    return harness.evaluate(dict(configurations), names)


def evaluate(configurations: dict[str, str], names: tuple[str, ...]) -> dict[str, dict[str, harness.Outcome]]:
    return _evaluated(tuple(configurations.items()), names)


def assert_device(outcome: harness.Outcome, device: str, link: str | None, mode: str, group: str) -> None:
    assert outcome.roslab_device == device, outcome.output[-1500:]
    assert (link in outcome.links) if link else not outcome.links, outcome.links
    assert (outcome.mode, outcome.group) == (mode, group), outcome.output[-1500:]


def assert_untouched(outcome: harness.Outcome) -> None:
    assert not outcome.matched_by_roslab, outcome.roslab_lines


def test_turtlebot3_every_lds_model_gets_tb3_lidar_and_the_opencr_its_mode():
    configurations = {f"{lds} {serial}": rules("turtlebot3", turtlebot3_model="waffle_pi", lds_model=lds,
                                               **({"lds_usb_serial": serial} if serial else {}))
                      for lds in ("LDS-01", "LDS-02", "LDS-03") for serial in (None, "0001")}
    assert len(set(configurations.values())) == 2  # the LDS model changes the driver, not the device
    results = evaluate({key: configurations[key] for key in ("LDS-03 None", "LDS-03 0001")},
                       ("cp2102_a", "cp2102_b", "cp2102_no_serial", "ch340", "opencr", "opencr_dfu", "oakd"))
    for key, result in results.items():
        assert_device(result["opencr"], "opencr", None, "0666", "dialout")
        assert_device(result["opencr_dfu"], "opencr_dfu", None, "0666", "plugdev")
        assert_device(result["cp2102_a"], "lidar", "tb3_lidar", "0666", "dialout")
        assert_untouched(result["ch340"])
        assert_untouched(result["oakd"])
    anyone = results["LDS-03 None"]
    assert_device(anyone["cp2102_no_serial"], "lidar", "tb3_lidar", "0666", "dialout")
    by_serial = results["LDS-03 0001"]  # lds_usb_serial picks one CP2102 when two share the Pi
    assert_untouched(by_serial["cp2102_b"])
    assert_untouched(by_serial["cp2102_no_serial"])


def test_turtlebot4_rplidar_oakd_display_bus_and_gpio_chip():
    configurations = {f"{model} {serial}": rules("turtlebot4", turtlebot4_model=model,
                                                 **({"rplidar_usb_serial": serial} if serial else {}))
                      for model in ("standard", "lite") for serial in (None, "0002")}
    assert len(set(configurations.values())) == 2
    results = evaluate({key: configurations[key] for key in ("standard None", "standard 0002")},
                       ("cp2102_a", "cp2102_b", "oakd", "i2c-1", "i2c-3", "gpiochip0", "opencr"))
    for result in results.values():
        assert_device(result["cp2102_b"], "rplidar", "RPLIDAR", "0666", "dialout")
        assert_device(result["oakd"], "oakd", None, "0666", "plugdev")
        assert_device(result["i2c-3"], "display_i2c", None, "0666", "dialout")
        assert_device(result["gpiochip0"], "gpiochip", None, "0666", "dialout")
        assert_untouched(result["i2c-1"])
        assert_untouched(result["opencr"])
    assert_device(results["standard None"]["cp2102_a"], "rplidar", "RPLIDAR", "0666", "dialout")
    assert_untouched(results["standard 0002"]["cp2102_a"])


def test_osr_roboclaws_on_serial1_and_the_servo_bus():
    result = evaluate({"osr": rules("osr")}, ("ttyAMA0", "ttyS0", "i2c-1", "i2c-3", "cp2102_a"))["osr"]
    assert_device(result["ttyAMA0"], "roboclaw_uart", "serial1", "0660", "dialout")
    assert_device(result["ttyS0"], "mini_uart", "serial0", "0660", "dialout")
    assert_device(result["i2c-1"], "servo_i2c", None, "0666", "i2c")
    assert_untouched(result["i2c-3"])
    assert_untouched(result["cp2102_a"])


@pytest.mark.parametrize("role", ["robot", "main"])
def test_esp32_board_by_chip_serial_port_or_alone_and_none_on_udp(role):
    where = {"esp32_attached_to": role}
    configurations = {
        "only": rules("esp32_microros", role, **where),
        "port": rules("esp32_microros", role, **where, esp32_usb_port="1-1.4"),  # the CH340's port
        "serial": rules("esp32_microros", role, **where, esp32_usb_serial="54D2012345"),  # the CH9102's
    }
    assert rules("esp32_microros", role, **where, esp32_transport="udp") == ""
    results = evaluate(configurations, USB_SERIALS)
    for chip in ("cp2102_a", "cp2102_no_serial", "ch340", "ch9102"):
        assert_device(results["only"][chip], "esp32", "esp32", "0660", "dialout")
    assert_device(results["port"]["ch340"], "esp32", "esp32", "0660", "dialout")
    assert_device(results["serial"]["ch9102"], "esp32", "esp32", "0660", "dialout")
    for key, chip in [("port", name) for name in USB_SERIALS if name != "ch340"] + \
                     [("serial", name) for name in USB_SERIALS if name != "ch9102"]:
        assert_untouched(results[key][chip])
    assert_untouched(results["only"]["opencr"])


def test_a_turtlebot3_and_esp32_robot_with_two_cp2102s_gets_each_on_its_own_name():
    team = (rules("turtlebot3", turtlebot3_model="burger", lds_model="LDS-03", lds_usb_serial="0001")
            + rules("esp32_microros", esp32_usb_serial="0002"))
    result = evaluate({"team": team}, ("cp2102_a", "cp2102_b", "cp2102_no_serial", "opencr"))["team"]
    assert_device(result["cp2102_a"], "lidar", "tb3_lidar", "0666", "dialout")
    assert "esp32" not in result["cp2102_a"].links
    assert_device(result["cp2102_b"], "esp32", "esp32", "0660", "dialout")
    assert "tb3_lidar" not in result["cp2102_b"].links
    assert_untouched(result["cp2102_no_serial"])
    assert_device(result["opencr"], "opencr", None, "0666", "dialout")


def every_built_in_rules_file() -> str:
    """Every rules file a built-in profile writes, for every side and setting value, joined: a
    rule only adds matches, so a device none of these match is matched by none of them."""
    texts = set()
    for profile in builtin_profiles().values():
        required = {name: setting.allowed[0] for name, setting in profile.settings.items() if setting.required}
        options = {name: [value for value in (setting.allowed or ("0001", "1-1.2")) if setting.problem(value) is None]
                   for name, setting in profile.settings.items()}
        combos = [required] + [{**required, name: value} for name, values in options.items() for value in values]
        for role in profile.sides:
            for given in combos:
                data, problems = resolve_host(profile, given, distro="jazzy", role=role)
                assert not problems, (profile.name, given, problems)
                texts.add(data["udev_rules"])
    return "".join(sorted(texts))


def test_no_built_in_profile_matches_a_device_it_did_not_declare():
    union = every_built_in_rules_file()
    assert union.count("ROSLAB_DEVICE") >= 15
    result = evaluate({"all": union}, harness.UNDECLARED)["all"]
    assert set(result) == {"keyboard", "console", "tty1", "i2c-0", "sda", "webcam"}
    for name, outcome in result.items():
        assert_untouched(outcome)
    # The harness sees udev's own rules act on them: a test that could not tell is no test.
    assert (result["keyboard"].group, result["sda"].group, result["webcam"].group) == ("input", "disk", "video")
