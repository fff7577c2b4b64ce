"""Rendered network files for every kind, method, renderer and Ubuntu release."""

from __future__ import annotations

import configparser

import pytest
import yaml
from pyinfra.api import HiddenValue

from deploy.network import DEFAULTS as NETWORK_DEFAULTS
from roslab.netcheck import network_settings
from roslab.network_render import (
    CLOUD_INIT_DISABLE_FILE,
    CLOUD_INIT_FILE,
    NETPLAN_FILE,
    NETPLAN_NETWORKD,
    NETPLAN_NM,
    NM_KEYFILE,
    RendererFacts,
    choose_layout,
    desired_files,
    mask_secrets,
    render_keyfile,
    render_netplan,
)

PASSWORD = 'se"cret: #1;x'

# The network deploy's own defaults, with a host's static address.
BASE = {
    **NETWORK_DEFAULTS,
    "network_address": "192.168.50.11/24",
    "network_gateway": "192.168.50.1",
    "network_nameservers": ["192.168.50.1", "fd00::53"],
}


def host_settings(kind, method, **changes):
    data = {**BASE, "network_kind": kind, "network_method": method, **changes}
    if kind == "wifi":
        data.update(wifi_ssid="Robo Lab", wifi_password_secret="lab", wifi_password=HiddenValue(PASSWORD))
    if method == "dhcp":
        data.update(network_address=None, network_gateway=None)
    return network_settings(data)


def keyfile(text):
    parser = configparser.ConfigParser(interpolation=None, comment_prefixes=("#",))
    parser.read_string(text)
    return parser


SERVER_2404 = RendererFacts(networkd_active=True, ubuntu_version="24.04")
SERVER_2204 = RendererFacts(networkd_active=True, ubuntu_version="22.04")
DESKTOP_2404 = RendererFacts(networkmanager_active=True, netplan_nm_renderer=True, ubuntu_version="24.04")
DESKTOP_2204 = RendererFacts(networkmanager_active=True, netplan_nm_renderer=True, ubuntu_version="22.04")


@pytest.mark.parametrize(
    "backend, facts, layout",
    [
        ("auto", SERVER_2404, NETPLAN_NETWORKD),
        ("auto", SERVER_2204, NETPLAN_NETWORKD),
        ("auto", DESKTOP_2404, NETPLAN_NM),
        ("auto", DESKTOP_2204, NM_KEYFILE),
        # NetworkManager installed but idle (the sandbox): networkd is in charge.
        ("auto", RendererFacts(networkd_active=True, networkmanager_active=False), NETPLAN_NETWORKD),
        # NM running beside networkd, but only NM's own netplan profiles say it is in charge.
        ("auto", RendererFacts(networkd_active=True, networkmanager_active=True,
                               netplan_nm_profiles=True, ubuntu_version="24.04"), NETPLAN_NM),
        ("auto", RendererFacts(networkmanager_active=True, netplan_installed=False,
                               ubuntu_version="22.04"), NM_KEYFILE),
        ("netplan", DESKTOP_2404, NETPLAN_NETWORKD),
        ("networkmanager", SERVER_2404, NETPLAN_NM),
        ("networkmanager", SERVER_2204, NM_KEYFILE),
    ],
)
def test_layout_follows_the_renderer_in_charge(backend, facts, layout):
    assert choose_layout(backend, facts).name == layout


def test_nothing_in_charge_asks_for_the_roster_setting():
    with pytest.raises(ValueError, match="set network_backend"):
        choose_layout("auto", RendererFacts(netplan_installed=False))


@pytest.mark.parametrize("renderer", ["networkd", "NetworkManager"])
def test_netplan_static_ethernet(renderer):
    text = render_netplan(host_settings("ethernet", "static"), renderer)
    assert text.startswith("# managed by roslab")
    network = yaml.safe_load(text)["network"]
    assert network["renderer"] == renderer
    assert network["ethernets"]["eth0"] == {
        "dhcp4": False,
        "addresses": ["192.168.50.11/24"],
        "routes": [{"to": "default", "via": "192.168.50.1"}],
        "nameservers": {"addresses": ["192.168.50.1", "fd00::53"]},
        "dhcp6": True,
        "accept-ra": True,
    }


def test_netplan_dhcp_wifi_with_quoted_password():
    network = yaml.safe_load(render_netplan(host_settings("wifi", "dhcp"), "networkd"))["network"]
    wlan0 = network["wifis"]["wlan0"]
    assert wlan0["dhcp4"] is True and "addresses" not in wlan0
    assert wlan0["access-points"] == {"Robo Lab": {"password": PASSWORD}}


def test_netplan_static_wifi_without_gateway_has_no_default_route():
    text = render_netplan(host_settings("wifi", "static", network_gateway=None), "networkd")
    wlan0 = yaml.safe_load(text)["network"]["wifis"]["wlan0"]
    assert wlan0["addresses"] == ["192.168.50.11/24"] and "routes" not in wlan0


@pytest.mark.parametrize(
    "ipv6, expected",
    [
        ("auto", {"dhcp6": True, "accept-ra": True}),
        ("disabled", {"dhcp6": False, "accept-ra": False, "link-local": []}),
        ("ignore", {}),
    ],
)
def test_netplan_ipv6_setting(ipv6, expected):
    eth0 = yaml.safe_load(render_netplan(host_settings("ethernet", "dhcp", network_ipv6=ipv6), "networkd"))
    eth0 = eth0["network"]["ethernets"]["eth0"]
    assert {key: eth0[key] for key in ("dhcp6", "accept-ra", "link-local") if key in eth0} == expected


def test_keyfile_static_ethernet():
    text = render_keyfile(host_settings("ethernet", "static"))
    assert text.startswith("# managed by roslab")
    parsed = keyfile(text)
    assert dict(parsed["connection"]) == {
        "id": "roslab-eth0",
        "uuid": parsed["connection"]["uuid"],
        "type": "ethernet",
        "interface-name": "eth0",
        "autoconnect": "true",
        "autoconnect-priority": "100",
    }
    assert dict(parsed["ipv4"]) == {
        "method": "manual",
        "address1": "192.168.50.11/24,192.168.50.1",
        "dns": "192.168.50.1;",
    }
    assert dict(parsed["ipv6"]) == {"method": "auto", "dns": "fd00::53;"}
    assert "wifi" not in parsed


def test_keyfile_dhcp_wifi():
    parsed = keyfile(render_keyfile(host_settings("wifi", "dhcp", network_ipv6="disabled")))
    assert parsed["connection"]["type"] == "wifi"
    assert parsed["connection"]["interface-name"] == "wlan0"
    assert dict(parsed["wifi"]) == {"mode": "infrastructure", "ssid": "Robo Lab"}
    assert dict(parsed["wifi-security"]) == {"key-mgmt": "wpa-psk", "psk": PASSWORD}
    assert parsed["ipv4"]["method"] == "auto" and "address1" not in parsed["ipv4"]
    assert parsed["ipv6"]["method"] == "disabled"


def test_keyfile_is_identical_on_every_render():
    assert render_keyfile(host_settings("ethernet", "static")) == render_keyfile(host_settings("ethernet", "static"))


@pytest.mark.parametrize("render", [lambda s: render_netplan(s, "networkd"), render_keyfile])
def test_masked_files_keep_everything_but_the_password(render):
    text = render(host_settings("wifi", "static"))
    masked = mask_secrets(text)
    assert PASSWORD not in masked
    assert "********" in masked
    assert masked.count("\n") == text.count("\n")
    assert "Robo Lab" in masked


@pytest.mark.parametrize(
    "facts, layout_path",
    [(SERVER_2404, NETPLAN_FILE), (DESKTOP_2404, NETPLAN_FILE),
     (DESKTOP_2204, "/etc/NetworkManager/system-connections/roslab-eth0.nmconnection")],
)
def test_desired_files_per_release(facts, layout_path):
    settings = host_settings("ethernet", "static")
    files = desired_files(settings, choose_layout("auto", facts), cloud_init_present=True)
    assert list(files.files) == [layout_path, CLOUD_INIT_DISABLE_FILE]
    assert files.files[CLOUD_INIT_DISABLE_FILE].startswith("# managed by roslab")
    assert yaml.safe_load(files.files[CLOUD_INIT_DISABLE_FILE]) == {"network": {"config": "disabled"}}
    assert files.superseded == (CLOUD_INIT_FILE,)


def test_no_cloud_init_means_no_disable_file():
    settings = host_settings("ethernet", "static")
    files = desired_files(settings, choose_layout("auto", SERVER_2404), cloud_init_present=False)
    assert list(files.files) == [NETPLAN_FILE] and files.superseded == ()


def test_cloud_init_left_alone_when_asked():
    settings = host_settings("ethernet", "static", network_disable_cloud_init=False)
    files = desired_files(settings, choose_layout("auto", SERVER_2404), cloud_init_present=True)
    assert list(files.files) == [NETPLAN_FILE] and files.superseded == ()
