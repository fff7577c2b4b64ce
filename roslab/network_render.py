"""What a host's network files should contain, and which files they are.

Pure functions from checked settings (`roslab.netcheck.NetworkSettings`) and
host facts to file contents, so every combination is unit-tested without a host:

- which renderer is in charge and which file format it reads (`choose_layout`);
- the netplan file, the NetworkManager keyfile, cloud-init's disable file;
- `mask_secrets`, the one place that hides a WiFi password in anything printed.
"""

from __future__ import annotations

import json
import re
import uuid
from dataclasses import dataclass
from pathlib import Path

import jinja2

from roslab.netcheck import NetworkSettings

TEMPLATES = Path(__file__).resolve().parent.parent / "templates"

# Sorts after 50-cloud-init.yaml and before NetworkManager's 90-NM-*.yaml profiles.
NETPLAN_FILE = "/etc/netplan/60-roslab.yaml"
KEYFILE_DIR = "/etc/NetworkManager/system-connections"
CLOUD_INIT_FILE = "/etc/netplan/50-cloud-init.yaml"
CLOUD_INIT_DISABLE_FILE = "/etc/cloud/cloud.cfg.d/99-disable-network-config.cfg"

# Layouts: who renders the configuration, and in which file.
NETPLAN_NETWORKD = "netplan-networkd"  # Ubuntu Server: netplan, rendered by systemd-networkd
NETPLAN_NM = "netplan-networkmanager"  # Ubuntu Desktop >= 23.10: NM profiles are netplan files
NM_KEYFILE = "networkmanager-keyfile"  # Ubuntu Desktop 22.04: NM keyfiles

MASK = "********"
# `password: ...` (netplan) and `psk=...` (keyfile): the value is masked, the key kept.
_SECRET_LINE = re.compile(r"^(\s*(?:password\s*:|psk\s*=)\s*).*$", re.MULTILINE)
# The same rule for sed on the host, so a diff compares like with like.
SED_MASK_SECRETS = r"s/^\([[:space:]]*\(password[[:space:]]*:\|psk[[:space:]]*=\)[[:space:]]*\).*$/\1" + MASK + "/"


def mask_secrets(text: str) -> str:
    """The text with every WiFi password replaced by ********."""
    return _SECRET_LINE.sub(lambda match: match.group(1) + MASK, text)


def _yaml_string(value: str) -> str:
    # A JSON string is a valid YAML double-quoted scalar.
    return json.dumps(str(value), ensure_ascii=False)


def _keyfile_string(value: str) -> str:
    # GLib key file escapes (nm-settings-keyfile(5) reads values with g_key_file).
    escaped = str(value).replace("\\", "\\\\").replace("\t", "\\t").replace("\n", "\\n")
    if escaped.startswith(" "):
        escaped = "\\s" + escaped[1:]
    return escaped


_environment = jinja2.Environment(
    loader=jinja2.FileSystemLoader(str(TEMPLATES)),
    undefined=jinja2.StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
    keep_trailing_newline=True,
    autoescape=False,
)
_environment.filters["yaml_string"] = _yaml_string
_environment.filters["keyfile_string"] = _keyfile_string


@dataclass(frozen=True)
class RendererFacts:
    """What a host shows about who manages its network (see network_ops.NetworkRenderer)."""

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


def _variables(settings: NetworkSettings) -> dict:
    return {
        "kind": settings.kind,
        "method": settings.method,
        "interface": settings.interface,
        "address": str(settings.address) if settings.address else None,
        "gateway": str(settings.gateway) if settings.gateway else None,
        "nameservers": list(settings.nameservers),
        "ipv6": settings.ipv6,
        "ssid": settings.wifi_ssid,
        "password": settings.password,
    }


def render_netplan(settings: NetworkSettings, renderer: str) -> str:
    return _environment.get_template("netplan.yaml.j2").render(renderer=renderer, **_variables(settings))


def render_keyfile(settings: NetworkSettings) -> str:
    # A fixed UUID per interface, so a re-render is byte-identical (idempotent).
    profile_uuid = uuid.uuid5(uuid.NAMESPACE_URL, f"roslab:network:{settings.interface}")
    # NetworkManager keeps DNS servers per address family (it drops IPv6 ones from ipv4.dns).
    ipv4_nameservers = [server for server in settings.nameservers if ":" not in server]
    ipv6_nameservers = [server for server in settings.nameservers if ":" in server]
    return _environment.get_template("nm-connection.nmconnection.j2").render(
        connection_id=connection_id(settings),
        uuid=profile_uuid,
        ipv4_nameservers=ipv4_nameservers,
        ipv6_nameservers=ipv6_nameservers,
        **_variables(settings),
    )


def render_cloud_init_disable() -> str:
    return _environment.get_template("cloud-init-disable-network.cfg.j2").render()


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
