"""The class lock's kept .debs on a host (roslab.class_debs keeps them on the controller): what
`roslab lock` reads from a host to keep them, and the operation that serves a host the locked
versions its own sources no longer list.

The served .debs are a flat local repository, /var/lib/roslab/class-debs (root's, 0755), named
by /etc/apt/sources.list.d/roslab-class-debs.sources with `Trusted: yes`: every file was checked
against the SHA256 of the index apt verified when the controller kept it, and apt checks each
again against the Packages file it is served with. The source exists only while some locked
version needs it: a run that finds every kept version listed elsewhere removes both.
"""

from __future__ import annotations

import io
import re
import shlex

from pyinfra import logger
from pyinfra.api import FactBase, FunctionCommand, QuoteString, StringCommand, operation

from roslab import class_debs
from roslab.class_lock import PACKAGE_NAME, VERSION
from roslab.connections import op_connector_arguments
from roslab.controller_files import file_sha256
from roslab.ops.apt import apt_get

LOCAL_DIR = "/var/lib/roslab/class-debs"
SOURCE_FILE = "/etc/apt/sources.list.d/roslab-class-debs.sources"
APT_ARCHIVES = "/var/cache/apt/archives"
SECTION = "--- roslab: served files ---"
# The folder `download_script` makes (mktemp's), as the controller accepts its name back.
DOWNLOAD_DIR = re.compile(r"/[A-Za-z0-9/._-]*/roslab-class-debs\.[A-Za-z0-9]{6}")
SOURCE = ("# Managed by roslab: the class lock's kept .debs that this host's other sources no longer list\n"
          "# (see docs/class-cache.md). Removed by roslab when no locked version needs it.\n"
          f"Types: deb\nURIs: file:{LOCAL_DIR}\nSuites: ./\nTrusted: yes\n")


class DownloadedDebs(FactBase):
    """The .deb files in the host's apt cache (/var/cache/apt/archives): what apt downloaded."""

    def command(self) -> str:
        return f"ls -1 {APT_ARCHIVES} 2>/dev/null || true"

    def process(self, output) -> list[str]:
        return [line.strip() for line in output if class_debs.DEB_FILE.fullmatch(line.strip())]


class IndexedDebs(FactBase):
    """(name, version) -> its stanza as the host's verified index has it (`apt-cache show`), for
    `packages` ("name=version" each, checked: never an option)."""

    def command(self, packages: list[str]) -> str:
        pairs = [pair for pair in packages if _pair(pair)]
        return "apt-cache show -- " + " ".join(shlex.quote(pair) for pair in pairs) + " 2>/dev/null || true"

    def process(self, output) -> dict:
        return class_debs.indexed("\n".join(output))


def _pair(text: str) -> bool:
    name, _, version = text.partition("=")
    return bool(PACKAGE_NAME.fullmatch(name) and VERSION.fullmatch(version))


def download_script(pairs: list[tuple[str, str]]) -> str:
    """Run as the login user: `apt-get download` of each name=version into a new folder, whose
    path is the last line printed (the controller copies the files, then removes the folder)."""
    wanted = " ".join(shlex.quote(f"{name}={version}") for name, version in pairs)
    return (f'dir=$(mktemp -d "${{TMPDIR:-/tmp}}/roslab-class-debs.XXXXXX") || exit 1; cd "$dir" || exit 1; '
            f"apt-get -q download -- {wanted} >/dev/null 2>&1 "
            f"|| for pair in {wanted}; do apt-get -q download -- \"$pair\" >/dev/null 2>&1; done; "
            'echo "$dir"')


def listed_script(names: list[str], lock_timeout: int) -> str:
    """Run as root: fresh lists, then the versions each of `names` is listed at (`apt-cache
    madison`), then the sha256 of each .deb the host serves already."""
    quoted = " ".join(shlex.quote(name) for name in names if PACKAGE_NAME.fullmatch(name))
    return "; ".join([
        f"{apt_get('-q update', lock_timeout)} >/dev/null 2>&1",
        f"apt-cache madison -- {quoted}",
        f"echo {shlex.quote(SECTION)}",
        f"cd {LOCAL_DIR} 2>/dev/null && sha256sum -- *.deb 2>/dev/null",
        "true",
    ])


def parse_listed(lines: list[str]) -> tuple[dict[str, set[str]], dict[str, str]]:
    """From `listed_script`'s output: package -> the versions a source other than the served
    folder lists, and file -> sha256 of the files the host serves already."""
    listed: dict[str, set[str]] = {}
    served: dict[str, str] = {}
    in_files = False
    for line in lines:
        if line.strip() == SECTION:
            in_files = True
        elif in_files:
            digest, _, name = line.strip().partition("  ")
            if class_debs.SHA256.fullmatch(digest) and class_debs.DEB_FILE.fullmatch(name):
                served[name] = digest
        else:
            parts = [part.strip() for part in line.split("|")]
            if len(parts) >= 3 and f"file:{LOCAL_DIR}" not in parts[2]:
                listed.setdefault(parts[0], set()).add(parts[1])
    return listed, served


def _as_root(state, host) -> dict:
    return {**op_connector_arguments(state, host), "_sudo": True}


def _put(state, host, source, remote: str) -> bool:
    """A file of root's, 0644, on the host (from a controller path or a file object)."""
    return host.put_file(source, remote, mode=0o644, user="root", group="root", **_as_root(state, host))


def _run(state, host, script: str) -> tuple[bool, list[str]]:
    ok, output = host.run_shell_command(StringCommand("sh", "-c", QuoteString(script)), **_as_root(state, host))
    if not ok:
        said = [line for line in output.stderr_lines if line.strip()]
        host.log_styled(f"roslab: class lock: {said[-1].strip() if said else 'a command failed without a message'}",
                        fg="red", log_func=logger.error)
    return ok, output.stdout_lines


def serve_dropped(state, host, root: str, key: str, date: str, lock_timeout: int) -> bool:
    """The kept .debs of group `key` whose version no other source of the host lists, served
    as the local source (only the files missing or changed are copied); none: the source removed."""
    debs = class_debs.read_kept(root, key)
    update = f"{apt_get('-q update', lock_timeout)} >/dev/null"
    ok, lines = _run(state, host, listed_script(sorted({name for name, _version in debs}), lock_timeout))
    if not ok:
        return False
    listed, served = parse_listed(lines)
    dropped = {pair: deb for pair, deb in debs.items() if deb.version not in listed.get(deb.name, set())}
    if not dropped:
        return _run(state, host, f"if [ -e {SOURCE_FILE} ] || [ -e {LOCAL_DIR} ]; then "
                                 f"rm -rf {SOURCE_FILE} {LOCAL_DIR} && {update}; fi")[0]
    folder = class_debs.folder(root, key)
    damaged = sorted(deb.file for deb in dropped.values() if file_sha256(folder / deb.file) != deb.sha256)
    if damaged:  # changed on the controller since `roslab lock` kept it: never served as the locked version
        host.log_styled(f"roslab: class lock: {folder / damaged[0]} is not the file `roslab lock` kept (its sha256 "
                        "differs): remove it and run `roslab lock` again while an archive lists it",
                        fg="red", log_func=logger.error)
        return False
    if not _run(state, host, f"install -d -m 755 {LOCAL_DIR}")[0]:
        return False
    packages = "\n".join(dropped[pair].stanza() for pair in sorted(dropped))
    files: list[tuple[str | io.BytesIO, str]] = [
        (str(folder / deb.file), f"{LOCAL_DIR}/{deb.file}") for deb in dropped.values()
        if served.get(deb.file) != deb.sha256]  # a file the host serves already is not copied again
    files += [(io.BytesIO(packages.encode()), f"{LOCAL_DIR}/Packages"),
              (io.BytesIO(class_debs.release_file(packages, date).encode()), f"{LOCAL_DIR}/Release"),
              (io.BytesIO(SOURCE.encode()), SOURCE_FILE)]
    if not all(_put(state, host, source, remote) for source, remote in files):
        return False
    serving = {deb.file for deb in dropped.values()}
    stale = [name for name in served if name not in serving]
    remove = f"rm -f -- {' '.join(shlex.quote(f'{LOCAL_DIR}/{name}') for name in stale)}; " if stale else ""
    if not _run(state, host, f"{remove}{update}")[0]:
        return False
    host.log(f"roslab: class lock: {len(dropped)} locked version(s) no source lists any more, served from the "
             f"class's kept .debs: {', '.join(f'{deb.name}={deb.version}' for deb in dropped.values())}")
    return True


@operation()
def dropped_versions_served(root: str, key: str, date: str, lock_timeout: int):
    """
    Ensure apt can install the class lock's versions that the host's own sources dropped (a
    ROS archive after a sync): the controller's kept .debs of the group that no other source
    lists are served as a local source; none such, no local source.

    + root: the class's folder of kept .debs on the controller (roslab.class_debs.class_root)
    + key: the host's lock group (distro/architecture)
    + date: when the group was taken (the local Release's date)
    + lock_timeout: seconds apt waits for its lock

    Planned only for a host with a locked package to install or move; which versions are
    dropped is read when it runs, after the run has set the host's ROS source.
    """
    yield FunctionCommand(serve_dropped, (root, key, date, lock_timeout), {})
