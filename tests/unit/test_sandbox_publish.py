"""`roslab sandbox publish`: the versions it makes, and its command line (the archive moves are
proved end to end in tests/e2e/test_class_lock_e2e.py)."""

from __future__ import annotations

import subprocess

import pytest

from roslab.class_lock import VERSION
from roslab.sandbox import cli, publish
from roslab.sandbox.system import SandboxError


@pytest.mark.parametrize("version, expected", [
    ("0.0.0-1noble", "0.0.0-1noble+roslab1"),
    ("0.11.0-1noble.20250101.000000", "0.11.0-1noble.20250101.000000+roslab1"),
    ("0.12.1-1", "0.12.1-1+roslab1"),
    ("1:9.2p1-2+deb12u3", "1:9.2p1-2+deb12u3+roslab1"),
    ("0.0.0-1noble+roslab1", "0.0.0-1noble+roslab2"),
    ("0.0.0-1noble+roslab9", "0.0.0-1noble+roslab10"),
])
def test_a_bump_is_the_next_version_in_debians_order_and_one_the_lock_accepts(version, expected):
    bumped = publish.bumped_version(version)
    assert bumped == expected
    assert VERSION.fullmatch(bumped)
    ordered = subprocess.run(["dpkg", "--compare-versions", bumped, "gt", version])
    assert ordered.returncode == 0, f"{bumped} does not sort after {version}"


def test_a_package_name_that_is_not_debians_is_refused_before_any_file_is_read(tmp_path):
    with pytest.raises(SandboxError, match="is not a Debian package name"):
        publish.bump(tmp_path, "-oAPT::x=1")


def test_a_package_no_archive_has_is_named(tmp_path):
    with pytest.raises(SandboxError, match="ros-jazzy-nothing: no .deb of that name in the sandbox's ROS or Ubuntu"):
        publish.bump(tmp_path, "ros-jazzy-nothing")


def test_revert_with_nothing_published_changes_nothing(tmp_path):
    assert publish.revert(tmp_path) == []


def test_publish_needs_bump_or_revert():
    import argparse

    parser = argparse.ArgumentParser(prog="roslab")
    cli.register(parser.add_subparsers(dest="command", required=True))
    with pytest.raises(SystemExit):
        parser.parse_args(["sandbox", "publish", "ros-jazzy-desktop"])
    args = parser.parse_args(["sandbox", "publish", "ros-jazzy-desktop", "--bump"])
    assert (args.package, args.bump, args.revert) == ("ros-jazzy-desktop", True, False)


def tiny_deb(folder, package: str, version: str):
    """A one-file Architecture: all .deb (dpkg-deb, milliseconds)."""
    root = folder / f"{package}-{version}"
    (root / "DEBIAN").mkdir(parents=True)
    (root / "DEBIAN/control").write_text(f"Package: {package}\nVersion: {version}\nArchitecture: all\n"
                                         "Maintainer: roslab tests <t@invalid>\nDescription: a test package\n")
    (root / "usr/share/doc").mkdir(parents=True)
    (root / "usr/share/doc/x").write_text("x\n")
    out = folder / f"{package}_{version}_all.deb"
    subprocess.run(["dpkg-deb", "--root-owner-group", "--build", str(root), str(out)], check=True,
                   capture_output=True)
    return out


def test_a_debian_package_bumped_twice_leaves_one_newest_version_in_updates_and_the_cache_untouched(
        tmp_path, monkeypatch):
    """The Ubuntu-layout archive is a link into the machine's cache: the first publish copies it
    (the cached .deb hard-linked, never written), and -updates holds only the newest bump."""
    cached = tmp_path / "cache/ubuntu-archive"
    (cached / "dists/noble-updates").mkdir(parents=True)
    (cached / "pool/universe").mkdir(parents=True)
    original = tiny_deb(cached / "pool/universe", "python3-colcon-core", "0.12.1-1")
    served = tmp_path / "served"
    served.mkdir()
    (served / "ubuntu").symlink_to(cached)
    signed = []
    monkeypatch.setattr(publish.upstream, "write_ubuntu_release", lambda dist_dir, *args: signed.append(dist_dir))

    first = publish.bump(served, "python3-colcon-core")
    second = publish.bump(served, "python3-colcon-core")

    assert {done.new for done in first} == {"0.12.1-1+roslab1"}
    assert {(done.old, done.new) for done in second} == {("0.12.1-1+roslab1", "0.12.1-1+roslab2")}
    assert [deb.name for deb in (served / "ubuntu/pool/updates").iterdir()] == [
        "python3-colcon-core_0.12.1-1+roslab2_all.deb"]
    packages = (served / "ubuntu/dists/noble-updates/universe/binary-amd64/Packages").read_text()
    assert "Version: 0.12.1-1+roslab2\n" in packages and "+roslab1" not in packages
    assert not (served / "ubuntu").is_symlink() and sorted(p.name for p in cached.rglob("*.deb")) == [original.name]
    assert not (cached / "pool/updates").exists() and signed

    assert publish.revert(served) == ["ubuntu"]
    assert (served / "ubuntu").resolve() == cached.resolve()
