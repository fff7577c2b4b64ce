"""The built-in profiles' parse, kept per content on the controller (roslab.profiles.parsed_cache):
parsed once, parsed again when a file or roslab changes, never read from a file another user
could have written, and never a reason to fail."""

from __future__ import annotations

import os
import stat

import pytest

from roslab.profiles import library, parsed_cache


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    folder = tmp_path / "profiles"
    folder.mkdir()
    (folder / "demo.yaml").write_text("profile: demo\n")
    parses = []

    def parse():
        parses.append(1)
        return {"parsed": (folder / "demo.yaml").read_text(), "count": len(parses)}

    return folder, parses, parse


def test_the_parse_is_kept_and_read_back_while_nothing_changed(cache):
    folder, parses, parse = cache
    assert parsed_cache.cached(folder, parse) == {"parsed": "profile: demo\n", "count": 1}
    assert parsed_cache.cached(folder, parse) == {"parsed": "profile: demo\n", "count": 1}
    assert len(parses) == 1
    entries = list(parsed_cache.cache_folder().glob("*.pickle"))
    assert len(entries) == 1 and stat.S_IMODE(entries[0].stat().st_mode) == 0o600
    assert stat.S_IMODE(parsed_cache.cache_folder().stat().st_mode) == 0o700


def test_a_changed_profile_file_or_a_new_one_is_parsed_again(cache):
    folder, parses, parse = cache
    parsed_cache.cached(folder, parse)
    (folder / "demo.yaml").write_text("profile: demo\nrobot: {}\n")
    assert parsed_cache.cached(folder, parse)["parsed"] == "profile: demo\nrobot: {}\n"
    (folder / "other.yaml").write_text("profile: other\n")
    parsed_cache.cached(folder, parse)
    assert len(parses) == 3


def test_an_entry_others_could_have_written_is_never_loaded(cache):
    folder, parses, parse = cache
    parsed_cache.cached(folder, parse)
    (entry,) = parsed_cache.cache_folder().glob("*.pickle")
    os.chmod(entry, 0o666)  # writable by anyone: a pickle from it could run anyone's code
    assert parsed_cache.cached(folder, parse)["count"] == 2
    os.chmod(parsed_cache.cache_folder(), 0o777)
    assert parsed_cache.cached(folder, parse)["count"] == 3  # the folder is re-closed when written


def test_a_corrupt_entry_or_an_unwritable_cache_only_means_parsing(cache, monkeypatch, tmp_path):
    folder, parses, parse = cache
    parsed_cache.cached(folder, parse)
    (entry,) = parsed_cache.cache_folder().glob("*.pickle")
    entry.write_bytes(b"not a pickle")
    assert parsed_cache.cached(folder, parse)["count"] == 2
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))  # a file where the folder would be
    assert parsed_cache.cached(folder, parse)["count"] == 3


def test_roslabs_own_profiles_from_the_cache_are_the_parsed_ones(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    parsed = library._parse_builtin()
    library._builtin.cache_clear()
    try:
        first, second = library._builtin(), None
        library._builtin.cache_clear()
        second = library._builtin()
        assert first == parsed and second == parsed and second is not first
        assert len(list(parsed_cache.cache_folder().glob("*.pickle"))) == 1
    finally:
        library._builtin.cache_clear()
