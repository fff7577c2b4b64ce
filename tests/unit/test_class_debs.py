"""The class lock's kept .debs (roslab/class_debs.py, roslab/ops/class_debs.py): what the controller
keeps, checked against the index a host verified, and how a run serves a host the locked versions
its sources dropped (issue 39). End to end: tests/e2e/test_class_lock_e2e.py."""

from __future__ import annotations

import hashlib
from types import SimpleNamespace

import pytest

from roslab import class_debs
from roslab.class_lock import LockedGroup
from roslab.ops import class_debs as debs_ops

KEY = "jazzy/amd64"
TAKEN = "2026-11-28T22:00:00Z"
DESKTOP = ("ros-jazzy-desktop", "0.11.0-1noble.20250101.000000")
BODY = b"!<arch>\nnot really a deb, but its bytes are what the sha256 is of\n"


def stanza(name=DESKTOP[0], version=DESKTOP[1], body=BODY, **more) -> str:
    fields = {"Package": name, "Version": version, "Architecture": "amd64", "Depends": "ros-jazzy-ros-base",
              "Filename": f"pool/main/r/{name}/{name}_{version.split(':')[-1]}_amd64.deb",
              "Size": str(len(body)), "SHA256": hashlib.sha256(body).hexdigest(),
              "Description": "ROS desktop", **more}
    return "".join(f"{key}: {value}\n" for key, value in fields.items())


def group(**packages) -> LockedGroup:
    return LockedGroup(TAKEN, "team1-main", {DESKTOP[0]: DESKTOP[1], "libc6": "2.39-0ubuntu8.4", **packages})


def keep(root, text=None, body=BODY):
    deb = class_debs.indexed(text or stanza(body=body))[DESKTOP]
    incoming = root / "incoming.deb"
    incoming.write_bytes(body)
    assert class_debs.kept_file(root, KEY, deb, incoming) is None
    class_debs.write_kept(root, KEY, {DESKTOP: deb})
    return deb


def test_a_kept_deb_is_read_back_with_its_stanza_pointing_at_the_file_beside_it(tmp_path):
    deb = keep(tmp_path)
    folder = tmp_path / "jazzy-amd64"
    assert (folder / deb.file).read_bytes() == BODY
    text = (folder / "Packages").read_text()
    assert f"Filename: ./{deb.file}\n" in text and "Depends: ros-jazzy-ros-base\n" in text
    assert class_debs.read_kept(tmp_path, KEY) == {DESKTOP: deb}
    (folder / deb.file).unlink()  # a stanza without its file is not kept
    assert class_debs.read_kept(tmp_path, KEY) == {}


def test_each_class_keeps_its_debs_in_a_folder_of_its_own_named_by_its_rosters_folder(tmp_path):
    """Two classes on one controller (a Pi class with a desktop main and the sandbox: both have a
    jazzy/amd64 group) never prune each other's .debs; one class reached by another path is one."""
    (tmp_path / "lab a").mkdir()
    (tmp_path / "sandbox").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "lab a")
    lab = class_debs.class_root("~/debs", tmp_path / "lab a" / "classroom.yaml")
    assert lab.parent == class_debs.Path("~/debs").expanduser() and lab.name.startswith("lab-a-")
    assert lab != class_debs.class_root("~/debs", tmp_path / "sandbox" / "classroom.yaml")
    assert lab == class_debs.class_root("~/debs", tmp_path / "link" / "other.yaml")


def test_a_file_whose_sha256_is_not_the_index_one_is_not_kept(tmp_path):
    deb = class_debs.indexed(stanza())[DESKTOP]
    incoming = tmp_path / "incoming.deb"
    incoming.write_bytes(BODY + b"tampered")
    problem = class_debs.kept_file(tmp_path, KEY, deb, incoming)
    assert problem == f"{DESKTOP[0]}={DESKTOP[1]}: the downloaded file's sha256 is not its index's: not kept"
    assert not incoming.exists() and not (tmp_path / "jazzy-amd64" / deb.file).exists()


@pytest.mark.parametrize("field, value", [
    ("Package", "-oAPT::x=1"), ("Version", "1.0; rm -rf /"), ("Architecture", "amd 64"),
    ("SHA256", "0" * 63), ("Size", "-1"), ("Filename", "pool/../../etc/passwd"), ("Filename", "pool/x.tar"),
])
def test_a_hostile_stanza_from_a_host_is_not_kept(field, value):
    assert class_debs.indexed(stanza(**{field: value})) == {}


def test_a_field_with_a_control_character_is_left_out_and_the_long_description_is_not_carried():
    text = stanza(Depends="libc6\x1b[31m") + " a long description\n .\n more\n"
    deb = class_debs.indexed(text)[DESKTOP]
    assert "Depends" not in dict(deb.fields) and dict(deb.fields)["Description"] == "ROS desktop"
    assert "long description" not in deb.stanza()


def test_apt_cache_shows_the_status_record_first_and_the_index_record_is_taken():
    status = "Package: ros-jazzy-desktop\nVersion: 0.11.0-1noble.20250101.000000\nStatus: install ok installed\n"
    assert class_debs.indexed(status + "\n" + stanza())[DESKTOP].sha256 == hashlib.sha256(BODY).hexdigest()


def test_the_wanted_debs_are_the_locked_versions_in_the_hosts_apt_cache_and_the_moved_kept_ones():
    downloaded = [class_debs.download_name(*DESKTOP, "amd64"), "libc6_2.39-0ubuntu9_amd64.deb",
                  class_debs.download_name("python3-colcon-core", "0.15.0-1", "all")]
    locked = group(**{"python3-colcon-core": "0.15.0-1"})
    # libc6 is in the cache at another version than locked: not wanted
    assert class_debs.wanted(locked, downloaded, "amd64", {}) == [("python3-colcon-core", "0.15.0-1"), DESKTOP]
    kept = {DESKTOP: object()}
    assert class_debs.wanted(locked, downloaded, "amd64", kept) == [("python3-colcon-core", "0.15.0-1")]
    moved = group(**{"ros-jazzy-desktop": "0.12.0-1noble"})  # `--update` moved a kept package (pruned since)
    assert class_debs.wanted(moved, [], "amd64", {}, kept) == [("ros-jazzy-desktop", "0.12.0-1noble")]


def test_an_epoch_is_written_as_apt_get_download_names_the_file():
    assert class_debs.download_name("vim", "2:9.1.0016-1ubuntu7", "amd64") == "vim_2%3a9.1.0016-1ubuntu7_amd64.deb"


def test_versions_no_longer_locked_and_files_not_matching_are_pruned(tmp_path):
    deb = keep(tmp_path)
    assert class_debs.pruned(tmp_path, KEY, group(), {DESKTOP: deb}) == {DESKTOP: deb}
    (tmp_path / "jazzy-amd64" / "stray.deb").write_bytes(b"x")
    moved = group(**{"ros-jazzy-desktop": "0.12.0-1noble"})
    assert class_debs.pruned(tmp_path, KEY, moved, {DESKTOP: deb}) == {}
    assert list((tmp_path / "jazzy-amd64").glob("*.deb")) == []


def test_the_release_names_the_packages_files_sha256_and_the_lock_date():
    release = class_debs.release_file("Package: x\n", TAKEN)
    assert release.startswith("Date: Sat, 28 Nov 2026 22:00:00 GMT\nSHA256:\n ")
    assert f" {hashlib.sha256(b'Package: x').hexdigest()[:8]}" not in release  # the whole text's digest
    assert f" {hashlib.sha256(b'Package: x' + bytes([10])).hexdigest()} 11 Packages\n" in release


# --- on the host -------------------------------------------------------------------------------

def test_the_facts_never_pass_an_option_to_apt():
    command = debs_ops.IndexedDebs().command(["ros-jazzy-desktop=1.0-1", "-oAPT::x=1", "x=1;reboot"])
    assert command == "apt-cache show -- ros-jazzy-desktop=1.0-1 2>/dev/null || true"
    script = debs_ops.listed_script(["libc6", "--evil"], 60)
    assert "apt-cache madison -- libc6;" in script
    assert debs_ops.DownloadedDebs().process(["a_1_amd64.deb", "partial", "lock", "../x.deb"]) == ["a_1_amd64.deb"]


def test_versions_listed_by_the_served_folder_itself_do_not_count_as_listed():
    lines = [f" ros-jazzy-desktop | 0.12.0-1noble | http://packages.ros.org/ros2/ubuntu noble/main amd64 Packages",
             f" ros-jazzy-desktop | {DESKTOP[1]} | file:{debs_ops.LOCAL_DIR} ./ Packages",
             debs_ops.SECTION, f"{'a' * 64}  ros-jazzy-desktop_0.11.0_amd64.deb", "garbage"]
    listed, served = debs_ops.parse_listed(lines)
    assert listed == {"ros-jazzy-desktop": {"0.12.0-1noble"}}
    assert served == {"ros-jazzy-desktop_0.11.0_amd64.deb": "a" * 64}


# pyinfra's State as serve_dropped reads it: the executing operation's arguments (a sudo password
# the roster gives goes with every command; a non-connector argument does not)
STATE = SimpleNamespace(get_op_data_for_host=lambda host, op_hash: SimpleNamespace(
    global_arguments={"_sudo_password": "secret", "_serial": False}))


class Host:
    """pyinfra's Host as serve_dropped uses it: commands answered by `madison`, files put recorded."""

    def __init__(self, madison: list[str]):
        self.madison, self.scripts, self.put, self.logged = madison, [], {}, []
        self.executing_op_hash = "op"

    def run_shell_command(self, command, **arguments):
        assert arguments == {"_sudo": True, "_sudo_password": "secret"}
        script = command.bits[-1].obj if hasattr(command.bits[-1], "obj") else str(command.bits[-1])
        self.scripts.append(script)
        lines = self.madison + [debs_ops.SECTION] if "madison" in script else []
        return True, SimpleNamespace(stdout_lines=lines, stderr_lines=[])

    def put_file(self, source, remote, **arguments):
        assert arguments == {"mode": 0o644, "user": "root", "group": "root", "_sudo": True, "_sudo_password": "secret"}
        self.put[remote] = source.read().decode() if hasattr(source, "read") else open(source, "rb").read()
        return True

    def log(self, message, *_):
        self.logged.append(message)

    def log_styled(self, message, **_):
        self.logged.append(message)


def test_a_host_is_served_exactly_the_kept_versions_its_sources_dropped(tmp_path):
    deb = keep(tmp_path)
    host = Host([" ros-jazzy-desktop | 0.12.0-1noble | http://packages.ros.org/ros2/ubuntu noble/main"])
    assert debs_ops.serve_dropped(STATE, host, str(tmp_path), KEY, TAKEN, 60)
    assert host.put[f"{debs_ops.LOCAL_DIR}/{deb.file}"] == BODY
    assert host.put[f"{debs_ops.LOCAL_DIR}/Packages"] == deb.stanza()
    assert "Trusted: yes" in host.put[debs_ops.SOURCE_FILE] and f"file:{debs_ops.LOCAL_DIR}" in host.put[debs_ops.SOURCE_FILE]
    assert "update" in host.scripts[-1]
    assert host.logged == [f"roslab: class lock: 1 locked version(s) no source lists any more, served from the "
                           f"class's kept .debs: {DESKTOP[0]}={DESKTOP[1]}"]


def test_a_host_whose_sources_list_every_kept_version_gets_no_local_source(tmp_path):
    keep(tmp_path)
    host = Host([f" ros-jazzy-desktop | {DESKTOP[1]} | http://packages.ros.org/ros2/ubuntu noble/main"])
    assert debs_ops.serve_dropped(STATE, host, str(tmp_path), KEY, TAKEN, 60)
    assert host.put == {}
    assert f"rm -rf {debs_ops.SOURCE_FILE} {debs_ops.LOCAL_DIR}" in host.scripts[-1]


def test_a_kept_file_changed_on_the_controller_is_never_served(tmp_path):
    deb = keep(tmp_path)
    (tmp_path / "jazzy-amd64" / deb.file).write_bytes(BODY + b"changed")
    host = Host([" ros-jazzy-desktop | 0.12.0-1noble | http://packages.ros.org/ros2/ubuntu noble/main"])
    assert not debs_ops.serve_dropped(STATE, host, str(tmp_path), KEY, TAKEN, 60)
    assert host.put == {}
    assert host.logged == [f"roslab: class lock: {tmp_path / 'jazzy-amd64' / deb.file} is not the file `roslab lock` "
                           "kept (its sha256 differs): remove it and run `roslab lock` again while an archive lists it"]


def test_a_class_debs_folder_that_cannot_be_written_is_one_line_and_exit_status_1(tmp_path, capsys, monkeypatch):
    from roslab.class_lock import ClassLock
    from roslab.cli import lock as lock_cli

    def full(*_):
        raise OSError(28, "No space left on device")

    reader = SimpleNamespace(name="team1-main")
    monkeypatch.setattr("roslab.host_settings.host_settings",
                        lambda host: SimpleNamespace(class_lock_debs_dir=str(tmp_path / "debs")))
    monkeypatch.setattr(lock_cli, "kept_group", full)
    found = {KEY: {"readers": [(None, reader, "amd64")]}}
    assert lock_cli.keep_debs(found, ClassLock(groups={KEY: group()}), tmp_path / "classroom.yaml") == 1
    folder = class_debs.folder(class_debs.class_root(tmp_path / "debs", tmp_path / "classroom.yaml"), KEY)
    assert capsys.readouterr().out == f"{KEY}: its .debs were not kept in {folder}: [Errno 28] No space left on device\n"


def test_copies_a_killed_roslab_lock_left_behind_are_removed_by_the_next(tmp_path):
    from roslab.cli import lock as lock_cli

    deb = keep(tmp_path)
    left = tmp_path / "jazzy-amd64" / f"{lock_cli.INCOMING}abc123"
    left.mkdir()
    (left / deb.file).write_bytes(b"half a file")
    kept, problems = lock_cli.kept_group(tmp_path, KEY, group(), readers=[])
    assert (kept, problems) == ({DESKTOP: deb}, []) and not left.exists()
