"""Saved sandbox states without hosts: names, what saved.json records, which classroom a saved
state restores onto, and that the copy keeps what an overlay's upper directory holds."""

from __future__ import annotations

import ipaddress
import os
import stat

import pytest

from roslab.sandbox import lifecycle
from roslab.sandbox.instance import Instance
from roslab.sandbox.system import SandboxError

INSTANCE = Instance("rl-saved", ipaddress.IPv4Network("10.213.111.0/24"))


def classroom(instance: Instance = INSTANCE, count: int = 4) -> lifecycle.Classroom:
    return lifecycle.Classroom(instance, instance.plan_hosts(count))


@pytest.mark.parametrize("name", ["converged", "class-1", "v1.2_ok", "0"])
def test_a_plain_name_is_kept_under_the_instances_folder(name):
    assert lifecycle.saved_path(INSTANCE, name) == INSTANCE.state_dir / "saved" / name


@pytest.mark.parametrize("name", ["", "..", "../x", "a/b", "-x", ".hidden", "Upper", "a b", "x" * 41, "a..b"])
def test_a_name_that_could_leave_the_folder_or_hide_is_refused(name):
    with pytest.raises(SandboxError, match="saved state name"):
        lifecycle.saved_path(INSTANCE, name)


def test_the_record_holds_each_hosts_address_boot_state_and_layers():
    record = lifecycle.saved_record(classroom(), {"team1-main": {"seeded": True}},
                                    {"team1-main": ["/run/roslab/sandbox/rl-saved/saved/a/hosts/team1-main"]})
    assert record["subnet"] == "10.213.111.0/24"
    assert record["hosts"]["team1-main"] == {"address": "10.213.111.11", "boot": {"seeded": True},
                                             "layers": ["/run/roslab/sandbox/rl-saved/saved/a/hosts/team1-main"]}
    assert record["hosts"]["team2-robot"] == {"address": "10.213.111.14", "boot": {}, "layers": []}


def test_a_saved_state_restores_only_onto_the_same_hosts_and_addresses():
    record = lifecycle.saved_record(classroom(), {}, {})
    lifecycle.check_restorable(record, classroom(), "a")
    with pytest.raises(SandboxError, match="holds other hosts"):
        lifecycle.check_restorable(record, classroom(count=2), "a")
    moved = Instance("rl-saved", ipaddress.IPv4Network("10.213.112.0/24"))
    with pytest.raises(SandboxError, match="restore it on the classroom it was saved from"):
        lifecycle.check_restorable(record, classroom(moved), "a")


@pytest.mark.skipif(os.geteuid() != 0, reason="owners, trusted xattrs and device nodes need root")
def test_the_copy_keeps_owners_modes_xattrs_and_whiteouts(tmp_path):
    upper = tmp_path / "upper"
    (upper / "etc").mkdir(parents=True)
    (upper / "etc" / "secret").write_text("x")
    os.chmod(upper / "etc" / "secret", 0o600)
    os.chown(upper / "etc" / "secret", 1000, 1000)
    os.setxattr(upper / "etc", "trusted.overlay.opaque", b"y")  # an overlay's opaque directory
    os.mknod(upper / "gone", stat.S_IFCHR | 0o000, os.makedev(0, 0))  # an overlay's whiteout
    lifecycle.copy_tree(upper, tmp_path / "saved" / "host")
    copy = tmp_path / "saved" / "host"
    secret = (copy / "etc" / "secret").stat()
    assert (secret.st_uid, secret.st_gid, stat.S_IMODE(secret.st_mode)) == (1000, 1000, 0o600)
    assert os.getxattr(copy / "etc", "trusted.overlay.opaque") == b"y"
    gone = (copy / "gone").lstat()
    assert stat.S_ISCHR(gone.st_mode) and gone.st_rdev == os.makedev(0, 0)
