"""roslab.checked.loading: libyaml's composer (FastStrictLoader) reads what StrictLoader reads, the same.

load_yaml takes libyaml for a text without `!` and falls back to the pure loader on any error, so
every message still names its line. Each case below is loaded both ways and compared: values,
types (Ambiguous and what YAML 1.1 reads), key lines, duplicates; and load_yaml's reports.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from roslab.checked import loading
from roslab.checked.problems import Report

REPO = Path(__file__).resolve().parents[2]

TEXTS = {
    "roster": (REPO / "tests/unit/rosters/two_teams.yaml").read_text(),
    "ambiguous": "a: 010\nb: yes\nc: 1:30\nd: 0x1F\ne: 1_000\nf: 08\ng: true\nh: ~\ni: 2026-01-01\nj: .5\n",
    "duplicates": "teams:\n  t1: {a: 1}\n  t1: {a: 2}\nx: 1\nx: 2\n",
    "aliases": "base: &b {role: robot, n: [1, 2]}\nteams:\n  t1: {h1: *b, h2: *b}\n  <<: *b\n",
    "flow and block": "- {a: [1, 2.5, -3], 'b c': \"d\\te\"}\n- ? complex\n  : value\n- |\n  literal\n  text\n",
    "unicode": "name: \"Ünïcödé ✓\"\nssid: 'A #1: {x}'\n",
    "empty": "",
    "comments only": "# nothing here\n",
    "crlf": "a: 1\r\nb:\r\n  c: 2\r\n",
    "byte order mark": "\ufeffa: 1\nb: 2\n",
    "outside the BMP": "name: \"robot \U0001f916\"\nx: 1\n",
    "folded plain": "a: this is\n  folded\nb: 2\n",
    "keys YAML reads as values": "~: 1\n1.5: a\n010: b\n",
}

BAD = {
    "unclosed": "teams: [a, b\n",
    "tab indent": "a:\n\tb: 1\n",
    "two documents": "a: 1\n---\nb: 2\n",
    "deep flow": "[" * 1200 + "]" * 1200,  # libyaml stops at 1,000 levels
    "billion laughs": "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 10)}]\n" for i in range(6)),
    "tag": "a: !!int 010\n",
    "python tag": "a: !!python/object:os.system x\n",
    "control character": "a: \x07\n",
    "unhashable key": "? [a, b]\n: 1\n",
}


def lines(value):
    """Every mapping's own line, key lines and duplicates, in document order."""
    found = []
    for mapping in loading.nested_mappings(value):
        found.append((mapping.line, sorted(mapping.key_lines.items(), key=repr), mapping.duplicates))
    return found


def typed(value):
    """The value with each scalar's type (and an Ambiguous's YAML 1.1 reading) beside it."""
    if isinstance(value, dict):
        return {typed(key): typed(item) for key, item in value.items()}
    if isinstance(value, list):
        return [typed(item) for item in value]
    return (type(value).__name__, value, getattr(value, "yaml11", None))


@pytest.mark.parametrize("name", list(TEXTS))
def test_libyaml_reads_what_the_pure_loader_reads(name):
    text = TEXTS[name]
    assert loading._fast_path_applies(text)
    fast, pure = loading._parse(loading.FastStrictLoader, text), loading._parse(loading.StrictLoader, text)
    assert typed(fast) == typed(pure)
    assert lines(fast) == lines(pure)


@pytest.mark.parametrize("name", list(TEXTS) + list(BAD))
def test_load_yaml_reports_what_the_pure_loader_alone_reports(name, tmp_path, monkeypatch):
    path = tmp_path / "lab.yaml"
    path.write_text(TEXTS[name] if name in TEXTS else BAD[name])
    fast_report, pure_report = Report(path), Report(path)
    fast = loading.load_yaml(path, fast_report)
    monkeypatch.setattr(loading, "_fast_path_applies", lambda text: False)
    pure = loading.load_yaml(path, pure_report)
    assert typed(fast) == typed(pure)
    assert [str(problem) for problem in fast_report.errors] == [str(problem) for problem in pure_report.errors]
    assert bool(pure_report.errors) == (name in BAD)


def test_a_text_with_a_tag_or_a_refused_character_never_takes_libyaml():
    assert not loading._fast_path_applies(BAD["tag"])
    assert not loading._fast_path_applies("password: 'x!y'\n")  # a `!` anywhere: the pure loader
    assert not loading._fast_path_applies(BAD["control character"])
    assert loading._fast_path_applies(TEXTS["roster"])
