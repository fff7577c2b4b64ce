"""SSH and identity: sshd's unit, the teacher's keys, hostname and /etc/hosts."""

from __future__ import annotations

import pytest
from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.api import DeployError

from deploy.ssh_identity import etc_hosts_lines, public_keys, ssh_identity

KEY = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIG teacher@laptop"


def test_keys_come_as_lines_or_from_pub_files_read_here(tmp_path):
    pub = tmp_path / "teacher.pub"
    pub.write_text("# the teacher's second laptop\nssh-rsa AAAAB3NzaC1yc2E teacher@old\n")
    keys = public_keys([KEY, "teacher.pub"], resolve_path=lambda entry: tmp_path / entry)
    assert keys == [KEY, "ssh-rsa AAAAB3NzaC1yc2E teacher@old"]


def test_an_entry_that_is_neither_key_nor_file_is_a_clear_error(tmp_path):
    with pytest.raises(DeployError, match="teacher_ssh_keys entry 'teacher.pbu'"):
        public_keys(["teacher.pbu"], resolve_path=lambda entry: tmp_path / entry)


def test_etc_hosts_lists_hosts_with_ip_addresses():
    hosts = [{"name": "team1-main", "address": "10.11.0.2"}, {"name": "pi-x", "address": "pi-x.local"}]
    assert etc_hosts_lines(hosts) == ["10.11.0.2 team1-main"]


def test_identity_converges_and_keeps_other_etc_hosts_lines(tmp_path):
    host = FakeUbuntu()
    (tmp_path / "teacher.pub").write_text(KEY + "\n")
    # a .pub path relative to the roster, as a teacher would write it in the roster
    data = host_data(tmp_path, teacher_ssh_keys=["teacher.pub"],
                     roslab_roster_path=str(tmp_path / "classroom.yaml"))
    result = plan(ssh_identity, host.facts(), data)
    assert result.operation("hostname is team1-main").text() == ["hostnamectl set-hostname team1-main"]
    assert result.uploads()["/etc/hosts"].splitlines() == [
        "127.0.0.1 localhost", "127.0.1.1 ubuntu", "",
        "# BEGIN roslab managed block (classroom hosts)",
        "10.11.0.2 team1-main", "10.11.0.3 team1-robot",
        "# END roslab managed block (classroom hosts)",
    ]
    host.apply(result)
    assert host.files["/home/student/.ssh/authorized_keys"] == [KEY]
    again = plan(ssh_identity, host.facts(), data)
    assert again.changing() == {}


def test_socket_activated_sshd_on_24_04_is_kept_socket_activated(tmp_path):
    host = FakeUbuntu()
    host.enabled_units = {"ssh.socket": True, "ssh.service": False}
    result = plan(ssh_identity, host.facts(), host_data(tmp_path))
    assert any("ssh.socket" in op.name for op in result.operations)
