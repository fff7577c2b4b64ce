"""The README and the docs pages link to each other: every relative link leads to a file of the
repository, and a link to a heading (`page.md#anchor`, `#anchor`) to a heading that page has
(GitHub's anchors: lower case, punctuation dropped, spaces as `-`). No page names a path of one
machine (a home folder or a checkout's place)."""

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def anchors(page: Path) -> set[str]:
    """The anchors GitHub gives a page's headings (a repeated one gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    found = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        if not line.startswith("#"):
            continue
        slug = re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def links(page: Path) -> list[str]:
    text = FENCE.sub("", page.read_text())
    return [a or b for a, b in LINK.findall(text)]


def test_the_pages_are_found():
    assert {page.name for page in PAGES} >= {"README.md", "architecture.md", "sandbox.md", "roster-and-settings.md"}


def broken_links(page: Path, root: Path = REPO) -> list[str]:
    broken = []
    for target in links(page):
        if re.match(r"[a-z]+:", target):
            continue  # https:, mailto:
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists() or root not in (dest, *dest.parents):
            broken.append(f"{target}: no such file in the repository")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: {dest.name} has no heading with that anchor")
    return broken


@pytest.mark.parametrize("page", PAGES, ids=lambda page: str(page.relative_to(REPO)))
def test_every_relative_link_leads_to_a_file_and_heading(page):
    assert broken_links(page) == []


@pytest.mark.parametrize("page", PAGES, ids=lambda page: str(page.relative_to(REPO)))
def test_no_page_names_a_path_of_one_machine(page):
    assert re.findall(r"(?:/work/|/root/|/home/\w+/)\S*", page.read_text()) == []


def test_the_checker_finds_a_broken_link_and_anchor(tmp_path):
    (tmp_path / "a.md").write_text("# Top: the `x`\n\n[ok](#top-the-x) [no](#nope) [gone](b.md) [up](../c.md)\n"
                                   "[page](d.md#top-the-x) ![img](i.png) [web](https://example.org/x)\n")
    (tmp_path / "d.md").write_text("# Other\n")
    (tmp_path / "i.png").write_bytes(b"")
    page = tmp_path / "a.md"
    assert anchors(page) == {"top-the-x"}
    assert broken_links(page, root=tmp_path) == [
        "#nope: a.md has no heading with that anchor", "b.md: no such file in the repository",
        "../c.md: no such file in the repository", "d.md#top-the-x: d.md has no heading with that anchor"]
