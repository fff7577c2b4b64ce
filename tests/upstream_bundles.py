"""Where tests find the robots' real repositories: git bundles in $ROSLAB_SANDBOX_SOURCES, else
../shared/sources beside the checkout (where .ci/run finds them too). A test that needs one skips,
saying so, where it is absent."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def folder() -> Path:
    given = os.environ.get("ROSLAB_SANDBOX_SOURCES", "").strip()
    return Path(given) if given else REPO.parent / "shared" / "sources"


def bundle(name: str) -> Path | None:
    """`<name>.bundle` (a repository's name: "osr-rover-code"), or None where it is absent."""
    path = folder() / f"{name}.bundle"
    return path if path.is_file() else None


def all_present(*names: str) -> Path | None:
    """The bundles' folder when it holds every one of `names`, else None."""
    return folder() if all(bundle(name) for name in names) else None
