"""`roslab check` stays cheap per host (issue 41): each distinct controller folder is resolved once.

The results are those of resolving per host: the clash messages' tests are test_roster_hostile's;
here a class of 100 hosts shares its folders, and a clash is still named once, at its first host.
"""

from __future__ import annotations

import os

import pytest

from roslab.roster import RosterError, load_roster


def roster(tmp_path, classroom: str = "") -> str:
    hosts = "\n".join(f"      t1-h{host}: {{role: {'main' if host == 0 else 'robot'}, address: 10.0.1.{host + 1}}}"
                      for host in range(100))
    path = tmp_path / "lab.yaml"
    path.write_text(f"classroom:\n  name: big\n{classroom}teams:\n  t1:\n    hosts:\n{hosts}\n")
    return path


def test_each_distinct_folder_is_resolved_once_for_the_whole_class(tmp_path, monkeypatch):
    calls = []
    real = os.path.realpath

    def counted(path, *args, **kwargs):
        calls.append(path)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os.path, "realpath", counted)
    assert len(load_roster(roster(tmp_path)).hosts) == 100
    folders = [path for path in calls if "cache" in str(path) or "wheel" in str(path)]
    assert folders and len(folders) == len(set(folders)), sorted(folders)


def test_a_clash_shared_by_every_host_is_named_once(tmp_path):
    shared = tmp_path / "caches"
    with pytest.raises(RosterError) as raised:
        load_roster(roster(tmp_path, f"  rosdep_cache_dir: {shared}\n  sources_cache_dir: {shared}/src\n"))
    text = str(raised.value)
    assert text.count("share a folder") == 1, text
    assert "t1-h0" in text and "t1-h1'" not in text, text
