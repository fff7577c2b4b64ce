"""Reading roster and secrets files: strict YAML, bounded, never a traceback.

PyYAML alone keeps the last of two equal keys without a word, forgets line numbers,
expands aliases without limit (a few lines of "billion laughs" hang the loader) and
recurses without limit on nesting. This loader records duplicate keys and lines, caps
the document's expanded size, and turns every failure into one problem in the report.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

from roslab.controller_files import UnreadableFile, read_regular_file

from roslab.checked.problems import Report

# Far above any classroom (a 5,000-host roster is about 100,000 nodes), far below a hang.
MAX_EXPANDED_NODES = 1_000_000
# A 5,000-host roster is about 400 KiB; parsing 1 MiB takes about half a second, so a
# bigger file (a log pasted in, a file of comments) is refused by its size before parsing.
MAX_FILE_BYTES = 1024 * 1024


class Mapping(dict):
    """A YAML mapping that remembers where it and its keys are, and repeated keys."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.line: int | None = None
        self.key_lines: dict = {}
        self.duplicates: list = []  # (key, line, line of the first)


class Ambiguous(str):
    """A plain scalar YAML 1.1 and YAML 1.2 read differently: kept as the text written.

    PyYAML reads YAML 1.1: `010` is the octal number 8, `1:30` is 90 (base 60), `yes`,
    `on` and `off` are booleans; YAML 1.2 (and most other tools) read `010` as 10 and
    `yes` as text, and `08` is no number at all in 1.1. Such a scalar is kept as the text
    the teacher wrote, with what YAML 1.1 would make of it, and the reader refuses it
    wherever the schema cannot tell which was meant (roslab.roster.reader).
    """

    yaml11: object = None

    def meaning(self) -> str:
        """What YAML 1.1 makes of the text, in words."""
        if isinstance(self.yaml11, bool):
            return f"YAML 1.1 reads {self} as {str(self.yaml11).lower()}, other YAML readers as text"
        digits = self.lstrip("+-")
        if ":" in self:
            return f"YAML 1.1 reads {self} as the base-60 number {self.yaml11}"
        if digits[:2] in ("0x", "0b", "0o"):
            return f"YAML reads {self} as a number in base {dict(x=16, b=2, o=8)[digits[1]]}"
        if "_" in self:
            return f"YAML 1.1 reads {self} as {self.yaml11}, other YAML readers as text"
        if isinstance(self.yaml11, int):
            return f"a leading zero makes YAML 1.1 read {self} as the octal number {self.yaml11}"
        return f"a leading zero makes YAML 1.1 read {self} as an octal number, which {self} is not"

    def hint(self, wanted: str = "text") -> str:
        """How to write what was meant, for a value of kind `wanted` ("number" or "text")."""
        if wanted == "number" and not isinstance(self.yaml11, bool):
            plain = self.lstrip("+").replace("_", "")
            if ":" not in plain and plain.lstrip("-").isdigit() and plain.isascii():
                return f"{self.meaning()}: write {int(plain, 10)} for the number {int(plain, 10)}"
            return f"{self.meaning()}: write the number in plain decimal digits"
        return f'{self.meaning()}: quote it, "{self}", for the text'


_AMBIGUOUS = "tag:roslab,2026:ambiguous"
# Plain scalars whose type YAML 1.1 and 1.2 disagree on (or 1.1 reads surprisingly).
_AMBIGUOUS_FORMS = (
    r"^(?:yes|Yes|YES|no|No|NO|on|On|ON|off|Off|OFF"
    r"|[-+]?0[0-9_]+"                                   # leading zero: octal in 1.1 (08: not even that)
    # hex, binary, 1.2 octal: only with the digits of their base (0ba5... is text to both)
    r"|[-+]?0(?:[xX][0-9a-fA-F_]+|[bB][01_]+|[oO][0-7_]+)"
    r"|[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?"  # sexagesimal 1:30 (and 1:30.5)
    r"|[-+]?[0-9][0-9]*_[0-9_]*(?:\.[0-9_]*)?"          # digits with underscores
    r")$")


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that keeps line numbers and records duplicate keys, and resolves plain
    scalars the way YAML 1.1 and 1.2 agree on: `true`/`false`, decimal integers without
    a leading zero, decimal floats and null; ambiguous forms become `Ambiguous` text,
    dates stay text."""


# Tags a roster may carry: none, or !!str (another way to quote). `!!int 011` would be
# octal again, `!!binary`, `!!set`, `!!timestamp` or a custom tag make values no setting takes.
_ALLOWED_TAGS = (None, "!", "tag:yaml.org,2002:str", "tag:yaml.org,2002:map", "tag:yaml.org,2002:seq")


def _refuse_explicit_tag(loader: "StrictLoader") -> None:
    event = loader.peek_event()
    tag = getattr(event, "tag", None)
    if tag not in _ALLOWED_TAGS:
        shown = tag.replace("tag:yaml.org,2002:", "!!")
        raise yaml.constructor.ConstructorError(
            None, None, f"the tag {shown} has no place in a roster: write the value plainly "
            "(quote it for text)", event.start_mark)


def _checked(compose):
    def compose_checked(self, anchor):
        _refuse_explicit_tag(self)
        return compose(self, anchor)
    return compose_checked


for _name in ("compose_scalar_node", "compose_sequence_node", "compose_mapping_node"):
    setattr(StrictLoader, _name, _checked(getattr(yaml.SafeLoader, _name)))

StrictLoader.yaml_implicit_resolvers = {}
for _tag, _regexp, _first in (
    (_AMBIGUOUS, _AMBIGUOUS_FORMS, list("yYnNoO-+0123456789")),
    ("tag:yaml.org,2002:bool", r"^(?:true|True|TRUE|false|False|FALSE)$", list("tTfF")),
    ("tag:yaml.org,2002:int", r"^[-+]?(?:0|[1-9][0-9]*)$", list("-+0123456789")),
    ("tag:yaml.org,2002:float",
     r"^(?:[-+]?[0-9]+\.[0-9]*(?:[eE][-+][0-9]+)?|[-+]?\.[0-9]+(?:[eE][-+][0-9]+)?"
     r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$", list("-+0123456789.")),
    ("tag:yaml.org,2002:null", r"^(?:~|null|Null|NULL|)$", ["~", "n", "N", ""]),
    ("tag:yaml.org,2002:merge", r"^(?:<<)$", ["<"]),
):
    StrictLoader.add_implicit_resolver(_tag, re.compile(_regexp, re.ASCII), _first)


def _construct_ambiguous(loader: StrictLoader, node: yaml.ScalarNode) -> Ambiguous:
    text = Ambiguous(node.value)
    for meaning in (yaml.SafeLoader.construct_yaml_bool, yaml.SafeLoader.construct_yaml_int,
                    yaml.SafeLoader.construct_yaml_float):
        try:
            value = meaning(loader, node)
        except (ValueError, KeyError, TypeError, IndexError):
            continue
        if meaning is not yaml.SafeLoader.construct_yaml_bool or isinstance(value, bool):
            text.yaml11 = value
            break
    return text


StrictLoader.add_constructor(_AMBIGUOUS, _construct_ambiguous)


def name_problem(key, what: str = "name") -> str | None:
    """Why a mapping key cannot be a name (`what`: a team name, a host name, a key), or None."""
    if isinstance(key, Ambiguous):
        return f"the {what} {str(key)!r} is ambiguous: {key.hint()}"
    if isinstance(key, bool):
        return f"YAML reads this {what} as {str(key).lower()}: quote it to use it as a name"
    if key is None:
        return f"YAML reads this {what} (null, ~ or nothing) as no value: quote it, or give a name"
    if isinstance(key, (int, float)):
        return f'YAML reads the {what} {key!r} as a number: quote it, "{key}", to use it as a name'
    if not isinstance(key, str):
        return f"the {what} {key!r} is not a name"
    return None


def ambiguous_inside(value) -> Ambiguous | None:
    """The first ambiguous scalar in a value (itself, a list's items, a mapping's keys and values)."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, Ambiguous):
            return item
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
    return None


def _construct_mapping(loader: StrictLoader, node: yaml.MappingNode):
    mapping = Mapping()
    mapping.line = node.start_mark.line + 1
    yield mapping
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            continue  # construct_mapping below reports it
        line = key_node.start_mark.line + 1
        if key in mapping.key_lines:
            mapping.duplicates.append((key, line, mapping.key_lines[key]))
        mapping.key_lines[key] = line  # the last one wins, as in PyYAML's value
    mapping.update(loader.construct_mapping(node, deep=True))


StrictLoader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)


if TYPE_CHECKING:
    _FastBase = yaml.CSafeLoader
else:  # PyYAML without libyaml has no CSafeLoader
    _FastBase = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class FastStrictLoader(_FastBase):
    """StrictLoader's constructors and resolvers on libyaml's parser and composer (PyYAML's
    CSafeLoader; several times faster on a 10,000-host roster). Used only for a text without
    `!` (no explicit tag, whose refusal is StrictLoader's composer's) and without characters
    PyYAML's reader refuses; on any error load_yaml reads the text again with StrictLoader,
    whose messages name the line."""

    yaml_implicit_resolvers = StrictLoader.yaml_implicit_resolvers
    yaml_constructors = StrictLoader.yaml_constructors
    yaml_multi_constructors = StrictLoader.yaml_multi_constructors


def _fast_path_applies(text: str) -> bool:
    """libyaml (when PyYAML has it) may read `text`: no tag can be written without `!`."""
    return hasattr(yaml, "CSafeLoader") and "!" not in text and not yaml.reader.Reader.NON_PRINTABLE.search(text)


class _TooLarge(Exception):
    pass


def expanded_size(root: yaml.Node, limit: int = MAX_EXPANDED_NODES) -> int:
    """How many nodes the document has once every alias is expanded (memoised: linear)."""
    sizes: dict[int, int] = {}
    # Iterative post-order walk: nesting depth cannot exhaust Python's stack here.
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        if id(node) in sizes:
            continue
        if isinstance(node, yaml.MappingNode):
            children = [child for pair in node.value for child in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        else:
            children = []
        if children_done:
            total = 1 + sum(sizes[id(child)] for child in children)
            if total > limit:
                raise _TooLarge
            sizes[id(node)] = total
            continue
        stack.append((node, True))
        stack.extend((child, False) for child in children if id(child) not in sizes)
    return sizes[id(root)]


def read_text(path: Path, report: Report, limit: int = MAX_FILE_BYTES) -> str | None:
    """A file's text as UTF-8; problems (missing, not a regular file, binary, not UTF-8,
    too big) go to `report` as one line each."""
    try:
        data = read_regular_file(path, limit)
    except UnreadableFile as exc:
        report.error(str(exc))
        return None
    if b"\0" in data:
        report.error("is a binary file, not YAML text")
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        report.error(f"is not UTF-8 text (byte 0x{data[exc.start]:02x}); save it as UTF-8", line=line)
        return None


def load_yaml(path: Path, report: Report, secret: bool = False, limit: int = MAX_FILE_BYTES):
    """Parse a YAML file strictly; problems go to `report`, the result may be None.

    `secret`: the file holds secrets, so a message names only the line, never the text
    PyYAML would quote from it.
    """
    text = read_text(path, report, limit)
    if text is None:
        return None
    if _fast_path_applies(text):
        try:
            return _parse(FastStrictLoader, text)
        except Exception:  # noqa: B902 - the pure loader below reads it again and names the problem
            pass
    try:
        return _parse(StrictLoader, text)
    except _TooLarge:
        report.error(f"expands to more than {MAX_EXPANDED_NODES:,} values through its aliases "
                     "(&anchor/*alias); refusing to load it")
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        if secret:
            report.error("not valid YAML (the parser's message is not shown: it may quote a secret)",
                         line=line)
        else:
            report.error(f"not valid YAML: {exc.problem}", line=line)
    except yaml.YAMLError:
        report.error("not valid YAML")
    except RecursionError:
        report.error("is nested too deeply to be a roster")
    return None


def _parse(loader_class, text: str):
    """The document `text` holds, through `loader_class` (errors raised as they come)."""
    loader = loader_class(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        expanded_size(node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def line_of(mapping, key=None) -> int | None:
    """The line of `key` in a loaded mapping (or of the mapping itself)."""
    if not isinstance(mapping, Mapping):
        return None
    return mapping.key_lines.get(key, mapping.line) if key is not None else mapping.line


def without(mapping: dict, key) -> Mapping:
    """A copy of a mapping without `key`, keeping its line numbers."""
    copy = Mapping((k, v) for k, v in mapping.items() if k != key)
    copy.line = getattr(mapping, "line", None)
    copy.key_lines = getattr(mapping, "key_lines", {})
    copy.duplicates = getattr(mapping, "duplicates", [])
    return copy


def nested_mappings(value):
    """Every mapping inside a setting's value (a dict or list of them)."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, Mapping):
            yield item
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
