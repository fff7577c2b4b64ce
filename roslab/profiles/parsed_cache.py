"""roslab's built-in profiles, parsed once per content: a cache of the parse on the controller.

Every roslab command and every run reads the built-in profiles (roslab/profiles/data) with the
strict YAML reader and checks them with the profile schema: about 30 ms of CPU on each start,
for files that change only with roslab itself. The parse (the profiles and the problems of the
files that are not sound) is kept in `~/.cache/roslab/profiles/` ($XDG_CACHE_HOME honoured),
under a key that changes with anything the parse depends on:

- the folder, each profile file's name and bytes (and where each symlink in the folder leads);
- the name, size and mtime of every module of roslab (the schema, the settings and the checks
  the parse runs are roslab's code), and Python's version.

A cache entry is a pickle, so it is read only from a folder and a file that are this user's
alone (0700 and 0600, owned by the user, not a link): nobody else can make roslab load one.
Anything wrong with the cache (unwritable, corrupt, another user's) means parsing as if there
were none; the cache is never a reason for a command to fail. The last few entries are kept
(one per roslab version in use), older ones are removed.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import stat
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from roslab.controller_files import replace_file

KEEP = 4  # entries kept: a few checkouts or versions of roslab side by side
T = TypeVar("T")


def cache_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "roslab" / "profiles"


def key_of(data_folder: Path) -> str:
    """The digest of everything the parse of `data_folder`'s profiles depends on."""
    digest = hashlib.sha256(f"{sys.version}\0{data_folder.resolve()}\0".encode())
    for path in sorted(data_folder.iterdir()):
        digest.update(path.name.encode() + b"\0")
        if path.is_symlink():
            digest.update(os.path.realpath(path).encode() + b"\0")
        if path.is_file():
            digest.update(path.read_bytes() + b"\0")
    package = Path(__file__).resolve().parent.parent
    for directory, folders, files in os.walk(package):
        folders[:] = sorted(name for name in folders if name != "__pycache__")
        for name in sorted(files):
            if name.endswith(".py"):
                info = os.stat(os.path.join(directory, name))
                digest.update(f"{directory}/{name}:{info.st_size}:{info.st_mtime_ns}\0".encode())
    return digest.hexdigest()


def cached(data_folder: Path, parse: Callable[[], T]) -> T:
    """`parse()`'s result for the profiles in `data_folder`, from the cache when it holds this
    content's parse, else parsed and kept."""
    try:
        key = key_of(data_folder)
    except OSError:
        return parse()
    entry = cache_folder() / f"{key}.pickle"
    found = _read(entry)
    if found is not None:
        return found
    result = parse()
    _write(entry, result)
    return result


def _own(info: os.stat_result, mode: int) -> bool:
    return info.st_uid == os.getuid() and stat.S_IMODE(info.st_mode) & 0o077 == 0 and (
        stat.S_IFMT(info.st_mode) == mode)


def _read(entry: Path):
    try:
        if not _own(os.lstat(entry.parent), stat.S_IFDIR):
            return None
        descriptor = os.open(entry, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None
    try:
        with os.fdopen(descriptor, "rb") as handle:
            if not _own(os.fstat(handle.fileno()), stat.S_IFREG):
                return None
            return pickle.load(handle)
    except Exception:  # noqa: BLE001  (a corrupt or older entry: parse as if there were none)
        return None


def _write(entry: Path, result) -> None:
    try:
        entry.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        folder = os.lstat(entry.parent)
        if stat.S_ISDIR(folder.st_mode) and folder.st_uid == os.getuid():
            os.chmod(entry.parent, 0o700)  # this user's alone, whatever the umask made it
        if not _own(os.lstat(entry.parent), stat.S_IFDIR):
            return
        replace_file(entry, pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL), mode=0o600, sync=False)
        entries = sorted(entry.parent.glob("*.pickle"), key=lambda path: path.stat().st_mtime, reverse=True)
        for old in entries[KEEP:]:
            old.unlink(missing_ok=True)
    except (OSError, pickle.PicklingError, TypeError, AttributeError):
        return
