"""SSH and identity: sshd's unit, the teacher's keys, hostname and /etc/hosts."""

from __future__ import annotations

from fixtures.classroom import host_data
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu

from deploy.ssh_identity import etc_hosts_lines, ssh_identity
from roslab import settings

KEY = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIG teacher@laptop"


def test_a_key_entry_that_is_neither_key_nor_pub_file_is_refused_by_the_schema(tmp_path):
    setting = settings.SETTINGS["teacher_ssh_keys"]
    assert "neither a public key line nor a readable .pub file" in settings.check_value(setting, ["teacher.pbu"])
    assert settings.check_value(setting, [KEY + "\nssh-ed25519 AAAA attacker"])


def test_etc_hosts_lists_hosts_with_ip_addresses():
    hosts = [{"name": "team1-main", "address": "10.11.0.2"}, {"name": "pi-x", "address": "pi-x.local"}]
    assert etc_hosts_lines(hosts) == ["10.11.0.2 team1-main"]


def test_identity_converges_and_keeps_other_etc_hosts_lines(tmp_path):
    host = FakeUbuntu()
    # key lines, as the roster loader gives them (it reads the roster's .pub files)
    data = host_data(tmp_path, teacher_ssh_keys=[KEY])
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


def test_a_broken_etc_hosts_block_is_repaired_keeping_the_hosts_own_lines(tmp_path):
    host = FakeUbuntu()
    # someone deleted the end marker and added a line of their own below
    host.files["/etc/hosts"] += ["", "# BEGIN roslab managed block (classroom hosts)",
                                 "10.11.0.2 team1-main", "10.11.0.3 team1-robot", "192.168.1.5 printer"]
    result = plan(ssh_identity, host.facts(), host_data(tmp_path))
    commands = result.operation("/etc/hosts lists every classroom host").text()
    assert commands[0].startswith("cp -p -- /etc/hosts /etc/hosts.roslab-")
    assert result.uploads()["/etc/hosts"].splitlines() == [
        "127.0.0.1 localhost", "127.0.1.1 ubuntu", "",
        "# BEGIN roslab managed block (classroom hosts)",
        "10.11.0.2 team1-main", "10.11.0.3 team1-robot",
        "# END roslab managed block (classroom hosts)",
        "192.168.1.5 printer",
    ]


def test_keys_for_a_login_user_the_host_lacks_stop_that_host(tmp_path):
    result = plan(ssh_identity, FakeUbuntu().facts(), host_data(tmp_path, teacher_ssh_keys=[KEY], login_user="ghost"))
    assert result.failed and "login_user 'ghost' does not exist on the host" in result.errors[0]
