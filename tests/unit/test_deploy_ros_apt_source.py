"""The ROS 2 apt source: a pinned, checked .deb fetched once; the mirror mode; no leftovers."""

from __future__ import annotations

import base64
import hashlib

import pytest
from fixtures.classroom import HOST_DEB, host_data, with_stand_in_deb
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.api import DeployError

from deploy.ros_apt_source import cached_package, dearmored, ros_apt_source

OLD_LIST = "/etc/apt/sources.list.d/ros2.list"
SOURCES = "/etc/apt/sources.list.d/ros2.sources"


def test_the_deb_is_downloaded_once_checked_and_then_served_from_the_cache(tmp_path):
    origin = tmp_path / "ros2-apt-source_1.2.0.noble_all.deb"
    origin.write_bytes(b"package bytes")
    sha = hashlib.sha256(b"package bytes").hexdigest()
    cached = cached_package(f"file://{origin}", sha, tmp_path / "cache")
    assert cached.read_bytes() == b"package bytes"
    origin.unlink()  # a second host (or run) must not need the origin again
    assert cached_package(f"file://{origin}", sha, tmp_path / "cache") == cached


def test_a_download_with_the_wrong_sha256_is_discarded_and_stops_the_run(tmp_path):
    origin = tmp_path / "ros2-apt-source_1.2.0.noble_all.deb"
    origin.write_bytes(b"tampered")
    with pytest.raises(DeployError, match="pins 0{64}: the file was discarded"):
        cached_package(f"file://{origin}", "0" * 64, tmp_path / "cache")
    assert list((tmp_path / "cache").iterdir()) == []


def test_package_mode_copies_the_deb_installs_it_and_moves_old_method_files_aside(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.files[OLD_LIST] = ["deb [signed-by=/usr/share/keyrings/ros-archive-keyring.gpg] http://packages.ros.org/ros2/ubuntu noble main"]
    result = plan(ros_apt_source, host.facts(), host_data(tmp_path))
    host_deb = HOST_DEB.format(codename="noble")
    assert result.operation("old ROS 2 apt source files").text() == [
        "mkdir -p /var/backups/roslab", f"mv --backup=numbered {OLD_LIST} /var/backups/roslab",
    ]
    assert result.uploads()[host_deb] == "stand-in ros2-apt-source for noble"
    assert result.operation("ros2-apt-source 1.2.0 is installed").text() == [
        f"dpkg --force-confdef --force-confold -i {host_deb}"
    ]
    assert result.operation("include the ROS 2 source").text()[0].endswith("update")


def test_package_mode_with_the_package_installed_is_a_noop(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(ros_apt_source, host.facts(), host_data(tmp_path)))
    host.links[SOURCES] = "/usr/share/ros-apt-source/ros2.sources"  # the package's own symlink
    result = plan(ros_apt_source, host.facts(), host_data(tmp_path))
    assert result.changing() == {}
    assert "ros2-apt-source 1.2.0.noble is already installed" in result.noops


def test_a_codename_without_a_pinned_sha256_is_a_clear_error(tmp_path):
    data = host_data(tmp_path, ros_apt_source_sha256={"jammy": "0" * 64})
    with pytest.raises(DeployError, match="ros_apt_source_sha256 has no sha256 for Ubuntu noble"):
        plan(ros_apt_source, FakeUbuntu().facts(), data)


KEY = bytes(range(40))
ARMORED = (
    "-----BEGIN PGP PUBLIC KEY BLOCK-----\nComment: test mirror\n\n"
    + base64.b64encode(KEY).decode()
    + "\n=AbCd\n-----END PGP PUBLIC KEY BLOCK-----\n"
)


def test_dearmoring_gives_the_binary_key_and_leaves_binary_keys_alone():
    assert dearmored(ARMORED.encode()) == KEY
    assert dearmored(KEY) == KEY


def test_mirror_mode_writes_the_keyring_and_a_signed_by_source_and_drops_the_package(tmp_path):
    key_file = tmp_path / "mirror.asc"
    key_file.write_text(ARMORED)
    host = FakeUbuntu()
    host.packages["ros2-apt-source"] = {"1.2.0.noble"}
    data = host_data(tmp_path, ros_apt_source_mode="mirror", ros_apt_mirror_url="http://10.11.0.1/ros2",
                     ros_apt_mirror_key_file=str(key_file))
    result = plan(ros_apt_source, host.facts(), data)
    assert result.operation("ros2-apt-source package is not installed").text() == ["dpkg --purge ros2-apt-source"]
    assert result.uploads()["/usr/share/keyrings/ros2-archive-keyring.gpg"].encode("latin-1") == KEY
    assert result.uploads()[SOURCES].splitlines()[1:] == [
        "Types: deb",
        "URIs: http://10.11.0.1/ros2",
        "Suites: noble",
        "Components: main",
        "Signed-By: /usr/share/keyrings/ros2-archive-keyring.gpg",
    ]
    host.apply(result)
    assert plan(ros_apt_source, host.facts(), data).changing() == {}


def test_mirror_mode_without_a_url_names_the_missing_field(tmp_path):
    data = host_data(tmp_path, ros_apt_source_mode="mirror", ros_apt_mirror_key_file="/k.asc")
    with pytest.raises(DeployError, match="host pi \\(team team1\\).*ros_apt_mirror_url is not set"):
        plan(ros_apt_source, FakeUbuntu().facts(), data)
