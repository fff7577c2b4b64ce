"""A STAND-IN for the ESP32 board of robot profile esp32_microros: a Linux DDS-XRCE client.

No ESP32 exists in the sandbox. `board/esp32_board_standin.c` speaks the board's protocol
(DDS-XRCE over UDP) to the REAL micro-ROS agent a sandbox host built from source, with the
client libraries the board's firmware is built on (eProsima's Micro-XRCE-DDS-Client and
Micro-CDR, from the bundles ROSLAB_SANDBOX_SOURCES names: real_sources.py), and publishes the
potentiometer reading the firmware publishes. It runs on this machine (the controller) and
talks to the agent's host over the sandbox's bridge, as a board on the classroom's WiFi would.

It is "flashed" as the firmware is: the same environment variables, with the values
`roslab esp32-firmware` prints for the team (roslab/robot_tools/esp32_firmware.py: the team's
domain, the node name esp32_board_<team>, the agent's address and port), and it reconnects to
a restarted agent as the firmware does. `roslab sandbox board TEAM start|stop|status` runs it
(one process per team, its pid and log in the sandbox's state folder, `esp32-boards/`).

Built once per bundle and source digest into the sandbox cache (`esp32-board/<key>/`).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import tempfile
import time
from pathlib import Path

from . import upstream
from roslab.robot_tools.esp32_firmware import BoardValues

from .real_sources import Bundles
from .system import SandboxError, log, pid_alive, stop_recorded

SOURCE = Path(__file__).resolve().parent / "board" / "esp32_board_standin.c"
# The client the board's firmware uses for Jazzy (micro_ros_platformio builds it at v2.4.3) and
# the Micro-CDR its CMakeLists.txt names (_microcdr_tag v2.0.1).
CLIENT = ("Micro-XRCE-DDS-Client", "v2.4.3")
CDR = ("Micro-CDR", "v2.0.1")
BUILD_VERSION = 1
EXECUTABLE = "esp32_board_standin"


def available(bundles: Bundles) -> bool:
    return all(name in bundles.paths for name, _ in (CLIENT, CDR))


def _key(bundles: Bundles) -> list:
    return [BUILD_VERSION, CLIENT, CDR, bundles.sums[CLIENT[0]], bundles.sums[CDR[0]],
            hashlib.sha256(SOURCE.read_bytes()).hexdigest()]


def _cmake(source: Path, build: Path, prefix: Path, *options: str) -> None:
    for argv in (["cmake", "-S", source, "-B", build, f"-DCMAKE_INSTALL_PREFIX={prefix}",
                  f"-DCMAKE_PREFIX_PATH={prefix}", "-DBUILD_SHARED_LIBS=OFF", "-DCMAKE_BUILD_TYPE=Release",
                  *options],
                 ["cmake", "--build", build, "-j", "2"], ["cmake", "--install", build]):
        done = subprocess.run([str(arg) for arg in argv], capture_output=True, text=True)
        if done.returncode:
            raise SandboxError(f"building the ESP32 stand-in: {' '.join(map(str, argv[:3]))}: "
                               f"{(done.stderr or done.stdout).strip()[-1500:]}")


def binary(bundles: Bundles) -> Path:
    """The stand-in board's executable (built from the bundles once, then cached)."""
    if not available(bundles):
        raise SandboxError(f"no bundles of {CLIENT[0]} and {CDR[0]} in {bundles.folder}: the ESP32 stand-in "
                           "cannot be built")

    def build(out: Path) -> None:
        log.warning(f"building the sandbox's ESP32 board stand-in from {CLIENT[0]} {CLIENT[1]} and "
                    f"{CDR[0]} {CDR[1]} (once)...")
        with tempfile.TemporaryDirectory(prefix="roslab-esp32-") as work_dir:
            work = Path(work_dir)
            prefix = work / "prefix"
            cdr = bundles.tree(CDR[0], CDR[1], work / "cdr")
            _cmake(cdr, work / "cdr-build", prefix, "-DUCDR_ISOLATED_INSTALL=OFF")
            client = bundles.tree(CLIENT[0], CLIENT[1], work / "client")
            _cmake(client, work / "client-build", prefix, "-DUCLIENT_SUPERBUILD=OFF", "-DUCLIENT_PROFILE_UDP=ON",
                   "-DUCLIENT_ISOLATED_INSTALL=OFF")
            libs = sorted(str(path) for path in prefix.rglob("*.a"))
            client_libs = [lib for lib in libs if "microxrcedds_client" in lib]
            cdr_libs = [lib for lib in libs if "microcdr" in lib]
            done = subprocess.run(["cc", "-O2", "-o", str(out / EXECUTABLE), str(SOURCE), f"-I{prefix / 'include'}",
                                   *client_libs, *cdr_libs], capture_output=True, text=True)
            if done.returncode:
                raise SandboxError(f"building the ESP32 stand-in: {done.stderr.strip()[-1500:]}")

    # cached like the sandbox's archives: built under the cache lock, renamed into place whole
    return upstream._cached_build("esp32-board", upstream._cache_key(*_key(bundles)), build) / EXECUTABLE


PUBLISHING = b"esp32 stand-in: publishing"


def board_files(state_dir: Path, team: str) -> tuple[Path, Path]:
    """(pid file, log file) of team `team`'s board in the sandbox's state folder."""
    folder = Path(state_dir) / "esp32-boards"
    return folder / f"{team}.pid", folder / f"{team}.log"


def running_pid(pid_file: Path) -> int | None:
    """The pid of the board `pid_file` names while that process runs and is a board, else None."""
    try:
        pid = int(pid_file.read_text())
        command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[:2]  # a program, or a script's
    except (OSError, ValueError):
        return None
    return pid if any(word.endswith(EXECUTABLE.encode()) for word in command) and pid_alive(pid) else None


def publishing_since(log_file: Path, offset: int) -> bool:
    """Whether the board said it publishes after byte `offset` of its log (its latest connection)."""
    try:
        text = log_file.read_bytes()[offset:]
    except OSError:
        return False
    last = text.rfind(PUBLISHING)
    return last >= 0 and b"stopped answering" not in text[last:]


def start(executable: Path, values: BoardValues, state_dir: Path, timeout: float = 30) -> bool:
    """Start team `values.team`'s board (a no-op when it runs) and wait up to `timeout` s until it
    publishes; False: it runs, still waiting for the agent (as a real board would)."""
    pid_file, log_file = board_files(state_dir, values.team)
    if running_pid(pid_file) is not None:
        return publishing_since(log_file, 0)
    pid_file.parent.mkdir(parents=True, exist_ok=True)
    offset = log_file.stat().st_size if log_file.exists() else 0
    environment = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), **values.environment()}
    with open(log_file, "ab") as log_handle:
        process = subprocess.Popen([str(executable)], stdout=log_handle, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=True, env=environment)
    pid_file.write_text(f"{process.pid}\n")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pid_file.unlink(missing_ok=True)
            raise SandboxError(f"the ESP32 stand-in of {values.team} exited (rc {process.returncode}): "
                               f"{log_file.read_text(errors='replace')[offset:].strip()[-500:]}")
        if publishing_since(log_file, offset):
            return True
        time.sleep(0.2)
    return False


def stop(state_dir: Path, team: str) -> bool:
    """Stop team `team`'s board; False: none was running."""
    return stop_recorded(board_files(state_dir, team)[0], running_pid)


def state(state_dir: Path, team: str) -> str:
    """In words: stopped, waiting for the agent, or publishing (with its pid)."""
    pid_file, log_file = board_files(state_dir, team)
    pid = running_pid(pid_file)
    if pid is None:
        return "stopped"
    return f"{'publishing' if publishing_since(log_file, 0) else 'waiting for the agent'} (pid {pid})"


def stop_all(state_dir: Path) -> None:
    """Stop every board of the sandbox (its `down`)."""
    for pid_file in sorted((Path(state_dir) / "esp32-boards").glob("*.pid")):
        stop(state_dir, pid_file.stem)
