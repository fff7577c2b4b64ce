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
import json
import os
import tempfile
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

TIMEOUT = 60  # seconds, per download

_lock = threading.Lock()
_fetched: dict[str, bytes | DownloadError] = {}
# The validators (ETag, Last-Modified) each URL came with this run: a second `kept` of the
# same URL (the package check, then rosdep's data) keeps them, or the next run could not ask
# conditionally and downloaded the whole file again.
_fetched_validators: dict[str, dict[str, str]] = {}


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


@dataclass(frozen=True)
class Kept:
    """A file kept on the controller: its bytes, and how they were had this run."""

    data: bytes
    # None: fresh (downloaded, confirmed unchanged, or younger than the max age). Else one
    # line saying the download failed and which kept copy stands in for it.
    stale: str | None = None


def _kept_path(url: str, cache_dir: Path) -> Path:
    return Path(cache_dir).expanduser() / hashlib.sha256(url.encode()).hexdigest()[:16] / (
        os.path.basename(url.rstrip("/")) or "index")


def _validators(meta: Path) -> dict[str, str]:
    try:
        found = json.loads(meta.read_text())
    except (OSError, ValueError):
        return {}
    return {key: value for key, value in found.items() if key in ("etag", "last_modified")
            and isinstance(value, str) and "\n" not in value and "\r" not in value}


def _conditional_fetch(url: str, validators: dict[str, str], timeout: float = TIMEOUT):
    """(bytes, or None when the server says the kept copy is current; its validators).

    Once per run per URL, like fetch(); a failure is remembered and raised as DownloadError.
    """
    with _lock:
        known = _fetched.get(url)
        if isinstance(known, DownloadError):
            raise known
        if known is not None:
            return known, dict(_fetched_validators.get(url, {}))
        request = urllib.request.Request(url)
        if validators.get("etag"):
            request.add_header("If-None-Match", validators["etag"])
        if validators.get("last_modified"):
            request.add_header("If-Modified-Since", validators["last_modified"])
        try:
            with urllib.request.urlopen(request, timeout=timeout) as response:
                data = response.read()
                headers = response.headers
        except urllib.error.HTTPError as error:
            if error.code == 304 and validators:
                return None, validators
            failure = DownloadError(f"cannot download {url}: {_reason(error)}")
            _fetched[url] = failure
            raise failure from None
        except (OSError, ValueError) as error:  # URLError, timeouts, a bad URL
            failure = DownloadError(f"cannot download {url}: {_reason(error)}")
            _fetched[url] = failure
            raise failure from None
        _fetched[url] = data
        found = {"etag": headers.get("ETag"), "last_modified": headers.get("Last-Modified")}
        _fetched_validators[url] = {key: value for key, value in found.items() if value}
        return data, dict(_fetched_validators[url])


def _age_text(seconds: float) -> str:
    if seconds < 2 * 3600:
        return f"{max(0, int(seconds // 60))} min"
    if seconds < 2 * 86400:
        return f"{int(seconds // 3600)} h"
    return f"{int(seconds // 86400)} days"


def kept(url: str, cache_dir: Path, offline: bool = False, max_age: float | None = None) -> Kept:
    """The bytes at `url`, kept in `cache_dir` for the next runs.

    For files that change upstream (rosdep's data). A kept copy is checked with a
    conditional request on every run (If-None-Match / If-Modified-Since: a 304 costs no
    body) and replaced when it changed, so a copy never hides an upstream change; the
    same URL may serve other content tomorrow (a mirror updated, a sandbox rebuilt).
    `max_age` only names how old a copy is when upstream is down. When upstream
    cannot be reached, a kept copy is used all the same, and `Kept.stale` says so; without
    one, DownloadError. `offline`: never ask, the kept copy or DownloadError.
    """
    key = (url, str(cache_dir), offline, max_age)
    with _lock:
        if key in _kept_this_run:
            return _kept_this_run[key]
    result = _kept(url, cache_dir, offline, max_age)
    with _lock:
        _kept_this_run[key] = result
    return result


_kept_this_run: dict[tuple, Kept] = {}


def _kept(url: str, cache_dir: Path, offline: bool, max_age: float | None) -> Kept:
    path = _kept_path(url, cache_dir)
    meta = path.with_name(path.name + ".roslab-meta.json")
    try:
        copy = path.read_bytes()
        age = time.time() - path.stat().st_mtime
    except OSError:
        copy, age = None, 0.0  # no copy: its age is never said
    if offline:
        if copy is None:
            raise DownloadError(f"offline, and {url} is not in the controller's cache ({path}): "
                                "run once online first")
        return Kept(copy)
    try:
        data, validators = _conditional_fetch(url, _validators(meta) if copy is not None else {})
    except DownloadError as error:
        if copy is None:
            raise
        return Kept(copy, stale=f"{error}; using the controller's copy from {_age_text(age)} ago ({path})")
    with _lock:
        try:
            if data is None:  # 304: the kept copy is current (asked with its validators only)
                if copy is None:
                    raise DownloadError(f"{url} answered 304 Not Modified to a request for the whole file")
                os.utime(path)
                return Kept(copy)
            if copy != data:
                _write_atomically(path, data)
            else:
                os.utime(path)
            if validators:
                _write_atomically(meta, json.dumps(validators).encode())
            else:
                meta.unlink(missing_ok=True)
        except OSError:
            pass  # an unwritable cache costs the next run a download, nothing else
    return Kept(data)
