"""`roslab lock`: take and move the class lock (classroom.lock beside the roster; roslab.class_lock).

    roslab lock [ROSTER] [--limit NAME ...]                 lock each group the lock lacks, as a converged
                                                            host of it has it now (dpkg-query)
    roslab lock [ROSTER] --update [--limit NAME ...] --dry  list package old -> new, for which hosts
    roslab lock [ROSTER] --update [--limit NAME ...]        move the lock; the next run moves the hosts

Taking also records the class's wheels for each group (its profiles' python_packages, as the
controller's wheelhouse holds them): name -> version and sha256; `--update` takes a wheel the
wheelhouse now holds at another version or hash. And the commit of each source repository the
group's hosts build (URL@VERSION -> commit, as the controller fetched it); `--update` takes the
commit a locked tag names upstream now (a moved tag: a run refuses it until then).

Both keep the group's .debs (class_lock_debs_dir, roslab.class_debs): each locked package apt
downloaded onto a host read, and each kept package's version `--update` moves to, downloaded on
that host and checked against its index; a run serves them to a host whose sources dropped them.

A group is (ROS distro, Debian architecture). A locked group is never rewritten by taking:
only `--update` moves its versions, and never those of the lock's `hold:` list.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from roslab import class_debs, class_lock
from roslab.ops import class_debs as debs_ops
from roslab.ops import class_lock as lock_ops
from roslab.controller_files import replace_file
from roslab.reach import RosterProblem, add_roster_argument, connected_state, fail, load_classroom_groups

INCOMING = ".incoming-"  # the folder a group's copies arrive in, inside its folder, until checked


def update_lines(moves: dict[str, list[tuple[str, str, str]]], hosts: dict[str, list[str]]) -> list[str]:
    """`--dry`'s listing: per group, each package old -> new and the hosts it moves."""
    lines = []
    for key, changes in sorted(moves.items()):
        for name, old, new in changes:
            lines.append(f"{key}: {name} {old} -> {new} ({', '.join(hosts[key])})")
        if not changes:
            lines.append(f"{key}: the archives offer nothing newer than the lock")
    return lines


def kept_wheels(state, host) -> dict[str, class_lock.LockedWheel]:
    """The wheels the controller's wheelhouse holds for `host` (its profile's python_packages,
    for its machine, glibc and Python as it reports them): what a run gives it. Nothing without
    python_packages, or before a run downloaded them (an incomplete wheelhouse is not read)."""
    from pyinfra.api.facts import get_fact

    from roslab.host_settings import host_settings
    from roslab.python_env import wheelhouse
    from roslab.python_env.venv import PythonTarget

    typed = host_settings(host)
    requirements = list(typed.roslab_profile.python.requirements) if typed.roslab_profile is not None else []
    if not requirements:
        return {}
    target = wheelhouse.Target(**get_fact(state, host, PythonTarget))
    if target.problem():
        return {}
    kept = wheelhouse.load(wheelhouse.set_dir(typed.python_wheelhouse_dir, target, requirements,
                                              typed.python_index_url))
    return class_lock.wheels_of(kept.files) if kept is not None else {}


def kept_sources(host) -> dict[str, str]:
    """source (class_lock.source_key) -> commit of each repository `host` builds, as the
    controller's cache recorded it when a run fetched it (a tag), or as pinned (a commit); a
    tag no run fetched yet is not read."""
    from roslab.host_settings import host_settings
    from roslab.sources import fetch as source_fetch

    typed = host_settings(host)
    if not typed.roslab_sources:
        return {}
    recorded = source_fetch.read_lock(Path(typed.sources_cache_dir).expanduser())
    found = {}
    for repo in typed.roslab_sources:
        url, version = repo["url"], repo["version"]
        commit = source_fetch.recorded_commit(recorded.get(url) or {}, version)
        if commit:
            found[class_lock.source_key(url, version)] = commit
    return found


def upstream_sources(host, group: class_lock.LockedGroup) -> tuple[dict[str, str], list[str]]:
    """The commit each locked source's tag names upstream now (`git ls-remote` through the roster's
    source_url_rewrites), for the repositories `host` builds; one line per source not asked."""
    from roslab.host_settings import host_settings
    from roslab.sources import fetch as source_fetch
    from roslab.sources.repos import rewritten

    typed = host_settings(host)
    found, lines = {}, []
    for repo in typed.roslab_sources or []:
        key = class_lock.source_key(repo["url"], repo["version"])
        if key not in group.sources or source_fetch.COMMIT.fullmatch(repo["version"]):
            continue
        try:
            commit, _branch = source_fetch.remote_refs(rewritten(repo["url"], typed.source_url_rewrites),
                                                      repo["version"], typed.sources_fetch_timeout)
        except source_fetch.SourceError as error:
            lines.append(f"source {key}: upstream cannot be asked ({error}): kept at {group.sources[key]}")
            continue
        if commit:
            found[key] = commit
    return found, lines


def read_hosts(args, classroom, groups, with_candidates: class_lock.ClassLock | None) -> dict:
    """Per lock group: {"hosts": [...], "installed": {...}, "from": host, "candidates": {...},
    "wheels": {...}} read from the hosts --limit selects that answer (the first one of each group
    is read; the wheels are those of all its hosts, the first of a name kept)."""
    from pyinfra.api.facts import get_fact

    state = connected_state(groups, args.limit)
    distro_of = {host.name: host.distro for host in classroom.hosts}
    found: dict[str, dict] = {}
    for host in state.inventory:
        if host not in state.active_hosts or not distro_of.get(host.name):
            continue
        reading = get_fact(state, host, lock_ops.InstalledVersions)
        key = class_lock.group_key(distro_of[host.name], reading["architecture"])
        entry = found.setdefault(key, {"hosts": [], "installed": reading["packages"], "from": host.name})
        entry["hosts"].append(host.name)
        entry.setdefault("readers", []).append((state, host, reading["architecture"]))
        entry["wheels"] = {**kept_wheels(state, host), **entry.get("wheels", {})}
        entry["sources"] = {**kept_sources(host), **entry.get("sources", {})}
        if with_candidates is not None and key in with_candidates.groups:
            upstream, lines = upstream_sources(host, with_candidates.groups[key])
            entry["upstream_sources"] = {**upstream, **entry.get("upstream_sources", {})}
            for line in lines:
                print(line)
        if with_candidates is not None and "candidates" not in entry and key in with_candidates.groups:
            locked = sorted(with_candidates.groups[key].packages)
            # what the archives offer now: the host's lists may be days old (apt_cache_max_age)
            versions = get_fact(state, host, lock_ops.AptVersionsNow, kwargs={"packages": locked}) if locked else {}
            entry["candidates"] = {name: found_versions[0] for name, found_versions in versions.items()}
    return found


def moved_lock(lock: class_lock.ClassLock, found: dict, taken: str) -> class_lock.ClassLock:
    """`--update`: print each locked group's moves (packages the archives offer newer, wheels the
    wheelhouse now holds at another version or hash) and return the lock moved to them."""
    moves: dict[str, list[tuple[str, str, str]]] = {}
    wheels: dict[str, dict[str, class_lock.LockedWheel]] = {}
    sources: dict[str, dict[str, str]] = {}
    for key, entry in found.items():
        if key not in lock.groups:
            continue
        wheel_moves = class_lock.wheel_updates(lock.groups[key], entry.get("wheels", {}), lock.hold)
        wheels[key] = {name: entry["wheels"][name] for name, _old, _new in wheel_moves}
        source_moves = class_lock.source_updates(lock.groups[key], entry.get("upstream_sources", {}))
        sources[key] = {name: new for name, _old, new in source_moves}
        moves[key] = (class_lock.updates(lock, key, entry.get("candidates", {}))
                      + [(f"wheel {name}", old, new) for name, old, new in wheel_moves]
                      + [(f"source {name}", old, new) for name, old, new in source_moves])
    print("\n".join(update_lines(moves, {key: entry["hosts"] for key, entry in found.items()})))
    for key, changes in moves.items():
        if changes:
            packages = [change for change in changes if not change[0].startswith(("wheel ", "source "))]
            lock = class_lock.updated(lock, key, packages, taken, wheels[key], sources[key])
    return lock


def run_lock(args: argparse.Namespace) -> int:
    try:
        classroom, groups = load_classroom_groups(args.roster, "lock")
    except RosterProblem as problem:
        return fail(problem)
    path = Path(classroom.path).parent / class_lock.LOCK_FILE
    lock, report = class_lock.read_lock(path)
    if lock is None:
        return fail(RosterProblem("\n".join(str(problem) for problem in report.errors)))
    found = read_hosts(args, classroom, groups, lock if args.update else None)
    taken = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    if args.update:
        lock = moved_lock(lock, found, taken)
    else:
        for key, entry in sorted(found.items()):
            before = lock.groups.get(key, class_lock.LockedGroup("", ""))
            lock, added = class_lock.merged(lock, key, entry["installed"], entry.get("sources", {}), taken,
                                            entry["from"], entry.get("wheels", {}))
            wheels = len(lock.groups[key].wheels) - len(before.wheels)
            sources = len(lock.groups[key].sources) - len(before.sources)
            print(f"{key}: {len(lock.groups[key].packages) - len(before.packages)} packages "
                  + (f"and {wheels} wheels " if wheels else "") + (f"and {sources} sources " if sources else "")
                  + f"locked from {entry['from']}" if added
                  else f"{key}: already locked; nothing new (roslab lock --update moves it)")
    if args.dry:
        print(f"--dry: {path.name} was not changed")
        return 0
    replace_file(path, class_lock.render_lock(lock))  # never half a lock, whatever stops the command
    return keep_debs(found, lock, classroom.path)


def keep_debs(found: dict, lock: class_lock.ClassLock, roster_path: str | Path) -> int:
    """Keep each read group's locked .debs that the controller lacks (class_lock_debs_dir: what
    apt downloaded onto the group's hosts, and the versions `--update` moved kept ones to), the
    versions no longer locked removed; one line per group, and one per .deb not kept. 1 if a
    group's folder could not be written (said in its line), else 0."""
    from roslab.host_settings import host_settings

    status = 0
    for key, entry in sorted(found.items()):
        group, readers = lock.groups.get(key), entry.get("readers", [])
        debs_dir = host_settings(readers[0][1]).class_lock_debs_dir if readers else None
        if group is None or not debs_dir:
            continue
        root = class_debs.class_root(debs_dir, roster_path)
        try:
            kept, problems = kept_group(root, key, group, readers)
        except OSError as error:  # the controller's folder: full disk, no permission
            print(f"{key}: its .debs were not kept in {class_debs.folder(root, key)}: {error}")
            status = 1
            continue
        size = sum(deb.size for deb in kept.values())
        print(f"{key}: {len(kept)} .debs kept in {class_debs.folder(root, key)} ({size / 1e6:.1f} MB)"
              + (f"; {len(problems)} not kept:" if problems else ""))
        for line in problems:
            print(f"  {line}")
    return status


def kept_group(root: Path, key: str, group: class_lock.LockedGroup, readers: list) -> tuple[dict, list[str]]:
    """The group's kept .debs after keeping what its `readers` (state, host, architecture) have
    and the folder lacks, and a line per .deb not kept."""
    for left in class_debs.folder(root, key).glob(f"{INCOMING}*"):  # a `roslab lock` killed mid-copy
        shutil.rmtree(left, ignore_errors=True)
    before = class_debs.read_kept(root, key)
    kept = class_debs.pruned(root, key, group, dict(before))
    problems = []
    for state, host, architecture in readers:
        problems += kept_from(state, host, (str(root), key), group, architecture, (kept, before))
    class_debs.write_kept(root, key, kept)
    return kept, problems


def _copied(host, remote: str, local: Path) -> bool:
    try:
        return bool(host.get_file(remote, str(local)))
    except OSError:  # not downloaded there (SFTP's "no such file"), or the connection went
        return False


def kept_from(state, host, where: tuple[str, str], group: class_lock.LockedGroup, architecture: str,
              folders: tuple[dict, dict]) -> list[str]:
    """Keep (into `folders`' first, the kept .debs, and the folder of `where`: class_lock_debs_dir
    and group) what `host` downloaded of the group's locked versions and the folder lacks, and the
    versions of packages kept before (`folders`' second) the lock moved: downloaded again on the
    host (`apt-get download`, as the login user), copied here, checked against the host's index."""
    from pyinfra.api import QuoteString, StringCommand
    from pyinfra.api.facts import get_fact

    (root, key), (kept, before) = where, folders
    wanted = class_debs.wanted(group, get_fact(state, host, debs_ops.DownloadedDebs), architecture, kept, before)
    if not wanted:
        return []
    index = get_fact(state, host, debs_ops.IndexedDebs, kwargs={"packages": [f"{n}={v}" for n, v in wanted]})
    ok, output = host.run_shell_command(StringCommand("sh", "-c", QuoteString(debs_ops.download_script(wanted))))
    remote = output.stdout_lines[-1].strip() if ok and output.stdout_lines else ""
    if not debs_ops.DOWNLOAD_DIR.fullmatch(remote):
        return [f"{len(wanted)} .debs: {host.name} could not download them (apt-get download)"]
    problems = []
    folder = class_debs.folder(root, key)
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder, prefix=INCOMING) as incoming:
        for name, version in wanted:
            deb = index.get((name, version))
            if deb is None:
                problems.append(f"{name}={version}: {host.name}'s sources do not list it any more: not kept")
                continue
            local = Path(incoming) / deb.file
            if not _copied(host, f"{remote}/{class_debs.download_name(name, version, deb.architecture)}", local):
                problems.append(f"{name}={version}: could not be copied from {host.name}: not kept")
                continue
            problem = class_debs.kept_file(root, key, deb, local)
            if problem:
                problems.append(problem)
            else:
                kept[(name, version)] = deb
    host.run_shell_command(StringCommand("rm", "-rf", "--", remote))
    return problems


def register(commands) -> None:
    lock = commands.add_parser(
        "lock",
        help="take or move the class lock (classroom.lock): one set of package versions per group",
        description="Without --update: lock each (distro, architecture) group the lock lacks, at the versions "
        "a converged host of the group has installed. With --update: move the locked versions to what the "
        "archives offer now (--dry only lists package old -> new and the hosts), except the lock's hold: list.",
    )
    add_roster_argument(lock)
    lock.add_argument("--update", action="store_true", help="move the locked versions to the archives' newest")
    lock.add_argument("--dry", action="store_true", help="list what would change; write nothing")
    lock.set_defaults(run=run_lock)

