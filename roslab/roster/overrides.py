"""pyinfra's command-line data (`--data key=value`, `--user`, `--port`, `--key`...) checked
like the roster.

pyinfra applies these on top of every host's data after the inventory is built, so a
value given there would skip the schema (`--data ros_domain_id=999` reached the diff).
inventories/lab.py reads them from pyinfra's own command line and the roster loader
treats them as one more level that wins over classroom, team and host: each value is
checked where its setting is declared, the classroom checks see it, and a key whose
host data roslab derives differently (a relative controller path, a .pub file, a secret's
name) is refused, since pyinfra would put the raw value back on top.
"""

from __future__ import annotations

import difflib
import json
import re

from roslab import settings

# How pyinfra's CLI names the connection options it turns into host data.
CONNECTION_OPTIONS = {
    "--ssh-user": "ssh_user", "--user": "ssh_user",
    "--ssh-port": "ssh_port", "--port": "ssh_port",
    "--ssh-key": "ssh_key", "--key": "ssh_key",
    "--ssh-key-password": "ssh_key_password", "--key-password": "ssh_key_password",
    "--ssh-password": "ssh_password", "--password": "ssh_password",
}

# Roster settings a command line cannot set: per host by nature, or resolved by the loader.
NOT_FROM_THE_COMMAND_LINE = {
    "role": "a host's role is set per host in the roster",
    "address": "a host's address is set per host in the roster",
    "name": "the classroom's name is set in the roster",
    "secrets_file": "the secrets file is named in the roster",
}
# pyinfra's own data keys that roslab lets through: how pyinfra runs commands and connects.
PYINFRA_KEYS = {
    "_sudo", "_sudo_user", "_use_sudo_login", "_preserve_sudo_env", "_su_user", "_use_su_login",
    "_preserve_su_env", "_su_shell", "_doas", "_doas_user", "_shell_executable", "_timeout",
    "_get_pty", "_retries", "_retry_delay", "_temp_dir",
    "ssh_allow_agent", "ssh_look_for_keys", "ssh_forward_agent", "ssh_connect_retries",
    "ssh_connect_retry_min_delay", "ssh_connect_retry_max_delay", "ssh_file_transfer_protocol",
}
REFUSED_PYINFRA_KEYS = {
    "ssh_hostname": "roslab decides where each host is (its address in the roster, or where the "
                    "network deploy moved it)",
    "ssh_password": "a password on the command line is visible to every user of this machine: use "
                    "--ssh-password-prompt, or a key",
    "ssh_key_password": "a password on the command line is visible to every user of this machine: "
                        "load the key into ssh-agent",
    "_sudo_password": "set sudo_password_secret in the roster (the password stays in the secrets file)",
    "_su_password": "a password on the command line is visible to every user of this machine",
    "wifi_password": "set wifi_password_secret in the roster (the password stays in the secrets file)",
    "ssh_config_file": "an SSH config can send the connection anywhere (ProxyCommand): not from here",
    "ssh_paramiko_connect_kwargs": "not from the command line",
}
NULL_PROBLEM = ("null is not a value from the command line: pyinfra would put it on top of every "
                "host's resolved value; leave the option out for roslab's default")
_DECIMAL = re.compile(r"-?(0|[1-9][0-9]*)", re.ASCII)


def _parse_cli_arg(text: str):
    """The value pyinfra 3.10 makes of `text` (pyinfra_cli.util.parse_cli_arg, mirrored: importing
    pyinfra_cli patches the process with gevent)."""
    if text.lower() == "false":
        return False
    if text.lower() == "true":
        return True
    try:
        return int(text)
    except (TypeError, ValueError):
        pass
    try:
        return json.loads(text)
    except ValueError:
        pass
    return text


def command_line_data(argv: list[str]) -> list[tuple[str, str, str, object]]:
    """Every (option, key, text, value) pyinfra's command line sets in host data, in order.

    Read from whatever program loads the inventory: pyinfra (whose `runpy`-style loading
    hides its own name) or a roslab command, none of which has these options otherwise.
    """
    found = []
    index = 1
    while index < len(argv):
        word = argv[index]
        if word == "--":
            break
        name, eq, inline = word.partition("=")
        if name == "--data" or name in CONNECTION_OPTIONS:
            if eq:
                text = inline
            elif index + 1 < len(argv):
                index += 1
                text = argv[index]
            else:
                break
            if name == "--data":
                key, _, raw = text.partition("=")
                found.append(("--data", key, raw, _parse_cli_arg(raw)))
            else:
                key = CONNECTION_OPTIONS[name]
                found.append((name, key, text, int(text) if key == "ssh_port" and text.isdigit() else text))
        index += 1
    return found


def key_problem(key: str) -> str | None:
    """Why `key` may not be set from the command line, or None (then its value is checked)."""
    if key in NOT_FROM_THE_COMMAND_LINE:
        return NOT_FROM_THE_COMMAND_LINE[key]
    if key.endswith("_secret") and key in settings.SETTINGS:
        return "a secret's name is set in the roster (its value is read from the secrets file)"
    if key in settings.SETTINGS or key in PYINFRA_KEYS:
        return None
    if key in REFUSED_PYINFRA_KEYS:
        return REFUSED_PYINFRA_KEYS[key]
    if key.startswith("roslab_"):
        return "roslab derives it from the roster"
    close = difflib.get_close_matches(key, [*settings.SETTINGS, *PYINFRA_KEYS], n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown key{hint}: a roster setting (docs/roster-and-settings.md) or one of pyinfra's own connection keys"


def text_problem(setting: settings.Setting, text: str, value) -> str | None:
    """Why the text given cannot stand for the value pyinfra makes of it, or None."""
    if not text.isascii() and setting.kind is not str:
        return f"{text!r} holds a character that is not ASCII"
    if isinstance(value, int) and not isinstance(value, bool) and not _DECIMAL.fullmatch(text.strip()):
        return f"{text!r} is not a plain decimal number (pyinfra reads it as {value}): write {value}"
    return None
