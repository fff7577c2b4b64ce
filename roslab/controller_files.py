"""Reading a file the roster names on the controller: a regular file, bounded, never a hang.

A roster, a secrets file, a key file: each is opened without waiting (a FIFO would wait
for a writer forever), must be a regular file (a device never ends, a directory is not
text), and is read up to a size limit, so a hostile or mistaken path is one line of the
report in well under a second.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

# A secrets file or a key file holds a few lines.
MAX_SMALL_FILE_BYTES = 64 * 1024


class UnreadableFile(Exception):
    """A file the loader refuses to read; the message is one line for the report."""


def kind_of(mode: int) -> str:
    for test, what in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return what
    return "not a regular file"


def read_regular_file(path: Path | str, limit: int = MAX_SMALL_FILE_BYTES) -> bytes:
    """The bytes of a regular file of at most `limit` bytes, or UnreadableFile.

    Never blocks and never reads more than `limit` bytes: the file is opened without
    waiting (a FIFO would wait for a writer forever), checked to be a regular file
    (a device never ends, a directory is not text), and read up to the limit, so a file
    that grows while being read is refused too. Symlinks are followed; a loop is an error.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise UnreadableFile("cannot read the file: it is a symlink loop") from None
        raise UnreadableFile(f"cannot read the file: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise UnreadableFile(f"is {kind_of(info.st_mode)}, not a regular file")
        if info.st_size > limit:
            raise UnreadableFile(f"the file is larger than {_size_text(limit)}; refusing to read it")
        chunks, total = [], 0
        while True:
            chunk = os.read(fd, min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise UnreadableFile(f"the file is larger than {_size_text(limit)}; refusing to read it")
        return b"".join(chunks)
    except OSError as exc:
        raise UnreadableFile(f"cannot read the file: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def _size_text(limit: int) -> str:
    return f"{limit // (1024 * 1024)} MiB" if limit >= 1024 * 1024 else f"{limit // 1024} KiB"


__all__ = ["MAX_SMALL_FILE_BYTES", "UnreadableFile", "kind_of", "read_regular_file"]


# Digests by file identity and change times: deploy.py runs once per host and hashes the same
# workspace files for each; a file that is written again gets a new ctime, so a new digest.
_DIGESTS: dict[tuple, str] = {}
# The kernel stamps files from a coarse clock (a tick: 4 to 10 ms): a file changed this recently
# could change again with the same ctime, so its digest is not kept (git's "racily clean").
RECENT_CHANGE_NS = 100_000_000


def file_sha256(path: Path | str) -> str:
    """The sha256 of a file on the controller, read in 1 MiB blocks (a packed underlay, a workspace
    file): hex, as the hosts' sha256sum prints it. Read once while the file is unchanged (same
    device, inode, size, mtime and ctime, as make and git judge it)."""
    with open(path, "rb") as stream:
        reading_since = time.time_ns()
        status = os.fstat(stream.fileno())
        key = (status.st_dev, status.st_ino, status.st_size, status.st_mtime_ns, status.st_ctime_ns)
        known = _DIGESTS.get(key)
        if known is not None:
            return known
        digest = hashlib.sha256()
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    hexdigest = digest.hexdigest()
    if status.st_ctime_ns < reading_since - RECENT_CHANGE_NS:
        _DIGESTS[key] = hexdigest
    return hexdigest


def replace_file(path: Path | str, data: bytes | str, mode: int = 0o644, sync: bool = True) -> None:
    """Replace `path` with `data` atomically: a reader (or a run killed mid-write) sees the old
    file or the new one, never half of one.

    The new file is made beside `path` (mkstemp: O_EXCL, 0600 from its first byte, never someone's
    link), written and synced, given `mode`, then renamed over `path` (a rename replaces the name
    and follows no link there). On any failure the temporary file goes and `path` is untouched.
    `sync=False`: the caller flushes the files it wrote itself, all at once (a seed on a card).
    """
    path = Path(path)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-")
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data.encode() if isinstance(data, str) else data)
            out.flush()
            if sync:
                os.fsync(out.fileno())
            os.fchmod(out.fileno(), mode)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on `path` (a lock file, created with its folder if missing) for the
    block, across processes and threads: flock() is per open file, so two threads of one run
    that each open it wait for each other as two runs do."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
