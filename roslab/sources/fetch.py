"""The controller fetches each repository of the class once, pinned, and keeps it.

A Pi never clones: the machine running pyinfra keeps a bare mirror of each repository
under `sources_cache_dir` (`git/<digest of the URL>.git`), resolves the version to a commit
and hands each host `git archive` of that commit (a tar: deterministic for a commit, so an
unchanged repository is a no-op on the hosts). The lock file beside the mirrors
(`sources.lock.json`) records, per URL as the .repos file gives it, each tag's commit and
each commit's sha256 (of its archive), the first time they are seen:

- a tag that now resolves to another commit, or a commit whose archive has another
  sha256, is a `SourceError` naming the repository: the hosts that need it fail, the others
  carry on (delete the repository's entry from the lock file to accept the new commit);
- a version that upstream has as a branch (not a tag) is refused, naming the .repos file,
  the repository and its `version` field;
- an unreachable repository fails the hosts that need it, naming it, unless the lock and the
  mirror already hold its pin: then the run goes on with one warning line;
- `offline`: no network; tags resolve through the lock file, commits come from the mirrors.

The class lock (classroom.lock beside the roster, roslab.class_lock) may lock a tag's commit
too (`locked`): then the class's commit wins over this controller's record. A controller that
recorded another commit for the tag (another class's, or before `roslab lock --update` moved
the class) checks upstream and takes the locked commit if upstream names it; a tag upstream
moved away from the locked commit is a `SourceError` naming the repository, both commits and
`roslab lock --update`. So a lock is met, and a moved tag named, on a new controller too.

When upstream is asked. A converged class asks nothing: a commit pin the mirror holds, and a
tag that the lock records, whose commit the mirror holds and that was checked against
upstream with the class's current set of pins, are served from the cache. A tag is checked
(`git ls-remote`) when it is first locked, and in every run whose set of pins (every
(URL, version) of every host of the roster) differs from the set of the last check (the
record `sources.checked.json`): a teacher changing a pin re-checks every tag, and a tag moved
upstream since is named then. Until then the lock wins: a moved tag is never taken silently.

Damage. A lock file that is not valid JSON (truncated, edited) is never rebuilt from what
upstream says now: the hosts that need sources stop, naming the file and what to do. A
missing lock beside existing mirrors is the same (it was deleted); no lock and no mirrors is
a class's first run. A mirror git cannot read (a corrupt loose object, a truncated pack,
missing objects: `git fsck` fails after an operation failed) is moved aside, kept as
`<mirror>.damaged-<time>` and named in one line, and fetched afresh once; if that fails too,
the hosts that need it fail naming the repository and the folder.

Each repository is asked once per run (threads share one result, a failure included), so a
classroom of 30 Pis fetches it once. `source_url_rewrites` (like git's insteadOf) points a
URL at a local mirror; the lock and messages keep the URL as given.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import subprocess
import tempfile
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from roslab.controller_files import UnreadableFile, file_lock, read_regular_file
from roslab.sources.repos import COMMIT, rewritten

LOCK_NAME = "sources.lock.json"
LOCK_MAX_BYTES = 16 * 1024 * 1024  # thousands of repositories' pins
# The set of pins whose tags were last checked against upstream, and the tags checked with it.
CHECKED_NAME = "sources.checked.json"
GIT_ENV = {
    "GIT_TERMINAL_PROMPT": "0",  # never wait for a password
    "GIT_ASKPASS": "true",
    "GIT_CONFIG_NOSYSTEM": "1",
    "GIT_CONFIG_GLOBAL": os.devnull,  # the teacher's own git config (insteadOf, hooks) does not apply
    "LC_ALL": "C",
}

_lock = threading.Lock()
_results: dict[tuple, "Fetched | SourceError"] = {}
# Cache folders that had neither a lock nor mirrors when this run first read them (a first run:
# the mirrors it makes before the lock is written are not a deleted lock).
_first_runs: set[str] = set()
_repo_locks: dict[str, threading.Lock] = {}


class SourceError(Exception):
    """A repository that cannot be fetched or verified (the message names it)."""


class _MirrorDamaged(SourceError):
    def __init__(self, message: str, damage: str):
        super().__init__(message)
        self.damage = damage


@dataclass(frozen=True)
class Fetched:
    path: str
    url: str
    version: str
    commit: str
    sha256: str  # of `archive`
    archive: bytes  # `git archive --format=tar <commit>`
    notes: tuple[str, ...] = ()  # warnings for the run (upstream unreachable, a mirror moved aside)


def reset() -> None:
    """Forget this run's results (tests; pyinfra runs once per process)."""
    with _lock:
        _results.clear()
        _selected.clear()
        _first_runs.clear()


def _named(repo: dict) -> str:
    return f"repository {repo['path']!r} ({repo['url']} {repo['version']}, {repo['file']})"


def _git(args: list[str], timeout: float, cwd: Path | None = None) -> bytes:
    env = {**os.environ, **GIT_ENV}
    try:
        done = subprocess.run(["git", *args], cwd=cwd, env=env, capture_output=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise SourceError(f"git {args[0]} did not finish in {timeout:g} s") from None
    except OSError as error:
        raise SourceError(f"cannot run git on this machine: {error.strerror or error}") from None
    if done.returncode != 0:
        lines = [line for line in done.stderr.decode("utf-8", "replace").splitlines() if line.strip()]
        reason = lines[-1].strip() if lines else f"exit {done.returncode}"
        raise SourceError(f"git {args[0]}: {reason}")
    return done.stdout


def mirror_path(cache_dir: Path, url: str) -> Path:
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", url.rstrip("/").rsplit("/", 1)[-1])[:60] or "repo"
    return Path(cache_dir) / "git" / f"{hashlib.sha256(url.encode()).hexdigest()[:16]}-{base}"


def _has_commit(mirror: Path, commit: str, timeout: float) -> bool:
    if not (mirror / "HEAD").is_file():
        return False
    try:
        _git(["cat-file", "-e", f"{commit}^{{commit}}"], timeout, cwd=mirror)
        return True
    except SourceError:
        return False


def remote_refs(url: str, version: str, timeout: float) -> tuple[str | None, bool]:
    """(the commit of tag `version` upstream or None, whether upstream has a branch `version`)."""
    out = _git(["ls-remote", "--", url, f"refs/tags/{version}", f"refs/tags/{version}^{{}}",
                f"refs/heads/{version}"], timeout).decode("utf-8", "replace")
    refs = {}
    for line in out.splitlines():
        sha, _, ref = line.partition("\t")
        refs[ref.strip()] = sha.strip()
    tag = refs.get(f"refs/tags/{version}^{{}}") or refs.get(f"refs/tags/{version}")
    return tag, f"refs/heads/{version}" in refs


def _fetch_into(mirror: Path, url: str, what: list[str], timeout: float) -> None:
    if not (mirror / "HEAD").is_file():
        mirror.parent.mkdir(parents=True, exist_ok=True)
        _git(["init", "--quiet", "--bare", str(mirror)], timeout)
    _git(["fetch", "--quiet", "--no-tags", "--", url, *what], timeout, cwd=mirror)


def _has_mirrors(cache_dir: Path) -> bool:
    try:
        return any((Path(cache_dir) / "git").iterdir())
    except OSError:
        return False


def read_lock(cache_dir: Path) -> dict:
    """The lock file's entries; {} on a class's first run (no lock, no mirrors).

    A lock that cannot be read as roslab writes it, or a missing one beside the controller's
    mirrors, is a SourceError naming the file: rebuilding it would take whatever upstream says
    now as the truth.
    """
    path = Path(cache_dir) / LOCK_NAME
    try:
        if not os.path.lexists(path):
            raise FileNotFoundError(path)
        # bounded and never waiting: a FIFO or a device here must not hang the run
        text = read_regular_file(path, LOCK_MAX_BYTES).decode("utf-8")
    except FileNotFoundError:
        if str(cache_dir) in _first_runs:
            return {}
        if _has_mirrors(cache_dir):
            raise SourceError(
                f"the lock file {path} is missing, but the controller's mirrors in {Path(cache_dir) / 'git'} "
                "exist: the commits the class verified are unknown. Restore the lock file from a backup; "
                f"or, to take every pin as upstream has it today, delete {Path(cache_dir) / 'git'} too") from None
        _first_runs.add(str(cache_dir))
        return {}
    except (UnreadableFile, UnicodeDecodeError) as error:
        raise SourceError(f"the lock file {path} cannot be read ({error}): restore it from a backup") from None
    reason: str | None
    try:
        data = json.loads(text)
    except ValueError as error:
        data, reason = None, f"not valid JSON: {error}"
    else:
        reason = _lock_shape_problem(data)
    if reason:
        raise SourceError(
            f"the lock file {path} is damaged ({reason}): it is never rebuilt from what upstream says now. "
            f"Restore it from a backup; or, to take every pin as upstream has it today, delete it and "
            f"{Path(cache_dir) / 'git'}")
    return data


def _lock_shape_problem(data) -> str | None:
    """What is wrong with a parsed lock file, or None: {url: {"tags": {tag: commit},
    "commits": {commit: sha256}}}."""
    if not isinstance(data, dict):
        return "not a JSON object"
    for url, entry in data.items():
        if not isinstance(entry, dict):
            return f"the entry of {url} is not an object"
        tags, commits = entry.get("tags", {}), entry.get("commits", {})
        if not isinstance(tags, dict) or not all(
                isinstance(value, str) and COMMIT.fullmatch(value) for value in tags.values()):
            return f"the tags of {url} are not tag: commit pairs"
        if not isinstance(commits, dict) or not all(
                COMMIT.fullmatch(key) and isinstance(value, str) and re.fullmatch(r"[0-9a-f]{64}", value)
                for key, value in commits.items()):
            return f"the commits of {url} are not commit: sha256 pairs"
    return None


def pins_digest(pins) -> str:
    """A set of (url, version) pairs, as recorded in the checked record."""
    return hashlib.sha256(json.dumps(sorted(map(list, pins))).encode()).hexdigest()


def _read_checked(cache_dir: Path) -> dict:
    """The record of the last check against upstream; {} when missing or unreadable (it only
    saves upstream requests: a damaged record costs one check of every tag)."""
    try:
        data = json.loads((Path(cache_dir) / CHECKED_NAME).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) and isinstance(data.get("checked"), dict) else {}


def _tag_checked(cache_dir: Path, digest: str, url: str, tag: str) -> bool:
    record = _read_checked(cache_dir)
    return record.get("pins") == digest and tag in (record["checked"].get(url) or [])


def _files_lock(cache_dir: Path) -> Path:
    """The lock of the cache's own files (the lock file of pins, the tag checks)."""
    return Path(cache_dir) / "locks" / "files.lock"


def _mark_checked(cache_dir: Path, digest: str, url: str, tag: str) -> None:
    with file_lock(_files_lock(cache_dir)):
        _mark_checked_locked(cache_dir, digest, url, tag)


def _mark_checked_locked(cache_dir: Path, digest: str, url: str, tag: str) -> None:
    record = _read_checked(cache_dir)
    if record.get("pins") != digest:
        record = {"pins": digest, "checked": {}}
    tags = record["checked"].setdefault(url, [])
    if tag in tags:
        return
    tags.append(tag)
    _write_json(Path(cache_dir) / CHECKED_NAME, record)


def _write_json(path: Path, data: dict) -> None:
    """Written beside and renamed into place, so a killed run leaves the old file or the new."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-")
    try:
        with os.fdopen(handle, "w") as out:
            json.dump(data, out, indent=2, sort_keys=True)
            out.write("\n")
            out.flush()
            os.fsync(out.fileno())
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temp)
        raise


def recorded_commit(entry: dict, version: str) -> str | None:
    """The commit pin `version` names in a repository's lock `entry` (read_lock()[url]): itself for a
    commit, the commit recorded for a tag, None for a tag never fetched."""
    return version if COMMIT.fullmatch(version) else (entry.get("tags") or {}).get(version)


def _record(cache_dir: Path, url: str, tag: str | None, commit: str, sha256: str,
            class_locked: bool = False) -> None:
    """Add what was seen to the lock file (atomically; entries never change once written, but for
    a tag whose commit the class lock names: `class_locked`). Read, added to and written under
    the cache's lock: repositories are fetched in parallel threads, and another run may share
    the cache, so an entry another writer added is never lost."""
    with file_lock(_files_lock(cache_dir)):
        _record_locked(cache_dir, url, tag, commit, sha256, class_locked)


def _record_locked(cache_dir: Path, url: str, tag: str | None, commit: str, sha256: str,
                   class_locked: bool = False) -> None:
    path = Path(cache_dir) / LOCK_NAME
    data = read_lock(cache_dir)
    entry = data.setdefault(url, {})
    entry.setdefault("tags", {})
    entry.setdefault("commits", {})
    changed = False
    if tag is not None and (tag not in entry["tags"] or (class_locked and entry["tags"][tag] != commit)):
        entry["tags"][tag], changed = commit, True
    if commit not in entry["commits"]:
        entry["commits"][commit], changed = sha256, True
    if not changed:
        return
    _write_json(path, data)


def fetched(repo: dict, cache_dir: Path, *, rewrites: dict | None = None, offline: bool = False,
            timeout: float = 300, pins=None, locked: str | None = None) -> Fetched:
    """The repository's pinned commit and archive (SourceError naming it), once per run.

    `pins`: the class's set of (url, version) pairs (every host of the roster); a tag is
    checked against upstream when the set differs from the last check's (None: this
    repository's pin alone). `locked`: the commit the class lock has for this tag (None: the
    class locks none).
    """
    cache_dir = Path(cache_dir).expanduser()
    pins = frozenset(pins) if pins is not None else frozenset({(repo["url"], repo["version"])})
    key = (repo["url"], repo["version"], str(cache_dir), offline, tuple(sorted((rewrites or {}).items())), locked)
    known = _once(_results, key, repo["url"], _named(repo), lambda: _fetch_healing(
        repo, cache_dir, rewritten(repo["url"], rewrites), offline, timeout, pins_digest(pins), locked))
    # the same repository under another path in another host's .repos file
    return Fetched(repo["path"], known.url, known.version, known.commit, known.sha256, known.archive, known.notes)


def _once(results: dict, key: tuple, url: str, named: str, compute) -> "Fetched":
    """`compute()` once per run for `key`, its SourceError (prefixed with `named`) kept as well:
    hosts planned in threads wait for one another per repository URL, so a classroom of Pis
    makes one fetch, or one archive, of the same repository."""
    with _lock:
        known = results.get(key)
        repo_lock = _repo_locks.setdefault(url, threading.Lock())
    if known is None:
        with repo_lock:
            with _lock:
                known = results.get(key)
            if known is None:
                try:
                    known = compute()
                except SourceError as error:
                    known = SourceError(f"{named}: {error}")
                with _lock:
                    results[key] = known
    if isinstance(known, SourceError):
        raise known
    return known


def _fetch_healing(repo: dict, cache_dir: Path, fetch_url: str, offline: bool, timeout: float,
                   digest: str, locked: str | None = None) -> Fetched:
    """_fetch, and once more from a fresh mirror when the controller's copy is damaged."""
    mirror = mirror_path(cache_dir, repo["url"])
    with file_lock(Path(cache_dir) / "locks" / f"{mirror.name}.lock"):  # another run may fetch the same mirror
        return _fetch_healing_locked(repo, cache_dir, mirror, fetch_url, offline, timeout, digest, locked)


def _fetch_healing_locked(repo: dict, cache_dir: Path, mirror: Path, fetch_url: str, offline: bool,
                          timeout: float, digest: str, locked: str | None = None) -> Fetched:
    try:
        return _fetch(repo, cache_dir, fetch_url, offline, timeout, digest, locked=locked)
    except SourceError as error:
        damage = error.damage if isinstance(error, _MirrorDamaged) else _damage(mirror, timeout)
        if damage is None:
            raise
        if offline:
            raise SourceError(f"{error}; the controller's mirror {mirror} is damaged ({damage}) and, offline, "
                              "cannot be fetched afresh: run once with the network") from None
        aside = mirror.with_name(f"{mirror.name}.damaged-{datetime.now(timezone.utc):%Y%m%dT%H%M%S%fZ}")
        try:
            mirror.rename(aside)
        except OSError as move_error:
            raise SourceError(f"the controller's mirror {mirror} is damaged ({damage}) and cannot be moved aside "
                              f"({move_error.strerror or move_error}): delete it") from None
    note = (f"the controller's mirror of {repo['url']} was damaged ({damage}): moved aside to {aside}, "
            "fetched afresh")
    try:
        got = _fetch(repo, cache_dir, fetch_url, offline, timeout, digest, fresh_mirror=True, locked=locked)
    except SourceError as again:
        raise SourceError(f"{again} (the controller's mirror {mirror} was damaged, moved aside to {aside} and "
                          "fetched afresh, and that failed too)") from None
    return Fetched(got.path, got.url, got.version, got.commit, got.sha256, got.archive, (*got.notes, note))


def _damage(mirror: Path, timeout: float) -> str | None:
    """Why git cannot read the mirror (`git fsck`'s first error), or None: absent or sound."""
    if not mirror.exists():
        return None
    if not (mirror / "HEAD").is_file() or not (mirror / "objects").is_dir():
        return "not a git repository"
    try:
        done = subprocess.run(["git", "fsck", "--no-dangling", "--no-progress"], cwd=mirror,
                              env={**os.environ, **GIT_ENV}, capture_output=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return f"git fsck did not finish in {timeout:g} s"
    except OSError as error:
        raise SourceError(f"cannot run git on this machine: {error.strerror or error}") from None
    if done.returncode == 0:
        return None
    # fsck says "missing tree ..." on stdout, "error: ..." on stderr
    text = (done.stdout + b"\n" + done.stderr).decode("utf-8", "replace")
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    # the first line that says what is wrong (fsck ends with notices about HEAD)
    telling = [line for line in lines if re.match(r"(error|fatal|missing|broken|bad)\b", line)]
    return (telling or lines or [f"git fsck: exit {done.returncode}"])[0]


def _fetch(repo: dict, cache_dir: Path, fetch_url: str, offline: bool, timeout: float, digest: str,
           fresh_mirror: bool = False, locked: str | None = None) -> Fetched:
    url, version = repo["url"], repo["version"]
    mirror = mirror_path(cache_dir, url)
    lock = read_lock(cache_dir).get(url, {})
    class_locked = bool(locked and not COMMIT.fullmatch(version))
    if class_locked and (lock.get("tags") or {}).get(version) != locked:
        # The class lock wins over this controller's record (another class's, or the class's
        # before `roslab lock --update`): upstream is asked below, and must name the locked commit.
        lock = {**lock, "tags": {**(lock.get("tags") or {}), version: locked}}
        ask_upstream = True
    else:
        ask_upstream = fresh_mirror
    tag: str | None = None
    notes: list[str] = []
    expected = recorded_commit(lock, version)
    if not fresh_mirror:
        _refuse_damaged_mirror(mirror, expected, lock, timeout)
    if COMMIT.fullmatch(version):
        commit = version
        _fetch_commit(mirror, fetch_url, commit, offline, timeout)
    else:
        tag = version
        commit = _tag_commit(mirror, cache_dir, fetch_url, url, tag, lock, offline, ask_upstream, digest,
                             timeout, notes, class_locked)
    archive, sha256 = _verified_archive(mirror, commit, lock, cache_dir, timeout)
    with _lock:
        _record(cache_dir, url, tag, commit, sha256, class_locked)
        if tag is not None and not offline and not notes:
            _mark_checked(cache_dir, digest, url, tag)
    return Fetched(repo["path"], url, version, commit, sha256, archive, tuple(notes))


def _refuse_damaged_mirror(mirror: Path, expected: str | None, lock: dict, timeout: float) -> None:
    """Raise _MirrorDamaged when the mirror lost a commit it once held (the lock has its digest)
    and git fsck finds damage: fetching around a damaged object store would leave it damaged."""
    if (expected and expected in (lock.get("commits") or {}) and mirror.exists()
            and not _has_commit(mirror, expected, timeout)):
        damage = _damage(mirror, timeout)
        if damage:
            raise _MirrorDamaged(f"the controller's mirror {mirror} lost commit {expected}: {damage}", damage)


def _fetch_commit(mirror: Path, fetch_url: str, commit: str, offline: bool, timeout: float) -> None:
    """Make the mirror hold a pinned commit, fetching it unless it does already."""
    if _has_commit(mirror, commit, timeout):
        return
    if offline:
        raise SourceError("offline, and the controller's cache does not hold this commit "
                          f"({mirror}): run once with the network")
    try:
        _fetch_into(mirror, fetch_url, [commit], timeout)
    except SourceError:
        # a server that does not serve single commits (git's dumb HTTP): everything
        _fetch_into(mirror, fetch_url, ["+refs/heads/*:refs/heads/*", "+refs/tags/*:refs/tags/*"], timeout)
    if not _has_commit(mirror, commit, timeout):
        raise SourceError(f"upstream has no commit {commit}")


def _tag_commit(mirror: Path, cache_dir: Path, fetch_url: str, url: str, tag: str, lock: dict, offline: bool,
                ask_upstream: bool, digest: str, timeout: float, notes: list[str],
                class_locked: bool = False) -> str:
    """The commit a tag names, in the mirror: the lock's when offline or already checked with this
    set of pins, else upstream's, refused if it moved from what the class recorded (the class
    lock's commit, in `lock` already, when `class_locked`)."""
    recorded = (lock.get("tags") or {}).get(tag)
    held = bool(recorded and _has_commit(mirror, recorded, timeout))
    if offline:
        if not held or not recorded:  # held: recorded is a commit
            raise SourceError(f"offline, and the controller's cache has no commit for tag {tag!r} "
                              f"({Path(cache_dir) / LOCK_NAME}): run once with the network")
        return recorded
    if held and recorded and not ask_upstream and _tag_checked(cache_dir, digest, url, tag):
        return recorded  # checked with this set of pins: upstream is not asked again
    commit = _upstream_tag_commit(fetch_url, url, tag, recorded, held, timeout, notes)
    if recorded and recorded != commit:
        if class_locked:  # `recorded` is the class lock's commit
            raise SourceError(f"tag {tag!r} now resolves to {commit}, but the class lock (classroom.lock) locks "
                              f"{recorded}: someone moved the tag; take the new commit with "
                              "`roslab lock --update`, or pin the commit you want")
        raise SourceError(f"tag {tag!r} now resolves to {commit}, but the class recorded {recorded} "
                          f"in {Path(cache_dir) / LOCK_NAME}: someone moved the tag; pin the commit "
                          "you want (or delete the repository's entry from the lock file to accept it)")
    if not _has_commit(mirror, commit, timeout):
        _fetch_into(mirror, fetch_url, [f"+refs/tags/{tag}:refs/tags/{tag}"], timeout)
        if not _has_commit(mirror, commit, timeout):
            raise SourceError(f"tag {tag!r} ({commit}) did not arrive from upstream")
    return commit


def _upstream_tag_commit(fetch_url: str, url: str, tag: str, recorded: str | None, held: bool,
                         timeout: float, notes: list[str]) -> str:
    """The commit upstream's tag names; the lock's (with a note) when upstream cannot be reached."""
    try:
        commit, is_branch = remote_refs(fetch_url, tag, timeout)
    except SourceError as error:
        if not held:
            raise
        # Upstream is down: the lock and the mirror hold the pin, checked when it was locked.
        notes.append(f"upstream of {url} cannot be reached ({error}): tag {tag!r} is taken as the lock "
                     f"records it ({recorded}), not checked against upstream in this run")
        commit, is_branch = recorded, False
    if commit is None and is_branch:
        raise SourceError(f"field 'version': {tag!r} is a branch upstream, not a tag: pin a commit "
                          "(40 hex digits) or a tag in the .repos file")
    if commit is None:
        raise SourceError(f"upstream has no tag {tag!r}")
    return commit


def _verified_archive(mirror: Path, commit: str, lock: dict, cache_dir: Path, timeout: float) -> tuple[bytes, str]:
    """The commit's tree as a tar and its sha256, refused if the class recorded another digest for it."""
    archive = _git(["archive", "--format=tar", commit], timeout, cwd=mirror)
    sha256 = hashlib.sha256(archive).hexdigest()
    recorded_digest = (lock.get("commits") or {}).get(commit)
    if recorded_digest and recorded_digest != sha256:
        raise SourceError(f"commit {commit} now has sha256 {sha256}, but the class recorded {recorded_digest} "
                          f"in {Path(cache_dir) / LOCK_NAME}: the sources differ from what was verified "
                          "before; nothing of it is copied")
    return archive, sha256


# -- what of a fetched repository a host gets -----------------------------------------------

# Folders colcon (and rosdep, through catkin_pkg) do not look into.
IGNORE_MARKERS = ("COLCON_IGNORE", "AMENT_IGNORE", "CATKIN_IGNORE")
_selected: dict[tuple, "Fetched | SourceError"] = {}


@dataclass(frozen=True)
class SourcePackage:
    """A package in a repository's tree: its folder (relative), name and colcon build type."""

    folder: str
    name: str
    build_type: str  # "ament_cmake", "ament_python", "cmake", "catkin" (ROS 1)...
    ignored: bool = False  # below an ignore marker: colcon and rosdep do not look at it


def packages_in(mirror: Path, commit: str, timeout: float = 60) -> list[SourcePackage]:
    """The packages in `commit`: each package.xml (its <export><build_type>, catkin when none is
    given, as colcon-ros reads it) and each colcon.pkg (its "type"), not inside another package;
    those below a folder with an ignore marker (which colcon does not build) are `ignored`."""
    import xml.etree.ElementTree as ElementTree

    names = _git(["ls-tree", "-r", "--name-only", commit], timeout, cwd=mirror).decode("utf-8", "replace")
    files = names.splitlines()
    ignored = {posixpath_dirname(path) for path in files if path.rsplit("/", 1)[-1] in IGNORE_MARKERS}
    found: dict[str, SourcePackage] = {}
    for path in sorted(files, key=lambda p: (p.count("/"), p)):
        base = path.rsplit("/", 1)[-1]
        if base not in ("package.xml", "colcon.pkg"):
            continue
        folder = posixpath_dirname(path)
        parents = _parents(folder)
        if any(parent in found for parent in parents - {folder}) or folder in found:
            continue
        text = _git(["cat-file", "blob", f"{commit}:{path}"], timeout, cwd=mirror)
        if base == "package.xml":
            try:
                root = ElementTree.fromstring(text)
            except ElementTree.ParseError as error:
                raise SourceError(f"{path} is not a package manifest: {error}") from None
            name = (root.findtext("name") or "").strip()
            build_type = (root.findtext("export/build_type") or "catkin").strip()
        else:
            try:
                spec = json.loads(text)
            except ValueError as error:
                raise SourceError(f"{path} is not colcon.pkg JSON: {error}") from None
            name, build_type = str(spec.get("name") or folder.rsplit("/", 1)[-1]), str(spec.get("type") or "")
        found[folder] = SourcePackage(folder, name, build_type, bool(parents & ignored))
    return sorted(found.values(), key=lambda package: package.folder)


def posixpath_dirname(path: str) -> str:
    return path.rsplit("/", 1)[0] if "/" in path else ""


def _parents(folder: str) -> set[str]:
    """The folder and every folder above it ("" is the repository's top)."""
    parts = folder.split("/") if folder else []
    return {"/".join(parts[:i]) for i in range(len(parts) + 1)}


def for_host(item: Fetched, cache_dir: Path, skip_packages=(), timeout: float = 300) -> Fetched:
    """What a host gets of a fetched repository: its archive without the packages the profile
    skips (`skip_packages`), once per run for each set of them.

    A ROS 1 (catkin) package that would be built is a SourceError naming the repository and
    the package: a ROS 2 underlay cannot build it, so the pin is wrong (or the package is to
    be skipped). The lock keeps the sha256 of the whole commit's archive; the returned
    Fetched carries the shipped archive and its own sha256.
    """
    skip = tuple(sorted(set(skip_packages)))
    key = (item.url, item.commit, str(Path(cache_dir).expanduser()), skip)
    known = _once(_selected, key, item.url, f"repository {item.path!r} ({item.url} {item.version})",
                  lambda: _for_host(item, Path(cache_dir).expanduser(), skip, timeout))
    return Fetched(item.path, item.url, item.version, item.commit, known.sha256, known.archive, item.notes)


def _for_host(item: Fetched, cache_dir: Path, skip: tuple[str, ...], timeout: float) -> Fetched:
    mirror = mirror_path(cache_dir, item.url)
    packages = packages_in(mirror, item.commit, timeout)
    ros1 = [package for package in packages
            if package.name not in skip and package.build_type == "catkin" and not package.ignored]
    if ros1:
        package = ros1[0]
        raise SourceError(
            f"package {package.name} ({package.folder or '.'}/package.xml) is a ROS 1 (catkin) package, "
            "which a ROS 2 underlay cannot build: pin the repository's ROS 2 code"
            + (", or skip the package (skip_packages)" if len(packages) > 1 else ""))
    excluded = [package.folder for package in packages if package.name in skip and package.folder]
    if not excluded:
        return item
    archive = _git(["archive", "--format=tar", item.commit, "--", ".",
                    *(f":(exclude){folder}" for folder in excluded)], timeout, cwd=mirror)
    return Fetched(item.path, item.url, item.version, item.commit, hashlib.sha256(archive).hexdigest(), archive,
                   item.notes)
