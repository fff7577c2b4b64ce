"""One record per Ubuntu/ROS 2 pair (REP 2000): the single source of what a release means.

Like rosdistro's index (one entry per distro with its platforms), each `Platform` holds
everything roslab needs to know about one LTS pair: the Ubuntu release and codename, the
ROS 2 distro a classroom gets on it, its Python, its Gazebo for simulation and the
ros2-apt-source pin. The roster's schema, the deploys (on the host's real facts) and the
sandbox (its emulated releases and stand-in archives) all read these records; a mapping
elsewhere is derived from them, never written by hand.

Adding the next pair is one `Platform(...)` below, its `RosDistro` inside it (a non-LTS
distro that is no release's default goes in OTHER_DISTROS). A value roslab does not know (a pin
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
    # The Debian package the simulator itself comes as, and those it cannot be installed beside
    # (the sandbox's stand-ins conflict the same way: turtlebot3_simulations#241).
    debian_package: str = ""
    conflicts_with: tuple[str, ...] = ()


@dataclass(frozen=True)
class RosDistro:
    """One ROS 2 distro: where its packages are and what its middleware reads.

    Every consumer reads these fields; none keeps a list of distro names of its own."""

    name: str  # "jazzy"
    # Iron and later: ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_STATIC_PEERS (REP 2000, the
    # "Improved Dynamic Discovery" of Iron); Humble has only ROS_LOCALHOST_ONLY.
    discovery_range: bool
    # The Fast DDS release it ships, as its rosdistro distribution.yaml pins fastdds/fastrtps.
    fastdds: tuple[int, int]
    lts: bool = True
    # The Ubuntu releases it has packages for besides the one whose default it is (a non-LTS
    # distro's: it is no release's default).
    codenames: tuple[str, ...] = ()

    @property
    def fastdds_profiles_variable(self) -> str:
        """Fast DDS 3 reads only FASTDDS_DEFAULT_PROFILES_FILE; 2.x only FASTRTPS_DEFAULT_PROFILES_FILE."""
        return "FASTDDS_DEFAULT_PROFILES_FILE" if self.fastdds >= (3, 0) else "FASTRTPS_DEFAULT_PROFILES_FILE"

    @property
    def fastdds_super_client_variable(self) -> bool:
        """Whether its Fast DDS reads ROS_SUPER_CLIENT (2.6 does not: it needs an XML profile)."""
        return self.fastdds > (2, 6)


@dataclass(frozen=True)
class Platform:
    """One Ubuntu LTS release and the ROS 2 LTS distro it carries."""

    release: str  # "24.04"
    codename: str  # "noble"
    ros: RosDistro  # the distro a host on this release gets by default
    python: str  # the release's python3 ("3.12")
    gazebo: Gazebo
    # sha256 of ros2-apt-source's .deb for this codename at ROS_APT_SOURCE_VERSION; None: unknown.
    ros_apt_source_sha256: str | None
    pretty: str = ""  # what /etc/os-release says, e.g. "Ubuntu 24.04.2 LTS"
    version_text: str = ""  # os-release's VERSION, e.g. "24.04.2 LTS (Noble Numbat)"

    @property
    def distro(self) -> str:
        """The default distro's name ("jazzy")."""
        return self.ros.name


# The pinned ros2-apt-source release every record's sha256 is of (2026-04).
ROS_APT_SOURCE_VERSION = "1.2.0"

PLATFORMS: list[Platform] = [
    Platform(
        release="22.04", codename="jammy", python="3.10",
        ros=RosDistro("humble", discovery_range=False, fastdds=(2, 6)),
        # turtlebot3_gazebo on Humble needs Gazebo Classic 11 (end of life 2025-01).
        gazebo=Gazebo("Classic 11", "gazebo_ros_pkgs", "Gazebo Harmonic's packages (gz-*)",
                      debian_package="gazebo11", conflicts_with=("gz-harmonic",)),
        # Copied from public install scripts that pin 1.2.0; not verified from here.
        ros_apt_source_sha256="767884cf4ed03116b9d64438930a832ed854147ae435279a7924dfdf60f94433",
        pretty="Ubuntu 22.04.5 LTS", version_text="22.04.5 LTS (Jammy Jellyfish)",
    ),
    Platform(
        release="24.04", codename="noble", python="3.12",
        ros=RosDistro("jazzy", discovery_range=True, fastdds=(2, 14)),
        gazebo=Gazebo("Harmonic", "ros_gz", "Gazebo Classic 11's packages (gazebo11, gazebo_ros_pkgs)",
                      debian_package="gz-harmonic", conflicts_with=("gazebo11",)),
        ros_apt_source_sha256="0804d9b13db770eb87019be414cd78378835228ad5fa801fc88758596dd8f7e5",
        pretty="Ubuntu 24.04.2 LTS", version_text="24.04.2 LTS (Noble Numbat)",
    ),
    Platform(
        release="26.04", codename="resolute", python="3.14",
        ros=RosDistro("lyrical", discovery_range=True, fastdds=(3, 6)),
        gazebo=Gazebo("Jetty", "ros_gz"),
        # As the official Docker images pin ros2-apt-source_1.2.0.resolute_all.deb
        # (osrf/docker_images); 1.2.0 is the first release that supports resolute.
        ros_apt_source_sha256="a275b9b819874e745a928e83e39c429fa4d607159285c4ef3ebcf75afa732ee3",
        pretty="Ubuntu 26.04 LTS", version_text="26.04 LTS (Resolute Raccoon)",
    ),
]

# Distros that are no release's default, accepted as an override (`ros_distro: kilted`).
OTHER_DISTROS: list[RosDistro] = [
    RosDistro("kilted", discovery_range=True, fastdds=(3, 2), lts=False, codenames=("noble",)),
]


def distros() -> list[RosDistro]:
    """Every distro roslab knows: each release's default, then the others."""
    return [p.ros for p in PLATFORMS] + list(OTHER_DISTROS)


VARIANTS = ("desktop", "ros-base", "ros-core", "desktop-full")

# Indexes and derived views (read-only by convention), for the callers that want a plain mapping.
# They are filled by `index()` in place, so a module that imported one sees a record added later.
BY_RELEASE: dict[str, Platform] = {}
BY_CODENAME: dict[str, Platform] = {}
BY_NAME: dict[str, RosDistro] = {}
UBUNTU_CODENAMES: dict[str, str] = {}
DEFAULT_DISTRO: dict[str, str] = {}
DISTRO_RELEASES: dict[str, set[str]] = {}
DISCOVERY_RANGE_DISTROS: set[str] = set()
# codename -> sha256 of ros2-apt-source's .deb, for the codenames whose pin is known (the schema's
# default of ros_apt_source_sha256 is this very mapping).
APT_SOURCE_PINS: dict[str, str] = {}


def index() -> None:
    """(Re)build the indexes from PLATFORMS and OTHER_DISTROS: after a record is added, every consumer
    (the roster schema, the deploys, discovery, sources, the sandbox) sees it."""
    for view in (BY_RELEASE, BY_CODENAME, BY_NAME, UBUNTU_CODENAMES, DEFAULT_DISTRO, DISTRO_RELEASES,
                 DISCOVERY_RANGE_DISTROS, APT_SOURCE_PINS):
        view.clear()
    for platform in PLATFORMS:
        BY_RELEASE[platform.release] = platform
        BY_CODENAME[platform.codename] = platform
        UBUNTU_CODENAMES[platform.release] = platform.codename
        DEFAULT_DISTRO[platform.codename] = platform.distro
        DISTRO_RELEASES.setdefault(platform.distro, set()).add(platform.codename)
        if platform.ros_apt_source_sha256:
            APT_SOURCE_PINS[platform.codename] = platform.ros_apt_source_sha256
    for ros in distros():
        BY_NAME[ros.name] = ros
        DISTRO_RELEASES.setdefault(ros.name, set()).update(ros.codenames)
        if ros.discovery_range:
            DISCOVERY_RANGE_DISTROS.add(ros.name)


index()


def record(name: str) -> RosDistro:
    """The record of a distro roslab knows (a KeyError for any other: names are checked earlier)."""
    return BY_NAME[name]


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


def default_distro(codename: str | None) -> str:
    """Return the distro a host on this Ubuntu codename gets unless overridden (None: not Ubuntu,
    refused as an unknown codename is)."""
    distro = DEFAULT_DISTRO.get(codename) if codename is not None else None
    if distro is None:
        known = ", ".join(sorted(DEFAULT_DISTRO))
        raise DistroError(f"Ubuntu {codename!r} has no ROS 2 packages roslab knows of (supported: {known})")
    return distro


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
    """codename -> sha256 of ros2-apt-source's .deb, for the codenames whose pin is known (the live
    index: copy it before changing it)."""
    return APT_SOURCE_PINS
