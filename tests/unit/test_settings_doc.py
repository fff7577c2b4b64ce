"""Every setting is documented once, in its deploy's DEFAULTS, and the README repeats it."""

import deploy
from roslab import settings_doc


def test_every_setting_has_a_comment():
    undocumented = [s.key for s in settings_doc.all_settings() if not s.doc]
    assert undocumented == [], f"settings without a comment above them in DEFAULTS: {undocumented}"


def test_table_covers_every_setting_a_roster_may_use():
    documented = {s.key for s in settings_doc.all_settings()}
    assert documented == set(deploy.ALL_DEFAULTS)


def test_readme_table_is_up_to_date():
    expected = settings_doc.markdown_table(settings_doc.all_settings())
    readme = settings_doc.README.read_text()
    assert settings_doc.readme_with_table(readme, expected) == readme, (
        "README's settings table is stale: run `python -m roslab.settings_doc --write`"
    )
