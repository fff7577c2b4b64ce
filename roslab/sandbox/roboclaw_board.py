"""A STAND-IN for the RoboClaw motor controllers of robot profile osr (the JPL Open Source Rover).

No RoboClaw exists in the sandbox. This program serves Basicmicro's packet serial protocol on a
pseudo-terminal, linked to the path the rover's code opens (/dev/serial1: osr-rover-code
v4.1.0's ROS/osr_bringup/config/roboclaw_params.yaml, the PL011 the osr profile's udev rule
names), for the addresses it is given (128, 129, 130 there), so that the REAL roboclaw_wrapper
node (ROS/osr_control/osr_control/roboclaw_wrapper.py, through its driver roboclaw.py) finds its
controllers and publishes /drive_state and /status as on a rover.

It answers exactly the commands roboclaw_wrapper v4.1.0 sends, framed and checked as roboclaw.py
does it (CRC16-CCITT, polynomial 0x1021, from 0, over address, command and data):
  reads (the host sends address and command; the answer carries the CRC): ReadVersion (21),
  ReadEncM1/M2 (16/17), ReadSpeedM1/M2 (18/19), ReadMainBatteryVoltage (24), ReadCurrents (49),
  ReadM1/M2PositionPID (63/64), ReadTemp (82), ReadError (90);
  writes (the host appends the CRC; the answer is 0xFF): ForwardM1/M2 (0/4, its stop_motors),
  ResetEncoders (20), DutyM1/M2 (32/33), SpeedAccelM1/M2 (38/39), DutyAccelM1/M2 (52/53),
  WriteNVM (94, with Basicmicro's key), ReadNVM (95).
A write with a wrong CRC, a packet for an address it does not serve and a command it does not
know get no answer, as on a real RoboClaw (the driver then times out and retries). A gap of more
than 50 ms between bytes drops a partial packet (the driver's retry starts a new one).

The motors are a simple model, not a RoboClaw: a speed command ramps each motor's speed (in
encoder counts per second) toward its target at the given acceleration; a duty command drives at
duty/32767 of TOP_QPPS; the encoders count what the speed covers over time. Battery, temperature
and error are constants; the currents grow with speed.

Pure Python standard library: it runs inside a sandbox host (`roslab sandbox board TEAM start`
copies this file there; roslab is not installed on a robot), as root, for `/dev/serial1`.
Usage: python3 roboclaw_board.py --link /dev/serial1 --address 128 --address 129 --address 130
"""

from __future__ import annotations

import argparse
import grp
import os
import select
import signal
import struct
import sys
import time
import tty

TOP_QPPS = 4096  # encoder counts/s at full duty (32767): the wrapper's duty = qpps * 8 maps back near its command
VERSION = "RoboClaw STAND-IN (roslab sandbox) v4.1.0\n"
NVM_KEY = 0xE22EAB7A  # roboclaw.py's WriteNVM sends it; a RoboClaw saves only with it
BATTERY_DECIVOLTS = 148  # a 4-cell LiPo, the rover's battery
TEMPERATURE_DECIDEGREES = 300
PACKET_GAP = 0.05
SERVING = "roboclaw stand-in: serving"


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC16 as roboclaw.py's crc_update computes it (CCITT polynomial 0x1021, from 0)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        crc &= 0xFFFF
    return crc


class Motor:
    """One channel (M1 or M2): speed ramped toward a target, encoder integrated over time."""

    def __init__(self, now: float) -> None:
        self.encoder = 0.0
        self.speed = 0.0
        self.target = 0.0
        self.accel = 0.0  # counts/s per s; 0: at once
        self.stamp = now

    def update(self, now: float) -> None:
        dt = max(0.0, now - self.stamp)
        self.stamp = now
        start = self.speed
        if self.accel > 0:
            step = self.accel * dt
            self.speed = min(self.target, start + step) if self.target > start else max(self.target, start - step)
        self.encoder += (start + self.speed) / 2 * dt

    def command(self, now: float, target: float, accel: float = 0.0) -> None:
        self.update(now)
        self.target, self.accel = target, accel
        if accel <= 0:
            self.speed = target  # at once

    def counts(self, now: float) -> int:
        self.update(now)
        return int(self.encoder)


def _signed(value: int, bits: int) -> int:
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


class Controller:
    """One RoboClaw (one address) with its two motors."""

    def __init__(self, now: float) -> None:
        self.motors = (Motor(now), Motor(now))

    # -- reads: the answer's data (the CRC is added by the bus) --
    def read(self, command: int, now: float) -> bytes:
        if command == 21:
            return VERSION.encode() + b"\0"
        if command in (16, 17):
            counts = self.motors[command - 16].counts(now)
            wrapped = counts & 0xFFFFFFFF
            return struct.pack(">IB", wrapped, 0x02 if self.motors[command - 16].speed < 0 else 0)
        if command in (18, 19):
            motor = self.motors[command - 18]
            motor.update(now)
            return struct.pack(">iB", int(motor.speed), 1 if motor.speed < 0 else 0)
        if command == 24:
            return struct.pack(">H", BATTERY_DECIVOLTS)
        if command == 49:  # two currents in 10 mA: 1 A at top speed
            m1, m2 = (int(abs(motor.speed) / TOP_QPPS * 100) for motor in self.motors)
            return struct.pack(">hh", m1, m2)
        if command in (63, 64):  # kp, ki, kd (x1024), kimax, deadzone, min, max: none set (velocity use)
            return struct.pack(">7I", 0, 0, 0, 0, 0, 0, 0)
        if command == 82:
            return struct.pack(">H", TEMPERATURE_DECIDEGREES)
        return struct.pack(">I", 0)  # 90: no error

    # -- writes: False refuses (no answer) --
    def write(self, command: int, data: bytes, now: float) -> bool:
        if command in (0, 4):  # ForwardM1/M2 0..127
            self.motors[command // 4].command(now, min(data[0], 127) / 127 * TOP_QPPS)
        elif command == 20:
            for motor in self.motors:
                motor.update(now)
                motor.encoder = 0.0
        elif command in (32, 33):
            self.motors[command - 32].command(now, _duty_qpps(struct.unpack(">h", data)[0]))
        elif command in (38, 39):
            accel, speed = struct.unpack(">Ii", data)
            self.motors[command - 38].command(now, float(speed), float(accel))
        elif command in (52, 53):
            duty, accel = struct.unpack(">hI", data)
            self.motors[command - 52].command(now, _duty_qpps(duty), _duty_qpps(accel))
        elif command == 94:
            return struct.unpack(">I", data)[0] == NVM_KEY
        return True


def _duty_qpps(duty: int) -> float:
    return duty / 32767 * TOP_QPPS


READS = frozenset({16, 17, 18, 19, 21, 24, 49, 63, 64, 82, 90})
WRITES = {0: 1, 4: 1, 20: 0, 32: 2, 33: 2, 38: 8, 39: 8, 52: 6, 53: 6, 94: 4, 95: 0}  # command: data bytes


class Bus:
    """The serial line with the RoboClaws on it: bytes in, answers out."""

    def __init__(self, addresses: list[int], now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self.controllers = {address: Controller(now) for address in addresses}
        self.pending = b""
        self.last = now

    def feed(self, data: bytes, now: float | None = None) -> bytes:
        """Take the bytes the host wrote; return what the RoboClaws answer."""
        now = time.monotonic() if now is None else now
        if now - self.last > PACKET_GAP:
            self.pending = b""  # a partial packet the host gave up on
        self.last = now
        self.pending += data
        answer = b""
        while len(self.pending) >= 2:
            used, reply = self._packet(self.pending, now)
            if used == 0:
                break  # wait for the rest
            self.pending = self.pending[used:]
            answer += reply
        return answer

    def _packet(self, pending: bytes, now: float) -> tuple[int, bytes]:
        """(bytes used, answer) for the packet at the start of `pending`; used 0: incomplete."""
        address, command = pending[0], pending[1]
        controller = self.controllers.get(address)
        if command in READS:
            if controller is None:
                return 2, b""  # another unit's: not ours to answer
            data = pending[:2] + controller.read(command, now)
            return 2, data[2:] + struct.pack(">H", crc16(data))
        if command not in WRITES:
            return len(pending), b""  # unknown: drop what came
        size = 2 + WRITES[command] + 2
        if len(pending) < size:
            return 0, b""
        packet = pending[:size]
        if controller is None or crc16(packet[:-2]) != struct.unpack(">H", packet[-2:])[0]:
            return size, b""
        return size, (b"\xff" if controller.write(command, packet[2:-2], now) else b"")


def open_line(link: str) -> tuple[int, int, str]:
    """A raw pty for the RoboClaws: (master, slave, slave's name), `link` pointing at the slave,
    dialout's and 0660 as the osr profile's udev rule makes /dev/serial1."""
    master, slave = os.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    try:
        os.chown(name, -1, grp.getgrnam("dialout").gr_gid)
    except KeyError:
        pass
    os.chmod(name, 0o660)
    temporary = f"{link}.roboclaw-standin"
    if os.path.lexists(temporary):
        os.unlink(temporary)
    os.symlink(name, temporary)
    os.replace(temporary, link)
    return master, slave, name


def serve(master: int, bus: Bus, stopped=lambda: False) -> None:
    """Answer on `master` until `stopped()`."""
    while not stopped():
        ready, _, _ = select.select([master], [], [], 0.2)
        if not ready:
            continue
        data = os.read(master, 4096)
        answer = bus.feed(data)
        if answer:
            os.write(master, answer)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="A stand-in for RoboClaw motor controllers on a pty.")
    parser.add_argument("--link", required=True, help="the path the rover's code opens (/dev/serial1)")
    parser.add_argument("--address", type=int, action="append", required=True, choices=range(128, 136),
                        help="a controller's packet serial address (128..135), repeatable")
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # systemctl stop: remove the link
    master, _slave, name = open_line(args.link)
    try:
        print(f"{SERVING} addresses {', '.join(map(str, args.address))} on {name} as {args.link}", flush=True)
        serve(master, Bus(args.address))
    except KeyboardInterrupt:
        pass
    finally:
        if os.path.islink(args.link) and os.readlink(args.link) == name:
            os.unlink(args.link)
    return 0


if __name__ == "__main__":
    sys.exit(main())
