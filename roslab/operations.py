"""pyinfra operations roslab needs beyond pyinfra's own, in pyinfra's style.

Each operation is named for the end state, reads facts, and either yields the commands
that reach that state or says with ``host.noop`` why nothing needs doing. Facts are read
again when an operation executes, so an operation that follows another one sees its effect.
"""

from __future__ import annotations

import re
import shlex
import time
import weakref
from io import StringIO

from pyinfra import host, logger, state
from pyinfra.api import QuoteString, StringCommand, operation
from pyinfra.api.util import format_text
from pyinfra.context import ctx_host
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import File, FileContents, Link
from pyinfra.facts.server import Locales, Which
from pyinfra.operations.util.files import generate_color_diff

from roslab.facts import FileAge, apt_lock_options
from roslab.probe import read
from roslab.quoting import apt_arguments, deb822_value, sources_list_word
from roslab.remote_files import OwnedFileUpload

# Ubuntu touches this after every successful `apt-get update`; Debian does not, so we do.
APT_UPDATE_STAMP = "/var/lib/apt/periodic/update-success-stamp"
ROSDEP_SOURCES_LIST = "/etc/ros/rosdep/sources.list.d/20-default.list"
# rosdep rewrites this index on every `rosdep update`: its age is the cache's age.
ROSDEP_CACHE_INDEX = ".ros/rosdep/sources.cache/index"


# Keep the host's edited configuration files when a package brings new ones (never ask).
DPKG_KEEP_CONFFILES = "-o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold"
# apt >= 2.1.16 (Ubuntu 22.04 has 2.4): `update` exits non-zero when any index failed to
# download, instead of 0 with "W: Failed to fetch" and the old lists kept.
APT_UPDATE_FAIL_ON_ANY_ERROR = "-o APT::Update::Error-Mode=any"


def as_user(user: str) -> dict:
    """pyinfra arguments that run an operation or fact as `user` (rosdep and colcon refuse root)."""
    return {"_sudo": True, "_sudo_user": user}


def apt_install_options(lock_timeout: int) -> str:
    """`extra_install_args`/`extra_uninstall_args` for pyinfra's apt.packages.

    The lock wait, then `--`: apt.packages appends the package names after these
    arguments, so none of them can ever be read as an option (`-oAPT::...`).
    """
    return f"{apt_lock_options(lock_timeout)} --"


def apt_get(command: str, lock_timeout: int) -> str:
    """An apt-get command line that waits (bounded) for the dpkg lock instead of failing.

    `command` is roslab's own text (a subcommand and options); values go after it quoted,
    behind `--` for package names.
    """
    return f"DEBIAN_FRONTEND=noninteractive apt-get -y {apt_lock_options(lock_timeout)} {command}"


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


# --- apt sources -----------------------------------------------------------------


def _is_release_suite(suite: str, codename: str) -> bool:
    return suite == codename or suite.startswith(f"{codename}-")


def _source_word(value: str) -> str:
    """A suite or component roslab adds to an apt source, checked for both layouts.

    Only roslab's additions go through here: the host's own words are written back as
    they were (refusing them would stop the whole run over one host's file).
    """
    return deb822_value(sources_list_word(value))


def with_deb822_suites(
    lines: list[str], codename: str, components: list[str], suites: list[str]
) -> list[str]:
    """Ubuntu deb822 sources (`ubuntu.sources`) with `components` and `<codename>-<suites>`.

    Only stanzas for the host's release are touched; everything else is kept verbatim.
    """
    out = list(lines)
    stanza: list[int] = []  # indexes of the current stanza's lines

    def fix(stanza_indexes: list[int]) -> None:
        fields = {}
        for i in stanza_indexes:
            match = re.match(r"^([A-Za-z-]+):\s*(.*)$", out[i])
            if match:
                fields[match.group(1).lower()] = (i, match.group(2).split())
        if "suites" not in fields or fields.get("enabled", (0, ["yes"]))[1] == ["no"]:
            return
        suites_at, current_suites = fields["suites"]
        if not any(_is_release_suite(s, codename) for s in current_suites):
            return
        if "components" in fields:
            comp_at, current_components = fields["components"]
            added = [_source_word(c) for c in components if c not in current_components]
            if added:
                out[comp_at] = "Components: " + " ".join(current_components + added)
        if codename in current_suites:
            extra = [f"{codename}-{s}" for s in suites]
            added = [_source_word(s) for s in extra if s not in current_suites]
            if added:
                out[suites_at] = "Suites: " + " ".join(current_suites + added)

    for index, line in enumerate(lines):
        if line.strip():
            if not line.lstrip().startswith("#"):
                stanza.append(index)
        else:
            fix(stanza)
            stanza = []
    fix(stanza)
    return out


ONE_LINE_SOURCE = re.compile(
    r"^(?P<type>deb(?:-src)?)\s+(?P<options>\[[^\]]*\]\s+)?(?P<uri>\S+)\s+(?P<suite>\S+)"
    r"(?P<components>(?:\s+\S+)*)\s*$"
)


def with_one_line_suites(
    lines: list[str], codename: str, components: list[str], suites: list[str]
) -> list[str]:
    """One-line `sources.list` with `components` and `<codename>-<suites>` lines added.

    apt reads everything from a `#` on as a comment: a line's comment is kept at its end.
    """
    parsed = []
    for line in lines:
        code, hash_sign, comment = line.partition("#")
        parsed.append((ONE_LINE_SOURCE.match(code), hash_sign + comment))
    present = {(m["type"], m["uri"], m["suite"]) for m, _ in parsed if m}
    out: list[str] = []
    for line, (match, comment) in zip(lines, parsed):
        if not match or not _is_release_suite(match["suite"], codename):
            out.append(line)
            continue
        current = match["components"].split()
        wanted = current + [_source_word(c) for c in components if c not in current]
        prefix = f"{match['type']} {match['options'] or ''}{match['uri']}"
        tail = f" {comment}" if comment else ""
        out.append(f"{prefix} {match['suite']} {' '.join(wanted)}{tail}" if wanted != current else line)
        if match["suite"] == codename:
            for suite in suites:
                suite = _source_word(f"{codename}-{suite}")
                key = (match["type"], match["uri"], suite)
                if key not in present:
                    present.add(key)
                    out.append(f"{prefix} {suite} {' '.join(wanted)}")
    return out


UBUNTU_SOURCE_FILES = (
    ("/etc/apt/sources.list.d/ubuntu.sources", with_deb822_suites),
    ("/etc/apt/sources.list", with_one_line_suites),
)


@operation()
def ubuntu_apt_sources(codename: str, components: list[str], suites: list[str]):
    """
    Ensure the host's own Ubuntu apt sources enable extra components and suites.

    + codename: the host's Ubuntu codename, e.g. ``noble``
    + components: components every release stanza must list, e.g. ``["universe"]``
    + suites: suffixes of suites to add beside the release, e.g. ``["updates", "backports"]``

    Edits whichever layout the host has, in place and keeping its URIs: deb822
    ``ubuntu.sources`` (24.04) and the one-line ``sources.list`` (22.04).
    """
    changed = False
    for path, edit in UBUNTU_SOURCE_FILES:
        current = host.get_fact(FileContents, path=path)
        if current is None:
            continue
        desired = edit(current, codename, components, suites)
        if desired != current:
            changed = True
            _log_diff(path, current, desired)
            yield from _upload_text(path, desired, user="root", group="root", mode="644")

    if not changed:
        wanted = " ".join([*components, *(f"{codename}-{s}" for s in suites)])
        host.noop(f"Ubuntu apt sources already enable {wanted}")


def ubuntu_apt_sources_reads() -> list:
    """What `ubuntu_apt_sources` reads (roslab.probe)."""
    return [read(FileContents, path=path) for path, _ in UBUNTU_SOURCE_FILES]


# An update that runs longer than this after the lock wait is stuck, not slow: apt can wait
# forever on a proxy that dropped a pipelined request. Killed, it fails the host, and the
# next run updates again.
APT_UPDATE_MAX_SECONDS = 1200


def reporting_a_signal(command: str, what: str) -> str:
    """`command`, then a line on stderr when it was killed by a signal, with the signal and
    the exit status: a killed command prints no error of its own, only whatever it printed
    last (e.g. debconf's "delaying package configuration"), which is not the reason.
    The command keeps its exit status."""
    report = (f"echo \"roslab: {what} was killed by signal SIG$(kill -l \"$status\" 2>/dev/null "
              f"|| echo \"$((status - 128))\") (exit status $status)\" >&2")
    return f"{command}; status=$?; if [ \"$status\" -gt 128 ]; then {report}; fi; exit \"$status\""


def apt_update_command(lock_timeout: int) -> str:
    """`apt-get update` that fails on any failed download and marks the lists fresh only then.

    The stamp goes first: a failed or interrupted update leaves the lists stale, so the
    next run updates again instead of trusting lists that lack a source for a day. On a
    failure apt's E:/W: lines are reported as one line, not its whole progress output; an
    update still running `APT_UPDATE_MAX_SECONDS` after the lock wait is stopped and said so.
    """
    stamp = shlex.quote(APT_UPDATE_STAMP)
    limit = int(lock_timeout) + APT_UPDATE_MAX_SECONDS
    update = apt_get(f"{APT_UPDATE_FAIL_ON_ANY_ERROR} update", lock_timeout)
    return (
        f"rm -f {stamp} && if out=$(timeout -k 30 {limit} env {update} 2>&1); "
        f"then mkdir -p /var/lib/apt/periodic && touch {stamp}; "
        "else status=$?; if [ $status -eq 124 ] || [ $status -eq 137 ]; then "
        f"echo \"roslab: apt-get update was stopped after {limit} s without finishing (a stuck download); "
        "the lists stay stale and the next run updates again\" >&2; "
        "else echo \"roslab: apt-get update failed, the lists stay stale until one succeeds: "
        "$(printf '%s\\n' \"$out\" | grep -E '^(E|W):' | tr -s '\\n ' '  ')\" >&2; fi; exit $status; fi"
    )


@operation(is_idempotent=False)
def apt_lists_updated(lock_timeout: int, max_age: int | None = None, sources=None):
    """
    Ensure the apt package lists are fresh.

    + lock_timeout: seconds apt waits for the dpkg lock
    + max_age: update only when the lists are older than this many seconds
    + sources: the operations (their results) that write apt sources: when one of them
      changed a source, the lists are updated whatever their age
    With neither ``max_age`` nor ``sources`` it always updates.

    A download that fails (a mirror gone, a source unreachable) fails the operation,
    and the lists count as stale until an update succeeds (see ``apt_update_command``).
    """
    if sources is not None and any(
        source.did_change() if source.is_complete() else source.will_change for source in sources
    ):
        yield apt_update_command(lock_timeout)
        return
    if max_age is not None:
        age = host.get_fact(FileAge, path=APT_UPDATE_STAMP)
        if age is not None and age < max_age:
            host.noop(f"apt lists are {age} s old (max age {max_age} s)")
            return
    elif sources is not None:
        host.noop("no apt source changed")
        return
    yield apt_update_command(lock_timeout)


def apt_lists_updated_reads() -> list:
    """What `apt_lists_updated` reads (roslab.probe)."""
    return [read(FileAge, path=APT_UPDATE_STAMP)]


@operation(is_idempotent=False)
def dpkg_interrupted_install_finished(lock_timeout: int):
    """
    Finish the install dpkg was interrupted in (a Pi unplugged, dpkg killed), as apt asks.

    + lock_timeout: seconds apt waits for the dpkg lock

    Call it when the ``AptProblem`` fact says ``interrupted``: ``dpkg --configure -a``
    configures what was unpacked, then ``apt-get -f install`` reinstalls what was left
    half-installed and completes missing dependencies. A package whose configuration
    still fails makes the second command fail, with apt's own message.
    """
    # dpkg's own failure (e.g. a half-installed dependency) is for apt-get -f to fix.
    yield (
        "DEBIAN_FRONTEND=noninteractive dpkg --force-confdef --force-confold --configure -a "
        "|| echo 'roslab: dpkg --configure -a failed; apt-get -f install follows' >&2"
    )
    yield apt_get(f"{DPKG_KEEP_CONFFILES} -f install", lock_timeout)


@operation()
def command_installed(command: str, package: str, lock_timeout: int):
    """
    Ensure a command is available, installing `package` only if nothing provides it yet.

    + command: the command to look for on ``PATH``
    + package: the apt package that provides it
    + lock_timeout: seconds apt waits for the dpkg lock
    """
    if host.get_fact(Which, command=command):
        host.noop(f"{command} is already installed")
        return
    yield StringCommand(
        apt_get(f"{DPKG_KEEP_CONFFILES} install --", lock_timeout), QuoteString(apt_arguments([package])[0])
    )


@operation()
def packages_installed(packages: list[str], lock_timeout: int):
    """
    Ensure the apt packages are installed (with their dependencies), installing only the
    missing ones; a host's edited configuration files are kept.

    + packages: package names (checked by the schema; `apt_arguments` refuses options)
    + lock_timeout: seconds apt waits for the dpkg lock

    If apt-get is killed (a student, the OOM killer), the failure says so with the signal
    and exit status (`reporting_a_signal`).
    """
    installed = host.get_fact(DebPackages) or {}
    names = apt_arguments(packages)
    missing = [name for name in names if _package_name(name) not in installed]
    if not missing:
        host.noop(f"{', '.join(names)} {'is' if len(names) == 1 else 'are'} installed")
        return
    install = f"{apt_get(f'{DPKG_KEEP_CONFFILES} install --', lock_timeout)} " + " ".join(
        shlex.quote(name) for name in missing)
    yield StringCommand(reporting_a_signal(install, "apt-get install"))


def packages_installed_reads() -> list:
    """What `packages_installed` reads (roslab.probe)."""
    return [read(DebPackages)]


@operation()
def packages_downloaded(packages: list[str], installed_here: list[str], lock_timeout: int):
    """
    Ensure apt has downloaded `packages` and their dependencies (through its proxy), without
    installing them: how one host fills the classroom's apt cache before the class installs.

    + packages: the packages to download (the ones already installed are skipped by apt)
    + installed_here: the packages this host installs itself; once all of them are installed,
      the run that installed them went through the cache, so nothing is downloaded again
    + lock_timeout: seconds apt waits for the dpkg lock
    """
    installed = host.get_fact(DebPackages) or {}
    if all(_package_name(name) in installed for name in installed_here):
        host.noop("the packages are installed here: the run that installed them filled the cache")
        return
    yield StringCommand(
        apt_get("install --download-only --", lock_timeout),
        *(QuoteString(name) for name in apt_arguments(packages)),
    )


def _package_name(spec: str) -> str:
    """`name` of an apt spec `name`, `name=version` or `name/suite`."""
    return re.split(r"[=/]", spec, maxsplit=1)[0]


def packages_downloaded_reads() -> list:
    """What `packages_downloaded` reads (roslab.probe)."""
    return [read(DebPackages)]


def command_installed_reads(command: str) -> list:
    """What `command_installed` reads (roslab.probe)."""
    return [read(Which, command=command)]


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


LOCALE_GEN = "/etc/locale.gen"


def with_locale_enabled(lines: list[str], locale: str) -> list[str]:
    """/etc/locale.gen with `locale`'s line uncommented (or added)."""
    charset = locale.split(".", 1)[1]
    wanted = f"{locale} {charset}"
    pattern = re.compile(rf"^#?\s*{re.escape(locale)}\s+{re.escape(charset)}\s*$")
    if wanted in lines:
        return list(lines)
    for index, line in enumerate(lines):
        if pattern.match(line):
            return lines[:index] + [wanted] + lines[index + 1 :]
    return lines + [wanted]


@operation()
def locale_generated(locale: str):
    """
    Ensure a locale is generated, the way both Ubuntu and Debian honour.

    + locale: e.g. ``en_US.UTF-8``

    Debian's ``locale-gen`` ignores its arguments and reads ``/etc/locale.gen``; Ubuntu's
    takes them. So the line is enabled in ``/etc/locale.gen`` and the name passed too.
    """
    if locale in host.get_fact(Locales):
        host.noop(f"locale {locale} is already generated")
        return
    current = host.get_fact(FileContents, path=LOCALE_GEN) or []
    desired = with_locale_enabled(current, locale)
    if desired != current:
        _log_diff(LOCALE_GEN, current, desired)
        yield from _upload_text(LOCALE_GEN, desired, user="root", group="root", mode="644")
    yield StringCommand("locale-gen", QuoteString(locale))


def locale_generated_reads() -> list:
    """What `locale_generated` reads on a host that has the locale (roslab.probe)."""
    return [read(Locales)]


@operation()
def rosdep_initialized():
    """
    Ensure rosdep's system sources list exists, running ``rosdep init`` only if it is missing.
    """
    if host.get_fact(File, path=ROSDEP_SOURCES_LIST):
        host.noop(f"{ROSDEP_SOURCES_LIST} already exists")
        return
    yield "rosdep init"


def rosdep_initialized_reads() -> list:
    """What `rosdep_initialized` reads (roslab.probe)."""
    return [read(File, path=ROSDEP_SOURCES_LIST)]


@operation(is_idempotent=False)
def rosdep_cache_updated(home: str, max_age: int | None = None, rosdistro_index_url=None):
    """
    Ensure the user's rosdep cache is fresh (run with ``_sudo_user`` = that user, never root).

    + home: the user's home directory (where ``~/.ros/rosdep`` lives)
    + max_age: update only when the cache is older than this many seconds, or missing;
      ``None`` always updates (gate it with ``_if=`` on a sources change)
    + rosdistro_index_url: where rosdep reads the rosdistro index (``None``: rosdep's own)
    """
    if max_age is not None:
        age = host.get_fact(FileAge, path=f"{home}/{ROSDEP_CACHE_INDEX}")
        if age is not None and age < max_age:
            host.noop(f"rosdep cache is {age} s old (max age {max_age} s)")
            return
    if rosdistro_index_url:
        yield StringCommand(
            "env", QuoteString(f"ROSDISTRO_INDEX_URL={rosdistro_index_url}"), "rosdep update"
        )
    else:
        yield "rosdep update"


def rosdep_cache_updated_reads(home: str) -> list:
    """What `rosdep_cache_updated` reads (roslab.probe)."""
    return [read(FileAge, path=f"{home}/{ROSDEP_CACHE_INDEX}")]
