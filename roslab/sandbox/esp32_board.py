"""A STAND-IN for the ESP32 board of robot profile esp32_microros: a Linux DDS-XRCE client.

No ESP32 exists in the sandbox. `board/esp32_board_standin.c` speaks the board's protocol
(DDS-XRCE over UDP) to the REAL micro-ROS agent a sandbox host built from source, with the
client libraries the board's firmware is built on (eProsima's Micro-XRCE-DDS-Client and
Micro-CDR, from the bundles ROSLAB_SANDBOX_SOURCES names: real_sources.py), and publishes the
potentiometer reading the firmware publishes. It runs on this machine (the controller) and
talks to the agent's host over the sandbox's bridge, as a board on the classroom's WiFi would.

Built once per bundle and source digest into the sandbox cache (`esp32-board/<key>/`).
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from . import upstream
from .real_sources import Bundles
from .system import SandboxError, log

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
        with tempfile.TemporaryDirectory(prefix="roslab-esp32-") as work:
            work = Path(work)
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


class Board:
    """One running stand-in board, publishing through the agent at `address`:`port`."""

    def __init__(self, executable: Path, address: str, port: int, domain_id: int, log_file: Path):
        self.argv = [str(executable), address, str(port), str(domain_id)]
        self.log_file = Path(log_file)
        self.process: subprocess.Popen | None = None

    def start(self, timeout: float = 30) -> "Board":
        """Start it and wait until it says it publishes (it retries while the agent starts)."""
        deadline = time.monotonic() + timeout
        while True:
            with open(self.log_file, "ab") as log_handle:
                self.process = subprocess.Popen(self.argv, stdout=log_handle, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL, start_new_session=True)
            while self.process.poll() is None and time.monotonic() < deadline:
                if b"esp32 stand-in: publishing" in self.log_file.read_bytes():
                    return self
                time.sleep(0.2)
            if self.process.poll() is None:
                self.stop()
                raise SandboxError(f"the ESP32 stand-in did not start publishing in {timeout:g} s "
                                   f"({self.log_file})")
            if time.monotonic() >= deadline:
                raise SandboxError(f"the ESP32 stand-in found no agent at {self.argv[1]}:{self.argv[2]} "
                                   f"in {timeout:g} s ({self.log_file})")
            time.sleep(1)  # the agent is not up yet: a board retries too

    def stop(self) -> None:
        if self.process and self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(10)
        self.process = None
