"""Every file roslab writes on a host goes through roslab.remote_files.WRITE_SCRIPT: never
through a symbolic link it did not make, never half-written, a secret 0600 from its first byte.

The script is run here with this machine's python3 on a temporary tree (as the host's
python3 runs it under sudo); the connector side with a stand-in connector."""

from __future__ import annotations

import base64
import os
import stat
import subprocess
import sys
from io import StringIO
from pathlib import Path
from types import SimpleNamespace

import pytest
from pyinfra.api.exceptions import ConnectError

from roslab import remote_files

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="owners of links and files need root")


def write(dest: Path | str, content: bytes = b"new\n", mode: int | None = None) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-c", remote_files.WRITE_SCRIPT, str(dest)] + ([f"{mode:o}"] if mode else [])
    return subprocess.run(argv, input=base64.b64encode(content), capture_output=True)


def leftovers(directory: Path) -> list[str]:
    return [path.name for path in directory.iterdir() if ".roslab-" in path.name]


def test_a_new_file_is_written_whole_with_cp_like_mode(tmp_path):
    dest = tmp_path / "unit.service"
    assert write(dest, b"[Unit]\n").returncode == 0
    assert dest.read_bytes() == b"[Unit]\n"
    assert stat.S_IMODE(dest.stat().st_mode) == 0o666 & ~_umask()
    assert leftovers(tmp_path) == []


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_secret_is_0600_and_an_existing_file_keeps_its_mode(tmp_path):
    secret = tmp_path / "wifi.yaml"
    assert write(secret, b"password: x\n", mode=0o600).returncode == 0
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    kept = tmp_path / "kept"
    kept.write_text("old")
    kept.chmod(0o640)
    assert write(kept).returncode == 0
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_bytes() == b"new\n"


@needs_root
def test_an_existing_file_keeps_its_owner(tmp_path):
    bashrc = tmp_path / ".bashrc"
    bashrc.write_text("# mine\n")
    os.chown(bashrc, 1000, 1000)
    assert write(bashrc).returncode == 0
    assert (bashrc.stat().st_uid, bashrc.stat().st_gid) == (1000, 1000)


def test_a_masked_unit_is_refused_and_dev_null_untouched(tmp_path):
    unit = tmp_path / "roslab-nodes.service"
    unit.symlink_to("/dev/null")
    before = os.stat("/dev/null")
    result = write(unit, b"[Service]\n")
    assert result.returncode == remote_files.REFUSED
    assert result.stderr.decode().splitlines() == [
        f"roslab: will not write {unit}: it is a symbolic link (to /dev/null) that roslab did not make"]
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and after.st_mode == before.st_mode
    assert os.readlink(unit) == "/dev/null" and leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["link to a file", "dangling link", "fifo", "directory", "hard link"])
def test_what_is_not_roslab_s_own_regular_file_is_refused(tmp_path, kind):
    target = tmp_path / "precious"
    target.write_text("keep me\n")
    dest = tmp_path / "dest"
    if kind == "link to a file":
        dest.symlink_to(target)
    elif kind == "dangling link":
        dest.symlink_to(tmp_path / "nowhere")
    elif kind == "fifo":
        os.mkfifo(dest)
    elif kind == "directory":
        dest.mkdir()
    else:
        os.link(target, dest)
    result = write(dest)
    assert result.returncode == remote_files.REFUSED, result.stderr
    assert result.stderr.decode().startswith(f"roslab: will not write {dest}")
    assert target.read_text() == "keep me\n"
    assert not (tmp_path / "nowhere").exists()


@needs_root
def test_a_directory_link_made_by_another_user_is_refused_root_s_are_followed(tmp_path):
    real = tmp_path / "etc"
    real.mkdir()
    student = tmp_path / "ros2_ws"
    student.symlink_to(real)
    os.lchown(student, 1000, 1000)
    result = write(student / "sudoers")
    assert result.returncode == remote_files.REFUSED
    assert "made by uid 1000, not by roslab" in result.stderr.decode()
    assert not (real / "sudoers").exists()
    system = tmp_path / "lib"
    system.symlink_to(real)  # root's own, like /lib -> usr/lib
    assert write(system / "file").returncode == 0 and (real / "file").read_bytes() == b"new\n"


class FakeConnector:
    """Stands in for pyinfra's SSH connector: records the command and its stdin."""

    def __init__(self, result=(True, SimpleNamespace(stderr_lines=[])), error=None):
        self.result, self.error, self.calls, self.logged = result, error, [], []
        self.host = SimpleNamespace(log_styled=lambda text, **kw: self.logged.append(text), log=print)

    def run_shell_command(self, command, **arguments):
        self.calls.append((command, arguments))
        if self.error:
            raise self.error
        return self.result


def test_put_file_sends_the_content_on_stdin_with_the_operation_s_sudo():
    connector = FakeConnector()
    assert remote_files.put_file(connector, StringIO("ünïcode\n"), "/etc/x", remote_temp_filename="/tmp/t",
                                 _sudo=True, mode=0o600)
    [(command, arguments)] = connector.calls
    assert command.get_raw_value().startswith("python3 -c ")
    assert command.get_raw_value().endswith("/etc/x 600")
    assert arguments["_sudo"] is True
    assert base64.b64decode(arguments["_stdin"]) == "ünïcode\n".encode()


def test_a_refusal_is_one_line_naming_the_file():
    refused = (False, SimpleNamespace(stderr_lines=["roslab: will not write /etc/x: it is a symbolic link"]))
    connector = FakeConnector(result=refused)
    assert remote_files.put_file(connector, StringIO("x"), "/etc/x") is False
    assert connector.logged == ["roslab: will not write /etc/x: it is a symbolic link"]


def test_a_connection_failure_fails_this_host_only():
    # pyinfra's executor turns an OSError into this host's failure; a ConnectError would stop the run.
    connector = FakeConnector(error=ConnectError("Unable to establish SFTP connection"))
    with pytest.raises(OSError, match="roslab: could not write /etc/x"):
        remote_files.put_file(connector, StringIO("x"), "/etc/x")


def test_install_replaces_the_ssh_connector_s_upload():
    from pyinfra.connectors.ssh import SSHConnector

    original = SSHConnector.put_file
    try:
        remote_files.install()
        remote_files.install()
        assert SSHConnector.put_file is remote_files.put_file
    finally:
        SSHConnector.put_file = original


def test_put_file_takes_pyinfra_s_full_connector_arguments():
    # pyinfra passes every connector argument, `_stdin=None` and `_chdir` among them.
    connector = FakeConnector()
    assert remote_files.put_file(connector, StringIO("x"), "/etc/x", _stdin=None, _chdir=None, _sudo=True)
    [(command, arguments)] = connector.calls
    assert arguments["_stdin"] == base64.b64encode(b"x").decode() and "_chdir" not in arguments


@needs_root
def test_an_owned_upload_has_its_owner_and_mode_before_it_takes_the_name(tmp_path):
    bashrc = tmp_path / ".bashrc"
    result = subprocess.run([sys.executable, "-c", remote_files.WRITE_SCRIPT, str(bashrc), "640", "daemon:daemon"],
                            input=base64.b64encode(b"x\n"), capture_output=True)
    assert result.returncode == 0, result.stderr
    import grp
    import pwd

    info = bashrc.stat()
    assert (pwd.getpwuid(info.st_uid).pw_name, grp.getgrgid(info.st_gid).gr_name) == ("daemon", "daemon")
    assert stat.S_IMODE(info.st_mode) == 0o640


def test_the_file_and_then_its_folder_reach_the_disk(tmp_path):
    """A power cut after the upload keeps the new file (a Pi's boot partition): the script
    fsyncs the file before the rename and the folder after it."""
    prelude = ("import os, sys\nreal = os.fsync\nrenamed = os.rename\n"
               "def fsync(fd):\n    print('fsync', os.readlink('/proc/self/fd/%d' % fd), file=sys.stderr)\n"
               "    real(fd)\n"
               "def rename(a, b):\n    print('rename', b, file=sys.stderr)\n    renamed(a, b)\n"
               "os.fsync, os.rename = fsync, rename\n")
    dest = tmp_path / "config.txt"
    done = subprocess.run([sys.executable, "-c", prelude + remote_files.WRITE_SCRIPT, str(dest)],
                          input=base64.b64encode(b"[all]\n"), capture_output=True)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.decode().splitlines()
    assert [line.split()[0] for line in lines] == ["fsync", "rename", "fsync"], lines
    assert lines[1] == f"rename {dest}" and lines[2] == f"fsync {tmp_path}"
