"""`roslab sandbox publish PACKAGE --bump`: move the sandbox's "upstream" on purpose.

A class lock (roslab/class_lock.py) is about what happens when the archives move on. Here they
move when a test, or a teacher rehearsing an upgrade, says so: the package's newest .deb in the
instance's served archive is published again under a higher version (`<version>+roslab<N>`;
the same files, only the version moves), the way each archive really moves:

- a ROS package (in the ROS archive): its codename's index then lists ONLY the newer version,
  as packages.ros.org does after a sync, so a host can no longer install the older one from it;
- a Debian package (in the Ubuntu-layout archive): the newer version goes to every release's
  `-updates` suite, as an Ubuntu update does, and the release pocket keeps the older one.

The archives the instance serves are symbolic links into the machine's cache, shared by every
instance: the first publish gives the instance its own copy (indexes copied, .debs hard-linked,
so seconds and no space) and changes only that. `--revert` serves the cached archives again.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from roslab.ros.distro import DEFAULT_DISTRO, PLATFORMS

from . import upstream
from .system import SandboxError, run, write_file

RECORD = "published.json"  # beside them: the cached archives the instance served before
PACKAGE = re.compile(r"[a-z0-9][a-z0-9+.-]+")  # Debian policy 5.6.1
BUMPED = re.compile(r"(?P<base>.+)\+roslab(?P<n>[0-9]+)")
UPDATES_POOL = "pool/updates"  # the Ubuntu-layout archive's -updates suites list these


@dataclass(frozen=True)
class Published:
    """One newer version served: which package, in which archive suite, old and new version."""

    package: str
    suite: str
    old: str
    new: str

    def line(self) -> str:
        return f"{self.package} {self.old} -> {self.new} ({self.suite})"


def bumped_version(version: str) -> str:
    """A version Debian orders right after `version`: `+roslab1`, then `+roslab2`, ..."""
    match = BUMPED.fullmatch(version)
    if match:
        return f"{match['base']}+roslab{int(match['n']) + 1}"
    return f"{version}+roslab1"


def _deb_version(deb: Path) -> str:
    return run("dpkg-deb", "--field", deb, "Version").stdout.strip()


def _newest(debs: list[Path]) -> tuple[Path, str]:
    """The .deb of the highest version among `debs` and that version (Debian's ordering,
    dpkg's own compare); each .deb's version is read once."""
    newest, highest = debs[0], _deb_version(debs[0])
    for deb in debs[1:]:
        version = _deb_version(deb)
        if run("dpkg", "--compare-versions", version, "gt", highest, check=False).returncode == 0:
            newest, highest = deb, version
    return newest, highest


def _rebuilt(deb: Path, version: str, out_dir: Path) -> Path:
    """`deb`'s files and scripts again, as `version` (its control file's Version only)."""
    with tempfile.TemporaryDirectory(prefix="roslab-publish-") as work:
        root = Path(work) / "root"
        run("dpkg-deb", "--raw-extract", deb, root)
        control = root / "DEBIAN/control"
        text = control.read_text()
        control.write_text(re.sub(r"^Version: .*$", f"Version: {version}", text, count=1, flags=re.M))
        package = deb.name.split("_", 1)[0]
        architecture = re.search(r"^Architecture: *(\S+)", text, flags=re.M)
        if architecture is None:
            raise SandboxError(f"{deb}: its control file has no Architecture field")
        out = out_dir / f"{package}_{version.replace(':', '%3a')}_{architecture[1]}.deb"
        out_dir.mkdir(parents=True, exist_ok=True)
        run("dpkg-deb", "-Zgzip", "--build", root, out)
    return out


def own_copy(served: Path, archive: str) -> Path:
    """The instance's own copy of one served archive, made on first use from the cached one
    its symbolic link names (indexes copied, .debs hard-linked); the cached one is recorded."""
    path = served / archive
    if not path.is_symlink():
        return path
    cached = path.resolve()
    building = path.with_name(path.name + ".copying")
    shutil.rmtree(building, ignore_errors=True)
    shutil.copytree(cached / "dists", building / "dists")
    shutil.copytree(cached / "pool", building / "pool", copy_function=_link_or_copy)
    record = served / RECORD
    recorded = json.loads(record.read_text()) if record.exists() else {}
    recorded[archive] = str(cached)
    write_file(record, json.dumps(recorded, indent=2, sort_keys=True) + "\n")
    path.unlink()
    building.rename(path)
    return path


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system: a copy (slower, same result)
        shutil.copy2(source, target)


def bump(served: Path, package: str) -> list[Published]:
    """Publish `package`'s newest .deb again under a higher version, in whichever archive of
    the instance (`served`: its upstream folder) has it. Raises SandboxError when none has it."""
    if not PACKAGE.fullmatch(package):
        raise SandboxError(f"{package!r} is not a Debian package name")
    ros_pools = {codename: served / "ros2/ubuntu/pool/main" / codename for codename in DEFAULT_DISTRO}
    ros_debs = {codename: sorted(pool.glob(f"{package}_*.deb")) for codename, pool in ros_pools.items()}
    if any(ros_debs.values()):
        return _bump_ros(served, package, {codename: debs for codename, debs in ros_debs.items() if debs})
    ubuntu_debs = sorted((served / "ubuntu/pool").glob(f"*/{package}_*.deb"))
    if ubuntu_debs:
        return _bump_ubuntu(served, package, ubuntu_debs)
    raise SandboxError(f"{package}: no .deb of that name in the sandbox's ROS or Ubuntu archive "
                       f"(see {served / 'ros2/ubuntu/pool'} and {served / 'ubuntu/pool'})")


def _bump_ros(served: Path, package: str, found: dict[str, list[Path]]) -> list[Published]:
    """The newer version replaces every older one in its codename's pool and index (`found`:
    codename -> the package's .debs in its pool; the same paths in the instance's own copy)."""
    archive = own_copy(served, "ros2/ubuntu")
    done = []
    for codename, debs in sorted(found.items()):
        newest, old = _newest(debs)
        new = bumped_version(old)
        _rebuilt(newest, new, newest.parent)
        superseded = archive / "pool/superseded" / codename
        superseded.mkdir(parents=True, exist_ok=True)
        for deb in debs:  # out of the indexed pool: the index lists the newer version only
            deb.rename(superseded / deb.name)
        dist_dir = archive / "dists" / codename
        upstream.write_indexes(archive, dist_dir, "main", f"pool/main/{codename}")
        upstream.write_ros_release(dist_dir, codename, DEFAULT_DISTRO[codename])
        done.append(Published(package, f"ROS {codename}", old, new))
    return done


def _bump_ubuntu(served: Path, package: str, debs: list[Path]) -> list[Published]:
    """The newer version in every release's -updates suite; the release pockets keep the older."""
    archive = own_copy(served, "ubuntu")
    newest, old = _newest(debs)  # the same paths, now in the instance's own copy
    new = bumped_version(old)
    published = _rebuilt(newest, new, archive / UPDATES_POOL)
    for stale in published.parent.glob(f"{package}_*.deb"):  # -updates holds one version, the newest
        if stale != published:
            stale.unlink()
    done = []
    for platform in PLATFORMS:
        suite = f"{platform.codename}-updates"
        dist_dir = archive / "dists" / suite
        upstream.write_indexes(archive, dist_dir, "universe", UPDATES_POOL)
        upstream.write_ubuntu_release(dist_dir, suite, platform.codename, platform.release)
        done.append(Published(package, f"Ubuntu {suite}", old, new))
    return done


def revert(served: Path) -> list[str]:
    """Serve the cached archives again (what `up` served); the archives it gave back."""
    record = served / RECORD
    if not record.exists():
        return []
    reverted = []
    for archive, cached in sorted(json.loads(record.read_text()).items()):
        path = served / archive
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        path.symlink_to(cached)
        reverted.append(archive)
    record.unlink()
    return reverted
