"""Escaping for the formats roster values are written into.

Values arrive checked by their format (`roslab.formats`); these functions then write
them so that the destination reads back exactly the value, never syntax. Each refuses
(ValueError) what its format cannot carry at all, so a missed check fails loudly
instead of changing the meaning of a file.
"""

from __future__ import annotations

import shlex

from roslab.formats import single_line


def _one_line(value: str, what: str) -> str:
    value = str(value)
    problem = single_line(value)
    if problem:
        raise ValueError(f"{what}: {value!r} {problem}")
    return value


def shell_word(value: str) -> str:
    """One word for sh/bash: single-quoted, so `$(...)`, backticks and `\\` stay text."""
    return shlex.quote(_one_line(value, "shell word"))


def shell_home_path(path: str) -> str:
    """A `~/...` path for the shell: `"$HOME"` and the rest single-quoted.

    A quoted `~` would not expand, and double quotes would expand `$(...)` in the rest.
    """
    path = _one_line(path, "path")
    if path == "~":
        return '"$HOME"'
    if path.startswith("~/"):
        return '"$HOME"/' + shlex.quote(path[2:])
    return shlex.quote(path)


def systemd_word(value: str) -> str:
    """One argument of a systemd `ExecStart=` line, read back exactly.

    systemd un-escapes C escapes (`\\x41`) inside words, expands `%` specifiers and, in
    ExecStart, `$VAR`/`${VAR}` (systemd.service(5), "Command lines"): each is escaped.
    """
    value = _one_line(value, "systemd argument")
    escaped = (value.replace("\\", "\\\\").replace('"', '\\"')
               .replace("%", "%%").replace("$", "$$"))
    return f'"{escaped}"'


def systemd_assignment(name: str, value: str) -> str:
    """A quoted `NAME=value` for `Environment=` (no `$` expansion there, specifiers yes)."""
    text = _one_line(f"{name}={value}", "systemd environment")
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("%", "%%")
    return f'"{escaped}"'


def systemd_value(value: str) -> str:
    """A plain one-line unit setting value (Description=, User=...): specifiers escaped."""
    return _one_line(value, "systemd value").replace("%", "%%")


def deb822_value(value: str) -> str:
    """A deb822 field value: one line, so it cannot add a field (`Trusted: yes`)."""
    value = _one_line(value, "deb822 field")
    if value != value.strip():
        raise ValueError(f"deb822 field: {value!r} has leading or trailing space")
    return value


def apt_arguments(names: list[str]) -> list[str]:
    """Package names for apt-get, never read as options: a leading `-` is refused."""
    for name in names:
        _one_line(name, "package name")
        if name.startswith("-"):
            raise ValueError(f"package name {name!r} starts with '-' (apt would read an option)")
    return list(names)


def sources_list_word(value: str) -> str:
    """One word of an apt source (a suite or a component): one-line or deb822 layout.

    A one-line `sources.list` splits its fields on whitespace, reads `[` as options and
    everything from `#` on as a comment; a deb822 `Suites:` field splits on whitespace.
    """
    value = _one_line(value, "apt source word")
    if any(char.isspace() or char in "#[]" for char in value):
        raise ValueError(f"apt source word: {value!r} holds whitespace, '#', '[' or ']'")
    return value


# --- YAML (netplan) and GKeyFile (NetworkManager) ------------------------------------------
# Each takes a string (or an ipaddress object) and returns text that the format's own
# parser reads back as exactly that string, or raises ValueError for what it cannot hold.


def _text(value) -> str:
    if value is None or isinstance(value, (bool, int, float, list, tuple, dict)):
        raise TypeError(f"{value!r} is not a string to write into a network file")
    return str(value)


def _yaml_escape(character: str) -> str:
    code = ord(character)
    if character == '"':
        return '\\"'
    if character == "\\":
        return "\\\\"
    if 0xD800 <= code <= 0xDFFF:
        raise ValueError(f"U+{code:04X} (a surrogate) cannot be written as UTF-8")
    if 0x20 <= code <= 0x7E or (
        # YAML's printable set, less its line breaks (U+2028, U+2029) and the byte order mark.
        (0xA0 <= code <= 0xFFFD or code >= 0x10000) and code not in (0x2028, 0x2029, 0xFEFF)
    ):
        return character
    if code <= 0xFF:
        return f"\\x{code:02X}"
    if code <= 0xFFFF:
        return f"\\u{code:04X}"
    return f"\\U{code:08X}"


def yaml_string(value) -> str:
    """`value` as a YAML double-quoted scalar that reads back as exactly `value`.

    Unlike `json.dumps`, this also escapes what YAML (libyaml, which netplan uses)
    treats differently from JSON: DEL and C1 controls (not printable in YAML), NEL,
    U+2028 and U+2029 (line breaks in YAML, folded into a space inside a scalar).
    """
    return '"' + "".join(_yaml_escape(character) for character in _text(value)) + '"'


def keyfile_string(value) -> str:
    """`value` as a GKeyFile string value (nm-settings-keyfile(5)), as g_key_file_set_string writes it.

    Backslash, newline, tab and carriage return are escaped everywhere; spaces at
    either end become `\\s` (GKeyFile drops the spaces after `=`, editors the ones
    at the end of a line). Other control characters have no escape in GKeyFile and
    are refused.
    """
    text = _text(value)
    for character in text:
        if (ord(character) < 0x20 and character not in "\t\n\r") or character == "\x7f":
            raise ValueError(f"U+{ord(character):04X} cannot be written in a keyfile")
    escaped = (
        text.replace("\\", "\\\\").replace("\n", "\\n").replace("\t", "\\t").replace("\r", "\\r")
    )
    core = escaped.strip(" ")
    if not core:
        return "\\s" * len(escaped)
    leading = len(escaped) - len(escaped.lstrip(" "))
    trailing = len(escaped) - len(escaped.rstrip(" "))
    return "\\s" * leading + core + "\\s" * trailing


def keyfile_ssid(value) -> str:
    """An SSID as NetworkManager's own keyfile writer writes it.

    NetworkManager reads an SSID made of digits and `;` (`12;34;`) as a list of
    byte values, and turns `\\;` back into `;` in any other: so each `;` is written
    as `\\;` first (never a byte list then), then escaped as a GKeyFile string.
    """
    return keyfile_string(_text(value).replace(";", "\\;"))


def keyfile_list(values) -> str:
    """A GKeyFile string list (`a;b;`), each item escaped and its own `;` as `\\;`."""
    return "".join(keyfile_string(value).replace(";", "\\;") + ";" for value in values)
