"""Read a host's state ahead, in one remote command, and serve pyinfra's facts from it.

pyinfra 3 runs one remote command per fact and keeps no fact cache, so a no-op run of
deploy.py used to cost 49 commands per host, several of them the same read (`dpkg -l`
four times). Here each deploy names the facts its operations read on a host that needs
no change (a *reader*, registered with `@reader`); `read_ahead` runs all of them in ONE
remote command (the `HostProbe` fact: each fact's own command, its output parsed by the
fact's own `process`), and from then on `host.get_fact` answers those facts from that
read, for roslab's operations and pyinfra's own alike (`apt.packages`, `files.put`, ...).

Correctness first: the read is served only while it is true. Once any operation has
run a command on the host, the read is dropped and every fact is read again from the
host, as pyinfra always does. So a no-op run reads each host in two commands (the basics
without sudo, then everything else: `deploy.common.supported_host`); a run that heals one
drift reads the same way, then fact by fact after the heal; a first run costs two
commands more than it would without the probe. A fact that is not read ahead, asked with other arguments, asked with its own
connection arguments (`_sudo`, ...), or whose command failed in the batch is read the
usual way. Values are handed out as copies: a caller that edits one changes nothing here.
"""

from __future__ import annotations

import base64
import copy
import dataclasses
import datetime
import functools
import gzip
import inspect
import posixpath
import re
import secrets
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TypeVar

from pyinfra import host as current_host
from pyinfra.api import FactBase, StringCommand
from pyinfra.context import ctx_host, ctx_state
from pyinfra.facts.deb import DebPackage, DebPackages
from pyinfra.facts.files import Directory, File, Sha1File
from pyinfra.facts.server import AuthorizedKeys, Home, Hostname, Which
from pyinfra.facts.systemd import SystemdEnabled, SystemdStatus

# pyinfra's marker for a fact whose `requires_command` is missing (pyinfra.api.facts).
_MISSING_COMMAND_MARKER = "##PYINFRA_NOCMD##"


def _hashable(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return tuple(_hashable(item) for item in value)
    if isinstance(value, dict):
        return tuple(sorted((key, _hashable(item)) for key, item in value.items()))
    return value


# Values that no caller can change: served as they are (frozenset's items are hashable,
# so of these types too).
_UNCHANGEABLE = frozenset({str, bytes, int, float, bool, type(None), frozenset,
                           datetime.datetime, datetime.date, datetime.time, datetime.timedelta})


def own_copy(value: Any) -> Any:
    """A copy of a fact's value that its caller may change, as `copy.deepcopy` gives.

    A fact's value is plain data (dicts, lists and sets of strings, numbers, dates): those
    types are copied here directly, each other type by `copy.deepcopy` (subclasses such as
    defaultdict included), which on a whole class's no-op cost more CPU than planning the
    operations (hundreds of installed packages per host, copied once per read).
    """
    kind = type(value)
    if kind in _UNCHANGEABLE:
        return value
    if kind is dict:
        return {key: own_copy(item) for key, item in value.items()}
    if kind is list:
        return [own_copy(item) for item in value]
    if kind is set:
        return set(value)  # hashable items: nothing in them to change
    if kind is tuple:
        return tuple(own_copy(item) for item in value)
    if _is_frozen_dataclass(kind) and all(  # type: ignore[arg-type]  # a class is hashable; mypy checks its unbound __hash__
            type(getattr(value, name)) in _UNCHANGEABLE for name in kind.__dataclass_fields__):
        return value  # a workspace entry, say: nothing in it can change
    return copy.deepcopy(value)


@functools.cache
def _is_frozen_dataclass(kind: type) -> bool:
    return dataclasses.is_dataclass(kind) and getattr(kind, "__dataclass_params__").frozen  # not in typeshed


@functools.cache
def _signature(command: Callable) -> inspect.Signature:
    """A fact's command's signature: read once per run, not once per read per host."""
    return inspect.signature(command)


def _normalized(fact: type[FactBase], arguments: dict) -> tuple | None:
    """The fact's arguments as pyinfra binds them (defaults filled in), hashable; None if
    they do not fit its command. Bound once per fact and arguments: every fact an operation
    asks on every host comes through here."""
    given = (fact, tuple((name, _hashable(arguments[name])) for name in sorted(arguments)))
    try:
        return _NORMALIZED[given]
    except KeyError:
        normalized = _NORMALIZED[given] = _bound(fact, arguments)
        return normalized
    except TypeError:  # an argument that no hashable form holds (a set, say)
        return _bound(fact, arguments)


_NORMALIZED: dict[tuple, tuple | None] = {}


def _bound(fact: type[FactBase], arguments: dict) -> tuple | None:
    command = getattr(fact, "command", None)
    if not callable(command):
        return () if not arguments else None
    try:
        bound = _signature(command).bind(None, **arguments)
    except TypeError:
        return None
    bound.apply_defaults()
    names = list(bound.arguments)[1:]  # without self
    return tuple((name, _hashable(bound.arguments[name])) for name in names)


@dataclass(frozen=True)
class Read:
    """One fact with its arguments, as an operation asks `host.get_fact(fact, **arguments)`."""

    fact: type[FactBase]
    arguments: tuple  # ((name, value), ...) as `_normalized` gives them

    def kwargs(self) -> dict:
        return dict(self.arguments)


# Names through which a fact's command could read the host it runs for (pyinfra's `host`,
# its context): such a command is not a function of the fact's arguments alone.
_HOST_NAMES = frozenset({"host", "ctx_host", "context", "state", "ctx_state"})


@functools.cache
def asks_the_host(fact: type[FactBase]) -> bool:
    """Whether the fact's command (or its requires_command) reads the host it runs for, as
    pyinfra's Uptime, Mounts and Port do: its command text then differs from host to host."""
    for method in (getattr(fact, "command", None), getattr(fact, "requires_command", None)):
        code = getattr(method, "__code__", None)
        if code is not None and _HOST_NAMES & set(code.co_names):
            return True
    return False


def read(fact: type[FactBase], **arguments) -> Read:
    """The read of `fact` with `arguments`, e.g. ``read(File, path="/etc/hosts")``.

    A fact whose command reads the host is not read ahead: the probe builds each read's
    command once per run, for every host alike."""
    if asks_the_host(fact):  # type: ignore[arg-type]  # a class is hashable; mypy checks its unbound __hash__
        raise TypeError(f"{fact.__name__}'s command reads the host: it cannot be read ahead")
    normalized = _normalized(fact, arguments)
    if normalized is None:
        raise TypeError(f"{fact.__name__} takes no arguments {sorted(arguments)}")
    return Read(fact, normalized)


def _section_command(item: Read, fact: FactBase) -> str:
    """The fact's command as pyinfra would run it (with its `requires_command` guard).

    `fact` is the instance whose `process` reads the output: some facts keep their
    arguments on it (pyinfra's FileContents, Sha1File).
    """
    kwargs = item.kwargs()
    command = fact.command(**kwargs) if callable(fact.command) else fact.command
    required = fact.requires_command(**kwargs) if callable(fact.requires_command) else None
    if isinstance(command, StringCommand):
        if command.get_masked_value() != command.get_raw_value():
            # A secret (HiddenValue) would show in pyinfra's log of the probe's command.
            raise ValueError(f"{item.fact.__name__}'s command holds a hidden value")
        text = command.get_raw_value()
    else:
        text = str(command)
    if required:
        text = (f"if command -v {required} >/dev/null 2>&1; then ( {text} ); "
                f"else echo '{_MISSING_COMMAND_MARKER}'; fi")
    return text


class Commands(tuple):
    """HostProbe's commands; shown in pyinfra's log as a count, not a page of shell."""

    def __repr__(self) -> str:
        return f"<{len(self)} commands>"

    __str__ = __repr__


def sections_script(commands: tuple, marker: str) -> str:
    """The shell that runs each command in its own subshell, stdin closed, and ends its output
    with the marker, its index and its exit status."""
    return "\n".join(
        [f"echo {marker}"]
        + [f"( {command}\n) </dev/null; printf '%s\\n' \"{marker} {index} $?\""
           for index, command in enumerate(commands)]
    )


# What `gzip | base64` output starts with: gzip's magic number and method (1f 8b 08).
GZIP_BASE64 = "H4sI"


def unpacked(output: list[str]) -> list[str]:
    """The probe's output lines as the host printed them: decoded and split the way pyinfra
    splits a command's output (at "\\n", which is dropped) when it came gzipped as one base64
    line; as they are when the host sent them plain. [] when they cannot be decoded (every
    fact is then read on its own)."""
    if len(output) != 1 or not output[0].startswith(GZIP_BASE64):
        return output
    try:
        text = gzip.decompress(base64.b64decode(output[0], validate=True)).decode("utf-8")
    except (ValueError, OSError, EOFError, zlib.error):
        return []
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()
    return lines


class HostProbe(FactBase):
    """
    Runs several facts' commands in one remote command.

    + commands: the commands, each run in its own subshell (an ``exit`` or ``cd`` in one
      does not reach the next), stdin closed
    + marker: a random word that ends each command's output, with its index and exit status

    Returns ``[(status, lines), ...]``, one per command, in order; ``(None, [])`` for a
    command whose end was not seen. A command's last line without a newline is kept as
    pyinfra keeps it.
    """

    @staticmethod
    def default():
        return []

    def command(self, commands: tuple, marker: str) -> str:
        # The sections travel gzipped, as one base64 line: pyinfra and paramiko cost CPU per
        # line of output (a queue, a thread switch, a readline each), and a host's installed
        # packages alone are hundreds of lines. A host without gzip or base64 sends them plain.
        return (f"roslab_probe() {{\n{sections_script(commands, marker)}\n}}\n"
                "if command -v gzip >/dev/null 2>&1 && command -v base64 >/dev/null 2>&1; "
                "then roslab_probe | gzip -1 -c | base64 -w 0; else roslab_probe; fi")

    def process(self, output):
        output = unpacked(output)
        # The first line is the marker: a random word per run, so no file can forge it.
        if not output:
            return []
        end = re.compile(rf"^(.*){re.escape(output[0])} ([0-9]+) ([0-9]+)$")
        sections: dict[int, tuple[int, list[str]]] = {}
        lines: list[str] = []
        for line in output[1:]:
            found = end.match(line)
            if not found:
                lines.append(line)
                continue
            if found.group(1):  # the command's last line had no newline
                lines.append(found.group(1))
            sections[int(found.group(2))] = (int(found.group(3)), lines)
            lines = []
        count = max(sections, default=-1) + 1
        return [sections.get(index, (None, [])) for index in range(count)]


def values_of(reads: list[tuple[Read, FactBase]], sections: list) -> dict[Read, Any]:
    """Each read's value, as `host.get_fact` would give it, from HostProbe's sections
    (`reads`: each read with the fact instance that made its command).

    Left out: a read whose command failed, was not seen to end, lacks its required
    command, or whose output the fact cannot process (the fact is then read on its own,
    and reports its error the usual way).
    """
    values = {}
    for (item, fact), (status, lines) in zip(reads, sections):
        if status != 0 or lines == [_MISSING_COMMAND_MARKER]:
            continue
        try:
            values[item] = fact.process(lines) if lines else fact.default()
        except Exception:  # noqa: BLE001 - the fact read on its own reports it properly
            continue
    return values


# Each read's command and the fact instance whose `process` reads its output, built once
# per run for every host (`read` takes only facts whose command is a function of their
# arguments; an instance keeps no more than its arguments): building them per host was a
# third of a converged host's planning CPU (pyinfra's File command runs shlex on every call).
_SECTIONS: dict[Read, tuple[str, FactBase]] = {}


def section(item: Read) -> tuple[str, FactBase]:
    """The read's command as pyinfra would run it, and the fact instance that made it."""
    built = _SECTIONS.get(item)
    if built is None:
        fact = item.fact()
        built = _SECTIONS[item] = (_section_command(item, fact), fact)
    return built


def run_probe(reads: list[Read], **connection) -> dict[Read, Any]:
    """Run `reads` on the current host in one remote command; their values by read.

    `connection`: pyinfra's connection arguments for it (``_sudo=False`` for reads any user
    may do).
    """
    commands = []
    kept = []
    for item in reads:
        try:
            command, fact = section(item)
        except Exception:  # noqa: BLE001 - a bad argument raises where the fact is asked
            continue
        commands.append(command)
        kept.append((item, fact))
    if not kept:
        return {}
    marker = secrets.token_hex(16)
    sections = current_host.get_fact(HostProbe, commands=Commands(commands), marker=marker, **connection)
    return values_of(kept, sections or [])


# --- serving the read ---------------------------------------------------------------

def _changes(state, host) -> int:
    """How many operations have run commands on `host` so far (none before pyinfra executes:
    planning runs facts' commands only)."""
    if not state.is_executing:
        return 0
    return sum(1 for op in state.ops.get(host, {}).values() if op.operation_meta.executed)


class ReadAhead:
    """A host's read-ahead facts, served by `host.get_fact` while no operation changed the host."""

    def __init__(self, host, state):
        self.host = host
        self.state = state
        self.values: dict[tuple, Any] = {}
        self.changes = _changes(state, host)
        self.unwrapped = type(host).get_fact.__get__(host)

    def add(self, values: dict[Read, Any]) -> None:
        if _changes(self.state, self.host) != self.changes:
            self.values.clear()
            self.changes = _changes(self.state, self.host)
        for item, value in values.items():
            self.values[(item.fact, item.arguments)] = value

    def lookup(self, fact, args, kwargs):
        """The read-ahead value, or `_NOT_READ`."""
        if args or any(name.startswith("_") for name in kwargs):
            return _NOT_READ
        if _changes(self.state, self.host) != self.changes:
            self.values.clear()  # the host changed: from now on, facts come from the host
            return _NOT_READ
        normalized = _normalized(fact, kwargs)
        key = (fact, normalized)
        if normalized is None or key not in self.values:
            return _NOT_READ
        return own_copy(self.values[key])  # the caller's to change, as a fact read from the host

    def __call__(self, fact, *args, **kwargs):
        value = self.lookup(fact, args, kwargs)
        if value is _NOT_READ:
            return self.unwrapped(fact, *args, **kwargs)
        return value


_NOT_READ = object()

READERS: list[Callable[[], Iterable[Read]]] = []


def reader(function: Callable[[], Iterable[Read]]):
    """Register a deploy's reader: what its operations read on a host that needs no change.

    Called with the host in context after `deploy.common.supported_host` has read the
    basics (release, login user's home), so it can use them.
    """
    READERS.append(function)
    return function


# What each step installs, declared once beside the step (`@installs`): the step installs exactly
# that list, and the class apt cache (deploy/apt_cache.py planned_packages) fills itself from it.
# An installer is `(settings, codename, python_sdist) -> apt package names`: `settings` is the
# host's roslab.host_settings.HostSettings (Any here: roslab.profiles, which HostSettings holds,
# builds on this module), `python_sdist` this run's note that the host's wheelhouse holds an sdist.
Installer = Callable[[Any, "str | None", bool], list[str]]
INSTALLERS: list[Installer] = []
_Installer = TypeVar("_Installer", bound=Installer)


def installs(function: _Installer) -> _Installer:
    """Register what a step installs: `function(settings, codename, python_sdist)` -> apt package
    names, for a host with these typed settings on this Ubuntu codename."""
    INSTALLERS.append(function)
    return function


def declared_packages(settings: Any, codename: str | None, python_sdist: bool = False) -> list[str]:
    """Every registered step's packages for one host (its HostSettings), in registration order, each once."""
    packages: list[str] = []
    for function in INSTALLERS:
        packages += [name for name in function(settings, codename, python_sdist) if name not in packages]
    return packages


def registered_reads() -> list[Read]:
    """Every registered reader's reads, in order, each once."""
    return list(dict.fromkeys(item for function in READERS for item in function() or ()))


def read_ahead(reads: Iterable[Read], **connection) -> None:
    """Read `reads` on the current host in one command and serve them from `host.get_fact`.

    `connection`: pyinfra's connection arguments for the read (``_sudo=False`` ...).
    """
    host = ctx_host.get()
    state = ctx_state.get()
    served = host.__dict__.get("get_fact")
    if not isinstance(served, ReadAhead) or served.state is not state:
        served = ReadAhead(host, state)
        host.get_fact = served  # this Host object only; Host.get_fact stays pyinfra's
    wanted = [item for item in reads if (item.fact, item.arguments) not in served.values]
    if wanted:
        served.add(run_probe(wanted, **connection))


# --- what pyinfra's own operations read on a host that needs no change ----------------

def put_reads(dest: str) -> list[Read]:
    """`files.put(dest=...)`: the file, its directory (create_remote_dir), its SHA1."""
    return [read(File, path=dest), read(Directory, path=posixpath.dirname(dest)),
            read(Sha1File, path=dest)]


def directory_reads(path: str) -> list[Read]:
    """`files.directory(path=...)`."""
    return [read(Directory, path=path)]


def packages_reads() -> list[Read]:
    """`apt.packages(...)` and the installed side of `apt.deb`."""
    return [read(DebPackages)]


def deb_reads(src: str) -> list[Read]:
    """`apt.deb(src=...)` of a file on the host."""
    return [read(DebPackage, package=src), *packages_reads()]


def service_reads(service: str) -> list[Read]:
    """`systemd.service(service=...)` (a unit name with its suffix)."""
    return [read(SystemdStatus, services=[service]), read(SystemdEnabled, services=[service])]


def hostname_reads() -> list[Read]:
    """`server.hostname(...)`."""
    return [read(Hostname), read(Which, command="hostnamectl")]


def authorized_keys_reads(user: str, home: str) -> list[Read]:
    """`server.user_authorized_keys(user=...)` with the default ~/.ssh/authorized_keys."""
    path = f"{home}/.ssh/authorized_keys"
    return [read(Home, user=user), read(Directory, path=f"{home}/.ssh"),
            read(AuthorizedKeys, user=user, path=path), read(File, path=path)]
