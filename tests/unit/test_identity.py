"""The classroom's SSH identity: host keys made once, known_hosts, strict checking, refusals."""

from __future__ import annotations

import logging
import shutil
import socket
import stat
import subprocess
import textwrap
import threading
from pathlib import Path

import paramiko
import pytest
from paramiko import BadHostKeyException, Ed25519Key, SSHException

from roslab.ssh import identity
from roslab.cli.main import main
from roslab.roster import RosterError, inventory_groups, load_roster

ROSTER = textwrap.dedent("""\
    classroom:
      teacher_ssh_keys: ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFlMtlfltx2Ordc++JZrFF/P0U8EAhdPijdaM3K81dM9 t"]
    teams:
      team1:
        hosts:
          team1-main: {{role: main, address: 127.0.0.1{main}}}
          team1-robot: {{role: robot, address: 192.0.2.12, network_address: 192.0.2.42/24}}
""")


@pytest.fixture
def roster(tmp_path) -> Path:
    path = tmp_path / "classroom.yaml"
    path.write_text(ROSTER.format(main=""))
    return path


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_host_key_is_made_once_private_and_kept(roster):
    assert not identity.has_host_keys(roster, "team1-main")
    keys = identity.host_keys(roster, "team1-main")
    assert identity.has_host_keys(roster, "team1-main")
    assert keys.private_path == roster.parent / ".roslab-state/host-keys/team1-main/ssh_host_ed25519_key"
    assert mode(keys.private_path) == 0o600
    assert mode(keys.private_path.parent) == 0o700 and mode(keys.private_path.parent.parent) == 0o700
    assert keys.public_line().startswith("ssh-ed25519 AAAA") and keys.public_line().endswith(" root@team1-main")
    private = keys.private_text()
    again = identity.host_keys(roster, "team1-main")
    assert again.private_text() == private and again.public_line() == keys.public_line()
    # OpenSSH reads it, and it is the public line's key.
    derived = Ed25519Key.from_private_key_file(str(keys.private_path))
    assert f"{derived.get_name()} {derived.get_base64()}" == " ".join(keys.public_line().split()[:2])
    assert identity.host_keys(roster, "team1-robot").public_line() != keys.public_line()


@pytest.mark.parametrize("name", ["../escape", "a/b", "..", "", "-x"])
def test_a_host_name_never_leaves_the_key_store(roster, name):
    with pytest.raises(identity.IdentityError):
        identity.host_keys(roster, name)
    assert not (roster.parent / ".roslab-state").exists()


def test_trust_and_forget_round_trip(roster):
    known = identity.known_hosts_path(roster)
    main_key = identity.host_keys(roster, "team1-main").public_line()
    robot_key = identity.host_keys(roster, "team1-robot").public_line()
    known.parent.mkdir(exist_ok=True)
    known.write_text("# mine\nother.example ssh-ed25519 " + main_key.split()[1] + "\n")
    assert identity.trust(roster, "team1-main", ["10.0.0.5"], main_key) is True
    assert identity.trust(roster, "team1-main", ["10.0.0.5"], main_key) is False  # nothing to change
    assert identity.trust(roster, "team1-robot", ["10.0.0.6"], robot_key, port=2222) is True

    host_keys = paramiko.HostKeys(str(known))
    assert host_keys.lookup("10.0.0.5")["ssh-ed25519"].get_base64() == main_key.split()[1]
    assert host_keys.lookup("team1-main") is not None
    assert host_keys.lookup("[10.0.0.6]:2222")["ssh-ed25519"].get_base64() == robot_key.split()[1]
    lines = known.read_text().splitlines()
    assert lines[0].startswith("# managed by roslab")
    assert "# mine" in lines and any(line.startswith("other.example ") for line in lines)
    owners = [line.split()[-1] for line in lines if " roslab:" in line and not line.startswith("#")]
    assert owners == ["roslab:team1-main", "roslab:team1-robot"]

    # An address moving to another host leaves its old line.
    identity.trust(roster, "team1-robot", ["10.0.0.5"], robot_key)
    host_keys = paramiko.HostKeys(str(known))
    assert host_keys.lookup("10.0.0.5")["ssh-ed25519"].get_base64() == robot_key.split()[1]
    assert host_keys.lookup("team1-main") is not None

    assert "team1-robot" in identity.forget(roster, "team1-robot")
    assert identity.known_key(roster, "team1-robot") is None
    assert paramiko.HostKeys(str(known)).lookup("10.0.0.5") is None
    assert identity.known_key(roster, "team1-main") is not None
    assert identity.forget(roster, "team1-robot") == []


def test_trust_refuses_what_is_not_a_key_or_an_address(roster):
    with pytest.raises(identity.IdentityError):
        identity.trust(roster, "team1-main", ["10.0.0.5"], "ssh-ed25519 not-base64!")
    with pytest.raises(identity.IdentityError):
        identity.trust(roster, "team1-main", ["10.0.0.5 evil"], identity.host_keys(roster, "x1").public_line())


def test_fingerprint_is_what_ssh_keygen_prints(roster):
    keys = identity.host_keys(roster, "team1-main")
    if shutil.which("ssh-keygen") is None:
        pytest.skip("ssh-keygen is not installed")
    printed = subprocess.run(["ssh-keygen", "-lf", str(keys.public_path)], capture_output=True, text=True).stdout
    assert printed.split()[1] == identity.fingerprint(keys.public_line())


def test_inventory_connects_strictly_through_the_classroom_known_hosts(roster):
    data = dict(inventory_groups(load_roster(roster))["team1"])
    for host in ("team1-main", "team1-robot"):
        assert data[host]["ssh_known_hosts_file"] == str(identity.known_hosts_path(roster))
        assert data[host]["ssh_strict_host_key_checking"] == "yes"
    assert not (roster.parent / ".roslab-state").exists()  # nothing known, nothing written


def test_a_roster_that_sets_host_key_checking_keeps_it(tmp_path):
    path = tmp_path / "sandbox.yaml"
    path.write_text(ROSTER.format(main="").replace(
        "classroom:\n", 'classroom:\n  ssh_known_hosts_file: /dev/null\n  ssh_strict_host_key_checking: "off"\n'))
    data = dict(inventory_groups(load_roster(path))["team1"])
    assert data["team1-main"]["ssh_known_hosts_file"] == "/dev/null"
    assert data["team1-main"]["ssh_strict_host_key_checking"] == "off"
    assert not (tmp_path / ".roslab-state").exists()


def test_a_seeded_host_is_known_at_every_address_it_will_be_reached_at(roster):
    public = identity.host_keys(roster, "team1-robot").public_line()
    inventory_groups(load_roster(roster))
    host_keys = paramiko.HostKeys(str(identity.known_hosts_path(roster)))
    # The roster's address, and the static address the network deploy reconnects at.
    for name in ("team1-robot", "192.0.2.12", "192.0.2.42"):
        assert host_keys.lookup(name)["ssh-ed25519"].get_base64() == public.split()[1], name
    assert host_keys.lookup("127.0.0.1") is None  # team1-main was not seeded
    # A second inventory writes nothing.
    before = identity.known_hosts_path(roster).stat().st_mtime_ns
    inventory_groups(load_roster(roster))
    assert identity.known_hosts_path(roster).stat().st_mtime_ns == before


# --- what a refused host is told ---------------------------------------------------------


def _connect_with(roster: Path, monkeypatch, raising):
    """Connect pyinfra's real SSH connector to team1-main, its paramiko connect replaced."""
    from pyinfra.api import Config, Inventory, State
    from pyinfra.connectors.sshuserclient import client as ssh_client

    groups = inventory_groups(load_roster(roster))
    hosts = [(name, data) for name, data in groups["team1"] if name == "team1-main"]
    state = State(Inventory((hosts, {})), Config())
    host = state.inventory.get_host("team1-main")
    monkeypatch.setattr(ssh_client.SSHClient, "connect", raising)
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    import pyinfra

    handler = Keep(level=logging.DEBUG)
    pyinfra.logger.addHandler(handler)
    try:
        host.connect(show_errors=True)
    finally:
        pyinfra.logger.removeHandler(handler)
    return host, "\n".join(records)


def test_a_changed_host_key_is_refused_with_the_roslab_commands(roster, monkeypatch):
    old = Ed25519Key.from_private_key_file(str(identity.host_keys(roster, "team1-main").private_path))
    new = Ed25519Key.from_private_key_file(str(identity.host_keys(roster, "someone-else").private_path))

    def raising(self, hostname, **kwargs):
        self._ssh_config = {"port": 22}
        raise BadHostKeyException(hostname, new, old)

    host, output = _connect_with(roster, monkeypatch, raising)
    assert not host.connected
    known = identity.known_hosts_path(roster)
    shown_known = str(known) if not str(known).startswith(str(Path.cwd())) else str(known.relative_to(Path.cwd()))
    assert "REMOTE HOST IDENTIFICATION HAS CHANGED" in output  # pyinfra's warning stays
    assert "ssh-keygen -R" not in output  # it edits another known_hosts
    assert f"roslab forget {roster} --limit team1-main" in output
    assert f"roslab trust {roster} --limit team1-main" in output
    assert shown_known in output
    assert "[team1-main] roslab: team1-main (127.0.0.1) answered with another SSH host key" in output
    assert "re-flashed without its seed" in identity.refusal("team1-main")
    # The run summary's line for the host says the same.
    from roslab.reporting.summary import RunSummary

    step, reason = RunSummary().failure(host.state, host)
    assert step == "connect" and reason == identity.refusal("team1-main")


def test_an_unknown_host_key_is_refused_with_the_roslab_commands(roster, monkeypatch):
    from pyinfra.connectors.sshuserclient.client import StrictPolicy

    key = Ed25519Key.from_private_key_file(str(identity.host_keys(roster, "someone-else").private_path))

    def raising(self, hostname, **kwargs):
        StrictPolicy().missing_host_key(self, hostname, key)

    host, output = _connect_with(roster, monkeypatch, raising)
    assert not host.connected
    assert "No host key for" not in output
    assert "roslab: no SSH host key of team1-main (127.0.0.1) is recorded in" in output
    assert f"run `roslab trust {roster} --limit team1-main`" in output


# --- roslab trust over real SSH on loopback ------------------------------------------------


class KeyOnlyServer(paramiko.ServerInterface):
    """A stand-in SSH server on 127.0.0.1 that shows its host key and lets nobody in."""


@pytest.fixture
def loopback_ssh_server(tmp_path):
    """An SSH server on 127.0.0.1 showing a fresh ed25519 host key: (port, public line)."""
    key_roster = tmp_path / "keys" / "r.yaml"
    key_roster.parent.mkdir()
    keys = identity.host_keys(key_roster, "server")
    host_key = Ed25519Key.from_private_key_file(str(keys.private_path))
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    stop = threading.Event()

    def serve():
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                connection, _ = listener.accept()
            except OSError:
                continue
            transport = paramiko.Transport(connection)
            transport.add_server_key(host_key)
            try:
                transport.start_server(server=KeyOnlyServer())
            except (SSHException, EOFError, OSError):
                pass
            threading.Timer(2, transport.close).start()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield listener.getsockname()[1], keys.public_line()
    stop.set()
    thread.join(timeout=2)
    listener.close()


def test_roslab_trust_records_the_key_a_host_shows_and_refuses_a_changed_one(tmp_path, loopback_ssh_server, capsys):
    port, public = loopback_ssh_server
    roster = tmp_path / "classroom.yaml"
    roster.write_text(ROSTER.format(main=f", ssh_port: {port}"))
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    out = capsys.readouterr().out
    assert f"team1-main (127.0.0.1): ssh-ed25519 {identity.fingerprint(public)} recorded" in out
    host_keys = paramiko.HostKeys(str(identity.known_hosts_path(roster)))
    assert host_keys.lookup(f"[127.0.0.1]:{port}")["ssh-ed25519"].get_base64() == public.split()[1]
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    assert "already recorded" in capsys.readouterr().out

    # The Pi "was re-flashed": another key is recorded than the one it shows.
    identity.trust(roster, "team1-main", ["127.0.0.1"], identity.host_keys(roster, "other").public_line(), port=port)
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 1
    err = capsys.readouterr().err
    assert f"run `roslab forget {roster} --limit team1-main` first" in err
    assert main(["forget", str(roster), "--limit", "team1-main"]) == 0
    assert main(["trust", str(roster), "--limit", "team1-main"]) == 0
    assert identity.known_key(roster, "team1-main").key == public.split()[1]


def test_a_classroom_without_known_hosts_yet_gets_no_warning_about_the_missing_file(roster):
    import pyinfra

    inventory_groups(load_roster(roster))
    known = identity.known_hosts_path(roster)
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep()
    pyinfra.logger.addHandler(handler)
    try:
        # What pyinfra's get_host_keys logs for a known_hosts file that does not exist.
        pyinfra.logger.warning("Failed to load host keys from %s: %s", known,
                               f"[Errno 2] No such file or directory: '{known}'")
        pyinfra.logger.warning("Failed to load host keys from /elsewhere: [Errno 2] No such file")
    finally:
        pyinfra.logger.removeHandler(handler)
    assert records == ["Failed to load host keys from /elsewhere: [Errno 2] No such file"]


@pytest.mark.parametrize("lines, refused", [
    (["192.0.2.12 {key}"], True),  # the roster's address only: the new one is unknown
    ([], False),  # not known at all: refused when connecting, with the `roslab trust` hint
    (["192.0.2.12,192.0.2.42 {key}"], False),
    (["192.0.2.12 {key}", "{hashed} {key}"], False),  # HashKnownHosts: the new address hashed
])
def test_a_move_to_an_address_the_rosters_own_known_hosts_lacks_is_refused_before_connecting(
        tmp_path, lines, refused, capsys):
    """ssh_known_hosts_file is the teacher's file, which roslab does not add addresses to: a
    network change to an address it holds no key for would be refused by pyinfra and roll back on
    every run, so the roster is refused, naming the host, its line and network_address."""
    import base64
    import hashlib
    import hmac

    key = "ssh-ed25519 " + identity.host_keys(tmp_path, "team1-robot").public_line().split()[1]
    salt = b"0123456789abcdef0123"
    hashed = "|1|{}|{}".format(base64.b64encode(salt).decode(), base64.b64encode(
        hmac.new(salt, b"192.0.2.42", hashlib.sha1).digest()).decode())
    own = tmp_path / "lab_known_hosts"
    own.write_text("".join(line.format(key=key, hashed=hashed) + "\n" for line in lines))
    path = tmp_path / "classroom.yaml"
    path.write_text(ROSTER.format(main="").replace("classroom:\n", "classroom:\n  ssh_known_hosts_file: lab_known_hosts\n"))
    if not refused:
        data = dict(inventory_groups(load_roster(path))["team1"])
        assert data["team1-robot"]["ssh_known_hosts_file"] == str(own)
        return
    with pytest.raises(RosterError) as raised:
        inventory_groups(load_roster(path))
    (problem,) = [str(p) for p in raised.value.problems]
    assert "classroom.yaml:8: team 'team1', host 'team1-robot', field 'network_address': " in problem
    assert "lab_known_hosts (ssh_known_hosts_file) holds its key for 192.0.2.12 but none for 192.0.2.42" in problem
    assert "roslab trust --limit team1-robot" in problem
    assert own.read_text().count("\n") == len(lines)  # the teacher's file is not written
    # pyinfra's inventory file gets the same problem as one line and exit 2, never a traceback
    from roslab.packaged import checked_groups

    with pytest.raises(SystemExit) as stopped:
        checked_groups(load_roster(path))
    assert stopped.value.code == 2
    said = capsys.readouterr().err
    assert said.startswith("roslab: the roster has errors, no host was touched:\n") and "Traceback" not in said
    assert "holds its key for 192.0.2.12 but none for 192.0.2.42" in said
