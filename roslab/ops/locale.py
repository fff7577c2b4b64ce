"""Locales: one generated the way both Ubuntu and Debian honour (roslab.ops)."""

from __future__ import annotations

import re

from pyinfra import host
from pyinfra.api import QuoteString, StringCommand, operation
from pyinfra.facts.files import FileContents
from pyinfra.facts.server import Locales

from roslab.ops.files import _log_diff, _upload_text
from roslab.probe import read


LOCALE_GEN = "/etc/locale.gen"


def with_locale_enabled(lines: list[str], locale: str) -> list[str]:
    """/etc/locale.gen with `locale`'s line uncommented (or added)."""
    charset = locale.split(".", 1)[1]
    wanted = f"{locale} {charset}"
    pattern = re.compile(rf"^#?\s*{re.escape(locale)}\s+{re.escape(charset)}\s*$")
    if wanted in lines:
        return list(lines)
    for index, line in enumerate(lines):
        if pattern.match(line):
            return lines[:index] + [wanted] + lines[index + 1 :]
    return lines + [wanted]


@operation()
def locale_generated(locale: str):
    """
    Ensure a locale is generated, the way both Ubuntu and Debian honour.

    + locale: e.g. ``en_US.UTF-8``

    Debian's ``locale-gen`` ignores its arguments and reads ``/etc/locale.gen``; Ubuntu's
    takes them. So the line is enabled in ``/etc/locale.gen`` and the name passed too.
    """
    if locale in host.get_fact(Locales):
        host.noop(f"locale {locale} is already generated")
        return
    current = host.get_fact(FileContents, path=LOCALE_GEN) or []
    desired = with_locale_enabled(current, locale)
    if desired != current:
        _log_diff(LOCALE_GEN, current, desired)
        yield from _upload_text(LOCALE_GEN, desired, user="root", group="root", mode="644")
    yield StringCommand("locale-gen", QuoteString(locale))


def locale_generated_reads() -> list:
    """What `locale_generated` reads on a host that has the locale (roslab.probe)."""
    return [read(Locales)]
