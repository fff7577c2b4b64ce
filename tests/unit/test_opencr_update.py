"""`roslab opencr-update` with ROBOTIS's real archive (roslab/robot_tools/opencr_update.py).

Stand-ins here: a pseudo-terminal for the OpenCR; Debian's armhf C library
(libc6-armhf-cross, under qemu-arm) for the Pi's libc6:armhf; a `uname` that says aarch64 and an
`opencr_ld_shell_arm` that prints its arguments, to show which flasher update.sh picks on a
64-bit Pi (the real ARM flasher runs under qemu-arm in its own test).

The archive is the one OpenCR-Binaries holds (ROSLAB_SANDBOX_SOURCES, else ../shared/sources
beside the checkout, as CI lays it); the tests that need it skip, saying so, without the bundle.
ROBOTIS's x86-64 flasher really runs here, against a pseudo-terminal (os.openpty) standing in for
the OpenCR's /dev/ttyACM0: nothing answers on it, which the flasher reports as a failed board-name
request. A full run tries three times, 3.3 s of fixed wait each (its own timing, about 13 s, run
end to end in tests/e2e/test_profiles_e2e.py); here it is stopped after its first failed request.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import select
import shutil
import subprocess
import tarfile
import time
from pathlib import Path

import pytest

from roslab.cli.main import main
from roslab.robot_tools import opencr_update as tool
from roslab.sandbox import real_sources
from tests.unit.test_profiles import rosdistro_url, tb3_roster  # noqa: F401 (a fixture, a roster)

REPO = Path(__file__).resolve().parents[2]


def bundles() -> real_sources.Bundles:
    folder = real_sources.sources_dir() or REPO.parent / "shared" / "sources"
    return real_sources.Bundles(folder if folder.is_dir() else None)


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> bytes:
    data = real_sources.opencr_archive(bundles(), tmp_path_factory.mktemp("bundle"))
    if data is None:
        pytest.skip("no OpenCR-Binaries.bundle (ROSLAB_SANDBOX_SOURCES or ../shared/sources): "
                    "ROBOTIS's real archive is not here")
    return data


@pytest.fixture(scope="module")
def unpacked(archive, tmp_path_factory) -> Path:
    """The archive unpacked as the robot does: `tar -xf` (it is gzip, whatever its name says)."""
    folder = tmp_path_factory.mktemp("robot")
    (folder / tool.ARCHIVE_NAME).write_bytes(archive)
    subprocess.run(["tar", "-xf", tool.ARCHIVE_NAME, "--no-same-owner", "--no-same-permissions"],
                   cwd=folder, check=True)
    return folder / tool.ARCHIVE_FOLDER


def test_the_pinned_archive_is_gzip_and_holds_each_models_firmware_and_robotis_flasher(archive, tmp_path):
    assert hashlib.sha256(archive).hexdigest() == tool.ARCHIVE_SHA256
    assert archive[:2] == b"\x1f\x8b"  # gzip: `tar -xjf` fails with "bzip2: (stdin) is not a bzip2 file"
    (tmp_path / tool.ARCHIVE_NAME).write_bytes(archive)
    bzip2 = subprocess.run(["tar", "-xjf", tool.ARCHIVE_NAME], cwd=tmp_path, capture_output=True, text=True)
    assert bzip2.returncode != 0 and "not a bzip2 file" in bzip2.stderr
    with tarfile.open(tmp_path / tool.ARCHIVE_NAME) as tar:
        names = {Path(name).name for name in tar.getnames() if name.startswith(tool.ARCHIVE_FOLDER + "/")}
    assert {f"{firmware}.opencr" for firmware in set(tool.FIRMWARE.values())} <= names
    assert "waffle_pi.opencr" not in names
    assert {"update.sh", "opencr_ld_shell_x86", "opencr_ld_shell_arm"} <= names


def test_update_sh_takes_port_and_firmware_and_picks_the_arm_flasher_on_aarch64(unpacked):
    script = (unpacked / "update.sh").read_text()
    assert "aarch64) architecture=\"arm\"" in script and "./opencr_ld_shell_arm" in script
    assert "$shell_cmd $1 115200 $2 1" in script
    # The ARM flasher is 32-bit armhf, hence the armhf step on a 64-bit Pi.
    arm = (unpacked / "opencr_ld_shell_arm").read_bytes()
    assert arm[:5] == b"\x7fELF\x01" and b"/lib/ld-linux-armhf.so.3" in arm


def test_each_model_flashes_a_firmware_the_archive_holds():
    assert tool.firmware_name("burger") == "burger"
    assert tool.firmware_name("waffle") == "waffle"
    assert tool.firmware_name("waffle_pi") == "waffle"
    from roslab.profiles.library import builtin_profiles
    assert set(tool.FIRMWARE) == set(builtin_profiles()["turtlebot3"].settings["turtlebot3_model"].allowed)


def test_the_robots_script_checks_the_digest_then_unpacks_with_tar_xf_and_runs_update_sh():
    script = tool.flash_script("/dev/ttyACM0", "waffle")
    steps = script.split(" && ")
    assert steps[0] == f"cd {tool.REMOTE_DIR}"
    assert steps[1] == f"echo '{tool.ARCHIVE_SHA256}  opencr_update.tar.bz2' | sha256sum -c --quiet -"
    assert "tar -xf opencr_update.tar.bz2 --no-same-owner --no-same-permissions" in steps
    assert not any("-xj" in step for step in steps)
    assert steps[-1] == "./update.sh /dev/ttyACM0 waffle.opencr"
    assert tool.flash_script("/dev/tty ACM0", "burger").endswith("./update.sh '/dev/tty ACM0' burger.opencr")


@pytest.mark.parametrize("facts, commands, line", [
    ({"machine": "aarch64", "armhf": False, "libc6_armhf": False},
     ["dpkg --add-architecture armhf", "apt-get update",
      "DEBIAN_FRONTEND=noninteractive apt-get install -y libc6:armhf"],
     "aarch64: added the armhf architecture and installed libc6:armhf for ROBOTIS's 32-bit ARM flasher"),
    ({"machine": "aarch64", "armhf": True, "libc6_armhf": False},
     ["apt-get update", "DEBIAN_FRONTEND=noninteractive apt-get install -y libc6:armhf"],
     "aarch64: installed libc6:armhf for ROBOTIS's 32-bit ARM flasher"),
    ({"machine": "aarch64", "armhf": True, "libc6_armhf": True}, [],
     "aarch64: armhf and libc6:armhf already present for ROBOTIS's 32-bit ARM flasher"),
    ({"machine": "x86_64", "armhf": False, "libc6_armhf": False}, [],
     "x86_64: update.sh runs the x86 flasher natively"),
    ({"machine": "armv7l", "armhf": False, "libc6_armhf": False}, [],
     "armv7l: update.sh runs the ARM flasher natively"),
])
def test_a_64_bit_arm_pi_gets_armhf_and_its_libc_once(facts, commands, line):
    assert tool.armhf_commands(facts) == (commands, line)


def test_the_architecture_fact_reads_uname_dpkg_and_the_libc():
    fact = tool.FlasherArchitecture()
    assert fact.process(["aarch64", "armhf ", "install ok installed"]) == {
        "machine": "aarch64", "armhf": True, "libc6_armhf": True}
    assert fact.process(["aarch64", "", ""]) == {"machine": "aarch64", "armhf": False, "libc6_armhf": False}
    assert fact.process(["x86_64", "i386 ", "deinstall ok config-files"])["libc6_armhf"] is False


def test_an_unidentified_port_is_flashed_only_when_allowed_and_another_device_never():
    assert tool.port_problem("r", "/dev/pts/3", "") == (
        "/dev/pts/3 on r is a device udev cannot identify, not an OpenCR (0483:5740): nothing was flashed "
        "(--allow-unidentified-port flashes through it all the same)")
    assert tool.port_problem("r", "/dev/pts/3", "", allow_unidentified=True) is None
    assert tool.port_problem("r", "/dev/ttyUSB0", "10c4:ea60", allow_unidentified=True) == (
        "/dev/ttyUSB0 on r is 10c4:ea60, not an OpenCR (0483:5740): nothing was flashed")
    assert tool.port_problem("r", "/dev/ttyACM0", None, allow_unidentified=True).startswith("no OpenCR board on r")


@pytest.mark.parametrize("value", ["ttyACM0", "/dev/../etc/shadow", "/dev/tty ACM0", "/dev/x;reboot", "/devx"])
def test_a_port_outside_dev_is_refused(value):
    with pytest.raises(argparse.ArgumentTypeError, match="not a device path under /dev"):
        tool.port_argument(value)
    assert tool.port_argument("/dev/serial/by-id/usb-ROBOTIS_OpenCR_Virtual_ComPort_in_FS_Mode-if00")


def test_the_verdict_is_the_flashers_output_not_its_exit_code():
    flashed = "[OK] Open port   \t: /dev/ttyACM0\n[OK] flash_erase \t: 1.2s\n[OK] Download \n[OK] jump_to_fw \n"
    assert tool.flasher_verdict("/dev/ttyACM0", "burger", flashed) == (
        True, "flashed burger.opencr through /dev/ttyACM0")
    crc = "[OK] flash_write \t: 2.0s \n[NG] CRC Check   \t: 0x1 : 2, 3 0.1 sec\n[NG] Download \n"
    assert tool.flasher_verdict("/dev/ttyACM0", "burger", crc) == (
        False, "ROBOTIS's flasher failed on /dev/ttyACM0: [NG] CRC Check : 0x1 : 2, 3 0.1 sec")
    assert tool.flasher_verdict("/dev/ttyACM0", "burger", "OpenCR Update Start..\n") == (
        False, "ROBOTIS's flasher did not report a download on /dev/ttyACM0")


def run_until_no_board_answers(command: list[str], cwd: Path, timeout: float = 10,
                               arguments: tuple[str, ...] = ("waffle.opencr",)) -> tuple[str, str, bytes]:
    """ROBOTIS's update.sh against a pseudo-terminal, stopped at its first failed board-name
    request. Its output goes to a terminal too, so the flasher prints line by line (to a pipe its
    C library would hold it all until the end)."""
    board, port_side = os.openpty()
    screen, screen_side = os.openpty()
    port = os.ttyname(port_side)
    process = subprocess.Popen([*command, port, *arguments], cwd=cwd, stdout=screen_side,
                               stderr=screen_side, stdin=subprocess.DEVNULL, start_new_session=True)
    os.close(screen_side)
    output, sent = b"", b""
    deadline = time.monotonic() + timeout
    try:
        while b"cmd_read_board_name fail" not in output and time.monotonic() < deadline:
            ready, _, _ = select.select([screen, board], [], [], 0.2)
            if board in ready:
                sent += os.read(board, 4096)
            if screen in ready:
                try:
                    chunk = os.read(screen, 4096)
                except OSError:  # EIO: every writer is gone
                    chunk = b""
                output += chunk
                if not chunk:
                    break
    finally:
        process.kill()
        process.wait()
        for fd in (board, port_side, screen):
            os.close(fd)
    return port, output.decode(errors="replace").replace("\r\n", "\n"), sent


@pytest.mark.skipif(platform.machine() != "x86_64", reason="ROBOTIS's x86 flasher runs on x86-64 only")
def test_robotis_flasher_runs_against_a_pty_and_no_opencr_answers(unpacked):
    port, output, sent = run_until_no_board_answers(["./update.sh"], unpacked)
    lines = [" ".join(line.split()) for line in output.splitlines()]
    # update.sh's own report: the machine, the flasher it chose, its arguments as passed on.
    assert lines[:3] == ["x86_64", "amd64", "OpenCR Update Start.."], lines
    assert "[ ] fw_name : waffle" in lines and "[ ] file name : waffle.opencr" in lines, lines
    assert f"[OK] Open port : {port}" in lines, lines
    # What it wrote to the port: the OpenCR's jump-to-bootloader word, then a board-name request.
    assert sent.startswith(b"OpenCR 5555AAAA"), sent
    assert tool.flasher_verdict(port, "waffle", output) == (
        False, f"no OpenCR answered on {port}: nothing was flashed")


def test_a_digest_mismatch_is_refused_before_any_robot_is_reached(tmp_path, archive, rosdistro_url,  # noqa: F811
                                                                  capsys, monkeypatch):
    from roslab import reach

    tampered = tmp_path / tool.ARCHIVE_NAME
    tampered.write_bytes(archive + b"\0")
    roster = tb3_roster(tmp_path, rosdistro_url, "turtlebot3_model: waffle_pi\nlds_model: LDS-03")
    monkeypatch.setattr(reach, "connected_state", lambda *a: pytest.fail("a robot was reached"))
    assert main(["opencr-update", str(roster), "--limit", "tb3-robot", "--url", tampered.as_uri()]) == 1
    got = hashlib.sha256(archive + b"\0").hexdigest()
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"roslab opencr-update: {tampered.as_uri()} has sha256 {got}, but --sha256 pins {tool.ARCHIVE_SHA256}: "
        "the file was discarded; no robot was flashed")
    assert (tmp_path / "cache").is_dir() is False or not list((tmp_path / "cache").rglob("*opencr*.tar.bz2*"))


def test_on_aarch64_update_sh_runs_the_arm_flasher_with_port_baud_firmware_and_go(unpacked, tmp_path):
    folder = tmp_path / "opencr_update"
    folder.mkdir()
    (folder / "update.sh").write_bytes((unpacked / "update.sh").read_bytes())
    (folder / "update.sh").chmod(0o755)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    # Stand-ins: a 64-bit Pi's uname, and a flasher that only says how it was called.
    (bin_dir / "uname").write_text("#!/bin/sh\necho aarch64\n")
    (folder / "opencr_ld_shell_arm").write_text("#!/bin/sh\necho \"stand-in arm flasher: $*\"\n")
    for path in (bin_dir / "uname", folder / "opencr_ld_shell_arm"):
        path.chmod(0o755)
    done = subprocess.run(["./update.sh", "/dev/ttyACM0", "waffle.opencr"], cwd=folder, capture_output=True,
                          text=True, env={**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}, timeout=10)
    assert done.stdout.splitlines() == ["aarch64", "arm", "OpenCR Update Start..",
                                        "stand-in arm flasher: /dev/ttyACM0 115200 waffle.opencr 1"], done


ARMHF_LIBC = Path("/usr/arm-linux-gnueabihf")  # Debian's libc6-armhf-cross: what libc6:armhf is on a Pi


@pytest.mark.skipif(not shutil.which("qemu-arm") or not (ARMHF_LIBC / "lib/ld-linux-armhf.so.3").exists(),
                    reason="no qemu-arm or armhf C library (scripts/install-host-tools installs qemu-user "
                    "and libc6-armhf-cross)")
def test_robotis_arm_flasher_runs_with_an_armhf_libc_and_no_opencr_answers(unpacked):
    port, output, sent = run_until_no_board_answers(["qemu-arm", "-L", str(ARMHF_LIBC), "./opencr_ld_shell_arm"],
                                                    unpacked, arguments=("115200", "waffle.opencr", "1"))
    lines = [" ".join(line.split()) for line in output.splitlines()]
    assert lines[0] == "opencr_ld_shell ver 1.0.0" and f"[OK] Open port : {port}" in lines, lines
    assert sent.startswith(b"OpenCR 5555AAAA"), sent
    assert tool.flasher_verdict(port, "waffle", output)[1] == f"no OpenCR answered on {port}: nothing was flashed"


class Output:
    def __init__(self, text: str = ""):
        self.output = text
        self.output_lines = text.splitlines()


class Robot:
    """A reached robot as flash() sees it: its facts given, its commands recorded."""

    def __init__(self, machine: str, usb_id: str, flasher_output: str, armhf: bool = False):
        self.facts = {tool.UsbSerialPort: usb_id,
                      tool.FlasherArchitecture: {"machine": machine, "armhf": armhf, "libc6_armhf": armhf}}
        self.flasher_output = flasher_output
        self.commands, self.uploads = [], []

    def get_fact(self, fact, **kwargs):
        return self.facts[fact]

    def run_shell_command(self, command, _sudo=False, print_output=False):
        assert _sudo
        self.commands.append(command)
        return True, Output(self.flasher_output if "update.sh" in command else "")

    def put_file(self, data, path, _sudo=False):
        self.uploads.append((path, data.read()))
        return True


def flash_args(**overrides) -> argparse.Namespace:
    values = {"port": "/dev/ttyACM0", "allow_unidentified_port": False, "sha256": tool.ARCHIVE_SHA256,
              "verbose": False, **overrides}
    return argparse.Namespace(**values)


def waffle_pi():
    # a roster Host as flash reads it: its typed settings' resolved profile (only its settings here)
    profile = argparse.Namespace(settings={"turtlebot3_model": "waffle_pi"})
    return argparse.Namespace(name="blue-robot", role="robot", settings=argparse.Namespace(roslab_profile=profile))


@pytest.mark.parametrize("machine, armhf, before", [
    ("aarch64", False, ["dpkg --add-architecture armhf", "apt-get update",
                        "DEBIAN_FRONTEND=noninteractive apt-get install -y libc6:armhf"]),
    ("aarch64", True, []),
    ("x86_64", False, []),
])
def test_flash_adds_armhf_on_a_64_bit_pi_then_runs_update_sh_with_waffle_for_a_waffle_pi(
        machine, armhf, before, capsys):
    robot = Robot(machine, tool.OPENCR_USB_ID, "[OK] Download \n[OK] jump_to_fw \n", armhf=armhf)
    assert tool.flash(waffle_pi(), robot, flash_args(), b"the archive") is True
    assert robot.commands == [*before, f"install -d -m 0700 -o root -g root {tool.REMOTE_DIR}",
                              tool.flash_script("/dev/ttyACM0", "waffle")]
    assert robot.uploads == [(f"{tool.REMOTE_DIR}/opencr_update.tar.bz2", b"the archive")]
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"blue-robot: {machine}: ") and out[-1] == (
        "blue-robot: flashed waffle.opencr through /dev/ttyACM0")


def test_flash_through_an_unidentified_port_says_so_and_reports_no_board_in_one_line(capsys):
    robot = Robot("x86_64", "", "[OK] Open port \t: /dev/pts/4\n[  ]\n[NG] cmd_read_board_name fail : 0xF020\n")
    assert tool.flash(waffle_pi(), robot, flash_args(port="/dev/pts/4"), b"a") is False
    assert robot.commands == []  # refused: udev cannot say it is an OpenCR
    assert tool.flash(waffle_pi(), robot, flash_args(port="/dev/pts/4", allow_unidentified_port=True), b"a") is False
    captured = capsys.readouterr()
    assert "blue-robot: udev cannot identify /dev/pts/4; flashing it as --allow-unidentified-port says" in captured.out
    assert captured.err.splitlines()[-1] == "blue-robot: no OpenCR answered on /dev/pts/4: nothing was flashed"
