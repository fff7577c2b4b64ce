"""Emulated Ubuntu: the files that make a Debian sandbox host look like an Ubuntu Pi.

The sandbox's hosts run Debian userlands (Ubuntu's archive is out of reach).
What the deploys read to tell an Ubuntu release and its apt layout is written
here per host, each file saying it is an emulation: `/etc/os-release`,
`/etc/lsb-release`, Ubuntu's apt sources (pointing at the sandbox upstream),
and the netplan file cloud-init would have written from the boot partition.
cloud-init (Debian's) is installed but disabled on these hosts, as on a Pi after
its first boot; a host booted from a seed runs it for real (seeding.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from roslab.ros.distro import BY_RELEASE

HEADER = "# roslab sandbox emulation of Ubuntu {release}: this host runs a Debian userland.\n"

UBUNTU_KEYRING = "/usr/share/keyrings/ubuntu-archive-keyring.gpg"


@dataclass(frozen=True)
class HostIdentity:
    """What one emulated host is: its name, release and address on the sandbox network."""

    hostname: str
    release: str  # "24.04", "22.04" or "26.04"
    address: str  # "10.213.0.11"
    prefixlen: int  # 24
    flavour: str = "server"  # "server" (networkd) or "desktop" (NetworkManager)

    @property
    def codename(self) -> str:
        return BY_RELEASE[self.release].codename


def os_release(host: HostIdentity) -> str:
    platform = BY_RELEASE[host.release]
    return HEADER.format(release=host.release) + (
        f'PRETTY_NAME="{platform.pretty}"\n'
        'NAME="Ubuntu"\n'
        f'VERSION_ID="{host.release}"\n'
        f'VERSION="{platform.version_text}"\n'
        f"VERSION_CODENAME={platform.codename}\n"
        "ID=ubuntu\n"
        "ID_LIKE=debian\n"
        'HOME_URL="https://www.ubuntu.com/"\n'
        f"UBUNTU_CODENAME={platform.codename}\n"
    )


def lsb_release(host: HostIdentity) -> str:
    platform = BY_RELEASE[host.release]
    return HEADER.format(release=host.release) + (
        "DISTRIB_ID=Ubuntu\n"
        f"DISTRIB_RELEASE={host.release}\n"
        f"DISTRIB_CODENAME={platform.codename}\n"
        f'DISTRIB_DESCRIPTION="{platform.pretty}"\n'
    )


def apt_sources(host: HostIdentity, archive_url: str) -> tuple[str, str]:
    """Ubuntu's apt layout as the Pi server image ships it: (path, content).

    Deliberately main and restricted only, without -updates and -backports:
    that is the gap on real Pi images which the apt_ready deploy must close.
    """
    header = HEADER.format(release=host.release) + f"# {archive_url} is the sandbox's stand-in for Ubuntu's archive.\n"
    codename = host.codename
    if host.release == "22.04":
        return "/etc/apt/sources.list", header + (
            f"deb {archive_url} {codename} main restricted\n"
            f"deb {archive_url} {codename}-security main restricted\n"
        )
    return "/etc/apt/sources.list.d/ubuntu.sources", header + (
        "Types: deb\n"
        f"URIs: {archive_url}\n"
        f"Suites: {codename} {codename}-security\n"
        "Components: main restricted\n"
        f"Signed-By: {UBUNTU_KEYRING}\n"
    )


def netplan_cloud_init(host: HostIdentity) -> str:
    """The netplan file cloud-init writes on Ubuntu Server from the boot partition's network-config."""
    return (
        "# roslab sandbox emulation of the file cloud-init writes on Ubuntu Server\n"
        "# from the boot partition's network-config (cloud-init is disabled on this host).\n"
        "# No default route: sandbox hosts reach only the sandbox network.\n"
        "network:\n"
        "  version: 2\n"
        "  renderer: networkd\n"
        "  ethernets:\n"
        "    eth0:\n"
        "      dhcp4: false\n"
        f"      addresses: [{host.address}/{host.prefixlen}]\n"
    )


def netplan_desktop(host: HostIdentity) -> str:
    """Ubuntu Desktop's netplan file, handing eth0 (with its static address) to NetworkManager."""
    return (
        "# roslab sandbox emulation of Ubuntu Desktop's netplan file: NetworkManager\n"
        "# manages the network (netplan's generator writes its profile for eth0).\n"
        "network:\n"
        "  version: 2\n"
        "  renderer: NetworkManager\n"
        "  ethernets:\n"
        "    eth0:\n"
        "      dhcp4: false\n"
        f"      addresses: [{host.address}/{host.prefixlen}]\n"
    )


CLOUD_CFG_README = (
    "roslab sandbox: cloud-init is installed but disabled on this host (/etc/cloud/cloud-init.disabled),\n"
    "as on a Pi after its first boot; `roslab sandbox reset HOST --seed DIR` boots a host through it.\n"
    "Deploys may drop configuration here (e.g. 99-disable-network-config.cfg).\n"
)


def host_files(host: HostIdentity, archive_url: str) -> dict[str, tuple[str, int]]:
    """Every emulation file of one host: path -> (content, mode)."""
    sources_path, sources = apt_sources(host, archive_url)
    if host.flavour == "desktop":
        netplan = {"/etc/netplan/01-network-manager-all.yaml": (netplan_desktop(host), 0o600)}
    else:
        netplan = {"/etc/netplan/50-cloud-init.yaml": (netplan_cloud_init(host), 0o600)}
    return {
        "/usr/lib/os-release": (os_release(host), 0o644),
        "/etc/lsb-release": (lsb_release(host), 0o644),
        sources_path: (sources, 0o644),
        **netplan,
        "/etc/cloud/cloud.cfg.d/README.roslab-sandbox": (CLOUD_CFG_README, 0o644),
    }
