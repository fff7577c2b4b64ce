"""ROS 2 distros and the Ubuntu releases they ship packages for (REP 2000).

The single source of the mapping: the roster validator uses it before any host
is touched, and the deploys use it again on the host's real facts.
"""

from __future__ import annotations

# Ubuntu version -> codename, for the releases roslab knows.
UBUNTU_CODENAMES = {
    "22.04": "jammy",
    "24.04": "noble",
    "26.04": "resolute",
}

# ROS 2 distro -> Ubuntu codenames with binary packages (amd64 and arm64).
DISTRO_RELEASES = {
    "humble": {"jammy"},
    "jazzy": {"noble"},
    "kilted": {"noble"},
    "lyrical": {"resolute"},
}

# Ubuntu codename -> the LTS distro a classroom gets by default.
DEFAULT_DISTRO = {
    "jammy": "humble",
    "noble": "jazzy",
    "resolute": "lyrical",
}

# Distros that have the Jazzy-era discovery variables
# (ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS); Humble has only ROS_LOCALHOST_ONLY.
DISCOVERY_RANGE_DISTROS = {"jazzy", "kilted", "lyrical"}

VARIANTS = ("desktop", "ros-base", "ros-core", "desktop-full")


class DistroError(ValueError):
    """A distro/release combination that has no packages, or an unknown name."""


def codename_for(release: str) -> str:
    """Return the codename of an Ubuntu version ("24.04" -> "noble")."""
    try:
        return UBUNTU_CODENAMES[str(release)]
    except KeyError:
        known = ", ".join(sorted(UBUNTU_CODENAMES))
        raise DistroError(f"Ubuntu {release} is not supported (supported: {known})") from None


def default_distro(codename: str) -> str:
    """Return the distro a host on this Ubuntu codename gets unless overridden."""
    try:
        return DEFAULT_DISTRO[codename]
    except KeyError:
        known = ", ".join(sorted(DEFAULT_DISTRO))
        raise DistroError(
            f"Ubuntu {codename!r} has no ROS 2 packages roslab knows of (supported: {known})"
        ) from None


def check_distro(distro: str, codename: str) -> None:
    """Raise DistroError unless `distro` has packages for Ubuntu `codename`."""
    if distro not in DISTRO_RELEASES:
        known = ", ".join(sorted(DISTRO_RELEASES))
        raise DistroError(f"ROS 2 distro {distro!r} does not exist (known: {known})")
    if codename not in DISTRO_RELEASES[distro]:
        has = ", ".join(sorted(DISTRO_RELEASES[distro]))
        raise DistroError(
            f"ROS 2 {distro} has no packages for Ubuntu {codename} (it has them for: {has})"
        )


def select_distro(codename: str, override: str | None = None) -> str:
    """The distro for a host: the override if given and valid, else the release default."""
    distro = override or default_distro(codename)
    check_distro(distro, codename)
    return distro
