"""A UTF-8 locale generated and set system-wide (ROS 2 tools expect UTF-8)."""

from __future__ import annotations

import re
from pathlib import Path

from pyinfra import host
from pyinfra.api import DeployError, deploy
from pyinfra.operations import apt, files

from deploy.common import setting, should_run, where
from roslab.operations import locale_generated

TEMPLATES = Path(__file__).resolve().parent.parent / "templates"

DEFAULTS = {
    # Generate the locale and set it system-wide.
    "locale_enabled": True,
    # The system-wide locale (LANG); must be a UTF-8 locale.
    "locale": "en_US.UTF-8",
}

UTF8_LOCALE = re.compile(r"^[a-z]{2,3}(_[A-Z]{2})?(@[a-z]+)?\.UTF-8$")


def checked_locale(value) -> str:
    if not isinstance(value, str) or not UTF8_LOCALE.match(value):
        raise DeployError(
            f"{where()}: locale {value!r} is not a UTF-8 locale name like 'en_US.UTF-8'"
        )
    return value


@deploy("A UTF-8 locale is generated and set system-wide", data_defaults=DEFAULTS)
def system_locale():
    """Generate the locale and make it the system default in /etc/default/locale.

    Reads host.data: locale_enabled, locale, apt_lock_timeout.
    """
    if not should_run("locale_enabled"):
        return
    locale = checked_locale(host.data.locale)

    apt.packages(
        name="Ensure the locales package is installed",
        packages=["locales"],
        extra_install_args=f"-o DPkg::Lock::Timeout={setting('apt_lock_timeout')}",
    )
    locale_generated(name=f"Ensure the locale {locale} is generated", locale=locale)
    files.template(
        name=f"Ensure {locale} is the system-wide locale",
        src=str(TEMPLATES / "default-locale.j2"),
        dest="/etc/default/locale",
        mode="644",
        locale=locale,
    )
