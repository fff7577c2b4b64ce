"""apt: the host's Ubuntu sources, its package lists, dpkg's interrupted installs and packages
(facts and operations side by side, roslab.ops).

The lock wait is spelled in one place, `apt_lock_options`: every apt-get command line here, the
AptProblem fact and `apt.packages(extra_install_args=apt_install_options(...))` use it.
"""

from __future__ import annotations

import re
import shlex

from pyinfra import host
from pyinfra.api import FactBase, QuoteString, StringCommand, operation
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import FileContents
from pyinfra.facts.server import Which
from typing_extensions import override

from roslab.ops.files import FileAge, _log_diff, _upload_text
from roslab.probe import read
from roslab.quoting import apt_arguments, deb822_value, sources_list_word


# Ubuntu touches this after every successful `apt-get update`; Debian does not, so we do.
APT_UPDATE_STAMP = "/var/lib/apt/periodic/update-success-stamp"


# Keep the host's edited configuration files when a package brings new ones (never ask).
DPKG_KEEP_CONFFILES = "-o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold"
# apt >= 2.1.16 (Ubuntu 22.04 has 2.4): `update` exits non-zero when any index failed to
# download, instead of 0 with "W: Failed to fetch" and the old lists kept.
APT_UPDATE_FAIL_ON_ANY_ERROR = "-o APT::Update::Error-Mode=any"


# apt's words for a dpkg lock another process holds (apt-get check waited for it).
_LOCK_HELD = ("Could not get lock", "Unable to acquire the dpkg frontend lock", "Unable to lock")
_UPDATE_PREFIX = "roslab-dpkg-update: "
_AUDIT_PREFIX = "roslab-dpkg-audit: "
_EXIT_PREFIX = "roslab-apt-exit="
_CLOUD_INIT_PREFIX = "roslab-cloud-init="
# cloud-init's systemd generator decided it runs this boot (else it is disabled, and
# `cloud-init status --wait` could wait for a stage that never starts) ...
CLOUD_INIT_RUNS = "/run/cloud-init/enabled"
# ... and its final stage has not written its result yet.
CLOUD_INIT_DONE = "/run/cloud-init/result.json"


def apt_lock_options(lock_timeout: int) -> str:
    """apt-get options that wait (bounded) for the dpkg lock instead of failing at once.

    The one place roslab spells the lock wait: every apt-get command line of this
    module, the AptProblem fact and
    `apt.packages(extra_install_args=apt_install_options(...))` use it.
    """
    return f"-o DPkg::Lock::Timeout={int(lock_timeout)}"

class AptProblem(FactBase):
    """
    Waits (bounded) until apt can take the dpkg lock, then reports whether apt is usable.

    Returns ``None`` when ``apt-get check`` succeeds within ``lock_timeout`` seconds and
    dpkg has nothing half-done (``{"interrupted": False, "message": None, "waited": line}``
    when it had to wait for the lock first: apt's line naming who held it), else
    ``{"interrupted": bool, "message": str}``:

    - ``interrupted``: dpkg was stopped in the middle of an install (a Pi unplugged,
      dpkg killed): its journal ``/var/lib/dpkg/updates/`` is not empty, ``dpkg --audit``
      lists half-installed or unconfigured packages, or apt says "dpkg was interrupted".
      ``dpkg --configure -a`` and ``apt-get -f install`` heal it
      (``dpkg_interrupted_install_finished``).
    - otherwise apt's own error lines, e.g. the lock still held by unattended-upgrades
      after the wait, or broken dependencies. Fresh Ubuntu images hold the lock for
      minutes at first boot.

    While another process holds the lock its half-done work is normal, not interrupted.

    First, on a freshly seeded Pi, it waits (bounded by ``lock_timeout`` too) for cloud-init
    to finish its first boot (``cloud-init status --wait``): cloud-init's own package step
    fails when a deploy takes the dpkg lock from under it. Only where cloud-init exists and
    has not finished this boot: on a settled host the wait costs a few ``test -e``. Then
    the result has ``"cloud_init": {"status": exit status (124: still running at the
    timeout), "seconds": waited, "output": its last words}`` (else no such key).
    """

    @override
    def command(self, lock_timeout: int) -> StringCommand:
        wait_for_cloud_init = (
            f"if [ -e {CLOUD_INIT_RUNS} ] && [ ! -e {CLOUD_INIT_DONE} ] && command -v cloud-init >/dev/null 2>&1; then "
            "started=$(date +%s); "
            f"said=$(timeout {int(lock_timeout) or 1} cloud-init status --wait 2>&1 </dev/null); rc=$?; "
            f'echo "{_CLOUD_INIT_PREFIX}$rc $(( $(date +%s) - started )) '
            '$(printf %s "$said" | tr -s \'.\\n\' \' \' | tail -c 200)"; '
            "fi;"
        )
        # `; echo` keeps the fact's exit status 0 so the failure reaches process().
        return StringCommand(
            wait_for_cloud_init,
            f"apt-get -qq {apt_lock_options(lock_timeout)} check 2>&1;",
            f'echo "{_EXIT_PREFIX}$?";',
            f"ls -A /var/lib/dpkg/updates 2>/dev/null | sed 's/^/{_UPDATE_PREFIX}/';",
            f"dpkg --audit 2>&1 | sed 's/^/{_AUDIT_PREFIX}/'",
        )

    @override
    def process(self, output):
        cloud_init = None
        for line in output:
            if line.startswith(_CLOUD_INIT_PREFIX):
                status, seconds, *said = line[len(_CLOUD_INIT_PREFIX):].split(" ", 2)
                cloud_init = {"status": int(status) if status.isdigit() else -1,
                              "seconds": int(seconds) if seconds.isdigit() else 0,
                              "output": (said[0] if said else "").strip()}
        apt = self._apt(line for line in output if not line.startswith(_CLOUD_INIT_PREFIX))
        if cloud_init is None:
            return apt
        return {**(apt or {"interrupted": False, "message": None}), "cloud_init": cloud_init}

    @staticmethod
    def _apt(output):
        check, updates, audit, status, waited = [], [], [], "", ""
        for line in output:
            if line.startswith(_EXIT_PREFIX):
                status = line
            elif line.startswith(_UPDATE_PREFIX):
                updates.append(line[len(_UPDATE_PREFIX):])
            elif line.startswith(_AUDIT_PREFIX):
                if line[len(_AUDIT_PREFIX):].strip():
                    audit.append(line[len(_AUDIT_PREFIX):].strip())
            # apt prints "Waiting for cache lock" lines while it waits: keep the verdict,
            # and the first of them to say who held the lock.
            elif line.startswith("Waiting for cache lock"):
                waited = waited or line
            else:
                check.append(line)
        text = "\n".join(check)
        ok = status == f"{_EXIT_PREFIX}0"
        lock_held = not ok and any(words in text for words in _LOCK_HELD)
        interrupted = not lock_held and bool(updates or audit or "dpkg was interrupted" in text)
        if ok and not interrupted:
            # A wait that ended well is no problem, but the teacher should know it happened.
            return {"interrupted": False, "message": None, "waited": waited} if waited else None
        if interrupted:
            found = []
            if updates:
                found.append(f"{len(updates)} pending entries in /var/lib/dpkg/updates/")
            if audit:
                found.append("dpkg --audit: " + " ".join(audit)[:300])
            message = "dpkg was interrupted" + (f" ({'; '.join(found)})" if found else "")
        else:
            message = text or status or "apt-get check printed nothing"
        return {"interrupted": interrupted, "message": message}


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


# A package dpkg left half-installed (reinst-required) whose installed version no apt source holds
# (a .deb installed from a file: ros2-apt-source) is one apt cannot reinstall: every apt-get then
# stops with "needs to be reinstalled, but I can't find an archive for it" (a run interrupted in
# its dpkg -i did that). dpkg's own way out removes it; the step that installed it installs it
# again. One a source holds stays for apt-get -f to reinstall.
REMOVE_UNFETCHABLE_HALF_INSTALLED = r"""
for package in $(dpkg-query -W -f '${db:Status-Eflag} ${binary:Package}\n' 2>/dev/null | awk '$1 == "reinstreq" {print $2}'); do
  version=$(dpkg-query -W -f '${Version}' "$package" 2>/dev/null)
  if ! apt-cache madison "${package%%:*}" 2>/dev/null | awk -F'|' -v want="$version" '{gsub(/ /, "", $2)} $2 == want {found = 1} END {exit !found}'; then
    echo "roslab: $package $version is half-installed and no apt source holds it: removing it (dpkg --force-remove-reinstreq); the step that installs it installs it again" >&2
    dpkg --remove --force-remove-reinstreq "$package" || exit 1
  fi
done
""".strip()


@operation(is_idempotent=False)
def dpkg_interrupted_install_finished(lock_timeout: int):
    """
    Finish the install dpkg was interrupted in (a Pi unplugged, dpkg killed), as apt asks.

    + lock_timeout: seconds apt waits for the dpkg lock

    Call it when the ``AptProblem`` fact says ``interrupted``: ``dpkg --configure -a``
    configures what was unpacked; a half-installed package no apt source holds is removed
    (REMOVE_UNFETCHABLE_HALF_INSTALLED: its own step installs it again); then ``apt-get -f
    install`` reinstalls what was left half-installed and completes missing dependencies. A
    package whose configuration still fails makes the last command fail, with apt's own message.
    """
    # dpkg's own failure (e.g. a half-installed dependency) is for apt-get -f to fix.
    yield (
        "DEBIAN_FRONTEND=noninteractive dpkg --force-confdef --force-confold --configure -a "
        "|| echo 'roslab: dpkg --configure -a failed; apt-get -f install follows' >&2"
    )
    yield REMOVE_UNFETCHABLE_HALF_INSTALLED
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
