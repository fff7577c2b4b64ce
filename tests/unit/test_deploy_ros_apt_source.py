"""The ROS 2 apt source: a pinned, checked .deb fetched once; the mirror mode; no leftovers."""

from __future__ import annotations

import base64
import hashlib
import urllib.request

import pytest
from fixtures.classroom import HOST_DEB, host_data, with_stand_in_deb
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from fixtures.openpgp_keys import RSA_BINARY as RSA_TEST_KEY, RSA_FINGERPRINT as RSA_TEST_FINGERPRINT

from deploy.apt_ready import apt_lists
from deploy.ros_apt_source import ros_apt_source
from roslab import downloads, openpgp, quoting, settings
from roslab.openpgp import dearmored
from roslab.ops.apt import apt_update_command

OLD_LIST = "/etc/apt/sources.list.d/ros2.list"
SOURCES = "/etc/apt/sources.list.d/ros2.sources"
NAME = "ros2-apt-source_1.2.0.noble_all.deb"


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --- the controller's download and cache ------------------------------------------------


def test_the_deb_is_downloaded_once_checked_and_then_served_from_the_cache(tmp_path):
    origin = tmp_path / NAME
    origin.write_bytes(b"package bytes")
    pin = sha(b"package bytes")
    url = f"file://{origin}"
    assert downloads.pinned(url, pin, tmp_path / "cache", NAME, "ros_apt_source_sha256") == b"package bytes"
    assert (tmp_path / "cache" / pin / NAME).read_bytes() == b"package bytes"
    origin.unlink()  # a later run (a new process) must not need the origin again
    downloads._fetched.clear()
    assert downloads.pinned(url, pin, tmp_path / "cache", NAME, "ros_apt_source_sha256") == b"package bytes"


def test_a_download_with_the_wrong_sha256_is_discarded(tmp_path):
    origin = tmp_path / NAME
    origin.write_bytes(b"tampered")
    with pytest.raises(downloads.DownloadError, match="ros_apt_source_sha256 pins 0{64}: the file was discarded"):
        downloads.pinned(f"file://{origin}", "0" * 64, tmp_path / "cache", NAME, "ros_apt_source_sha256")
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.deb"))


def test_the_cache_is_keyed_by_the_pin_so_another_rosters_file_never_stands_in(tmp_path):
    """Two rosters on one controller share the cache dir: each pin has its own file."""
    cache = tmp_path / "cache"
    origin = tmp_path / NAME
    origin.write_bytes(b"the real package")
    pin = sha(b"the real package")
    # Another roster's (or an attacker's) file under the same name, and a corrupt copy under our pin.
    (cache / sha(b"other")).mkdir(parents=True)
    (cache / sha(b"other") / NAME).write_bytes(b"other")
    (cache / NAME).write_bytes(b"old flat cache entry")
    (cache / pin).mkdir()
    (cache / pin / NAME).write_bytes(b"half-written")
    assert downloads.pinned(f"file://{origin}", pin, cache, NAME, "ros_apt_source_sha256") == b"the real package"
    assert (cache / pin / NAME).read_bytes() == b"the real package"  # re-verified, replaced
    assert [p.name for p in (cache / pin).iterdir()] == [NAME]  # no temporary file left


def test_the_uploaded_bytes_are_the_checked_bytes_whatever_happens_to_the_cache_later(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    data = host_data(tmp_path)
    pin = data["ros_apt_source_sha256"]["noble"]
    with_cache_swapped = []

    def deploy_then_swap():
        ros_apt_source()
        # Between planning and the upload, someone replaces the cached file.
        cached = tmp_path / "cache" / pin / NAME
        cached.write_bytes(b"evil")
        with_cache_swapped.append(cached)

    result = plan(deploy_then_swap, host.facts(), data)
    assert with_cache_swapped
    assert result.uploads()[HOST_DEB.format(codename="noble")] == "stand-in ros2-apt-source for noble"


def test_a_failed_download_is_remembered_for_the_run(tmp_path, monkeypatch):
    calls = []

    def refuse(url, timeout):
        calls.append(url)
        raise OSError("Connection refused")

    monkeypatch.setattr(urllib.request, "urlopen", refuse)
    url = f"http://10.11.0.1/{tmp_path.name}/{NAME}"
    for _ in range(3):
        with pytest.raises(downloads.DownloadError, match=f"cannot download {url}: Connection refused"):
            downloads.fetch(url)
    assert calls == [url]


def test_a_failed_download_stops_only_the_hosts_that_need_it(tmp_path):
    data = host_data(tmp_path, ros_apt_source_url=f"file://{tmp_path}/gone/{{codename}}.deb")
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed and result.operations == []
    (error,) = result.errors
    assert "roslab stops this host: host pi (team team1): ros2-apt-source: cannot download" in error
    assert f"file://{tmp_path}/gone/noble.deb" in error and "nothing was changed on it" in error
    # A host that does not need it (mirror mode, or the step switched off) is not stopped.
    other = plan(ros_apt_source, FakeUbuntu().facts(), {**data, "ros_apt_source_enabled": False})
    assert not other.failed


# --- package mode -------------------------------------------------------------------------


def ros_apt_source_then_the_lists():
    ros_apt_source()
    apt_lists()


def test_package_mode_copies_the_deb_installs_it_and_moves_old_method_files_aside(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.ages["/var/lib/apt/periodic/update-success-stamp"] = 60  # young lists: the new source updates them
    host.files[OLD_LIST] = ["deb [signed-by=/usr/share/keyrings/ros-archive-keyring.gpg] http://packages.ros.org/ros2/ubuntu noble main"]
    result = plan(ros_apt_source_then_the_lists, host.facts(), host_data(tmp_path))
    host_deb = HOST_DEB.format(codename="noble")
    names = [op.name for op in result.operations]
    assert names.index(next(n for n in names if "old ROS 2 apt source" in n)) == 0  # before apt runs
    assert result.operation("old ROS 2 apt source files").text() == [
        "mkdir -p /var/backups/roslab", f"mv --backup=numbered {OLD_LIST} /var/backups/roslab",
    ]
    assert result.uploads()[host_deb] == "stand-in ros2-apt-source for noble"
    install = result.operation("ros2-apt-source 1.2.0 is installed").text()  # pyinfra's apt.deb
    assert install[-1] == f"dpkg --force-confdef --force-confold -i {host_deb}"
    assert result.operation("apt lists are fresh").text() == [apt_update_command(600)]


def test_package_mode_with_the_package_installed_is_a_noop(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(ros_apt_source, host.facts(), host_data(tmp_path)))
    host.links[SOURCES] = "/usr/share/ros-apt-source/ros2.sources"  # the package's own symlink
    result = plan(ros_apt_source, host.facts(), host_data(tmp_path))
    assert result.changing() == {}
    assert f"deb {HOST_DEB.format(codename='noble')} is installed" in result.noops


def test_a_codename_without_a_pinned_sha256_stops_only_that_host(tmp_path):
    data = host_data(tmp_path, ros_apt_source_sha256={"jammy": "0" * 64})
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed
    assert "ros_apt_source_sha256 has no sha256 for Ubuntu noble" in result.errors[0]


# --- mirror mode --------------------------------------------------------------------------

KEY = bytes(range(40))
ARMORED = (
    "-----BEGIN PGP PUBLIC KEY BLOCK-----\nComment: test mirror\n\n"
    + base64.b64encode(KEY).decode()
    + "\n=AbCd\n-----END PGP PUBLIC KEY BLOCK-----\n"
)


def test_dearmoring_gives_the_binary_key_and_leaves_binary_keys_alone():
    assert dearmored(ARMORED.encode()) == KEY
    assert dearmored(KEY) == KEY


def mirror_data(tmp_path, **more):
    key_file = tmp_path / "mirror.asc"
    key_file.write_text(ARMORED)
    mirror = {"ros_apt_mirror_url": "http://10.11.0.1/ros2", "ros_apt_mirror_key_file": str(key_file)}
    return host_data(tmp_path, ros_apt_source_mode="mirror", **{**mirror, **more})


def test_mirror_mode_writes_the_keyring_and_a_signed_by_source_and_drops_the_package(tmp_path):
    host = FakeUbuntu()
    host.packages["ros2-apt-source"] = {"1.2.0.noble"}
    data = mirror_data(tmp_path)
    result = plan(ros_apt_source, host.facts(), data)
    assert result.operation("ros2-apt-source package is not installed").text() == [
        "DEBIAN_FRONTEND=noninteractive apt-get -y -o Dpkg::Options::=\"--force-confdef\" "
        "-o Dpkg::Options::=\"--force-confold\" purge -o DPkg::Lock::Timeout=600 -- ros2-apt-source"
    ]
    assert result.uploads()["/usr/share/keyrings/ros2-archive-keyring.gpg"].encode("latin-1") == KEY
    assert result.uploads()[SOURCES].splitlines()[1:] == [
        "Types: deb",
        "URIs: http://10.11.0.1/ros2",
        "Suites: noble",
        "Components: main",
        "Signed-By: /usr/share/keyrings/ros2-archive-keyring.gpg",
    ]
    host.apply(result)
    host.packages.pop("ros2-apt-source")  # FakeUbuntu models `dpkg --purge`, not apt-get purge
    assert plan(ros_apt_source, host.facts(), data).changing() == {}


def test_mirror_mode_without_a_url_stops_that_host_naming_the_field(tmp_path):
    data = host_data(tmp_path, ros_apt_source_mode="mirror", ros_apt_mirror_key_file="/k.asc")
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed
    assert "host pi (team team1): ros_apt_source_mode is 'mirror' but ros_apt_mirror_url is not set" in result.errors[0]


def test_an_unreadable_mirror_key_stops_that_host(tmp_path):
    data = mirror_data(tmp_path, ros_apt_mirror_key_file=str(tmp_path / "missing.asc"))
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed and "ros_apt_mirror_key_file" in result.errors[0]


@pytest.mark.parametrize("url", [
    "http://10.11.0.1/ros2\nTrusted: yes",
    "http://10.11.0.1/ros2 [trusted=yes]",
    "http://10.11.0.1/ros2\u2028Trusted: yes",
    "ftp://10.11.0.1/ros2",
])
def test_a_mirror_url_that_would_add_a_field_is_refused_by_the_schema_and_the_writer(url):
    assert settings.check_value(settings.SETTINGS["ros_apt_mirror_url"], url)
    if "\n" in url or "\u2028" in url:
        with pytest.raises(ValueError):
            quoting.deb822_value(url)


def test_a_legal_but_awkward_mirror_url_is_written_exactly(tmp_path):
    url = "https://mirror.example.org:8443/ros2/ubuntu/?token=a%20b&x=1;y"
    assert settings.check_value(settings.SETTINGS["ros_apt_mirror_url"], url) is None
    result = plan(ros_apt_source, FakeUbuntu().facts(), mirror_data(tmp_path, ros_apt_mirror_url=url))
    assert f"URIs: {url}" in result.uploads()[SOURCES].splitlines()


# --- snapshot mode ----------------------------------------------------------------------------

SNAPSHOT_MIRROR = "http://10.11.0.1/ros-snapshots"


def snapshot_data(tmp_path, codename="noble", **more):
    """Snapshot mode from a local mirror of the snapshot server (its own key, a test key)."""
    key_file = tmp_path / "snapshots.asc"
    key_file.write_bytes(RSA_TEST_KEY)
    snapshot = {"ros_apt_snapshot": "2026-08-07", "ros_apt_snapshot_url": SNAPSHOT_MIRROR,
                "ros_apt_snapshot_key_file": str(key_file)}
    return host_data(tmp_path, codename=codename, ros_apt_source_mode="snapshot", **{**snapshot, **more})


@pytest.mark.parametrize("codename, distro", [("noble", "jazzy"), ("jammy", "humble")])
def test_snapshot_mode_points_the_ros_source_at_the_distros_snapshot_and_drops_the_package(tmp_path, codename,
                                                                                        distro):
    host = FakeUbuntu(codename=codename)
    host.packages["ros2-apt-source"] = {f"1.2.0.{codename}"}
    data = snapshot_data(tmp_path, codename)
    result = plan(ros_apt_source, host.facts(), data)
    assert result.uploads()["/usr/share/keyrings/ros2-archive-keyring.gpg"].encode("latin-1") == RSA_TEST_KEY
    assert result.uploads()[SOURCES].splitlines()[1:] == [
        "Types: deb",
        f"URIs: {SNAPSHOT_MIRROR}/{distro}/2026-08-07/ubuntu",
        f"Suites: {codename}",
        "Components: main",
        "Signed-By: /usr/share/keyrings/ros2-archive-keyring.gpg",
    ]
    assert "ros2-apt-source package is not installed (the ROS " in " ".join(result.changing())
    host.apply(result)
    host.packages.pop("ros2-apt-source")  # FakeUbuntu models `dpkg --purge`, not apt-get purge
    assert plan(ros_apt_source, host.facts(), data).changing() == {}


def test_from_snapshots_ros_org_only_its_own_key_is_taken(tmp_path):
    data = snapshot_data(tmp_path, ros_apt_snapshot_url="http://snapshots.ros.org")
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed and result.changing() == {}
    assert (f"ros_apt_snapshot_key_file {tmp_path / 'snapshots.asc'} holds the key "
            f"{openpgp.spaced(RSA_TEST_FINGERPRINT)}, not snapshots.ros.org's "
            "(4B63 CF8F DE49 746E 98FA  01DD AD19 BAB3 CBF1 25EA); nothing was changed on it") in result.errors[0]


def test_snapshot_mode_on_a_distro_without_snapshots_stops_that_host(tmp_path):
    data = snapshot_data(tmp_path, ros_distro="kilted")
    result = plan(ros_apt_source, FakeUbuntu().facts(), data)
    assert result.failed and "ROS kilted is not an LTS distro" in result.errors[0]


def test_snapshot_mode_without_a_snapshot_stops_that_host_naming_the_field(tmp_path):
    result = plan(ros_apt_source, FakeUbuntu().facts(), snapshot_data(tmp_path, ros_apt_snapshot=None))
    assert result.failed
    assert "ros_apt_source_mode is 'snapshot' but ros_apt_snapshot is not set" in result.errors[0]


@pytest.mark.parametrize("value, good", [("2026-08-07", True), ("final", True), ("2026-02-30", False),
                                         ("2026-8-7", False), ("latest", False), ("2026-08-07\nx", False)])
def test_a_snapshot_is_a_real_date_or_final(value, good):
    problem = settings.check_value(settings.SETTINGS["ros_apt_snapshot"], value)
    assert (problem is None) is good, problem
