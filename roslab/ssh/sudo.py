"""Sudo with a password, without the password on the host's command lines.

pyinfra 3.10 runs every `_sudo` command that has a sudo password as

    env SUDO_ASKPASS=/tmp/pyinfra-sudo-askpass-XXXX PYINFRA_SUDO_PASSWORD=<password> sudo -H -A -k sh -c '...'

(`pyinfra.connectors.util.make_unix_command_for_host`): the password is an
argument of `env`, which every local user of the host can catch in `ps`, and it
stays in the environment of `sudo` and of pyinfra's askpass process (and `-E`
would pass it on to the command). The same happens to a password pyinfra
prompted for after "sudo: a password is required".

`install()` replaces that one function (in `pyinfra.connectors.util` and in the
connector modules that imported it by name) with `make_unix_command_for_host`
below, which keeps the password off the host's command lines and environments:

1. The first sudo command on a host that needs the password runs, as the login
   user and without sudo, a setup command that removes the askpass files that
   crashed earlier runs left behind (see `setup_command`), creates a private
   file in pyinfra's temp dir (`mktemp`: mode 0600, a random name; then 0700)
   and writes into it, from the setup command's *stdin*, a script that prints
   its own last line: the password. The password is never an argument or in
   the environment of any process.
2. Every sudo command then runs as
   `env SUDO_ASKPASS=/tmp/roslab-sudo-askpass-<sshd pid>-XXXX sudo -H -A -k sh -c '...'`:
   pyinfra's own command without a password (`sudo -H -n ...`) with `-n`
   replaced by pyinfra's askpass flags.
3. The script's path is kept under one of pyinfra's own askpass cache keys, so
   pyinfra removes it when it disconnects (at the end of every run, also one that
   failed) and before `server.reboot`, and forgets it after a reboot.

The password stays a `roslab.secrets.Secret` (masked in every output) until it is
written to the setup command's stdin. tests/unit/test_sudo.py pins the pyinfra
code this relies on: when pyinfra changes it, that test fails.
"""

from __future__ import annotations

import re
import shlex
import sys
from collections.abc import Iterable

import gevent.lock
from pyinfra.api import QuoteString, StringCommand
from pyinfra.api.exceptions import PyinfraError
from pyinfra.connectors import util as pyinfra_util

from roslab.secrets import Secret

# pyinfra's function, kept before install() replaces it.
pyinfra_make_unix_command_for_host = pyinfra_util.make_unix_command_for_host

# What pyinfra puts in front of a sudo command without a password, and what replaces it.
SUDO_WITHOUT_PASSWORD = ("sudo", "-H", "-n")
SUDO_WITH_ASKPASS_FLAGS = ("sudo", "-H", "-A", "-k")  # askpass, and never sudo's cached credentials

# Under a key pyinfra treats as one of its askpass files (`ASKPASS_PATH_KEYS` + "__"),
# so its disconnect and reboot handling removes and forgets ours too.
ASKPASS_CACHE_KEY = "sudo_askpass_path__roslab"
PASSWORD_KEY = "roslab_sudo_password"  # the password the askpass file holds (a Secret)
PROMPTED_KEY = "prompted_sudo_password"  # where pyinfra keeps a password it prompted for
PROMPTED_COPY_KEY = "roslab_prompted_sudo_password"  # where roslab keeps it instead (a Secret)
LOCK_KEY = "roslab_sudo_lock"

FILE_PREFIX = "roslab-sudo-askpass-"
ASKPASS_SCRIPT_HEAD = (
    "#!/bin/sh\n"
    "# roslab: the sudo askpass of one run, removed when the run ends.\n"
    "# It prints its own last line (the password) through sed, never as an argument.\n"
    "exec sed -n '$p' \"$0\"\n"
)


def setup_command(temp_dir: str) -> str:
    """The shell command that writes the askpass script (password from stdin) and prints its path.

    `mktemp` creates the file with mode 0600 and a random name (O_EXCL, so never
    someone else's file or link; in the sticky temp dir nobody else can replace
    it); only then is the script written into it. The name carries `$PPID`, the
    pid of this SSH connection's sshd process, which lives as long as the run's
    connection: a file of the login user's whose sshd is gone was left by a run
    that crashed, and is removed; a run still connected keeps its file.
    """
    temp_dir = shlex.quote(temp_dir.rstrip("/") or "/")
    prefix = f"{temp_dir}/{FILE_PREFIX}"
    return (
        "umask 077 && "
        f"for old in {prefix}*; do "
        "if [ -f \"$old\" ] && [ ! -L \"$old\" ] && [ -O \"$old\" ]; then "
        f"pid=${{old##*/{FILE_PREFIX}}}; pid=${{pid%%-*}}; "
        "case $pid in ''|*[!0-9]*) rm -f \"$old\";; *) [ -d \"/proc/$pid\" ] || rm -f \"$old\";; esac; "
        "fi; done; "
        f"askpass=$(mktemp {prefix}$PPID-XXXXXXXXXX) && "
        f"{{ printf %s {shlex.quote(ASKPASS_SCRIPT_HEAD)} && cat; }} > \"$askpass\" && "
        "chmod 0700 \"$askpass\" && printf '%s\\n' \"$askpass\""
    )


def _unmasked(password) -> str:
    return password.unmask() if isinstance(password, Secret) else str(password)


def _password_for(host, arguments: dict):
    """The sudo password for this command, as pyinfra would choose it (None: sudo -n).

    A password pyinfra prompted for is moved out of pyinfra's reach, so that its own
    command builder never sees it again.
    """
    prompted = host.connector_data.pop(PROMPTED_KEY, None)
    if prompted:
        host.connector_data[PROMPTED_COPY_KEY] = Secret(prompted)
    return arguments.get("_sudo_password") or host.connector_data.get(PROMPTED_COPY_KEY)


def ensure_askpass(host, password) -> str:
    """The path of the host's askpass script for `password`, written on first use."""
    lock = host.connector_data.setdefault(LOCK_KEY, gevent.lock.Semaphore())
    with lock:
        path = host.connector_data.get(ASKPASS_CACHE_KEY)
        known = host.connector_data.get(PASSWORD_KEY)
        if path and known is not None and _unmasked(known) == _unmasked(password):
            return path
        secret = _unmasked(password)
        if any(char in secret for char in "\r\n\0"):
            raise PyinfraError(f"{host.name}: the sudo password is not one line; sudo cannot read it")
        if path:  # another password for this host: its file goes
            host.run_shell_command(StringCommand("rm", "-f", QuoteString(path)))
        temp_dir = host.get_temp_dir_config()
        ok, output = host.run_shell_command(StringCommand(setup_command(temp_dir)), _stdin=secret)
        path = output.stdout_lines[0] if ok and output.stdout_lines else ""
        if not path.startswith(f"{temp_dir.rstrip('/')}/{FILE_PREFIX}"):
            raise PyinfraError(f"{host.name}: could not write sudo's askpass file: {output.stderr or path}")
        host.connector_data[ASKPASS_CACHE_KEY] = path
        host.connector_data[PASSWORD_KEY] = password if isinstance(password, Secret) else Secret(secret)
        return path


def with_askpass(command: StringCommand, askpass: str) -> StringCommand:
    """pyinfra's password-less sudo command (`sudo -H -n ...`), made to ask `askpass`."""
    bits = list(command.bits)
    for start in range(len(bits) - len(SUDO_WITHOUT_PASSWORD) + 1):
        if all(isinstance(bit, str) and bit == word
               for bit, word in zip(bits[start:], SUDO_WITHOUT_PASSWORD)):
            bits[start:start + len(SUDO_WITHOUT_PASSWORD)] = [
                "env", StringCommand("SUDO_ASKPASS=", QuoteString(askpass), _separator=""),
                *SUDO_WITH_ASKPASS_FLAGS,
            ]
            return StringCommand(*bits, _separator=command.separator, **command.connector_arguments)
    raise PyinfraError(f"roslab.ssh.sudo: pyinfra's sudo command changed shape, refusing to send it: {command}")


def make_unix_command_for_host(state, host, command, **arguments) -> StringCommand:
    """pyinfra's `make_unix_command_for_host`, with the sudo password in an askpass file."""
    if arguments.get("_sudo"):
        password = _password_for(host, arguments)
        if password:
            askpass = ensure_askpass(host, password)
            arguments["_sudo_password"] = ""  # pyinfra builds `sudo -H -n ...`
            return with_askpass(pyinfra_make_unix_command_for_host(state, host, command, **arguments), askpass)
    return pyinfra_make_unix_command_for_host(state, host, command, **arguments)


def install() -> None:
    """Make pyinfra build its sudo commands with `make_unix_command_for_host` above.

    Idempotent. Patches `pyinfra.connectors.util` (connectors imported later bind
    the replacement) and every connector module already imported.
    """
    pyinfra_util.make_unix_command_for_host = make_unix_command_for_host
    for name, module in list(sys.modules.items()):
        if (name.startswith("pyinfra.connectors.") and module is not None
                and getattr(module, "make_unix_command_for_host", None) is pyinfra_make_unix_command_for_host):
            setattr(module, "make_unix_command_for_host", make_unix_command_for_host)


# sudo's own words when the password it was given is wrong (or it got none).
_SUDO_PASSWORD = re.compile(
    r"^(?:sudo: )?(?:\d+ incorrect password attempts?|Sorry, try again\.?|a password is required|"
    r"no password was provided|no askpass program specified.*)$"
)
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def sudo_refusal(host, lines: Iterable[str]) -> str | None:
    """One line naming the roster setting when sudo's own words say the password was wrong
    (or that it needed one and got none), else None. sudo says it in whatever step first
    needs root, which says nothing about the cause."""
    words = [" ".join(_ANSI.sub("", str(line)).split()) for line in lines]
    said = next((line for line in reversed(words) if _SUDO_PASSWORD.match(line)), None)
    if said is None:
        return None
    data = getattr(host, "data", None)
    secret = data.get("sudo_password_secret") if data is not None else None
    if secret and data is not None and data.get("_sudo_password"):
        return (f"sudo refused the password from the roster's sudo_password_secret: the secret it names "
                f"does not hold this host's sudo password (sudo: {said.removeprefix('sudo: ')})")
    return (f"sudo asks for a password and the roster sets no sudo_password_secret for this host "
            f"(sudo: {said.removeprefix('sudo: ')})")
