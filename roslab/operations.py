"""pyinfra operations roslab needs beyond pyinfra's own, in pyinfra's style.

Each operation is named for the end state, reads facts, and either yields the commands
that reach that state or says with ``host.noop`` why nothing needs doing. Facts are read
again when an operation executes, so an operation that follows another one sees its effect.
"""

from __future__ import annotations

import re
from io import StringIO

from pyinfra import host, logger, state
from pyinfra.api import FileUploadCommand, QuoteString, StringCommand, operation
from pyinfra.api.util import format_text
from pyinfra.facts.deb import DebPackage, DebPackages
from pyinfra.facts.files import File, FileContents, Link
from pyinfra.facts.server import Locales, Which
from pyinfra.operations.util.files import chmod, chown, generate_color_diff

from roslab.facts import FileAge

# Ubuntu touches this after every successful `apt-get update`; Debian does not, so we do.
APT_UPDATE_STAMP = "/var/lib/apt/periodic/update-success-stamp"
ROSDEP_SOURCES_LIST = "/etc/ros/rosdep/sources.list.d/20-default.list"
# rosdep rewrites this index on every `rosdep update`: its age is the cache's age.
ROSDEP_CACHE_INDEX = ".ros/rosdep/sources.cache/index"


def apt_get(command: str, lock_timeout: int) -> str:
    """An apt-get command line that waits (bounded) for the dpkg lock instead of failing."""
    return (
        f"DEBIAN_FRONTEND=noninteractive apt-get -y -o DPkg::Lock::Timeout={int(lock_timeout)} "
        f"{command}"
    )


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
    """Commands that replace `path` with `lines`, then restore its owner and mode."""
    yield FileUploadCommand(
        StringIO("".join(line + "\n" for line in lines)),
        path,
        remote_temp_filename=host.get_temp_filename(path),
    )
    if user or group:
        yield chown(path, user, group)
    if mode:
        yield chmod(path, mode)


# --- marked blocks ---------------------------------------------------------------


def block_markers(label: str) -> tuple[str, str]:
    return (f"# BEGIN roslab managed block ({label})", f"# END roslab managed block ({label})")


def with_block(lines: list[str], label: str, content: str) -> list[str]:
    """`lines` with roslab's block for `label` holding `content`: replaced in place, else appended."""
    begin, end = block_markers(label)
    block = [begin, *content.rstrip("\n").split("\n"), end]
    if begin in lines and end in lines[lines.index(begin) :]:
        start = lines.index(begin)
        stop = lines.index(end, start)
        return lines[:start] + block + lines[stop + 1 :]
    separator = [""] if lines and lines[-1].strip() else []
    return lines + separator + block


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
    desired = with_block(current or [], label, content)
    if current == desired:
        host.noop(f"block ({label}) in {path} is already up to date")
        return

    existing = host.get_fact(File, path=path) if current is not None else None
    if existing:
        user, group, mode = existing["user"], existing["group"], f"{existing['mode']:03d}"
    _log_diff(path, current, desired)
    yield from _upload_text(path, desired, user=user, group=group, mode=mode)


# --- apt sources -----------------------------------------------------------------


def _is_release_suite(suite: str, codename: str) -> bool:
    return suite == codename or suite.startswith(f"{codename}-")


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
            wanted = current_components + [c for c in components if c not in current_components]
            if wanted != current_components:
                out[comp_at] = "Components: " + " ".join(wanted)
        if codename in current_suites:
            extra = [f"{codename}-{s}" for s in suites]
            wanted = current_suites + [s for s in extra if s not in current_suites]
            if wanted != current_suites:
                out[suites_at] = "Suites: " + " ".join(wanted)

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
    """One-line `sources.list` with `components` and `<codename>-<suites>` lines added."""
    parsed = [ONE_LINE_SOURCE.match(line) for line in lines]
    present = {(m["type"], m["uri"], m["suite"]) for m in parsed if m}
    out: list[str] = []
    for line, match in zip(lines, parsed):
        if not match or not _is_release_suite(match["suite"], codename):
            out.append(line)
            continue
        current = match["components"].split()
        wanted = current + [c for c in components if c not in current]
        prefix = f"{match['type']} {match['options'] or ''}{match['uri']}"
        out.append(f"{prefix} {match['suite']} {' '.join(wanted)}" if wanted != current else line)
        if match["suite"] == codename:
            for suite in suites:
                key = (match["type"], match["uri"], f"{codename}-{suite}")
                if key not in present:
                    present.add(key)
                    out.append(f"{prefix} {codename}-{suite} {' '.join(wanted)}")
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


@operation(is_idempotent=False)
def apt_lists_updated(lock_timeout: int, max_age: int | None = None):
    """
    Ensure the apt package lists are fresh.

    + lock_timeout: seconds apt waits for the dpkg lock
    + max_age: update only when the lists are older than this many seconds;
      ``None`` always updates (gate it with ``_if=`` on a sources change)
    """
    if max_age is not None:
        age = host.get_fact(FileAge, path=APT_UPDATE_STAMP)
        if age is not None and age < max_age:
            host.noop(f"apt lists are {age} s old (max age {max_age} s)")
            return
    yield apt_get("update", lock_timeout)
    yield StringCommand("mkdir -p /var/lib/apt/periodic && touch", APT_UPDATE_STAMP)


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
    yield StringCommand(apt_get("install", lock_timeout), QuoteString(package))


@operation()
def deb_file_installed(src: str):
    """
    Ensure the package in a ``.deb`` already on the host is installed at that file's version.

    + src: path of the ``.deb`` on the host
    """
    info = host.get_fact(DebPackage, package=src)
    if info and info.get("version") in host.get_fact(DebPackages).get(info.get("name"), []):
        host.noop(f"{info['name']} {info['version']} is already installed")
        return
    yield StringCommand("dpkg --force-confdef --force-confold -i", QuoteString(src))


@operation()
def deb_purged(package: str):
    """
    Ensure a package is not installed (purged, with its configuration).

    + package: the package name
    """
    if package not in host.get_fact(DebPackages):
        host.noop(f"{package} is not installed")
        return
    yield StringCommand("dpkg --purge", QuoteString(package))


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


@operation()
def rosdep_initialized():
    """
    Ensure rosdep's system sources list exists, running ``rosdep init`` only if it is missing.
    """
    if host.get_fact(File, path=ROSDEP_SOURCES_LIST):
        host.noop(f"{ROSDEP_SOURCES_LIST} already exists")
        return
    yield "rosdep init"


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

