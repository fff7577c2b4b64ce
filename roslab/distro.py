"""One record per Ubuntu/ROS 2 pair (REP 2000): the single source of what a release means.

Like rosdistro's index (one entry per distro with its platforms), each `Platform` holds
everything roslab needs to know about one LTS pair: the Ubuntu release and codename, the
ROS 2 distro a classroom gets on it, its Python, its Gazebo for simulation and the
ros2-apt-source pin. The roster's schema, the deploys (on the host's real facts) and the
sandbox (its emulated releases and stand-in archives) all read these records; a mapping
elsewhere is derived from them, never written by hand.

Adding the next pair is one `Platform(...)` below. A value roslab does not know (a pin
not yet published, verified or copied) is None: the roster check then says so before any
host is touched and names the setting the teacher can set instead.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Gazebo:
    """The simulator a distro's TurtleBot3 simulation runs on."""

    name: str  # "Harmonic"
    ros_package: str  # the ROS package that brings it ("ros_gz", "gazebo_ros_pkgs")
    conflicts: str = ""  # what it cannot be installed beside, in words


@dataclass(frozen=True)
class Platform:
    """One Ubuntu LTS release and the ROS 2 LTS distro it carries."""

    release: str  # "24.04"
    codename: str  # "noble"
    distro: str  # "jazzy": the distro a host on this release gets by default
    python: str  # the release's python3 ("3.12")
    gazebo: Gazebo
    # sha256 of ros2-apt-source's .deb for this codename at ROS_APT_SOURCE_VERSION; None: unknown.
    ros_apt_source_sha256: str | None
    pretty: str = ""  # what /etc/os-release says, e.g. "Ubuntu 24.04.2 LTS"
    version_text: str = ""  # os-release's VERSION, e.g. "24.04.2 LTS (Noble Numbat)"


# The pinned ros2-apt-source release every record's sha256 is of (2026-04).
ROS_APT_SOURCE_VERSION = "1.2.0"

PLATFORMS: tuple[Platform, ...] = (
    Platform(
        release="22.04", codename="jammy", distro="humble", python="3.10",
        # turtlebot3_gazebo on Humble needs Gazebo Classic 11 (end of life 2025-01).
        gazebo=Gazebo("Classic 11", "gazebo_ros_pkgs", "Gazebo Harmonic's packages (gz-*)"),
        # Copied from public install scripts that pin 1.2.0; not verified from here.
        ros_apt_source_sha256="767884cf4ed03116b9d64438930a832ed854147ae435279a7924dfdf60f94433",
        pretty="Ubuntu 22.04.5 LTS", version_text="22.04.5 LTS (Jammy Jellyfish)",
    ),
    Platform(
        release="24.04", codename="noble", distro="jazzy", python="3.12",
        gazebo=Gazebo("Harmonic", "ros_gz", "Gazebo Classic 11's packages (gazebo11, gazebo_ros_pkgs)"),
        ros_apt_source_sha256="0804d9b13db770eb87019be414cd78378835228ad5fa801fc88758596dd8f7e5",
        pretty="Ubuntu 24.04.2 LTS", version_text="24.04.2 LTS (Noble Numbat)",
    ),
    Platform(
        release="26.04", codename="resolute", distro="lyrical", python="3.14",
        gazebo=Gazebo("Jetty", "ros_gz"),
        # As the official Docker images pin ros2-apt-source_1.2.0.resolute_all.deb
        # (osrf/docker_images); 1.2.0 is the first release that supports resolute.
        ros_apt_source_sha256="a275b9b819874e745a928e83e39c429fa4d607159285c4ef3ebcf75afa732ee3",
        pretty="Ubuntu 26.04 LTS", version_text="26.04 LTS (Resolute Raccoon)",
    ),
)

# Non-LTS distros roslab accepts as an override on an LTS release (`ros_distro: kilted`).
OTHER_DISTROS: dict[str, set[str]] = {"kilted": {"noble"}}

# Distros that have the Jazzy-era discovery variables
# (ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS); Humble has only ROS_LOCALHOST_ONLY.
DISCOVERY_RANGE_DISTROS = {"jazzy", "kilted", "lyrical"}

VARIANTS = ("desktop", "ros-base", "ros-core", "desktop-full")

BY_RELEASE: dict[str, Platform] = {p.release: p for p in PLATFORMS}
BY_CODENAME: dict[str, Platform] = {p.codename: p for p in PLATFORMS}

# Derived views (read-only by convention), for the callers that want a plain mapping.
UBUNTU_CODENAMES = {p.release: p.codename for p in PLATFORMS}
DEFAULT_DISTRO = {p.codename: p.distro for p in PLATFORMS}
DISTRO_RELEASES: dict[str, set[str]] = {p.distro: {p.codename} for p in PLATFORMS}
for _name, _codenames in OTHER_DISTROS.items():
    DISTRO_RELEASES.setdefault(_name, set()).update(_codenames)


class DistroError(ValueError):
    """A distro/release combination that has no packages, or an unknown name."""


def platform_for(release: str) -> Platform | None:
    """The record of an Ubuntu version ("24.04"), or None."""
    return BY_RELEASE.get(str(release))


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


def ros_apt_source_pins() -> dict[str, str]:
    """codename -> sha256 of ros2-apt-source's .deb, for the codenames whose pin is known."""
    return {p.codename: p.ros_apt_source_sha256 for p in PLATFORMS if p.ros_apt_source_sha256}
