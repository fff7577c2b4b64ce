"""The ESP32 demo's Pi side (nodes/roslab_esp32), tested without ROS: the arithmetic, the
topics the firmware uses, and the launch the esp32_microros profile runs."""

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "nodes" / "roslab_esp32"))

from roslab_esp32 import logic  # noqa: E402  (importable only once the path is set)


@pytest.mark.parametrize("raw, angle", [(0, 0), (4095, 180), (2048, 90), (2047, 90), (1, 0), (23, 1)])
def test_a_reading_becomes_an_angle_from_0_to_180(raw, angle):
    assert logic.servo_angle(raw) == angle


@pytest.mark.parametrize("raw, angle", [(-5, 0), (5000, 180), (2**31 - 1, 180)])
def test_a_reading_outside_the_adc_range_is_clamped(raw, angle):
    assert logic.servo_angle(raw) == angle


def test_the_angle_never_decreases_as_the_knob_turns():
    angles = [logic.servo_angle(raw) for raw in range(0, 4096)]
    assert angles == sorted(angles) and set(angles) == set(range(0, 181))


def test_the_firmware_uses_the_topics_the_node_uses():
    firmware = (REPO / "firmware" / "esp32_microros" / "src" / "main.cpp").read_text()
    assert '"esp32/potentiometer"' in firmware and '"esp32/servo_angle"' in firmware
    assert logic.POTENTIOMETER_TOPIC == "/esp32/potentiometer"
    assert logic.SERVO_ANGLE_TOPIC == "/esp32/servo_angle"


def test_the_profile_runs_the_launch_that_starts_the_node():
    from roslab.profiles.library import builtin_profiles

    launch = builtin_profiles()["esp32_microros"].sides["robot"].launch
    package, launch_file = launch.split()
    text = (REPO / "nodes" / package / "launch" / launch_file).read_text()
    assert "package='roslab_esp32', executable='servo_follower'" in text
    setup = (REPO / "nodes" / "roslab_esp32" / "setup.py").read_text()
    assert "'servo_follower = roslab_esp32.servo_follower:main'" in setup
