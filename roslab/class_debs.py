"""The class lock's .debs, kept by the controller (issue 39): what brings a locked version back
after its archive dropped it.

apt installs only a version some index lists, and packages.ros.org lists one version of each
package: after a sync (every few weeks) the version a class locked is gone from its index, and
a re-imaged Pi could not install it. So `roslab lock` keeps, per lock group, the .debs of the
locked packages that apt downloaded onto the group's hosts (what roslab's runs installed; the
image's own packages come with the image, on every Pi), and `roslab lock --update` the versions
it moves them to. Each file is downloaded on a host of the group (`apt-get download`, while its
sources still list it) and checked on the controller against the SHA256 of the index that apt
verified on that host (`apt-cache show`), under class_lock_debs_dir, in a folder per class (its
roster's folder: `class_root`):

    <class_lock_debs_dir>/<class>/<distro>-<architecture>/Packages        a stanza per kept .deb
    <class_lock_debs_dir>/<class>/<distro>-<architecture>/<file>.deb

Only locked versions are kept: what a move replaced is removed (`pruned`). A run whose host has
a locked package to install or move serves it the kept .debs its own sources no longer list, as
a local apt source (roslab.ops.class_debs).

Everything read from a host is hostile until checked here: a stanza keeps only the fields apt
needs, each one line of printable text; a name and version are checked as the lock checks them,
a file name has no path, a SHA256 is 64 hex digits.
"""

from __future__ import annotations

import hashlib
import os
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from email.utils import format_datetime
from pathlib import Path

from roslab.class_lock import PACKAGE_NAME, SHA256, VERSION, LockedGroup
from roslab.controller_files import file_sha256, replace_file

PACKAGES_FILE = "Packages"
ARCHITECTURE = re.compile(r"[a-z0-9]+")
SIZE = re.compile(r"[0-9]{1,12}")
DEB_FILE = re.compile(r"[A-Za-z0-9][A-Za-z0-9+.~%_-]*\.deb")
ONE_LINE = re.compile(r"[^\x00-\x1f\x7f]*")
# The fields a kept stanza carries: what apt resolves and installs with (the long description,
# tags and translations' checksums are left out). Filename is the kept file's, next to it.
FIELDS = ("Package", "Version", "Architecture", "Multi-Arch", "Essential", "Priority", "Section",
          "Installed-Size", "Maintainer", "Source", "Depends", "Pre-Depends", "Recommends", "Suggests",
          "Enhances", "Breaks", "Conflicts", "Replaces", "Provides", "Size", "SHA256", "Description")


@dataclass(frozen=True)
class KeptDeb:
    """One .deb of the class, as the index its host verified describes it."""

    name: str
    version: str
    architecture: str
    file: str  # the file's name in the group's folder (the archive's pool name, no path)
    sha256: str
    size: int
    fields: tuple[tuple[str, str], ...]  # the stanza's fields (FIELDS), checked, Filename excluded

    def stanza(self) -> str:
        """The stanza of the group's Packages file: who it is, what apt resolves it with, then
        the file (beside it), its size and sha256 that apt checks it against."""
        own = ("Package", "Version", "Architecture", "Size", "SHA256")
        lines = [f"Package: {self.name}", f"Version: {self.version}", f"Architecture: {self.architecture}",
                 *(f"{name}: {value}" for name, value in self.fields if name not in own),
                 f"Filename: ./{self.file}", f"Size: {self.size}", f"SHA256: {self.sha256}"]
        return "\n".join(lines) + "\n"


def class_root(debs_dir: str | Path, roster_path: str | Path) -> Path:
    """The class's own folder under class_lock_debs_dir: named by the roster's folder and a digest
    of its real path, so that two classes on one controller (a Pi class and the sandbox both have
    a jazzy/amd64 group) never prune each other's kept .debs."""
    folder = os.path.realpath(os.path.dirname(os.path.abspath(os.path.expanduser(str(roster_path)))))
    name = re.sub(r"[^A-Za-z0-9._-]+", "-", os.path.basename(folder)).strip(".-")[:40] or "class"
    return Path(debs_dir).expanduser() / f"{name}-{hashlib.sha256(folder.encode()).hexdigest()[:12]}"


def folder(root: str | Path, key: str) -> Path:
    """The group's folder under the class's (class_root; `jazzy/arm64` -> `jazzy-arm64`)."""
    return Path(root).expanduser() / key.replace("/", "-")


def download_name(name: str, version: str, architecture: str) -> str:
    """The name `apt-get download` gives the file (an epoch's colon written %3a)."""
    return f"{name}_{version.replace(':', '%3a')}_{architecture}.deb"


def parse_stanzas(text: str) -> list[dict[str, str]]:
    """The stanzas of an index or of `apt-cache show`, each field -> its first line."""
    stanzas: list[dict[str, str]] = []
    current: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            if current:
                stanzas.append(current)
            current = {}
        elif not line[0].isspace() and ":" in line:
            name, value = line.split(":", 1)
            current.setdefault(name.strip(), value.strip())
    if current:
        stanzas.append(current)
    return stanzas


def checked(fields: dict[str, str]) -> KeptDeb | None:
    """The stanza as a KeptDeb, or None if anything in it is not what an index says."""
    name, version = fields.get("Package", ""), fields.get("Version", "")
    architecture, sha256 = fields.get("Architecture", ""), fields.get("SHA256", "")
    file = os.path.basename(fields.get("Filename", ""))
    if not (PACKAGE_NAME.fullmatch(name) and VERSION.fullmatch(version) and ARCHITECTURE.fullmatch(architecture)
            and SHA256.fullmatch(sha256) and SIZE.fullmatch(fields.get("Size", "")) and DEB_FILE.fullmatch(file)):
        return None
    kept = tuple((field, fields[field]) for field in FIELDS
                 if field in fields and ONE_LINE.fullmatch(fields[field]))
    return KeptDeb(name, version, architecture, file, sha256, int(fields["Size"]), kept)


def indexed(text: str) -> dict[tuple[str, str], KeptDeb]:
    """(name, version) -> the first checked stanza with a SHA256 (`apt-cache show` prints the
    installed package's status record too, which has none)."""
    found: dict[tuple[str, str], KeptDeb] = {}
    for fields in parse_stanzas(text):
        deb = checked(fields)
        if deb is not None:
            found.setdefault((deb.name, deb.version), deb)
    return found


def read_kept(root: str | Path, key: str) -> dict[tuple[str, str], KeptDeb]:
    """The group's kept .debs whose file is there, by (name, version)."""
    path = folder(root, key)
    try:
        text = (path / PACKAGES_FILE).read_text()
    except (FileNotFoundError, NotADirectoryError):
        return {}
    return {pair: deb for pair, deb in indexed(text).items()
            if (path / deb.file).is_file()}


def write_kept(root: str | Path, key: str, debs: dict[tuple[str, str], KeptDeb]) -> None:
    """The group's Packages file: a stanza per kept .deb, sorted (rewritten whole, atomically)."""
    path = folder(root, key)
    path.mkdir(parents=True, exist_ok=True)
    replace_file(path / PACKAGES_FILE, "\n".join(debs[pair].stanza() for pair in sorted(debs)))


def wanted(group: LockedGroup, downloaded: list[str], architecture: str, kept: dict,
           kept_before: dict | None = None) -> list[tuple[str, str]]:
    """(name, version) the group's folder should keep and lacks (`kept`): each locked package
    whose locked version's .deb is in the host's apt cache (`downloaded`: its file names), and
    each package kept at another version before (`kept_before`: moved by `roslab lock --update`), sorted."""
    files = set(downloaded)
    names_kept = {name for name, _version in [*kept, *(kept_before or {})]}
    out = set()
    for name, version in group.packages.items():
        if (name, version) in kept:
            continue
        if name in names_kept or any(download_name(name, version, arch) in files for arch in (architecture, "all")):
            out.add((name, version))
    return sorted(out)


def kept_file(root: str | Path, key: str, deb: KeptDeb, downloaded: Path) -> str | None:
    """Move a downloaded file into the group's folder if its sha256 is the index's; else remove
    it and say why (one line)."""
    if file_sha256(downloaded) != deb.sha256:  # read in blocks: a .deb may be hundreds of MB
        downloaded.unlink(missing_ok=True)
        return f"{deb.name}={deb.version}: the downloaded file's sha256 is not its index's: not kept"
    target = folder(root, key) / deb.file
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(downloaded, target)
    return None


def pruned(root: str | Path, key: str, group: LockedGroup,
           debs: dict[tuple[str, str], KeptDeb]) -> dict[tuple[str, str], KeptDeb]:
    """`debs` without the versions the lock no longer names (their files removed), and without
    files that do not match their stanza any more."""
    path = folder(root, key)
    out = {}
    for pair, deb in debs.items():
        if group.packages.get(deb.name) == deb.version and file_sha256(path / deb.file) == deb.sha256:
            out[pair] = deb
    files = {deb.file for deb in out.values()}
    for entry in path.glob("*.deb") if path.is_dir() else ():
        if entry.name not in files:
            entry.unlink(missing_ok=True)
    return out


def release_file(packages: str, taken: str) -> str:
    """A flat repository's Release for `packages` (the Packages file's text): its SHA256 and size,
    which apt checks the Packages file against, dated when the group was taken (`taken`, as the
    lock writes it). Unsigned: the source is `Trusted: yes`, written by root on the host, and each
    .deb was checked when the controller kept it."""
    data = packages.encode()
    when = datetime.strptime(taken, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=timezone.utc)
    return f"Date: {format_datetime(when, usegmt=True)}\nSHA256:\n {hashlib.sha256(data).hexdigest()} {len(data)} {PACKAGES_FILE}\n"
