"""Files the machine running pyinfra downloads for the hosts, once per run.

Hosts are planned one after another (and may be in threads): each URL is fetched at most
once per run, and a failure is remembered too, so a classroom of 30 Pis waits for one
timeout, not 30. A failure is a `DownloadError` naming the URL and the reason, for the
deploy to stop the hosts that need the file (never the whole run).

A pinned file (`pinned`) is cached under the directory named by its sha256: the bytes
returned are the bytes whose sha256 was just checked, whatever else shares the cache.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import threading
import urllib.error
import urllib.request
from pathlib import Path

TIMEOUT = 60  # seconds, per download

_lock = threading.Lock()
_fetched: dict[str, bytes | DownloadError] = {}


class DownloadError(Exception):
    """A download that failed or whose content is not what was pinned."""


def _reason(error: Exception) -> str:
    if isinstance(error, urllib.error.HTTPError):
        return f"HTTP {error.code} {error.reason}"
    if isinstance(error, urllib.error.URLError):
        return str(error.reason)
    return str(error) or type(error).__name__


def fetch(url: str, timeout: float = TIMEOUT) -> bytes:
    """The bytes at `url`, fetched once per run; DownloadError (also remembered) on failure."""
    with _lock:
        known = _fetched.get(url)
        if isinstance(known, DownloadError):
            raise known
        if known is not None:
            return known
        try:
            with urllib.request.urlopen(url, timeout=timeout) as response:
                data = response.read()
        except (OSError, ValueError) as error:  # URLError, HTTPError, timeouts, a bad URL
            failure = DownloadError(f"cannot download {url}: {_reason(error)}")
            _fetched[url] = failure
            raise failure from None
        _fetched[url] = data
        return data


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def pinned(url: str, sha256: str, cache_dir: Path, name: str, pin_setting: str,
           offline: bool = False) -> bytes:
    """The file at `url` whose sha256 is `sha256`, from the cache or downloaded into it.

    The cache holds it as `<cache_dir>/<sha256>/<name>`, written atomically (a complete
    file or none) and checked again on every read: a file another roster (another pin)
    or a half-written download left never stands in for this one. A download whose
    sha256 differs is discarded (DownloadError naming `pin_setting`). `offline`: never
    download; a file missing from the cache is a DownloadError.
    """
    path = Path(cache_dir) / sha256 / name
    with _lock:
        try:
            data = path.read_bytes()
        except OSError:
            data = None
        if data is not None and sha256_hex(data) == sha256:
            return data
    if offline:
        raise DownloadError(f"offline, and {path} (from {url}) is not in the controller's cache: "
                            "run once online first")
    data = fetch(url)
    got = sha256_hex(data)
    if got != sha256:
        raise DownloadError(
            f"{url} has sha256 {got}, but {pin_setting} pins {sha256}: the file was discarded"
        )
    with _lock:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{name}.", suffix=".part",
                                             delete=False) as part:
                part.write(data)
            os.replace(part.name, path)
        except OSError:
            # An unwritable cache costs a download next run, nothing else: the bytes are checked.
            try:
                os.unlink(part.name)
            except (OSError, NameError):
                pass
    return data


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".part",
                                     delete=False) as part:
        part.write(data)
    os.replace(part.name, path)


def kept(url: str, cache_dir: Path, offline: bool = False) -> bytes:
    """The bytes at `url`: fetched once per run and kept in `cache_dir`, or, offline, the kept copy.

    For files that change upstream (rosdep's data): online, the download is the truth and
    replaces the kept copy; offline, the copy from the last online run is used, and a
    file never kept is a DownloadError.
    """
    path = Path(cache_dir).expanduser() / hashlib.sha256(url.encode()).hexdigest()[:16] / (
        os.path.basename(url.rstrip("/")) or "index")
    if offline:
        try:
            return path.read_bytes()
        except OSError:
            raise DownloadError(f"offline, and {url} is not in the controller's cache ({path}): "
                                "run once online first") from None
    data = fetch(url)
    with _lock:
        try:
            if not path.exists() or path.read_bytes() != data:
                _write_atomically(path, data)
        except OSError:
            pass  # an unwritable cache costs the offline mode this file, nothing else
    return data
