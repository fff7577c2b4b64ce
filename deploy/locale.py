"""A UTF-8 locale generated and set system-wide (ROS 2 tools expect UTF-8)."""

from __future__ import annotations

from io import StringIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.operations import apt, files

from deploy.common import should_run
from roslab import probe, settings
from roslab.ops.apt import apt_install_options
from roslab.ops.locale import locale_generated, locale_generated_reads
from roslab.quoting import shell_word
from roslab.templating import render
from roslab.host_settings import HostSettings, host_settings

DEFAULTS = settings.defaults("locale")

DEFAULT_LOCALE = "/etc/default/locale"


@probe.installs
def locale_packages(settings: HostSettings, codename: str | None, python_sdist: bool = False) -> list[str]:
    """What this step installs (roslab.probe.installs): the locales package."""
    return ["locales"] if settings.locale_enabled else []


@deploy("A UTF-8 locale is generated and set system-wide", data_defaults=DEFAULTS)
def system_locale():
    """Generate the locale and make it the system default in /etc/default/locale.

    Reads host_settings(host): locale_enabled, locale, apt_lock_timeout.
    (`locale` is a UTF-8 locale name: roslab.formats.utf8_locale checked it.)
    """
    typed = host_settings(host)
    if not should_run("locale_enabled"):
        return
    locale = typed.locale

    apt.packages(
        name="Ensure the locales package is installed",
        packages=locale_packages(typed, None),
        extra_install_args=apt_install_options(typed.apt_lock_timeout),
    )
    locale_generated(name=f"Ensure the locale {locale} is generated", locale=locale)
    files.put(
        name=f"Ensure {locale} is the system-wide locale",
        # /etc/default/locale is read by pam_env and sourced by shells.
        src=StringIO(render("default-locale.j2", locale=shell_word(locale))),
        dest=DEFAULT_LOCALE,
        mode="644",
    )


@probe.reader
def locale_reads() -> list:
    """What system_locale's operations read on a host that needs no change."""
    if not should_run("locale_enabled"):
        return []
    return [*probe.packages_reads(), *locale_generated_reads(), *probe.put_reads(DEFAULT_LOCALE)]
