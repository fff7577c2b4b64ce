"""Reading roster and secrets files: strict YAML, bounded, never a traceback.

PyYAML alone keeps the last of two equal keys without a word, forgets line numbers,
expands aliases without limit (a few lines of "billion laughs" hang the loader) and
recurses without limit on nesting. This loader records duplicate keys and lines, caps
the document's expanded size, and turns every failure into one problem in the report.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from roslab.roster.problems import Report

# Far above any classroom (a 5,000-host roster is about 100,000 nodes), far below a hang.
MAX_EXPANDED_NODES = 1_000_000
MAX_FILE_BYTES = 32 * 1024 * 1024


class Mapping(dict):
    """A YAML mapping that remembers where it and its keys are, and repeated keys."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.line: int | None = None
        self.key_lines: dict = {}
        self.duplicates: list = []  # (key, line, line of the first)


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that keeps line numbers and records duplicate keys."""


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


def read_text(path: Path, report: Report) -> str | None:
    """A file's text as UTF-8; problems (missing, binary, not UTF-8, too big) go to `report`."""
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            report.error(f"the file is larger than {MAX_FILE_BYTES // (1024 * 1024)} MiB")
            return None
        data = path.read_bytes()
    except OSError as exc:
        report.error(f"cannot read the file: {exc.strerror or exc}")
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


def load_yaml(path: Path, report: Report, secret: bool = False):
    """Parse a YAML file strictly; problems go to `report`, the result may be None.

    `secret`: the file holds secrets, so a message names only the line, never the text
    PyYAML would quote from it.
    """
    text = read_text(path, report)
    if text is None:
        return None
    loader = StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        expanded_size(node)
        return loader.construct_document(node)
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
    finally:
        loader.dispose()
    return None


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
