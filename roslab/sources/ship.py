"""One host builds a group's underlay; the controller ships its install tree to the others.

pyinfra runs each operation on every host before the next, so the group's builder runs colcon
(roslab.sources.underlay.built) in one operation and the receivers get the result in a later one
(`received`): its first command, on the controller, makes sure the controller's cache holds the
build (`ensure_cached`: packed on the builder as a tar, checked by sha256 on both ends, kept
under `sources_cache_dir/underlays/<digest>`), then the tar goes to the host, is checked again
by sha256 there, extracted into the same install path the builder built it in
(`install-<digest>`) and made the `install` in one rename, the last good install kept until
then (as a build does). A later run, or a new host of the group, receives from the cache:
nothing is built again.

A builder whose build failed fails the group's receivers with one line naming the builder and
the package; the other groups go on.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import posixpath
import re
import shlex
import tempfile
import weakref
from pathlib import Path

from pyinfra import host, logger
from pyinfra.api import FileUploadCommand, FunctionCommand, StringCommand, operation
from pyinfra.api.arguments import CONNECTOR_ARGUMENT_KEYS

from roslab.controller_files import file_sha256
from roslab.sources.underlay import ARCHIVE_DIR, ORIGIN, _as_user, keep_in_use, origin_line, switch_script
from roslab.sources.groups import short
from roslab.connections import connection_lost
from roslab.ros.workspace import STATE_DIR_NAME, _write_stamp

CACHE_FOLDER = "underlays"
# What a packed tree's install folder may be called (the builder says it; checked here).
SLOT = re.compile(r"install-[A-Za-z0-9]{1,64}", re.ASCII)
DIGEST = re.compile(r"[0-9a-f]{64}", re.ASCII)
HOST_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9.-]{0,252}", re.ASCII)

# The builds planned in a run: state -> {digest: (builder name, the build's OperationMeta, cache group)}.
_builds: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
# The digests some host of a run needs: state -> set; never pruned from the cache in that run.
_wanted: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
# Packed builds kept per cache group (the same repositories, distro, architecture and install
# path at other pins): the newest few, so a pin moved back is shipped, not rebuilt.
KEEP_PER_GROUP = 3
_pull_locks: dict[str, object] = {}


class ShipError(Exception):
    """Why a host cannot receive its group's underlay (one line, naming the builder)."""


def cache_paths(cache_dir: Path, digest: str) -> tuple[Path, Path]:
    """(the packed tree, its record) of a digest in the controller's cache."""
    if not DIGEST.fullmatch(digest):
        raise ValueError(f"not an underlay digest: {digest!r}")
    folder = Path(cache_dir).expanduser() / CACHE_FOLDER
    return folder / f"{digest}.tar.gz", folder / f"{digest}.json"


_verified: dict[tuple, dict] = {}


def cached(cache_dir: Path, digest: str) -> dict | None:
    """The cache's record of a digest's build ({"builder", "slot", "sha256", "bytes"}) when the
    packed tree is there with that sha256; None otherwise (a damaged entry is ignored: the
    group builds again)."""
    tar, record = cache_paths(cache_dir, digest)
    try:
        meta = json.loads(record.read_text())
        stat = tar.stat()
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or not SLOT.fullmatch(str(meta.get("slot"))) \
            or not HOST_NAME.fullmatch(str(meta.get("builder"))) or not DIGEST.fullmatch(str(meta.get("sha256"))):
        return None
    key = (str(tar), stat.st_size, stat.st_mtime_ns, meta["sha256"])
    if key not in _verified:
        if file_sha256(tar) != meta["sha256"]:
            return None
        _verified[key] = meta
    return dict(meta)


def note_build(state, digest: str, builder: str, op_meta, group: str = "") -> None:
    """Record that `builder` builds `digest` in this run (its build operation's meta; `group`:
    its cache group, roslab.sources.groups.cache_group). Where two hosts hold the build
    already, the first noted (roster order, as receivers choose) is kept."""
    _builds.setdefault(state, {}).setdefault(digest, (builder, op_meta, group))


def note_wanted(state, digest: str) -> None:
    """Record that a host of this run needs `digest`: the cache keeps it whatever its age."""
    _wanted.setdefault(state, set()).add(digest)


def planned_builder(state, digest: str) -> str | None:
    entry = _builds.get(state, {}).get(digest)
    return entry[0] if entry else None


def pack_script(underlay_dir: str, stamp: str) -> str:
    """Run on the builder: its finished build as a gzip'd tar, base64, after its install folder's
    name and sha256."""
    stamp_file = posixpath.join(STATE_DIR_NAME, "build.sha256")
    return "\n".join([
        f"cd {shlex.quote(underlay_dir)} || exit 1",
        f'[ "$(cat {stamp_file} 2>/dev/null)" = {shlex.quote(stamp)} ] || '
        '{ echo "roslab: underlay: it holds no finished build of these sources" >&2; exit 1; }',
        'slot=$(readlink install)',
        'case "$slot" in install-*) ;; *) echo "roslab: underlay: install is not a roslab build" >&2; exit 1 ;; esac',
        't=$(mktemp) || exit 1',
        'if ! tar --numeric-owner -C "$slot" -czf "$t" .; then rm -f "$t"; exit 1; fi',
        'echo "slot $slot"',
        'echo "sha256 $(sha256sum < "$t" | cut -c1-64)"',
        'echo "## data"',
        'base64 "$t"',
        'rm -f "$t"',
    ])


def parse_pack(lines: list[str]) -> tuple[str, str, bytes]:
    """(slot, sha256, the tar's bytes) from the pack script's output; ShipError when it is not
    a whole, intact tree."""
    slot = sha = None
    data: list[str] = []
    in_data = False
    for line in lines:
        if in_data:
            data.append(line.strip())
        elif line.startswith("slot "):
            slot = line[5:].strip()
        elif line.startswith("sha256 "):
            sha = line[7:].strip()
        elif line.strip() == "## data":
            in_data = True
    if not slot or not SLOT.fullmatch(slot) or not sha or not DIGEST.fullmatch(sha) or not in_data:
        raise ShipError("its packed build came back incomplete")
    try:
        body = base64.b64decode("".join(data), validate=True)
    except (binascii.Error, ValueError):
        raise ShipError("its packed build came back damaged (not base64)") from None
    if hashlib.sha256(body).hexdigest() != sha:
        raise ShipError("its packed build's sha256 differs from what the builder computed")
    return slot, sha, body


def store(cache_dir: Path, digest: str, builder: str, slot: str, sha: str, body: bytes, group: str = "") -> dict:
    """Keep a packed build in the cache: the tar first, then its record (each renamed into place)."""
    tar, record = cache_paths(cache_dir, digest)
    tar.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    meta = {"builder": builder, "slot": slot, "sha256": sha, "bytes": len(body), **({"group": group} if group else {})}
    for path, content in ((tar, body), (record, (json.dumps(meta, indent=2) + "\n").encode())):
        handle, temp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
        with os.fdopen(handle, "wb") as stream:
            stream.write(content)
        os.replace(temp, path)
    return meta


def pruned(cache_dir: Path, group: str, in_use=(), keep: int = KEEP_PER_GROUP) -> list[str]:
    """Remove all but the `keep` newest packed builds of `group` from the cache, never one in
    `in_use` (a host of the run needs it); the digests removed. Records without a group (kept
    before groups were recorded) are left alone."""
    folder = Path(cache_dir).expanduser() / CACHE_FOLDER
    members = []
    for record in folder.glob("*.json"):
        try:
            meta, stored = json.loads(record.read_text()), record.stat().st_mtime_ns
        except (OSError, ValueError):
            continue
        if isinstance(meta, dict) and meta.get("group") == group and DIGEST.fullmatch(record.stem):
            members.append((stored, record.stem))
    removed = []
    for _, digest in sorted(members, reverse=True)[keep:]:
        if digest in in_use:
            continue
        tar, record = cache_paths(cache_dir, digest)
        for path in (record, tar, ship_record(cache_dir, digest)):  # the record first: no record, no entry
            path.unlink(missing_ok=True)
        removed.append(digest)
    return removed


def _lock_for(digest: str):
    import gevent.lock

    return _pull_locks.setdefault(digest, gevent.lock.RLock())


def build_failure(op_meta) -> str:
    """The builder's own line about its failed build (the package and its first error)."""
    lines = []
    try:
        lines = list(op_meta.stderr_lines)
    except Exception:  # noqa: BLE001 - an operation that never ran has no output
        lines = []
    for line in lines:
        if "roslab: underlay: package" in line:
            return line.split("roslab: underlay: ", 1)[1].split("; the last good install", 1)[0]
    return "its build failed (its own line says why)"


def ensure_cached(state, host, digest: str, builder: str, cache_dir: str, underlay_dir: str,
                  stamp: str) -> bool:
    """On the controller, before a receiver's (`host`'s) upload: the cache holds `digest`'s build, packed
    on `builder` now if it does not yet. False (with one line) when it cannot."""
    try:
        with _lock_for(digest):
            if cached(Path(cache_dir), digest):
                return True
            _pull(state, digest, builder, Path(cache_dir), underlay_dir, stamp)
            return True
    except ShipError as error:
        host.log_styled(f"roslab: underlay: {error}", fg="red", log_func=logger.error)
        return False


def builder_lost(source) -> bool:
    """Whether the builder's connection was made and has ended (its power cut, its cable pulled):
    it did not fail to build, it went away (roslab.reporting.summary says the same in its line)."""
    return connection_lost(source)


def _pull(state, digest: str, builder: str, cache_dir: Path, underlay_dir: str, stamp: str) -> None:
    entry = _builds.get(state, {}).get(digest)
    source = state.inventory.get_host(builder) if builder else None
    if entry is None or source is None:
        raise ShipError(f"its group's builder {builder} did not build it in this run (stopped before its "
                        "build: its own line says why)")
    op_meta = entry[1]
    # (a build that had nothing to do may be left incomplete by pyinfra: only a failure counts)
    if source in state.failed_hosts and builder_lost(source):
        raise ShipError(f"its group's builder {builder} was lost before it finished building it (it stopped "
                        "answering: powered off, rebooted or off the network; nothing failed to compile); "
                        "this host receives its underlay from there: run again once the builder answers")
    if source in state.failed_hosts or (op_meta.is_complete() and not op_meta.did_succeed()):
        raise ShipError(f"its group's builder {builder} failed to build it: {build_failure(op_meta)}; "
                        "this host receives its underlay from there")
    op_data = state.get_op_data_for_host(source, op_meta._hash)
    arguments = {key: op_data.global_arguments[key] for key in CONNECTOR_ARGUMENT_KEYS
                 if key in op_data.global_arguments}
    ok, output = source.run_shell_command(StringCommand("sh", "-c", shlex.quote(pack_script(underlay_dir, stamp))),
                                          **arguments)
    if not ok:
        said = [line for line in output.stderr_lines if line.strip()]
        raise ShipError(f"packing the build on {builder} failed: {said[-1].strip() if said else 'no message'}")
    try:
        slot, sha, body = parse_pack(output.stdout_lines)
    except ShipError as error:
        raise ShipError(f"from {builder}: {error}") from None
    group = entry[2]
    store(cache_dir, digest, builder, slot, sha, body, group)
    if group:
        gone = pruned(cache_dir, group, in_use=_wanted.get(state, set()) | {digest})
        if gone:
            logger.info("roslab: underlay cache: %d older build(s) of this group removed (the newest %d kept)",
                        len(gone), KEEP_PER_GROUP)


def ship_record(cache_dir: Path, digest: str) -> Path:
    """The small file each receiver gets beside the tar: the install folder's name and the sha256."""
    return cache_paths(cache_dir, digest)[1].with_suffix(".ship")


def _write_ship_record(state, host, cache_dir: str, digest: str) -> bool:
    meta = cached(Path(cache_dir), digest)
    if meta is None:
        host.log_styled("roslab: underlay: the cached build is gone or damaged", fg="red", log_func=logger.error)
        return False
    path = ship_record(Path(cache_dir), digest)
    path.write_text(f"slot={meta['slot']}\nsha256={meta['sha256']}\n")
    return True


def _printf_safe(text: str) -> str:
    """`text` inside a double-quoted shell string as itself: no $, `, \\ or " expands there."""
    return "".join("\\" + char if char in '$`\\"' else char for char in text)


def receive_script(underlay_dir: str, tar: str, record: str, stamp: str, digest: str, builder: str) -> str:
    """Run as the login user: the shipped tree into its install folder, then `install` switched
    to it (one rename); the build stamp and its origin written last."""
    stamp_file = posixpath.join(STATE_DIR_NAME, "build.sha256")
    return "\n".join([
        f"cd {shlex.quote(underlay_dir)} || exit 1",
        f"mkdir -p {STATE_DIR_NAME}",
        f"slot=$(sed -n 's/^slot=\\(install-[A-Za-z0-9]\\{{1,64\\}}\\)$/\\1/p' {shlex.quote(record)})",
        '[ -n "$slot" ] || { echo "roslab: underlay: the shipped build names no install folder" >&2; exit 1; }',
        f"rm -f {stamp_file}",  # no stamp while the tree changes: an interrupted receive is tried again
        *keep_in_use('"$slot"'),
        'rm -rf "$slot.roslab-new" && mkdir "$slot.roslab-new" || exit 1',
        # tar's own complaints are kept back: one line says what happened, naming the folder
        f'if ! said=$(tar -xzf {shlex.quote(tar)} --no-same-owner -C "$slot.roslab-new" 2>&1 >/dev/null); then',
        '  rm -rf "$slot.roslab-new"',
        '  case "$said" in',
        f'  *"No space left on device"*) echo "roslab: underlay: the disk holding {_printf_safe(underlay_dir)} is full '
        f'(the build shipped from {builder} did not fit; $(df -Ph . | awk \'NR == 2 {{print $4}}\') free there): '
        'free space there and run again; the last good install stays in use" >&2;;',
        f'  *) echo "roslab: underlay: the build shipped from {builder} does not extract into '
        f'{_printf_safe(underlay_dir)} ($(printf \'%s\' "$said" | head -n 1 | cut -c 1-200)); the last good '
        'install stays in use" >&2;;',
        "  esac",
        "  exit 1",
        "fi",
        'rm -rf "$slot" && mv "$slot.roslab-new" "$slot" || exit 1',
        *switch_script('"$slot"'),
        _write_stamp(stamp_file, stamp),
        _write_stamp(ORIGIN, origin_line(digest, builder)),
    ])


@operation()
def received(underlay_dir: str, digest: str, stamp: str, user: str, cache_dir: str, builder: str):
    """
    Install a group's underlay, built on another host, from the controller's cache.

    + underlay_dir: the underlay on this host (absolute; the same path as on the builder)
    + digest: the group's input digest (roslab.sources.groups.input_digest)
    + stamp: the build stamp it is recorded with (roslab.sources.underlay.build_stamp)
    + user: the login user, who owns the underlay
    + cache_dir: the controller's sources_cache_dir
    + builder: the host that builds it (or built it: the cache's record)

    A host already holding it is a no-op. The tar is checked by sha256 on the controller and on
    the host; a failed receive leaves the last good install in use.
    """
    from roslab.ros.workspace import WorkspaceStamps

    stamps = host.get_fact(WorkspaceStamps, workspace_dir=underlay_dir)
    if stamps.get("build") == stamp and stamps.get("installed"):
        host.noop(f"{underlay_dir} holds the underlay {short(digest)} already")
        return
    tar_local, _record = cache_paths(Path(cache_dir), digest)
    record_local = ship_record(Path(cache_dir), digest)
    tar = f"{ARCHIVE_DIR}/underlay-{digest}.tar.gz"
    record = f"{ARCHIVE_DIR}/underlay-{digest}.ship"
    yield FunctionCommand(ensure_cached, (digest, builder, cache_dir, underlay_dir, stamp), {})
    yield FunctionCommand(_write_ship_record, (cache_dir, digest), {})
    yield StringCommand("install", "-d", "-m", "755", ARCHIVE_DIR)
    yield FileUploadCommand(str(tar_local), tar, remote_temp_filename=host.get_temp_filename(tar))
    yield FileUploadCommand(str(record_local), record, remote_temp_filename=host.get_temp_filename(record))
    check = (f"sha=$(sed -n 's/^sha256=\\([0-9a-f]\\{{64\\}}\\)$/\\1/p' {record}); "
             f'if [ -z "$sha" ] || ! printf "%s  %s\\n" "$sha" {tar} | sha256sum -c --status; then '
             f"rm -f {tar} {record}; echo 'roslab: underlay: the build shipped from {builder} did not arrive "
             "intact (sha256)' >&2; exit 1; fi")
    yield StringCommand("sh", "-c", shlex.quote(check))
    yield _as_user(user, receive_script(underlay_dir, tar, record, stamp, digest, builder))
    yield StringCommand("rm", "-f", tar, record)
