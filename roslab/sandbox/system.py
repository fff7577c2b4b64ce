"""Small helpers for driving the machine: commands, locks, files."""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import signal
import threading
import time
import subprocess
from pathlib import Path

log = logging.getLogger("roslab.sandbox")


class SandboxError(RuntimeError):
    """Something the sandbox needs is missing or broken; the message says what."""


def run(*command: str | os.PathLike[str], check: bool = True, capture: bool = True,
        **kwargs) -> subprocess.CompletedProcess:
    """Run a command; on failure raise SandboxError carrying its stderr."""
    argv = [os.fspath(arg) for arg in command]
    log.debug("$ %s", " ".join(argv))
    result = subprocess.run(argv, text=True, capture_output=capture, **kwargs)
    if check and result.returncode != 0:
        detail = (result.stderr or result.stdout or "").strip()
        raise SandboxError(f"`{' '.join(argv)}` failed (exit {result.returncode}): {detail}")
    return result


def folder_setting(name: str, holds: str) -> Path | None:
    """The folder environment variable `name` names (resolved), None when it is unset or empty;
    a value that is no folder is an error naming the setting and what the folder `holds`."""
    value = os.environ.get(name, "").strip()
    if not value:
        return None
    path = Path(value).expanduser()
    if not path.is_dir():
        raise SandboxError(f"{name}={value}: no such folder (it should hold {holds})")
    return path.resolve()


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def write_file(path: Path, content: str | bytes, mode: int = 0o644, owner: tuple[int, int] | None = None) -> None:
    """Write a whole file with a given mode (and owner), creating parent directories."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_symlink():
        path.unlink()
    data = content.encode() if isinstance(content, str) else content
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
    os.chmod(path, mode)
    if owner:
        os.chown(path, *owner)


def pid_alive(pid: int) -> bool:
    """True while the process runs (a zombie waiting for its parent counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def terminate(pid: int, timeout: float = 2.0) -> None:
    """SIGTERM the process, SIGKILL it if it is still there after `timeout`."""
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + timeout
    while pid_alive(pid):
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            break
        time.sleep(0.01)


def stop_recorded(pid_file: Path, running) -> bool:
    """Stop the process `pid_file` names when `running(pid_file)` says it is still the one started
    (a sandbox stand-in: a board, a Create 3), and forget the file. False: none was running."""
    pid = running(pid_file)
    if pid is not None:
        terminate(pid)
    pid_file.unlink(missing_ok=True)
    return pid is not None


@contextlib.contextmanager
def announced(what: str, every: float = 15.0):
    """Say what the sandbox is doing, again every `every` seconds while it lasts, and how long
    it took: a long step (building the image, tearing hosts down) is never silent."""
    log.info("%s ...", what)
    started = time.monotonic()
    done = threading.Event()

    def heartbeat() -> None:
        while not done.wait(every):
            log.info("  still %s (%d s)", what, time.monotonic() - started)

    beat = threading.Thread(target=heartbeat, name="roslab-sandbox-progress", daemon=True)
    beat.start()
    try:
        yield
    finally:
        done.set()
        beat.join(timeout=1)
    log.info("%s: done in %.0f s", what, time.monotonic() - started)


# Where a removed tree waits for its background delete: beside the instances, under a name no
# instance can have (a leading dot: `_release_machine` and `down` do not count it as one).
DISCARDED_DIR = ".discarded"


def discard(path: Path, root: Path) -> None:
    """Remove the tree `path` at once as far as anyone can see: rename it into `root`'s
    `.discarded/` (one rename on the same filesystem), then delete it there in a detached,
    low-priority `rm -rf`. A converged host's overlay holds ~557 MB in tens of thousands of
    files: deleting it in the foreground took minutes on a busy machine. Nothing under `path`
    may be mounted (the caller unmounted it). A delete cut short (a reboot) is finished by
    the next `sweep_discarded`."""
    if not path.exists() and not path.is_symlink():
        return
    trash = root / DISCARDED_DIR
    trash.mkdir(parents=True, exist_ok=True)
    target = trash / f"{path.name}-{os.getpid()}-{time.monotonic_ns()}"
    os.rename(path, target)
    _delete_in_background(target)


def sweep_discarded(root: Path) -> None:
    """Start deleting whatever an earlier `discard` left (its delete was cut short)."""
    trash = root / DISCARDED_DIR
    if trash.is_dir():
        for entry in trash.iterdir():
            _delete_in_background(entry)


def _delete_in_background(path: Path) -> None:
    # The shell starts rm in the background and exits at once: rm belongs to init, never a
    # zombie of this (possibly long-lived) process.
    subprocess.run(
        ["sh", "-c", 'nice -n 19 ionice -c 3 rm -rf --one-file-system -- "$1" </dev/null >/dev/null 2>&1 &',
         "roslab-discard", str(path)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True, check=False,
    )


def mounts_under(directory: Path) -> list[Path]:
    """Mount points at or below `directory`, deepest first."""
    found = []
    prefix = str(directory).rstrip("/") + "/"
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        point = line.split()[4].replace("\\040", " ")
        if point == str(directory) or point.startswith(prefix):
            found.append(Path(point))
    return sorted(found, key=lambda p: -len(str(p)))


def unmount_all(directory: Path) -> None:
    for point in mounts_under(directory):
        if run("umount", point, check=False).returncode != 0:
            run("umount", "--lazy", point, check=False)
    if mounts_under(directory):
        raise SandboxError(f"cannot unmount {mounts_under(directory)[0]}")
