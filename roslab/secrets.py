"""Secrets a roster refers to by name, kept out of the roster and out of output.

A roster never holds a password: a `*_secret` key names an entry in the
classroom's secrets file (`secrets_file`, default `secrets.yaml` beside the
roster, gitignored), a flat YAML mapping of name -> string. This module checks
that file's permissions and wraps each value so that pyinfra prints it masked.
"""

from __future__ import annotations

import stat
from pathlib import Path

from pyinfra.api import HiddenValue

# Committed example files hold placeholders, and git does not keep a 0600 mode:
# for them a loose mode is a warning, for any other secrets file an error.
EXAMPLE_SUFFIX = ".example.yaml"

SECRET_SUFFIX = "_secret"


class Secret(HiddenValue):
    """A secret value: printed masked by pyinfra (in commands and `debug-inventory`).

    Deploys read the real value with `.unmask()`.
    """

    def to_json(self) -> str:
        # pyinfra's JSON output (debug-inventory) uses `to_json` for unknown objects.
        return self.masked_value

    # Equal by value: pyinfra hands out copies of host data and type-checks a global
    # argument (`_sudo_password` must be a str) only when it differs from the host's own.
    def __eq__(self, other) -> bool:
        if isinstance(other, HiddenValue):
            return self.unmask() == other.unmask()
        return NotImplemented

    def __hash__(self) -> int:
        return hash(self.unmask())


def plain_text(value) -> str:
    """The real text of a secret (a Secret from the secrets file: unmasked), or of a value a
    hand-made inventory or --data gave as plain text."""
    unmask = getattr(value, "unmask", None)
    return str(unmask() if unmask is not None else value)


def is_secret_reference(key: str) -> bool:
    """Whether a roster key names a secret rather than holding a value."""
    return key.endswith(SECRET_SUFFIX)


def resolved_key(reference_key: str) -> str:
    """The host data key a secret reference resolves into.

    `wifi_password_secret` -> `wifi_password`; `sudo_password_secret` -> pyinfra's
    own `_sudo_password`.
    """
    if reference_key == "sudo_password_secret":
        return "_sudo_password"
    return reference_key[: -len(SECRET_SUFFIX)]


def wrap(reference_key: str, value: str) -> Secret:
    """The host data value for a resolved secret: a `Secret`, masked in every output.

    The sudo password too: `roslab.ssh.sudo` unmasks it only to write it into the
    host's askpass file. Without `roslab.ssh.sudo` installed, pyinfra would send the
    mask instead of the password (sudo fails), never the password on a command line.
    """
    return Secret(value)


def permission_problem(path: Path, shown: str | None = None) -> str | None:
    """Describe why `path` is too open for a secrets file, or None if it is private."""
    mode = stat.S_IMODE(path.stat().st_mode)
    shown = shown or str(path)
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        return (
            f"secrets file {shown} is open to other users (mode {mode:04o}); "
            f"run: chmod 600 {shown}"
        )
    return None


def is_example(path: Path) -> bool:
    return path.name.endswith(EXAMPLE_SUFFIX)
