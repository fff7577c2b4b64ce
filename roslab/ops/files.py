"""Files on a host: roslab's managed blocks, files moved aside, a file's age, and files written
beside their place and renamed over it (facts and operations side by side, roslab.ops)."""

from __future__ import annotations

import os
import posixpath
import secrets
import time
import weakref
from io import StringIO

from pyinfra import host, logger, state
from pyinfra.api import FactBase, QuoteString, StringCommand, operation
from pyinfra.api.util import format_text
from pyinfra.context import ctx_host
from pyinfra.facts.files import File, FileContents, Link
from pyinfra.operations.util.files import generate_color_diff
from typing_extensions import override

from roslab.probe import read
from roslab.quoting import shell_word
from roslab.remote_files import OwnedFileUpload


def _log_diff(path: str, current_lines: list[str] | None, desired_lines: list[str]) -> None:
    """Print a unified diff like files.put does under ``--diff``."""
    if not state.config.DIFF:
        return
    verb = "create" if current_lines is None else "modify"
    host.log(f"Will {verb} {format_text(path, bold=True)}", logger.info)
    for line in generate_color_diff(
        [line + "\n" for line in current_lines or []], [line + "\n" for line in desired_lines]
    ):
        logger.info("  %s", line)
    logger.info("")


def _upload_text(path: str, lines: list[str], user=None, group=None, mode=None):
    """The upload that replaces `path` with `lines`, with its owner and mode from its first
    byte (roslab.remote_files: a chown/chmod after it would follow a link put there)."""
    yield OwnedFileUpload(
        StringIO("".join(line + "\n" for line in lines)), path, user=user, group=group, mode=mode,
    )


# --- marked blocks ---------------------------------------------------------------

# One name per pyinfra run for the backups a repair leaves beside a file.
BACKUP_SUFFIX = ".roslab-" + time.strftime("%Y%m%d-%H%M%S")
# (path, label) of the repairs already reported, per host of this run.
_REPAIRS_REPORTED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def block_markers(label: str) -> tuple[str, str]:
    return (f"# BEGIN roslab managed block ({label})", f"# END roslab managed block ({label})")


def _scan_markers(lines: list[str], begin: str, end: str):
    """Marker kinds by line index, the (begin, end) pairs in order, and the lone markers.

    An end closes the nearest open begin before it; a begin that another begin follows
    before any end, and an end with no open begin, are lone markers.
    """
    kinds: dict[int, str] = {}
    for index, line in enumerate(lines):
        if line.strip() == begin:
            kinds[index] = "begin"
        elif line.strip() == end:
            kinds[index] = "end"
    pairs: list[tuple[int, int]] = []
    lone: list[int] = []
    open_begin = None
    for index, kind in kinds.items():
        if kind == "begin":
            if open_begin is not None:
                lone.append(open_begin)
            open_begin = index
        elif open_begin is None:
            lone.append(index)
        else:
            pairs.append((open_begin, index))
            open_begin = None
    if open_begin is not None:
        lone.append(open_begin)
    return kinds, pairs, sorted(lone)


def block_repair(lines: list[str], label: str, content: str) -> tuple[list[str], str | None]:
    """`lines` with one roslab block for `label` holding `content`, and what was repaired.

    The usual cases repair nothing (None): no block yet (appended after the user's lines)
    or one begin/end pair (replaced in place). Any other arrangement of markers (a
    deleted end or begin marker, a second begin, two blocks, an end before its begin) is
    repaired without dropping a single line outside the markers:

    - the lines between a begin and its end are roslab's (as in the usual case) and go;
    - a lone marker goes, and with it the lines beside it only when they are exactly
      `content` (the old block, on the side the missing marker would have closed);
    - every other line stays where it is, and the one block goes where the first marker was.
    """
    begin, end = block_markers(label)
    body = content.rstrip("\n").split("\n")
    block = [begin, *body, end]
    kinds, pairs, lone = _scan_markers(lines, begin, end)
    if not kinds:
        separator = [""] if lines and lines[-1].strip() else []
        return lines + separator + block, None
    if len(pairs) == 1 and not lone:
        start, stop = pairs[0]
        return lines[:start] + block + lines[stop + 1 :], None

    drop: set[int] = set()
    for start, stop in pairs:
        drop.update(range(start, stop + 1))

    def is_old_block(first: int) -> bool:
        span = range(first, first + len(body))
        return (first >= 0 and span.stop <= len(lines) and not drop.intersection(span)
                and not kinds.keys() & set(span)
                and [line.rstrip() for line in lines[first : span.stop]] == [line.rstrip() for line in body])

    for index in lone:
        drop.add(index)
        first = index + 1 if kinds[index] == "begin" else index - len(body)
        if is_old_block(first):
            drop.update(range(first, first + len(body)))
    at = min(kinds)
    repaired = []
    for index, line in enumerate(lines):
        if index == at:
            repaired.extend(block)
        if index not in drop:
            repaired.append(line)
    begins = sum(kind == "begin" for kind in kinds.values())
    ends = len(kinds) - begins
    found = ", ".join(f"{'begin' if kinds[i] == 'begin' else 'end'} at line {i + 1}" for i in sorted(kinds))
    return repaired, f"{begins} begin and {ends} end markers ({found}), expected one pair"


def with_block(lines: list[str], label: str, content: str) -> list[str]:
    """`lines` with roslab's block for `label` holding `content` (see `block_repair`)."""
    return block_repair(lines, label, content)[0]


@operation()
def managed_block(
    path: str,
    content: str,
    label: str,
    user: str | None = None,
    group: str | None = None,
    mode: str | None = None,
):
    """
    Ensure a file holds one roslab-managed block between markers; the rest stays untouched.

    + path: the file to edit (created when missing)
    + content: the text between the markers
    + label: names the block in its markers, ``# BEGIN roslab managed block (<label>)``
    + user/group/mode: owner and mode for a file this creates; an existing file keeps its own

    Unlike ``files.block``, this prints a unified diff of the file under ``--diff``.
    Markers someone edited (a deleted end marker, a duplicated block, ...) are repaired
    without dropping any line outside the block (see ``block_repair``): the file is first
    copied to ``<path>.roslab-<date>-<time>`` and the repair is logged in one line.

    **Example:**

    .. code:: python

        managed_block(
            name="Ensure ~/.bashrc sources ROS 2",
            path="/home/student/.bashrc",
            content="source /opt/ros/jazzy/setup.bash",
            label="ROS 2 environment",
            user="student",
        )
    """
    current = host.get_fact(FileContents, path=path)
    desired, repaired = block_repair(current or [], label, content)
    if current == desired:
        host.noop(f"block ({label}) in {path} is already up to date")
        return

    existing = host.get_fact(File, path=path) if current is not None else None
    if existing:
        user, group, mode = existing["user"], existing["group"], f"{existing['mode']:03d}"
    if repaired:
        backup = path + BACKUP_SUFFIX
        # Once per host and file, whether pyinfra calls this when planning, executing or both.
        reported = _REPAIRS_REPORTED.setdefault(ctx_host.get(), set())
        if (path, label) not in reported:
            reported.add((path, label))
            logger.warning(
                f"{host.print_prefix}roslab repairs the markers of the block ({label}) in {path}: "
                f"{repaired}; no line outside the block is dropped, the file is kept as {backup}"
            )
        yield StringCommand("cp -p --", QuoteString(path), QuoteString(backup))
    _log_diff(path, current, desired)
    yield from _upload_text(path, desired, user=user, group=group, mode=mode)


def managed_block_reads(path: str) -> list:
    """What `managed_block` reads on a file it need not change (roslab.probe)."""
    return [read(FileContents, path=path)]


@operation()
def files_moved_aside(paths: list[str], backup_dir: str, only_regular_files: bool = False):
    """
    Ensure files are gone from their place, kept as numbered backups in `backup_dir`.

    + paths: the files that must not be where they are
    + backup_dir: where they go (``mv --backup=numbered`` never overwrites an older copy)
    + only_regular_files: leave symlinks in place (a package's own symlink is not a leftover)
    """
    moved = False
    for path in paths:
        # File is False for a symlink, Link is False for a regular file; both None if missing.
        if not host.get_fact(File, path=path) and (
            only_regular_files or not host.get_fact(Link, path=path)
        ):
            continue
        moved = True
        if state.config.DIFF:
            host.log(f"Will move {format_text(path, bold=True)} to {backup_dir}", logger.info)
        yield StringCommand("mkdir -p", QuoteString(backup_dir))
        yield StringCommand("mv --backup=numbered", QuoteString(path), QuoteString(backup_dir))
    if not moved:
        host.noop(f"none of {', '.join(paths)} exists")


def files_moved_aside_reads(paths: list[str]) -> list:
    """What `files_moved_aside` reads (roslab.probe)."""
    return [item for path in paths for item in (read(File, path=path), read(Link, path=path))]


class FileAge(FactBase):
    """
    Returns how many seconds ago a file was last modified, by the host's clock, or ``None``
    when the file does not exist.
    """

    @override
    def command(self, path: str) -> StringCommand:
        return StringCommand(
            "if [ -e",
            QuoteString(path),
            "]; then echo $(( $(date +%s) - $(stat -c %Y",
            QuoteString(path),
            ") )); fi",
        )

    @override
    def process(self, output):
        for line in output:
            line = line.strip()
            if line.lstrip("-").isdigit():
                return int(line)
        return None


# This controller run's mark on the files it writes beside a record before renaming them over it:
# two runs at once never write through the same temporary name (each run also holds the host's
# run lock: roslab/ssh/run_lock.py).
RUN_MARK = f"{os.getpid()}-{secrets.token_hex(4)}"


def run_temporary(path: str) -> str:
    """Where this run writes `path`'s new content before it is renamed over it."""
    return f"{path}.roslab-new-{RUN_MARK}"


def durably_renamed(new: str, path: str, *also_synced: str) -> str:
    """Shell: `new` (and `also_synced`, a backup) reach the disk, `new` is renamed over `path`
    and the rename reaches the disk too (the directory synced): a power cut at any moment
    leaves the old file or the new one, never half of one, on a Pi's FAT partition as anywhere."""
    directory = posixpath.dirname(path) or "/"
    synced = " ".join(shell_word(each) for each in (new, *also_synced))
    # The folder's sync is best effort (a filesystem that cannot sync a folder has nothing more
    # to give); the rename has happened by then, so it does not fail the step.
    return (f"sync -- {synced} && mv -f -- {shell_word(new)} {shell_word(path)} && "
            f"{{ sync -- {shell_word(directory)} 2>/dev/null || true; }}")
