"""What a host's network files should contain, and which files they are.

Pure functions from checked settings (`roslab.network.settings.NetworkSettings`)
and host facts to file contents, so every combination is unit-tested without a host:

- which renderer is in charge and which file format it reads (`choose_layout`);
- the netplan file, the NetworkManager keyfile, cloud-init's disable file;
- the escaping each format needs (`yaml_string`, `keyfile_string`, `keyfile_ssid`,
  `keyfile_list`, from roslab.quoting): the templates do no quoting of their own, and
  every value they print comes from `netplan_values` or `keyfile_values`, escaped;
- `mask_secrets`, the one place that hides a WiFi password in anything printed.
"""

from __future__ import annotations

import re
import uuid
from dataclasses import dataclass

from roslab.network.apply import NETPLAN_DIR, NETPLAN_NETWORKD, NETPLAN_NM, NM_KEYFILE
from roslab.network.settings import NetworkSettings
from roslab.quoting import keyfile_list, keyfile_ssid, keyfile_string, yaml_string  # noqa: F401
from roslab.templating import render

# Sorts after 50-cloud-init.yaml and before NetworkManager's 90-NM-*.yaml profiles.
NETPLAN_FILE = f"{NETPLAN_DIR}/60-roslab.yaml"
KEYFILE_DIR = "/etc/NetworkManager/system-connections"
CLOUD_INIT_FILE = f"{NETPLAN_DIR}/50-cloud-init.yaml"
CLOUD_INIT_DISABLE_FILE = "/etc/cloud/cloud.cfg.d/99-disable-network-config.cfg"

MASK = "********"
# `password: ...` (netplan) and `psk=...` (keyfile): the value is masked, the key kept.
_SECRET_LINE = re.compile(r"^(\s*(?:password\s*:|psk\s*=)\s*).*$", re.MULTILINE)
# The same rule for sed on the host, so a diff compares like with like.
SED_MASK_SECRETS = r"s/^\([[:space:]]*\(password[[:space:]]*:\|psk[[:space:]]*=\)[[:space:]]*\).*$/\1" + MASK + "/"


def mask_secrets(text: str) -> str:
    """The text with every WiFi password replaced by ********."""
    return _SECRET_LINE.sub(lambda match: match.group(1) + MASK, text)


@dataclass(frozen=True)
class RendererFacts:
    """What a host shows about who manages its network (see operation.NetworkRenderer)."""

    networkmanager_active: bool = False
    networkd_active: bool = False
    netplan_installed: bool = True
    netplan_nm_renderer: bool = False  # a netplan file says `renderer: NetworkManager`
    netplan_nm_profiles: bool = False  # /etc/netplan/90-NM-*.yaml exist (NM stores profiles there)
    ubuntu_version: str | None = None  # VERSION_ID, e.g. "24.04"


@dataclass(frozen=True)
class Layout:
    """Where this host's configuration goes, and why."""

    name: str
    reason: str

    @property
    def renderer(self) -> str:
        return "networkd" if self.name == NETPLAN_NETWORKD else "NetworkManager"

    @property
    def uses_netplan(self) -> bool:
        return self.name != NM_KEYFILE


def _version_tuple(version: str | None) -> tuple[int, ...]:
    try:
        return tuple(int(part) for part in (version or "").split("."))
    except ValueError:
        return ()


def _netplan_everywhere(facts: RendererFacts) -> bool:
    # Since Ubuntu 23.10 NetworkManager stores its profiles as netplan files.
    return facts.netplan_installed and (
        facts.netplan_nm_profiles or _version_tuple(facts.ubuntu_version) >= (23, 10)
    )


def choose_layout(backend: str, facts: RendererFacts) -> Layout:
    """Decide which renderer and file format a host gets.

    `backend` is the roster's `network_backend`: `auto` follows whoever is in
    charge on the host; `netplan` forces netplan with networkd; `networkmanager`
    forces NetworkManager (as netplan file where NM reads netplan, else keyfile).
    """
    if backend == "netplan":
        if not facts.netplan_installed:
            raise ValueError("network_backend is netplan but netplan is not installed on the host")
        return Layout(NETPLAN_NETWORKD, "network_backend: netplan in the roster")
    if backend == "networkmanager":
        nm_reason = "network_backend: networkmanager in the roster"
    else:
        nm_in_charge = facts.networkmanager_active and (
            facts.netplan_nm_renderer
            or facts.netplan_nm_profiles
            or not facts.netplan_installed
            or not facts.networkd_active
        )
        if not nm_in_charge:
            if not facts.netplan_installed:
                raise ValueError(
                    "neither NetworkManager nor netplan manages the network on this host; "
                    "set network_backend in the roster"
                )
            return Layout(NETPLAN_NETWORKD, "netplan with systemd-networkd is in charge")
        nm_reason = "NetworkManager is in charge"
    if _netplan_everywhere(facts):
        return Layout(NETPLAN_NM, f"{nm_reason}; it keeps its profiles in netplan here")
    return Layout(NM_KEYFILE, f"{nm_reason}; it reads keyfiles here")


def connection_id(settings: NetworkSettings) -> str:
    return f"roslab-{settings.interface}"


def keyfile_path(settings: NetworkSettings) -> str:
    return f"{KEYFILE_DIR}/{connection_id(settings)}.nmconnection"


def netplan_values(settings: NetworkSettings, renderer: str, regulatory_domain: str | None = None) -> dict:
    """The netplan template's variables: every value it prints is a YAML double-quoted
    scalar; `kind`, `method` and `ipv6` (checked choices) are for its conditions only.
    `regulatory_domain`: a checked country code for a WiFi interface (the seed's)."""
    password = settings.password
    return {
        "regulatory_domain": yaml_string(regulatory_domain) if regulatory_domain else None,
        "kind": settings.kind,
        "method": settings.method,
        "ipv6": settings.ipv6,
        "renderer": yaml_string(renderer),
        "interface": yaml_string(settings.interface),
        "address": yaml_string(settings.address) if settings.address else None,
        "gateway": yaml_string(settings.gateway) if settings.gateway else None,
        "nameservers": [yaml_string(server) for server in settings.nameservers],
        "ssid": yaml_string(settings.wifi_ssid) if settings.wifi_ssid is not None else None,
        "password": yaml_string(password) if password is not None else None,
    }


def keyfile_values(settings: NetworkSettings) -> dict:
    """The keyfile template's variables: every value it prints is escaped as GKeyFile (and,
    for the SSID, NetworkManager) reads it; `kind` and `method` are for its conditions only."""
    # A fixed UUID per interface, so a re-render is byte-identical (idempotent).
    profile_uuid = uuid.uuid5(uuid.NAMESPACE_URL, f"roslab:network:{settings.interface}")
    # NetworkManager keeps DNS servers per address family (it drops IPv6 ones from ipv4.dns).
    ipv4_nameservers = [server for server in settings.nameservers if ":" not in server]
    ipv6_nameservers = [server for server in settings.nameservers if ":" in server]
    address = None
    if settings.address is not None:
        address = keyfile_string(settings.address)
        if settings.gateway is not None:
            address += "," + keyfile_string(settings.gateway)
    password = settings.password
    return {
        "kind": settings.kind,
        "method": settings.method,
        "connection_id": keyfile_string(connection_id(settings)),
        "uuid": keyfile_string(profile_uuid),
        "interface": keyfile_string(settings.interface),
        "address": address,
        "ipv4_dns": keyfile_list(ipv4_nameservers) if ipv4_nameservers else None,
        "ipv6_dns": keyfile_list(ipv6_nameservers) if ipv6_nameservers else None,
        "ipv6_method": keyfile_string(settings.ipv6),
        "ssid": keyfile_ssid(settings.wifi_ssid) if settings.wifi_ssid is not None else None,
        "password": keyfile_string(password) if password is not None else None,
    }


def render_netplan(settings: NetworkSettings, renderer: str, regulatory_domain: str | None = None) -> str:
    return render("netplan.yaml.j2", **netplan_values(settings, renderer, regulatory_domain))


def render_keyfile(settings: NetworkSettings) -> str:
    return render("nm-connection.nmconnection.j2", **keyfile_values(settings))


def render_cloud_init_disable() -> str:
    return render("cloud-init-disable-network.cfg.j2")


@dataclass(frozen=True)
class NetworkFiles:
    """The files a host should have, and the files they replace (moved to a backup)."""

    files: dict[str, str]  # path -> content
    superseded: tuple[str, ...]


def desired_files(
    settings: NetworkSettings, layout: Layout, cloud_init_present: bool,
    netplan_files_for_interface: tuple[str, ...] = (),
) -> NetworkFiles:
    """Every file the network deploy writes on a host, in the order they are installed.

    `cloud_init_present`: the host has cloud-init's network file or /etc/cloud.
    `netplan_files_for_interface`: netplan files on the host that configure the same
    interface; netplan would merge their addresses with ours, so they are superseded.
    """
    files: dict[str, str] = {}
    superseded: list[str] = []
    if layout.uses_netplan:
        files[NETPLAN_FILE] = render_netplan(settings, layout.renderer)
    else:
        files[keyfile_path(settings)] = render_keyfile(settings)
    if settings.disable_cloud_init and cloud_init_present:
        files[CLOUD_INIT_DISABLE_FILE] = render_cloud_init_disable()
        # cloud-init's file would configure the same interface by DHCP beside ours.
        superseded.append(CLOUD_INIT_FILE)
    if layout.uses_netplan:
        superseded.extend(
            path for path in netplan_files_for_interface if path not in files and path not in superseded
        )
    return NetworkFiles(files, tuple(superseded))
