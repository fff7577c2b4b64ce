"""The classroom's SSH identity, kept on the controller beside the roster.

Each Pi's SSH host key is generated once here and put into its seed (`roslab seed`),
so a re-flashed Pi keeps its key; the classroom's known_hosts lists every host's key
under each address it is reached at, and roslab's inventories connect with strict
host key checking against it:

    <roster dir>/.roslab-state/host-keys/<host>/ssh_host_ed25519_key(.pub)   dirs 0700, key 0600
    <roster dir>/.roslab-state/known_hosts                                  one line per host

A known_hosts line names the host first, then its addresses, and ends with the comment
`roslab:<host>`, so each line is attributable to its host:

    team1-main,192.168.50.11 ssh-ed25519 AAAA... roslab:team1-main

Lines roslab did not write (no `roslab:` comment) are kept, less any name roslab takes
over. Every change is an atomic rewrite. `RefusalExplainer` turns pyinfra's host key
errors into one line saying which roslab command to run.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from roslab import formats
from roslab.controller_files import UnreadableFile, read_regular_file, replace_file
from roslab.network.state import STATE_DIR

KNOWN_HOSTS_FILE = "known_hosts"
HOST_KEYS_DIR = "host-keys"
KEY_NAME = "ssh_host_ed25519_key"
ATTRIBUTION = "roslab:"
HEADER = (
    "# managed by roslab: the classroom's SSH host keys, one line per host (the last word names it).\n"
    "# Change it with `roslab trust`, `roslab forget` or `roslab seed`, not by hand.\n"
)
_KEY_TYPE = re.compile(r"ssh-ed25519|ssh-rsa|ecdsa-sha2-nistp(256|384|521)|ssh-dss")


class IdentityError(ValueError):
    """A host name, address or key line that cannot go into the identity store."""


def state_dir(roster_path: str | os.PathLike) -> Path:
    return Path(roster_path).resolve().parent / STATE_DIR


def known_hosts_path(roster_path: str | os.PathLike) -> Path:
    """The classroom's known_hosts: `<roster dir>/.roslab-state/known_hosts`."""
    return state_dir(roster_path) / KNOWN_HOSTS_FILE


# --- host keys ------------------------------------------------------------------------


@dataclass(frozen=True)
class HostKeys:
    """One Pi's SSH host key pair on the controller."""

    host: str
    private_path: Path
    public_path: Path

    def private_text(self) -> str:
        return self.private_path.read_text(encoding="ascii")

    def public_line(self) -> str:
        """The `ssh-ed25519 AAAA... root@<host>` line."""
        return self.public_path.read_text(encoding="ascii").strip()


def _host_keys_dir(roster_path, host_name: str) -> Path:
    problem = formats.host_label(host_name)
    if problem:
        raise IdentityError(problem)
    base = state_dir(roster_path) / HOST_KEYS_DIR
    directory = base / host_name
    if directory.parent != base:  # a checked label has no '/' or '..'; confine anyway
        raise IdentityError(f"{host_name!r} is not a host name")
    return directory


def _private_dir(path: Path) -> None:
    """Create `path` (and missing parents) with mode 0700."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(path, 0o700)


def has_host_keys(roster_path: str | os.PathLike, host_name: str) -> bool:
    """Whether the host's key pair exists on the controller (the Pi was seeded)."""
    directory = _host_keys_dir(roster_path, host_name)
    return (directory / KEY_NAME).is_file() and (directory / f"{KEY_NAME}.pub").is_file()


def host_keys(roster_path: str | os.PathLike, host_name: str) -> HostKeys:
    """The host's ed25519 host key pair, generated on the first call and unchanged after.

    Generated into a private temporary directory that is then renamed into place, so a
    concurrent call or an interrupted one never leaves half a key pair: the first
    rename wins and every caller returns that pair.
    """
    directory = _host_keys_dir(roster_path, host_name)
    keys = HostKeys(host_name, directory / KEY_NAME, directory / f"{KEY_NAME}.pub")
    if keys.private_path.is_file() and keys.public_path.is_file():
        return keys
    _private_dir(state_dir(roster_path))
    _private_dir(directory.parent)
    staging = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{host_name}-"))
    try:
        private, public = _generate_ed25519(f"root@{host_name}")
        _write_private(staging / KEY_NAME, private)
        (staging / f"{KEY_NAME}.pub").write_text(public + "\n", encoding="ascii")
        try:
            os.rename(staging, directory)
        except OSError:
            if not (keys.private_path.is_file() and keys.public_path.is_file()):
                raise  # not a lost race: something else is in the way
    finally:
        if staging.exists():
            for child in staging.iterdir():
                child.unlink()
            staging.rmdir()
    return keys


def _generate_ed25519(comment: str) -> tuple[str, str]:
    """(OpenSSH private key text, public key line) of a new ed25519 key."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    key = Ed25519PrivateKey.generate()
    private = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()
    ).decode("ascii")
    public = key.public_key().public_bytes(
        serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH
    ).decode("ascii")
    return private, f"{public} {comment}"


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as out:
        out.write(text)


# --- known_hosts ----------------------------------------------------------------------


@dataclass
class KnownHost:
    """One known_hosts line: its names, key type and key, and the roslab host it belongs to."""

    names: list[str]
    key_type: str
    key: str
    owner: str | None = None  # the roslab host (from the `roslab:<host>` comment)
    marker: str = ""  # @cert-authority / @revoked
    raw: str | None = None  # a line roslab keeps as it was (comments, lines it cannot parse)

    def line(self) -> str:
        if self.raw is not None:
            return self.raw
        words = [self.marker] if self.marker else []
        words += [",".join(self.names), self.key_type, self.key]
        if self.owner:
            words.append(ATTRIBUTION + self.owner)
        return " ".join(words)

    def public_line(self) -> str:
        return f"{self.key_type} {self.key}"


def parse_public_line(public_line: str) -> tuple[str, str]:
    """(key type, base64 key) of an `ssh-ed25519 AAAA... comment` line; IdentityError if not one."""
    words = str(public_line).split()
    if len(words) < 2 or not _KEY_TYPE.fullmatch(words[0]):
        raise IdentityError(f"not an SSH public key line: {str(public_line)[:40]!r}")
    try:
        decoded = base64.b64decode(words[1], validate=True)
    except ValueError:
        raise IdentityError(f"the key of {words[0]} is not base64") from None
    # The key blob starts with its own type name, length-prefixed.
    if decoded[4:4 + len(words[0])] != words[0].encode():
        raise IdentityError(f"the key does not match its type {words[0]}")
    return words[0], words[1]


def _parse_line(text: str) -> KnownHost:
    stripped = text.strip()
    if not stripped or stripped.startswith("#"):
        return KnownHost([], "", "", raw=text)
    words = stripped.split()
    marker = words.pop(0) if words[0].startswith("@") else ""
    if len(words) < 3:
        return KnownHost([], "", "", raw=text)
    owner = None
    if len(words) > 3 and words[-1].startswith(ATTRIBUTION):
        owner = words[-1][len(ATTRIBUTION):]
    return KnownHost(words[0].split(","), words[1], words[2], owner=owner, marker=marker,
                     raw=None if owner else text)


def known_hosts_of(roster_path: str | os.PathLike, chosen: str | None = None) -> Path:
    """The known_hosts file a run checks a host against: the roster's `ssh_known_hosts_file`
    for it (`chosen`, absolute in its settings), else the classroom's own beside the roster."""
    return Path(chosen) if chosen else known_hosts_path(roster_path)


def read_known_hosts(roster_path: str | os.PathLike, known_hosts: Path | None = None) -> list[KnownHost]:
    """Every line of the classroom's known_hosts, or of `known_hosts` (none if it does not exist)."""
    path = Path(known_hosts or known_hosts_path(roster_path))
    if str(path) == os.devnull or not os.path.lexists(path):
        return []
    try:
        text = read_regular_file(path, formats.MAX_KNOWN_HOSTS_BYTES).decode("utf-8")
    except (UnreadableFile, UnicodeDecodeError) as error:
        raise IdentityError(f"{path}: {error}") from None
    return [_parse_line(line) for line in text.splitlines()
            if line.rstrip("\n") not in HEADER.splitlines()]


def _write_known_hosts(roster_path, entries: list[KnownHost], known_hosts: Path | None = None) -> None:
    """Replace the known_hosts file at once. The classroom's own gets roslab's header and
    a private folder; a file the roster names (ssh_known_hosts_file) keeps its mode and
    folder, and gets no header: roslab only edits its own lines and names in it."""
    own = known_hosts is None or Path(known_hosts) == known_hosts_path(roster_path)
    path = known_hosts_path(roster_path) if own or known_hosts is None else Path(known_hosts)
    if str(path) == os.devnull:
        raise IdentityError("ssh_known_hosts_file is /dev/null: no host key can be recorded there")
    if own:
        _private_dir(path.parent)
    try:
        mode = 0o644 if own else stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        mode = 0o644
    body = "".join(entry.line() + "\n" for entry in entries)
    replace_file(path, (HEADER if own else "") + body, mode)  # public keys: ssh refuses nothing for being readable


def _name_matches(name: str, wanted: str) -> bool:
    """Whether a known_hosts name (plain or `|1|salt|hash`) stands for `wanted`."""
    if not name.startswith("|1|"):
        return name.lower() == wanted.lower()
    try:
        _, _, salt, digest = name.split("|")
        expected = hmac.new(base64.b64decode(salt), wanted.encode(), hashlib.sha1).digest()
        return hmac.compare_digest(expected, base64.b64decode(digest))
    except (ValueError, TypeError):
        return False


def knows_address(entries: list[KnownHost], address: str, port: int = 22) -> bool:
    """Whether a known_hosts file's lines (plain or hashed names) hold a key for `address`."""
    wanted = address if port == 22 else f"[{address}]:{port}"
    return any(_name_matches(name, wanted) for entry in entries for name in entry.names)


def host_names(host_name: str, addresses: Iterable[str], port: int = 22) -> list[str]:
    """The known_hosts names of a host: its name and addresses (`[addr]:port` too off port 22)."""
    names: list[str] = []
    for name in (host_name, *addresses):
        name = str(name).strip() if name else ""
        if not name:
            continue
        if formats.address(name) is not None:
            raise IdentityError(f"{name!r} is neither an IP address nor a host name")
        for form in ((name, f"[{name}]:{port}") if port != 22 else (name,)):
            if form.lower() not in (known.lower() for known in names):
                names.append(form)
    return names


def _without_names(entries: list[KnownHost], names: list[str]) -> list[KnownHost]:
    """The entries with `names` taken out of every line (a line left with none is dropped)."""
    plain = {name.lower() for name in names}
    kept = []
    for entry in entries:
        if not entry.names:
            kept.append(entry)
            continue
        remaining = [name for name in entry.names
                     if not (name.lower() in plain if not name.startswith("|1|")
                             else any(_name_matches(name, wanted) for wanted in names))]
        if len(remaining) == len(entry.names):
            kept.append(entry)
        elif remaining:
            kept.append(replace(entry, names=remaining, raw=None))
    return kept


def trust(roster_path: str | os.PathLike, host_name: str, addresses: Iterable[str],
          public_line: str, port: int = 22, known_hosts: Path | None = None) -> bool:
    """Record `public_line` as the host's key under its name and every address.

    Replaces the host's own line and takes those names out of any other line. Returns
    whether the file changed (a second call with the same arguments writes nothing).
    """
    problem = formats.host_label(host_name)
    if problem:
        raise IdentityError(problem)
    key_type, key = parse_public_line(public_line)
    names = host_names(host_name, addresses, port)
    entries = read_known_hosts(roster_path, known_hosts)
    wanted = KnownHost(names, key_type, key, owner=host_name)
    others = [entry for entry in entries if entry.owner != host_name]
    new = _sorted(_without_names(others, names) + [wanted])
    if [entry.line() for entry in new] == [entry.line() for entry in entries]:
        return False
    _write_known_hosts(roster_path, new, known_hosts)
    return True


def _sorted(entries: list[KnownHost]) -> list[KnownHost]:
    """Foreign lines first as they were, then roslab's lines by host (a stable file)."""
    foreign = [entry for entry in entries if not entry.owner]
    own = sorted((entry for entry in entries if entry.owner), key=lambda entry: entry.owner or "")
    return foreign + own


def forget(roster_path: str | os.PathLike, *hosts_or_addresses: str,
           known_hosts: Path | None = None) -> list[str]:
    """Remove the keys of hosts (by roslab host name) or of addresses; the names removed.

    A host name removes that host's whole line; any name also leaves every other line.
    """
    entries = read_known_hosts(roster_path, known_hosts)
    wanted = [str(name).strip() for name in hosts_or_addresses if str(name).strip()]
    kept = _without_names([entry for entry in entries if entry.owner not in wanted], wanted)
    removed = [name for entry in entries for name in entry.names
               if not any(name in other.names for other in kept)]
    if removed:
        _write_known_hosts(roster_path, kept, known_hosts)
    return removed


def known_key(roster_path: str | os.PathLike, host_name: str,
              entries: list[KnownHost] | None = None, known_hosts: Path | None = None) -> KnownHost | None:
    """The host's own known_hosts line, or None."""
    for entry in read_known_hosts(roster_path, known_hosts) if entries is None else entries:
        if entry.owner == host_name:
            return entry
    return None


def other_keys(entries: list[KnownHost], names: Iterable[str], public_line: str) -> list[KnownHost]:
    """Lines that list one of `names` (plain or hashed) with a key other than `public_line`'s."""
    key_type, key = parse_public_line(public_line)
    wanted = list(names)
    return [entry for entry in entries
            if entry.names and not entry.marker and (entry.key_type, entry.key) != (key_type, key)
            and any(_name_matches(name, one) for name in entry.names for one in wanted)]


def fingerprint(public_line: str) -> str:
    """The key's SHA256 fingerprint as `ssh-keygen -l` prints it."""
    _, key = parse_public_line(public_line)
    digest = hashlib.sha256(base64.b64decode(key)).digest()
    return "SHA256:" + base64.b64encode(digest).decode().rstrip("=")


def sync_addresses(roster_path: str | os.PathLike, hosts: Mapping[str, tuple[list[str], int]]) -> list[str]:
    """Make known_hosts list every address of each host whose key roslab knows.

    `hosts`: host name -> (its addresses, its SSH port), from a checked roster. A host
    with a line gets the missing addresses added; a seeded host without a line gets its
    seeded key. Other hosts are left alone (strict checking refuses them with the
    `roslab trust` hint). Writes only when something is missing: otherwise one read of
    the file and one listing of the host key directory. Returns the hosts whose line changed.
    """
    entries = read_known_hosts(roster_path)
    own = {entry.owner: entry for entry in entries if entry.owner}
    try:
        seeded = set(os.listdir(state_dir(roster_path) / HOST_KEYS_DIR))
    except OSError:
        seeded = set()
    updated: dict[str, KnownHost] = {}
    for host_name, (addresses, port) in hosts.items():
        entry = own.get(host_name)
        if entry is None and host_name not in seeded:
            continue
        names = []
        for name in (host_name, *addresses):
            for form in ((name, f"[{name}]:{port}") if port != 22 else (name,)):
                if form not in names:
                    names.append(form)
        if entry is not None:
            have = {name.lower() for name in entry.names}
            missing = [name for name in names if name.lower() not in have and not any(
                _name_matches(known, name) for known in entry.names if known.startswith("|1|"))]
            if not missing:
                continue
            updated[host_name] = KnownHost(entry.names + missing, entry.key_type, entry.key, owner=host_name)
        elif has_host_keys(roster_path, host_name):
            key_type, key = parse_public_line(host_keys(roster_path, host_name).public_line())
            updated[host_name] = KnownHost(names, key_type, key, owner=host_name)
    if not updated:
        return []
    taken = [name for entry in updated.values() for name in entry.names]
    others = [entry for entry in entries if entry.owner not in updated]
    _write_known_hosts(roster_path, _sorted(_without_names(others, taken) + list(updated.values())))
    return list(updated)


# --- what a refused host is told --------------------------------------------------------


@dataclass(frozen=True)
class HostTarget:
    """How roslab tells the teacher to fix one host's known key."""

    host: str
    roster: str  # the roster as the teacher would type it
    known_hosts: str

    def changed_message(self, address: str) -> str:
        return (f"roslab: {self.host} ({address}) answered with another SSH host key than the one "
                f"recorded in {self.known_hosts}; if it was re-flashed without its seed, run "
                f"`roslab forget {self.roster} --limit {self.host}` then "
                f"`roslab trust {self.roster} --limit {self.host}` (compare the fingerprint it prints), "
                f"or flash it again with its seed (`roslab seed {self.roster} --limit {self.host} ...`)")

    def unknown_message(self, address: str) -> str:
        return (f"roslab: no SSH host key of {self.host} ({address}) is recorded in {self.known_hosts}; "
                f"run `roslab trust {self.roster} --limit {self.host}` (compare the fingerprint it prints), "
                f"or flash it with its seed (`roslab seed {self.roster} --limit {self.host} ...`)")


_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
_PREFIX = re.compile(r"^\s*\[([^\]\s]+)\]\s*")
_BAD_KEY = re.compile(r"SSH host key error \(Host key for (\S+) does not match\.\)")
_NO_KEY = re.compile(r"No host key for (\S+) found in known_hosts")
_KEYGEN_HINT = re.compile(r"^\s*ssh-keygen -R (\S+)\s*$")
_HINT_INTRO = "If this is expected, you can remove the bad key using:"
_NO_FILE = re.compile(r"^\s*Failed to load host keys from (\S+): \[Errno 2\]")


class RefusalExplainer(logging.Filter):
    """A filter on pyinfra's logger: host key refusals become roslab's one-line instruction.

    pyinfra (3.10, connectors/ssh.py) answers a changed key with `ssh-keygen -R ADDRESS`,
    which edits ~/.ssh/known_hosts, not the classroom's; strict checking's refusal of an
    unknown key names only the address. This drops that hint and rewrites the host's
    error line to name the host, the known_hosts file and the roslab commands; pyinfra's
    man-in-the-middle warning stays. `refusals` maps each refused host to its line, for
    roslab's run summary. Classrooms are added as they are (`add_classroom`) and indexed
    by address only when a refusal is logged: an inventory stays as fast as before.
    """

    def __init__(self) -> None:
        super().__init__("roslab-host-keys")
        self.targets: dict[str, HostTarget] = {}  # host name -> target
        self.by_address: dict[str, list[str]] = {}  # ssh address (and [addr]:port) -> host names
        self.refusals: dict[str, str] = {}
        self._pending: list[tuple[str, str, Mapping[str, tuple[list[str], int]]]] = []
        self.files: set[str] = set()  # the classroom known_hosts files (absolute)

    def add_classroom(self, roster: str, known_hosts: str,
                      hosts: Mapping[str, tuple[list[str], int]], known_hosts_file: str = "") -> None:
        """Hosts (name -> (addresses, SSH port)) whose keys `known_hosts` holds, as the
        teacher types the roster and the file."""
        self._pending.append((roster, known_hosts, hosts))
        if known_hosts_file:
            self.files.add(known_hosts_file)

    def add_host(self, target: HostTarget, addresses: Iterable[str]) -> None:
        self.targets[target.host] = target
        for address in addresses:
            hosts = self.by_address.setdefault(str(address).lower(), [])
            if target.host not in hosts:
                hosts.append(target.host)

    def _index(self) -> dict[str, HostTarget]:
        while self._pending:
            roster, known_hosts, hosts = self._pending.pop(0)
            for name, (addresses, port) in hosts.items():
                forms = [*addresses, *(f"[{address}]:{port}" for address in addresses)]
                self.add_host(HostTarget(name, roster, known_hosts), forms)
        return self.targets

    def _hosts_at(self, address: str) -> list[str]:
        self._index()
        address = address.lower()
        bare = re.sub(r"^\[(.*)\]:\d+$", r"\1", address)
        return self.by_address.get(address) or self.by_address.get(bare) or []

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            return self._rewrite(record)
        except Exception:  # noqa: BLE001 - a log filter must never break the run
            return True

    def _rewrite(self, record: logging.LogRecord) -> bool:
        text = _ANSI.sub("", record.getMessage())
        # `ssh-keygen -R` edits ~/.ssh/known_hosts, not the classroom's: the host's error
        # line just after says what to run instead.
        if "host key" not in text.lower() and text.strip() != _HINT_INTRO and not _KEYGEN_HINT.match(text):
            return True  # the common case: not about host keys
        missing = _NO_FILE.match(text)
        if missing and missing.group(1) in self.files:
            return False  # no classroom known_hosts yet: no key is known, the refusals say what to run
        targets = self._index()
        if text.strip() == _HINT_INTRO:
            return not targets
        hint = _KEYGEN_HINT.match(text)
        if hint:
            return not any(host in targets for host in self._hosts_at(hint.group(1)))
        prefix = _PREFIX.match(text)
        for pattern, kind in ((_BAD_KEY, "changed"), (_NO_KEY, "unknown")):
            found = pattern.search(text)
            if not found:
                continue
            address = found.group(1)
            hosts = [prefix.group(1)] if prefix and prefix.group(1) in self.targets else [
                host for host in self._hosts_at(address) if host in self.targets]
            if not hosts:
                return True
            lines = [self._note(host, kind, address) for host in hosts]
            if not prefix:
                # StrictPolicy's own line; pyinfra logs the host's error line right after.
                return False
            self._set(record, f"[{hosts[0]}] {lines[0]}")
            return True
        return True

    def _note(self, host: str, kind: str, address: str) -> str:
        target = self.targets[host]
        address = re.sub(r"^\[(.*)\]:\d+$", r"\1", address)
        message = target.changed_message(address) if kind == "changed" else target.unknown_message(address)
        self.refusals[host] = message
        return message

    @staticmethod
    def _set(record: logging.LogRecord, message: str) -> None:
        record.msg, record.args = message, ()


_explainer: RefusalExplainer | None = None


def explainer() -> RefusalExplainer:
    """The one RefusalExplainer on pyinfra's logger (installed on first use)."""
    global _explainer
    if _explainer is None:
        import pyinfra

        _explainer = RefusalExplainer()
        pyinfra.logger.addFilter(_explainer)
    return _explainer


def refusal(host_name: str) -> str | None:
    """The roslab line a host key refusal of `host_name` printed in this run, or None."""
    return _explainer.refusals.get(host_name) if _explainer is not None else None
