"""The one renderer of roslab's templates (`templates/`, shipped as `roslab/templates`).

    render("roslab-nodes.service.j2", role="robot", ...) -> the file's text

Every template renders the same way: an undefined variable is an error (never an empty
string in a unit file), block tags leave no blank lines, and the file's last newline is
kept. Templates do no quoting of their own: callers pass values already written for
their destination by `roslab.quoting` (shell words, systemd words, ...).

A deploy uploads the text with `files.put(src=StringIO(render(...)), ...)`.
"""

from __future__ import annotations

from pathlib import Path

import jinja2

# A symlink to the checkout's top-level templates/ (package data when installed).
TEMPLATES = Path(__file__).parent / "templates"

ENVIRONMENT = jinja2.Environment(
    loader=jinja2.FileSystemLoader(str(TEMPLATES)),
    undefined=jinja2.StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
    keep_trailing_newline=True,
    autoescape=False,
)


def render(name: str, **variables) -> str:
    """The text of template `name` (a file in templates/) with `variables`."""
    return ENVIRONMENT.get_template(name).render(**variables)


# HTML pages (`roslab status`): the same templates, every value escaped for HTML.
HTML_ENVIRONMENT = ENVIRONMENT.overlay(autoescape=True)


def render_html(name: str, **variables) -> str:
    """The text of HTML template `name` with `variables`, each escaped (jinja2 autoescape)."""
    return HTML_ENVIRONMENT.get_template(name).render(**variables)
