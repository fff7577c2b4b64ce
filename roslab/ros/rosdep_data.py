"""rosdep's data for the class, downloaded once by the controller and copied to each host.

`rosdep init` and `rosdep update` on every Pi download the same files from GitHub (which
rate-limits a classroom behind one address, ros/rosdistro#48409). Instead the controller
downloads, once per run, and keeps (for the offline mode, for no-op runs, which only ask
upstream whether each file changed and download nothing when it did not, and for a run
when upstream is down, which uses the kept copy and says so):

- rosdep's sources list (20-default.list) and every rule file it lists (`yaml` and
  `gbpdistro` lines, tags kept);
- the rosdistro index and, for the host's distro only, its distribution files and its
  distribution cache (what `rosdep update` reads for a ROS 2 distro).

It hands each host one tar archive of those files (deterministic: the same data makes the
same bytes, so an unchanged archive is a no-op upload), a sources list whose lines point at
them as `file://` URLs, and the `file://` URL of an index that lists the host's distro with
its files. rosdep reads `file://` URLs as it reads Debian's own 10-debian.list.
"""

from __future__ import annotations

import io
import os
import tarfile
import threading
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urljoin, urlsplit

import yaml

from roslab import downloads

OFFICIAL_SOURCES_LIST_URL = (
    "https://raw.githubusercontent.com/ros/rosdistro/master/rosdep/sources.list.d/20-default.list"
)
OFFICIAL_INDEX_URL = "https://raw.githubusercontent.com/ros/rosdistro/master/index-v4.yaml"
# Where a host keeps the copies (root's, readable by the login user who runs rosdep update).
HOST_DIR = "/var/lib/roslab/rosdep-data"
SOURCE_TYPES = ("yaml", "gbpdistro")

_lock = threading.Lock()
_built: dict[tuple, "RosdepData"] = {}


class RosdepDataError(Exception):
    """rosdep's data cannot be downloaded or read (the message names the URL)."""


@dataclass(frozen=True)
class RosdepData:
    archive: bytes  # tar of the files, to unpack into HOST_DIR
    sources_list: bytes  # the host's 20-default.list, pointing into HOST_DIR
    index_url: str  # ROSDISTRO_INDEX_URL on the host
    files: tuple[str, ...]  # paths inside the archive
    # None, or one line per file whose download failed and whose kept copy stands in for it
    stale: tuple[str, ...] = ()


def _local_name(number: int, url: str) -> str:
    base = url.rstrip("/").rsplit("/", 1)[-1] or "file"
    safe = "".join(char if (char.isascii() and char.isalnum()) or char in "._-" else "_" for char in base)
    return f"{number:02d}-{safe}"


def local_sources_list(text: str, source_url: str) -> tuple[str, dict[str, str]]:
    """(the sources list pointing into HOST_DIR, local path -> URL to download).

    Relative URLs are resolved against the list's own URL; comments and unknown lines
    are dropped (rosdep ignores what it does not know too).
    """
    lines = [f"# managed by roslab (deploy/rosdep.py): rosdep's sources list from {source_url},\n"
             f"# its files downloaded once by the controller and copied to {HOST_DIR}.\n"]
    wanted: dict[str, str] = {}
    for raw in text.splitlines():
        words = raw.split("#", 1)[0].split()
        if len(words) < 2 or words[0] not in SOURCE_TYPES:
            continue
        url = urljoin(source_url, words[1])
        local = f"sources/{_local_name(len(wanted) + 1, url)}"
        wanted[local] = url
        lines.append(" ".join([words[0], f"file://{HOST_DIR}/{local}", *words[2:]]) + "\n")
    return "".join(lines), wanted


def local_index(text: str, index_url: str, distro: str) -> tuple[str, dict[str, str]]:
    """(an index listing only `distro`, its files pointing into HOST_DIR; local path -> URL)."""
    try:
        index = yaml.safe_load(text)
        entry = dict(index["distributions"][distro])
    except (yaml.YAMLError, TypeError, KeyError) as error:
        reason = f"it has no distro {distro!r}" if isinstance(error, KeyError) else "it is not an index"
        raise RosdepDataError(f"rosdistro index {index_url}: {reason}") from None
    wanted: dict[str, str] = {}
    files = entry.get("distribution") or []
    if isinstance(files, str):
        files = [files]
    local_files = []
    for number, relative in enumerate(files, 1):
        local = f"rosdistro/{distro}/{_local_name(number, relative)}"
        wanted[local] = urljoin(index_url, relative)
        local_files.append(f"file://{HOST_DIR}/{local}")
    entry["distribution"] = local_files
    if entry.get("distribution_cache"):
        url = urljoin(index_url, entry["distribution_cache"])
        local = f"rosdistro/{distro}/{_local_name(0, url)}"
        wanted[local] = url
        entry["distribution_cache"] = f"file://{HOST_DIR}/{local}"
    result = {key: value for key, value in index.items() if key != "distributions"}
    result["distributions"] = {distro: entry}
    header = (f"%YAML 1.1\n# managed by roslab (deploy/rosdep.py): the rosdistro index from {index_url},\n"
              f"# with {distro} only, its files downloaded once by the controller.\n---\n")
    return header + yaml.safe_dump(result, sort_keys=True), wanted


def listed_url_problem(url: str, given: tuple[str, ...]) -> str | None:
    """Why a URL a sources list or index lists must not be fetched, or None.

    What the controller fetches is copied to every Pi. A listed file:// URL could name any
    file on the controller (an SSH key, the secrets file), so it must stay inside the folder
    of a file:// URL the roster gave (checked to be inside the roster's folder); anything
    else must be http(s).
    """
    parts = urlsplit(url)
    if parts.scheme in ("http", "https"):
        return None
    if parts.scheme != "file":
        return f"rosdep's data lists {url}: only http://, https:// (or file:// beside the roster) are fetched"
    path = os.path.realpath(unquote(parts.path))
    for base in given:
        base_parts = urlsplit(base)
        if base_parts.scheme == "file":
            folder = os.path.realpath(os.path.dirname(unquote(base_parts.path)))
            if os.path.commonpath([folder, path]) == folder:
                return None
    return (f"rosdep's data lists {url}, a file outside the folder of the file:// URL the roster "
            "gave: it would be copied to every Pi, so it is not read")


def _tar(files: dict[str, bytes]) -> bytes:
    """A tar of `files` that depends on their content only (no times, owners or order)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", format=tarfile.PAX_FORMAT) as archive:
        for path in sorted(files):
            info = tarfile.TarInfo(path)
            info.size, info.mode, info.mtime = len(files[path]), 0o644, 0
            info.uid = info.gid = 0
            info.uname = info.gname = "root"
            archive.addfile(info, io.BytesIO(files[path]))
    return buffer.getvalue()


def for_distro(sources_list_url: str | None, index_url: str | None, distro: str, cache_dir: Path,
               offline: bool = False, max_age: float | None = None) -> RosdepData:
    """rosdep's data for hosts of `distro`, built once per run (RosdepDataError naming the URL).

    Each file is checked against the controller's kept copy with a conditional request
    (no body when unchanged); when upstream cannot be reached the kept copy is used and
    `stale` says so (downloads.kept).
    """
    sources_list_url = sources_list_url or OFFICIAL_SOURCES_LIST_URL
    index_url = index_url or OFFICIAL_INDEX_URL
    key = (sources_list_url, index_url, distro, str(cache_dir), offline, max_age)
    with _lock:
        if key in _built:
            return _built[key]
    stale: list[str] = []

    def get(url: str) -> bytes:
        try:
            got = downloads.kept(url, cache_dir, offline=offline, max_age=max_age)
        except downloads.DownloadError as error:
            raise RosdepDataError(str(error)) from None
        if got.stale:
            stale.append(got.stale)
        return got.data

    sources_text, wanted = local_sources_list(get(sources_list_url).decode("utf-8", "replace"),
                                              sources_list_url)
    index_text, index_wanted = local_index(get(index_url).decode("utf-8", "replace"), index_url, distro)
    wanted.update(index_wanted)
    for url in wanted.values():
        problem = listed_url_problem(url, (sources_list_url, index_url))
        if problem:
            raise RosdepDataError(problem)
    files = {local: get(url) for local, url in wanted.items()}
    files["rosdistro/index.yaml"] = index_text.encode()
    data = RosdepData(archive=_tar(files), sources_list=sources_text.encode(),
                      index_url=f"file://{HOST_DIR}/rosdistro/index.yaml", files=tuple(sorted(files)),
                      stale=tuple(stale))
    with _lock:
        _built[key] = data
    return data
