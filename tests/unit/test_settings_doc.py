"""Every setting is documented once, in the schema, and the docs' generated tables repeat it
(docs/roster-and-settings.md: settings and releases; docs/robots.md: profiles)."""

from roslab import settings, settings_doc


def test_every_setting_has_a_doc_line_and_its_allowed_values():
    undocumented = [s.key for s in settings.SCHEMA if not s.doc]
    assert undocumented == [], f"settings without a doc line: {undocumented}"
    unchecked = [s.key for s in settings.SCHEMA if s.kind is not bool and not s.allowed_text()]
    assert unchecked == [], f"settings without a format check or allowed values: {unchecked}"


def test_every_default_passes_its_own_check():
    bad = {s.key: settings.check_value(s, s.default) for s in settings.SCHEMA
           if not s.required and s.key not in ("ssh_key", "ros_apt_mirror_key_file")}
    assert {key: problem for key, problem in bad.items() if problem} == {}


def test_settings_table_is_up_to_date():
    expected = settings_doc.markdown_table()
    page = settings_doc.SETTINGS_PAGE.read_text()
    assert settings_doc.page_with_settings(page, expected) == page, (
        "docs/roster-and-settings.md's settings table is stale: run `python -m roslab.settings_doc --write`"
    )


def test_releases_table_is_up_to_date_and_has_a_row_per_release_record():
    from roslab.ros.distro import PLATFORMS

    expected = settings_doc.releases_table()
    page = settings_doc.SETTINGS_PAGE.read_text()
    assert settings_doc.page_with_releases(page, expected) == page, (
        "docs/roster-and-settings.md's releases table is stale: run `python -m roslab.settings_doc --write`"
    )
    for platform in PLATFORMS:
        assert f"| {platform.release} {platform.codename} | {platform.distro.capitalize()} |" in expected


def test_profiles_table_is_up_to_date_and_has_a_row_per_profile_file():
    from roslab.profiles.library import builtin_files

    expected = settings_doc.profiles_table()
    page = settings_doc.PROFILES_PAGE.read_text()
    assert settings_doc.page_with_profiles(page, expected) == page, (
        "docs/robots.md's profiles table is stale: run `python -m roslab.settings_doc --write`"
    )
    for path in builtin_files():
        assert f"| `{path.stem}` |" in expected


def test_boards_table_is_up_to_date_and_has_a_row_per_board_record():
    from roslab.boards import BOARDS

    expected = settings_doc.boards_table()
    page = settings_doc.PROFILES_PAGE.read_text()
    assert settings_doc.page_with_boards(page, expected) == page, (
        "docs/robots.md's boards table is stale: run `python -m roslab.settings_doc --write`"
    )
    for board in BOARDS:
        assert f"| `{board.name}` | {board.title} |" in expected


def test_each_generated_table_has_one_home_in_the_docs():
    """Each table's markers are in its own page once and in no other markdown file of the repo (the
    README links to them), so `--write` and the drift tests above see every copy there is."""
    homes = {settings_doc.BEGIN_MARKER: settings_doc.SETTINGS_PAGE,
             settings_doc.RELEASES_BEGIN_MARKER: settings_doc.SETTINGS_PAGE,
             settings_doc.PROFILES_BEGIN_MARKER: settings_doc.PROFILES_PAGE,
             settings_doc.BOARDS_BEGIN_MARKER: settings_doc.PROFILES_PAGE}
    pages = [settings_doc.REPO / "README.md", *sorted((settings_doc.REPO / "docs").glob("*.md"))]
    for marker, home in homes.items():
        holding = {page: page.read_text().count(marker) for page in pages if marker in page.read_text()}
        assert holding == {home: 1}, marker


def test_settings_table_lists_every_setting_with_type_and_allowed_values():
    table = settings_doc.markdown_table()
    for s in settings.SCHEMA:
        row = next(line for line in table.splitlines() if line.startswith(f"| `{s.key}` |"))
        assert s.type_text() in row


def test_generated_host_settings_module_is_up_to_date():
    """roslab/host_fields.py (the typed HostSettings the deploys read) is generated from the schema."""
    assert settings_doc.HOST_FIELDS.read_text() == settings_doc.host_fields_module(), (
        "roslab/host_fields.py is stale: run `python -m roslab.settings_doc --write`"
    )


def test_host_settings_has_a_typed_field_per_host_setting_and_host_key():
    from dataclasses import fields

    from roslab.host_fields import HostSettings

    declared = {item.name: item.type for item in fields(HostSettings)}
    for s in settings.HOST_SETTINGS:
        assert declared.pop(s.key) == settings.annotation(s), s.key
    for key in settings.HOST_KEYS:
        assert declared.pop(key.key) == f"{key.annotation} | None", key.key
    assert declared == {}  # no embedded mapping: the fields are the whole of a host's settings
    assert settings.annotation(settings.SETTINGS["network_address"]) == "str | None"
    assert settings.annotation(settings.SETTINGS["apt_extra_suites"]) == "list[str]"
    assert settings.annotation(settings.SETTINGS["apt_cache_upstream_ports"]) == "list[int]"
    assert settings.annotation(settings.SETTINGS["ssh_port"]) == "int | None"  # pyinfra's default when absent
