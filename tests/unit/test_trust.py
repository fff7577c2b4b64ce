"""`roslab trust`, `forget` and `seed` record keys where the run reads them (issue 18).

The run checks each host against the roster's `ssh_known_hosts_file` when it sets one:
recording the key anywhere else made `trust` say "recorded" and the run fail. And a host
the network deploy moved may be back on its roster address: `trust` asks every address.
The stand-in SSH server (tests/unit/test_identity.py) listens on 127.0.0.1 only.
"""

from __future__ import annotations

import paramiko
import pytest

from roslab.ssh import identity
from roslab.cli.main import main
from roslab.network.state import record_address
from roslab.roster import inventory_groups, load_roster
from tests.unit.test_identity import ROSTER, KeyOnlyServer, loopback_ssh_server  # noqa: F401

OWN_FILE = "keys/lab_known_hosts"


@pytest.fixture
def classroom(tmp_path, loopback_ssh_server):  # noqa: F811
    """A roster whose hosts are checked against keys/lab_known_hosts; team1-main is the stand-in server."""
    port, public = loopback_ssh_server
    roster = tmp_path / "classroom.yaml"
    (tmp_path / "keys").mkdir(exist_ok=True)
    roster.write_text(ROSTER.format(main=f", ssh_port: {port}").replace(
        "classroom:\n", f"classroom:\n  ssh_known_hosts_file: {OWN_FILE}\n"))
    return roster, port, public


def lookup(known_hosts, name):
    entry = paramiko.HostKeys(str(known_hosts)).lookup(name)
    return entry["ssh-ed25519"].get_base64() if entry else None


def test_trust_and_forget_use_the_file_the_run_checks_against(classroom, capsys):
    roster, port, public = classroom
    own = roster.parent / OWN_FILE
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    out = capsys.readouterr().out
    assert f"recorded in {own}" in out
    assert lookup(own, f"[127.0.0.1]:{port}") == public.split()[1]
    assert not identity.known_hosts_path(roster).exists()
    # The run reads the same file.
    data = dict(inventory_groups(load_roster(roster))["team1"])["team1-main"]
    assert data["ssh_known_hosts_file"] == str(own)

    assert main(["forget", str(roster), "--limit", "team1-main"]) == 0
    assert f"removed from {own}" in capsys.readouterr().out
    assert lookup(own, f"[127.0.0.1]:{port}") is None


def test_trust_keeps_other_lines_and_refuses_a_different_key_on_any_line(classroom, capsys):
    roster, port, public = classroom
    own = roster.parent / OWN_FILE
    other = identity.host_keys(roster, "other").public_line().split()
    own.write_text(f"# the teacher's own\ngitlab.example {other[0]} {other[1]}\n"
                   f"[127.0.0.1]:{port} {other[0]} {other[1]}\n")
    own.chmod(0o600)
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 1
    assert "another key is recorded for it" in capsys.readouterr().err
    # Forgetting the host takes its address off the teacher's own line too (the line that refused it).
    assert main(["forget", str(roster), "--limit", "team1-main"]) == 0
    assert f"team1-main: removed from {own}: [127.0.0.1]:{port}" in capsys.readouterr().out
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    text = own.read_text()
    assert "# the teacher's own" in text and "gitlab.example" in text and "managed by roslab" not in text
    assert (own.stat().st_mode & 0o777) == 0o600  # the file keeps its mode
    assert lookup(own, f"[127.0.0.1]:{port}") == public.split()[1]


def test_trust_asks_the_roster_address_when_the_last_confirmed_one_is_gone(tmp_path, loopback_ssh_server,  # noqa: F811
                                                                           capsys):
    port, public = loopback_ssh_server
    roster = tmp_path / "classroom.yaml"
    roster.write_text(ROSTER.format(main=f", ssh_port: {port}"))
    record_address(roster, "team1-main", "127.0.0.2")  # nothing listens there: refused at once
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    out = capsys.readouterr().out
    assert "team1-main (127.0.0.1): ssh-ed25519" in out and "recorded" in out
    host_keys = paramiko.HostKeys(str(identity.known_hosts_path(roster)))
    for name in (f"[127.0.0.1]:{port}", f"[127.0.0.2]:{port}", "team1-main"):
        found = host_keys.lookup(name)
        assert found and found["ssh-ed25519"].get_base64() == public.split()[1], name


def test_trust_names_every_address_it_tried(tmp_path, capsys):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(ROSTER.format(main=", ssh_port: 9"))  # discard: nothing listens
    record_address(roster, "team1-main", "127.0.0.2")
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("team1-main: no host key: 127.0.0.2: ") and "; 127.0.0.1: " in err


def test_trust_refuses_a_known_hosts_file_of_dev_null(tmp_path, capsys):
    roster = tmp_path / "classroom.yaml"
    roster.write_text(ROSTER.format(main="").replace(
        "classroom:\n", 'classroom:\n  ssh_known_hosts_file: /dev/null\n  ssh_strict_host_key_checking: "no"\n'))
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 1
    assert "its ssh_known_hosts_file is /dev/null" in capsys.readouterr().err
