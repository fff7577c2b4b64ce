"""What `roslab status` shows of the class lock (classroom.lock beside the roster; roslab.class_lock).

Per locked group (distro/architecture): when the lock was taken (date and age in days), from
which host, how many packages it pins and how many of them its `hold:` list keeps back; then how
many of the group's locked packages the apt sources of its hosts offer in a newer version than the
lock, as each host's last `apt-get update` left its package lists (status runs no update).

Read on the host by one more section of status's one command (`policy_command`, no root):
`dpkg --print-architecture` (which group the host is in, as `roslab lock` names it) and
`apt-cache policy` of the locked packages of the host's distro. `parse_policy` and `lock_lines`
are pure: facts in, lines out.
"""

from __future__ import annotations

import shlex
from datetime import datetime, timezone

from roslab import class_lock

SECTION = "apt-policy"
# The names go into the one command status runs (one `sh -c` argument, which Linux bounds at
# 128 KiB): a lock of more names than this is not asked about, and its line says so.
MAX_NAMES_CHARS = 100_000
DPKG_STATUS = "/var/lib/dpkg/status"


def asked_packages(lock: class_lock.ClassLock, distro: str | None) -> tuple[str, ...]:
    """The locked packages of every group of `distro` (the host's architecture is known only once
    it answers), checked names only, sorted: what its `apt-cache policy` is asked about."""
    names = {name for key, group in lock.groups.items() if key.split("/")[0] == distro
             for name in group.packages if class_lock.PACKAGE_NAME.fullmatch(name)}
    return tuple(sorted(names))


def policy_command(packages: tuple[str, ...]) -> str:
    """The section's shell: the Debian architecture, then apt's view of each of `packages` in the C
    locale (apt translates its labels); no policy at all when there are none or too many."""
    names = " ".join(shlex.quote(name) for name in packages if class_lock.PACKAGE_NAME.fullmatch(name))
    ask = f"LC_ALL=C apt-cache policy -- {names} 2>/dev/null" if names and len(names) <= MAX_NAMES_CHARS \
        else f"echo {'#too-many' if names else '#none'}"
    return f"dpkg --print-architecture 2>/dev/null || echo '?'; {ask}"


def parse_policy(lines) -> dict:
    """The section's output as ``{"architecture": "arm64", "offered": {package: [version, ...]},
    "too_many": bool}``: per package, the versions some apt source lists (a version only in
    /var/lib/dpkg/status, installed but served by no source, is not offered); `too_many`: the
    lock named more packages than one command can ask about."""
    lines = list(lines)
    architecture = lines[0].strip() if lines else ""
    offered: dict[str, list[str]] = {}
    package = version = None
    for line in lines[1:]:
        stripped = line.strip()
        if not stripped:
            continue
        if not line[0].isspace() and stripped.endswith(":"):  # "bash:" opens a package
            package, version = stripped[:-1], None
            offered.setdefault(package, [])
        elif package is None or stripped.endswith(":") or stripped.split(":")[0] in (
                "Installed", "Candidate", "Version table", "Package pin"):
            continue
        elif _is_version_line(line):  # " *** 9.1-1 500" or "     5.2.15-2+b13 500"
            version = stripped.removeprefix("***").split()[0]
        elif version is not None and stripped.split(maxsplit=1)[-1] != DPKG_STATUS \
                and version not in offered[package]:  # "500 http://deb.debian.org/debian ..."
            offered[package].append(version)
    return {"architecture": architecture if class_lock.GROUP.fullmatch(f"x/{architecture}") else "",
            "offered": offered, "too_many": any(line.strip() == "#too-many" for line in lines[1:2])}


def _is_version_line(line: str) -> bool:
    """A version-table line: 5 columns of indent (or ` *** `), the version, its priority."""
    words = line.removeprefix(" *** ").split()
    return (line.startswith(" *** ") or (line.startswith("     ") and not line.startswith("      "))) \
        and len(words) == 2 and words[1].lstrip("-").isdigit()


# Debian's version order (dpkg's verrevcmp, policy 5.6.12): `~` sorts before everything, even the end.


def _order(char: str) -> int:
    if char == "" or char.isdigit():
        return 0
    if char == "~":
        return -1
    return ord(char) if char.isalpha() else ord(char) + 256


def _compare_part(a: str, b: str) -> int:
    i = j = 0
    while i < len(a) or j < len(b):
        while (i < len(a) and not a[i].isdigit()) or (j < len(b) and not b[j].isdigit()):
            ac, bc = _order(a[i] if i < len(a) else ""), _order(b[j] if j < len(b) else "")
            if ac != bc:
                return ac - bc
            i, j = i + 1, j + 1
        start_a, start_b = i, j
        while i < len(a) and a[i].isdigit():
            i += 1
        while j < len(b) and b[j].isdigit():
            j += 1
        number_a, number_b = int(a[start_a:i] or 0), int(b[start_b:j] or 0)
        if number_a != number_b:
            return 1 if number_a > number_b else -1
    return 0


def compare_versions(a: str, b: str) -> int:
    """<0, 0 or >0 as Debian version `a` sorts before, with or after `b` (`dpkg --compare-versions`)."""
    def split(version: str) -> tuple[int, str, str]:
        epoch, _, rest = version.partition(":") if ":" in version else ("0", "", version)
        upstream, _, revision = rest.rpartition("-") if "-" in rest else (rest, "", "")
        return int(epoch or 0), upstream, revision

    (epoch_a, upstream_a, revision_a), (epoch_b, upstream_b, revision_b) = split(a), split(b)
    if epoch_a != epoch_b:
        return epoch_a - epoch_b
    return _compare_part(upstream_a, upstream_b) or _compare_part(revision_a, revision_b)


def newer_upstream(group: class_lock.LockedGroup, offered: dict[str, list[str]]) -> set[str]:
    """The group's locked packages some apt source of the host lists in a newer version."""
    return {name for name, locked in group.packages.items()
            if any(compare_versions(version, locked) > 0 for version in offered.get(name, []))}


# The lines
# ---------


def age(taken: str, now: datetime) -> str:
    """The lock's date and its age in whole days: '2026-11-20 (8 days ago)'."""
    moment = datetime.strptime(taken, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=timezone.utc)
    days = (now - moment).days
    ago = "today" if days == 0 else "in the future" if days < 0 else "1 day ago" if days == 1 else f"{days} days ago"
    return f"{taken[:10]} ({ago})"


def host_groups(lock: class_lock.ClassLock, hosts) -> dict[str, list]:
    """Group key -> (host name, its parsed policy) of each host that answered the section."""
    found: dict[str, list] = {}
    for host in hosts:
        policy = (host.probe or {}).get("apt_policy")  # only from a whole answer: none cut short
        if host.reachable and host.probe["probed"] and policy and policy["architecture"] and host.expected_distro:
            found.setdefault(f"{host.expected_distro}/{policy['architecture']}", []).append((host.name, policy))
    return found


def lock_lines(lock: class_lock.ClassLock | None, hosts, now: datetime) -> list[dict]:
    """The lock's lines, each ``{"text", "level"}`` (ok, warn, muted, plain), for the terminal and
    the page; none without a lock. `hosts`: status's HostStatus list, probed."""
    if lock is None:
        return []
    found = host_groups(lock, hosts)
    lines = []
    for key, group in sorted(lock.groups.items()):
        held = len(set(lock.hold) & set(group.packages))
        lines.append({"level": "plain", "text": f"class lock {key}: taken {age(group.taken, now)} from "
                      f"{group.taken_from}; {count(len(group.packages), 'package')} pinned, {held} held"})
        lines.append(newer_line(group, set(lock.hold), found.get(key, [])))
    for key, members in sorted(found.items()):
        if key not in lock.groups:
            names = ", ".join(name for name, _ in members)
            lines.append({"level": "warn", "text": f"{key} ({names}): not in the class lock: roslab lock takes it"})
    if not lock.groups and not found:
        lines.append({"level": "muted", "text": "class lock: no group locked yet: roslab lock takes one"})
    return lines


def count(number: int, word: str) -> str:
    return f"{number} {word}{'' if number == 1 else 's'}"


def newer_line(group: class_lock.LockedGroup, hold: set[str], members: list) -> dict:
    """How many of the group's locked packages its hosts' apt sources offer newer (any host)."""
    asked = [(name, policy) for name, policy in members if not policy["too_many"]]
    if not members:
        return {"level": "muted", "text": "  newer upstream: not read (no host of this group answered)"}
    if not asked:
        return {"level": "muted", "text": f"  newer upstream: not read ({count(len(group.packages), 'package')} "
                "are more than one status command can name)"}
    newer = set().union(*(newer_upstream(group, policy["offered"]) for _, policy in asked))
    moving, held = newer - hold, newer & hold
    where = f"apt sources of {count(len(asked), 'host')}"
    held_text = f" ({len(held)} more held back)" if held else ""
    if not moving:
        return {"level": "ok", "text": f"  nothing newer upstream than the lock on the {where}{held_text}"}
    return {"level": "warn", "text": f"  {count(len(moving), 'package')} newer upstream than the lock on the "
            f"{where}{held_text}: roslab lock --update --dry lists them"}
