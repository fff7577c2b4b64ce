"""The sandbox's RoboClaw STAND-IN (roslab/sandbox/roboclaw_board.py) driven by the REAL driver.

osr-rover-code's own osr_control/roboclaw.py (at the tag roslab/profiles/data/osr.repos pins,
from the bundle in ROSLAB_SANDBOX_SOURCES, else ../shared/sources beside the clone) talks to the
stand-in over a pty, as roboclaw_wrapper does on a rover: whatever the stand-in frames or checks
differently from the driver fails here. Skipped only when the bundle is absent.
"""

from __future__ import annotations

import importlib.util
import os
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from roslab.sandbox import roboclaw_board as board
from roslab.sandbox import rover_board
from tests import upstream_bundles

REPO = Path(__file__).resolve().parents[2]
TAG = yaml.safe_load((REPO / "roslab/profiles/data/osr.repos").read_text())["repositories"]["osr-rover-code"]["version"]
DRIVER = "ROS/osr_control/osr_control/roboclaw.py"
ADDRESSES = [128, 129, 130]  # osr_bringup/config/roboclaw_params.yaml at the tag


def bundle() -> Path | None:
    return upstream_bundles.bundle("osr-rover-code")


@pytest.fixture(scope="module")
def upstream(tmp_path_factory):
    """show(path): a file of osr-rover-code at TAG, from a clone of the bundle."""
    path = bundle()
    if path is None:
        pytest.skip("osr-rover-code.bundle is absent (set ROSLAB_SANDBOX_SOURCES, or put ../shared/sources "
                    "beside the clone): no real RoboClaw driver to drive the stand-in with")
    clone = tmp_path_factory.mktemp("osr") / "osr-rover-code"
    subprocess.run(["git", "clone", "--quiet", "--no-checkout", str(path), str(clone)], check=True, capture_output=True)
    return lambda name: subprocess.run(["git", "-C", str(clone), "show", f"{TAG}:{name}"], check=True,
                                       capture_output=True).stdout


@pytest.fixture(scope="module")
def roboclaw_module(upstream, tmp_path_factory):
    """The upstream driver module (its class Roboclaw), imported from the bundle's file."""
    driver = tmp_path_factory.mktemp("driver") / "roboclaw.py"
    driver.write_bytes(upstream(DRIVER))
    spec = importlib.util.spec_from_file_location("upstream_roboclaw", driver)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture()
def line(tmp_path):
    """The stand-in serving ADDRESSES on a pty linked at tmp/serial1, in a thread of this process."""
    link = tmp_path / "serial1"
    master, slave, name = board.open_line(str(link))
    bus = board.Bus(ADDRESSES)
    done = threading.Event()
    thread = threading.Thread(target=board.serve, args=(master, bus, done.is_set), daemon=True)
    thread.start()
    yield link, bus
    done.set()
    thread.join(timeout=2)
    os.close(slave)
    os.close(master)


def connect(roboclaw_module, link: Path):
    rc = roboclaw_module.Roboclaw(str(link), 115200)
    assert rc.Open() == 1
    rc._port.timeout = 0.2  # a refused packet costs 0.2 s here, not the driver's 1 s per try
    return rc


def test_the_board_serves_where_the_wrappers_params_look(upstream):
    params = yaml.safe_load(upstream("ROS/osr_bringup/config/roboclaw_params.yaml"))["roboclaw_wrapper"]
    assert params["ros__parameters"]["device"] == rover_board.PORT
    assert params["ros__parameters"]["addresses"] == list(rover_board.ADDRESSES) == ADDRESSES


def test_crc_is_the_drivers(roboclaw_module):
    driver = roboclaw_module.Roboclaw("/dev/null", 115200)
    driver.crc_clear()
    for byte in b"\x80\x26\x00\x00\x6a\x1c\x00\x00\x01\x00":
        driver.crc_update(byte)
    assert board.crc16(b"\x80\x26\x00\x00\x6a\x1c\x00\x00\x01\x00") == driver._crc & 0xFFFF


def test_the_wrappers_start_answers_for_each_address(roboclaw_module, line):
    link, _ = line
    rc = connect(roboclaw_module, link)
    for address in ADDRESSES:
        ok, version = rc.ReadVersion(address)
        assert ok == 1 and "STAND-IN" in version
        assert rc.ResetEncoders(address) and rc.ForwardM1(address, 0) and rc.ForwardM2(address, 0)
        assert rc.WriteNVM(address) and rc.ReadNVM(address)
        assert rc.ReadMainBatteryVoltage(address) == (1, board.BATTERY_DECIVOLTS)
        assert rc.ReadTemp(address) == (1, board.TEMPERATURE_DECIDEGREES)
        assert rc.ReadError(address) == (1, 0)
        assert rc.ReadCurrents(address) == (1, 0, 0)
        assert rc.ReadM1PositionPID(address)[0] == 1 and rc.ReadM2PositionPID(address)[0] == 1
    assert rc.ReadVersion(131) == (0, 0)  # no controller there: no answer


def test_encoders_move_after_a_speed_command(roboclaw_module, line):
    link, _ = line
    rc = connect(roboclaw_module, link)
    assert rc.ResetEncoders(129)
    assert rc.SpeedAccelM1(129, 0, 2000) and rc.DutyAccelM2(129, 26213, -16000)
    time.sleep(0.3)
    ok, counts, _status = rc.ReadEncM1(129)
    assert ok == 1 and 400 < counts < 1000
    speed = rc.ReadSpeedM1(129)
    assert speed[:2] == (1, 2000)
    ok, counts2, _status = rc.ReadEncM2(129)
    assert ok == 1 and counts2 < -100  # duty backwards, ramped
    assert rc.ReadSpeedM2(129)[1] < 0
    assert rc.DutyM1(129, 0) and rc.ReadSpeedM1(129)[:2] == (1, 0)
    assert rc.ReadEncM1(128)[:2] == (1, 0)  # the other controllers did not move


def test_a_bad_crc_gets_no_answer(roboclaw_module, line):
    link, _ = line
    rc = connect(roboclaw_module, link)
    packet = bytes([128, 38]) + struct.pack(">Ii", 0, 500)
    crc = board.crc16(packet)
    rc._port.write(packet + struct.pack(">H", crc ^ 0x0101))
    assert rc._port.read(1) == b""  # refused, as a RoboClaw does
    time.sleep(board.PACKET_GAP * 2)
    assert rc.ReadSpeedM1(128)[:2] == (1, 0)  # and not obeyed
    rc._port.write(packet + struct.pack(">H", crc))
    assert rc._port.read(1) == b"\xff"
    assert rc.ReadSpeedM1(128)[:2] == (1, 500)


def test_a_write_for_another_address_gets_no_answer(roboclaw_module, line):
    link, _ = line
    rc = connect(roboclaw_module, link)
    packet = bytes([131, 20])
    rc._port.write(packet + struct.pack(">H", board.crc16(packet)))
    assert rc._port.read(1) == b""


def test_runs_without_roslab(tmp_path):
    """The host runs the file alone (roslab is not installed on a robot): standard library only."""
    done = subprocess.run([sys.executable, "-I", "-c", f"import runpy; runpy.run_path({str(board.__file__)!r})"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
