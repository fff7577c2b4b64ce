"""roslab.ssh.sudo: sudo commands carry no password; the password reaches the host only on stdin.

The fake host runs the askpass setup command for real (in a temp dir on this machine),
so the file's mode, content and the leftover cleanup are the shell's, not a mock's.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from pyinfra.api import StringCommand
from pyinfra.api.exceptions import PyinfraError
from pyinfra.connectors import util as pyinfra_util
from pyinfra.connectors.util import CommandOutput, OutputLine

from roslab.ssh import sudo
from roslab.secrets import Secret

PASSWORD = "pl4nted-'sudo' $(pw) \\ \"x\""

# The pyinfra 3.10.0 code roslab.ssh.sudo relies on (sha256 of the source, first 16 hex digits).
# When pyinfra changes one, re-read it against roslab/ssh/sudo.py's docstring, then update here.
PINNED_PYINFRA_SOURCE = {
    "make_unix_command_for_host": "524b0f3bc27f73ab",  # replaced by install()
    "make_unix_command": "68efd9b832857acc",  # builds `sudo -H -n ...`, which with_askpass rewrites
    "execute_command_with_sudo_retry": "130a71a62314b7d4",  # puts a prompted password where we take it
    "remove_any_sudo_askpass_file": "151b014d0d7cf0c6",  # removes our file on disconnect, before reboot
    "_iter_askpass_cache_keys": "a115c0dfafd44003",  # ... found by our cache key
    "clear_askpass_cache": "c42ce8d7782a926b",  # forgets it after a reboot
}


class FakeHost:
    """What roslab.ssh.sudo and pyinfra's askpass helpers use of a host; commands run locally."""

    def __init__(self, temp_dir: Path):
        self.name = "team1-main"
        self.print_prefix = "[team1-main] "
        self.connector_data: dict = {}
        self.temp_dir = temp_dir
        self.commands: list[tuple[str, str | None]] = []  # (command line, stdin)

    def get_temp_dir_config(self) -> str:
        return str(self.temp_dir)

    def run_shell_command(self, command, **arguments):
        assert not arguments.get("_sudo"), "the askpass setup must not need sudo"
        stdin = arguments.get("_stdin")
        line = StringCommand(command).get_raw_value() if not isinstance(command, str) else command
        self.commands.append((line, stdin))
        proc = subprocess.run(["sh", "-c", line], input=(stdin + "\n") if stdin else "",
                              capture_output=True, text=True)
        lines = [OutputLine("stdout", out) for out in proc.stdout.splitlines()]
        lines += [OutputLine("stderr", err) for err in proc.stderr.splitlines()]
        return proc.returncode == 0, CommandOutput(lines)


@pytest.fixture
def host(tmp_path):
    return FakeHost(tmp_path)


def build(host, **arguments) -> StringCommand:
    return sudo.make_unix_command_for_host(None, host, StringCommand("apt-get", "update"), **arguments)


def test_pyinfra_code_it_relies_on_is_unchanged():
    functions = {name: getattr(pyinfra_util, name) for name in PINNED_PYINFRA_SOURCE}
    functions["make_unix_command_for_host"] = sudo.pyinfra_make_unix_command_for_host  # even once installed
    changed = {name for name, function in functions.items()
               if hashlib.sha256(inspect.getsource(function).encode()).hexdigest()[:16]
               != PINNED_PYINFRA_SOURCE[name]}
    assert not changed, f"pyinfra changed {sorted(changed)}: re-check roslab/ssh/sudo.py, then update the pins"
    assert pyinfra_util.SUDO_ASKPASS_ENV_VAR == "PYINFRA_SUDO_PASSWORD"


def test_install_reaches_every_module_that_builds_commands():
    package = Path(pyinfra_util.__file__).resolve().parent.parent
    users = sorted(
        "pyinfra." + ".".join(path.relative_to(package).with_suffix("").parts)
        for path in package.rglob("*.py")
        if "make_unix_command_for_host" in path.read_text(encoding="utf-8")
    )
    # Each of these binds the function by name; a new one must be patched too.
    assert users == ["pyinfra.connectors.chroot", "pyinfra.connectors.docker", "pyinfra.connectors.dockerssh",
                     "pyinfra.connectors.local", "pyinfra.connectors.ssh", "pyinfra.connectors.util"]
    original = sudo.pyinfra_make_unix_command_for_host
    try:
        sudo.install()
        sudo.install()  # idempotent
        for name in users:
            module = importlib.import_module(name)
            assert module.make_unix_command_for_host is sudo.make_unix_command_for_host, name
    finally:
        for name in users:
            sys.modules[name].make_unix_command_for_host = original


def test_without_the_fix_pyinfra_puts_the_password_on_the_command_line(host):
    """Why the module exists (and what the e2e leak test's sampler looks for)."""
    host.connector_data["sudo_askpass_path__" + str(host.temp_dir)] = "/tmp/pyinfra-sudo-askpass-x"
    command = sudo.pyinfra_make_unix_command_for_host(
        None, host, StringCommand("true"), _sudo=True, _sudo_password=PASSWORD)
    assert "PYINFRA_SUDO_PASSWORD=" in command.get_raw_value()
    assert PASSWORD.split("'")[0] in command.get_raw_value()


def test_sudo_command_names_an_askpass_file_and_carries_no_password(host):
    command = build(host, _sudo=True, _sudo_password=Secret(PASSWORD))
    askpass = host.connector_data[sudo.ASKPASS_CACHE_KEY]
    assert command.get_raw_value() == f"env SUDO_ASKPASS={askpass} sudo -H -A -k sh -c 'apt-get update'"
    for text in (command.get_raw_value(), str(command), repr(command)):
        assert "pl4nted" not in text
    # The password went to the host once, on the setup command's stdin only.
    [(setup, stdin)] = host.commands
    assert "pl4nted" not in setup and stdin == PASSWORD


def test_askpass_file_is_private_and_prints_the_password(host):
    build(host, _sudo=True, _sudo_password=PASSWORD)
    askpass = Path(host.connector_data[sudo.ASKPASS_CACHE_KEY])
    assert askpass.parent == host.temp_dir and askpass.name.startswith("roslab-sudo-askpass-")
    assert stat.S_IMODE(askpass.stat().st_mode) == 0o700
    # sudo runs it with the prompt as its argument and reads the first line of its output.
    out = subprocess.run([str(askpass), "[sudo] password for ubuntu: "], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout == PASSWORD + "\n"


def test_one_askpass_file_per_host_and_password(host):
    build(host, _sudo=True, _sudo_password=Secret(PASSWORD))
    first = host.connector_data[sudo.ASKPASS_CACHE_KEY]
    build(host, _sudo=True, _sudo_password=Secret(PASSWORD), _sudo_user="student")
    assert len(host.commands) == 1
    build(host, _sudo=True, _sudo_password="another")
    second = host.connector_data[sudo.ASKPASS_CACHE_KEY]
    assert len(host.commands) == 3 and second != first  # rm of the old file, setup of the new
    assert not Path(first).exists() and Path(second).exists()


def test_leftover_of_a_crashed_run_is_removed_but_not_a_running_one(host):
    """A file names its run's sshd (the setup's parent); here the parent is this test process."""
    crashed = [host.temp_dir / "roslab-sudo-askpass-999999999-AbCdEf1234",  # above any pid_max
               host.temp_dir / "roslab-sudo-askpass-AbCdEf1234"]
    running = host.temp_dir / f"roslab-sudo-askpass-{os.getpid()}-AbCdEf1234"
    unrelated = host.temp_dir / "pyinfra-sudo-askpass-keep"
    for path in (*crashed, running, unrelated):
        path.write_text("#!/bin/sh\nold\n")
    build(host, _sudo=True, _sudo_password=PASSWORD)
    assert not any(path.exists() for path in crashed)
    assert running.exists() and unrelated.exists()
    assert Path(host.connector_data[sudo.ASKPASS_CACHE_KEY]).name.startswith(f"roslab-sudo-askpass-{os.getpid()}-")


@pytest.mark.parametrize("arguments", [
    {},
    {"_sudo_user": "student"},
    {"_use_sudo_login": True, "_preserve_sudo_env": True},
    {"_env": {"A": "1"}, "_chdir": "/srv"},
])
def test_same_command_as_pyinfra_but_the_askpass(host, arguments):
    ours = build(host, _sudo=True, _sudo_password=PASSWORD, **arguments).get_raw_value()
    askpass = host.connector_data[sudo.ASKPASS_CACHE_KEY]
    without_password = pyinfra_util.make_unix_command(
        StringCommand("apt-get", "update"), _sudo=True, **arguments).get_raw_value()
    assert without_password.startswith("sudo -H -n ")
    assert ours == f"env SUDO_ASKPASS={askpass} sudo -H -A -k " + without_password[len("sudo -H -n "):]


def test_without_password_or_sudo_it_is_pyinfra_unchanged(host):
    for arguments in ({"_sudo": True}, {"_sudo_password": PASSWORD}, {}):
        assert build(host, **arguments).get_raw_value() == pyinfra_util.make_unix_command(
            StringCommand("apt-get", "update"), **arguments).get_raw_value()
    assert host.commands == []


def test_password_pyinfra_prompted_for_goes_the_same_way(host, monkeypatch):
    """pyinfra's retry: `sudo -n` says a password is required, pyinfra prompts and runs again."""
    monkeypatch.setattr(pyinfra_util, "getpass", lambda prompt: PASSWORD)
    sent = []

    def execute_command():
        command = build(host, _sudo=True, _sudo_password="")
        sent.append(command.get_raw_value())
        if len(sent) == 1:
            return 1, CommandOutput([OutputLine("stderr", "sudo: a password is required")])
        return 0, CommandOutput([])

    pyinfra_util.execute_command_with_sudo_retry(host, {}, execute_command)
    assert sent[0].startswith("sudo -H -n ")
    assert sent[1].startswith("env SUDO_ASKPASS=") and "pl4nted" not in sent[1]
    assert "prompted_sudo_password" not in host.connector_data  # out of pyinfra's own reach
    assert build(host, _sudo=True).get_raw_value() == sent[1]  # later commands use it too
    assert len(host.commands) == 1


def test_pyinfra_removes_the_file_on_disconnect_and_forgets_it_after_reboot(host):
    build(host, _sudo=True, _sudo_password=PASSWORD)
    askpass = Path(host.connector_data[sudo.ASKPASS_CACHE_KEY])
    pyinfra_util.remove_any_sudo_askpass_file(host)
    assert not askpass.exists() and host.connector_data[sudo.ASKPASS_CACHE_KEY] is None
    build(host, _sudo=True, _sudo_password=PASSWORD)  # written again when needed again
    assert Path(host.connector_data[sudo.ASKPASS_CACHE_KEY]).exists()
    pyinfra_util.clear_askpass_cache(host)
    assert host.connector_data[sudo.ASKPASS_CACHE_KEY] is None


def test_multi_line_password_is_refused(host):
    with pytest.raises(PyinfraError, match="not one line"):
        build(host, _sudo=True, _sudo_password="one\ntwo")
    assert host.commands == []


def test_failed_setup_fails_the_command(tmp_path):
    host = FakeHost(tmp_path / "missing")
    with pytest.raises(PyinfraError, match="askpass"):
        build(host, _sudo=True, _sudo_password=PASSWORD)


def test_unknown_command_shape_is_refused():
    with pytest.raises(PyinfraError, match="changed shape"):
        sudo.with_askpass(StringCommand("doas", "-n", "true"), "/tmp/x/askpass")



def test_without_roslab_sudo_a_secret_password_is_never_sent(host):
    """Fail closed: pyinfra's own builder given the roster's Secret sends its mask, not the password."""
    host.connector_data["sudo_askpass_path__" + str(host.temp_dir)] = "/tmp/pyinfra-sudo-askpass-x"
    command = sudo.pyinfra_make_unix_command_for_host(
        None, host, StringCommand("true"), _sudo=True, _sudo_password=Secret(PASSWORD))
    assert "pl4nted" not in command.get_raw_value()


def test_secret_copies_are_equal_so_pyinfra_does_not_type_check_them():
    """pyinfra hands out copies of host data and type-checks `_sudo_password` (a str) only
    when a deploy's value differs from the host's own: a copy must compare equal."""
    import copy
    secret = Secret(PASSWORD)
    assert copy.copy(secret) == secret and copy.copy(secret) is not secret
    assert Secret("other") != secret and secret != PASSWORD
    assert "pl4nted" not in str(secret) + repr(secret)
