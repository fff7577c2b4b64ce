"""Rendered network files for every kind, method, renderer and Ubuntu release."""

from __future__ import annotations

import configparser

import jinja2
import pytest
import yaml
from fixtures.classroom import typed
from pyinfra.api import HiddenValue

from deploy.network import DEFAULTS as NETWORK_DEFAULTS
from roslab.network.apply import NETPLAN_NETWORKD, NETPLAN_NM, NM_KEYFILE
from roslab.network.render import (
    CLOUD_INIT_DISABLE_FILE,
    CLOUD_INIT_FILE,
    NETPLAN_FILE,
    RendererFacts,
    choose_layout,
    desired_files,
    keyfile_values,
    keyfile_list,
    keyfile_ssid,
    keyfile_string,
    mask_secrets,
    netplan_values,
    render_keyfile,
    render_netplan,
    yaml_string,
)
from roslab.network.settings import network_settings
from roslab.templating import ENVIRONMENT, TEMPLATES

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
    return network_settings(typed(data))


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


# Escaping: every value lands in its file so that the file's own reader gets it back exactly.

# Legal SSIDs that YAML, GKeyFile, NetworkManager or a shell would misread if written bare.
AWKWARD_SSIDS = [
    'Lab "A" — Café #2',
    "$(reboot)",
    "`id`",
    "it's",
    "a;b",
    "12;34;",  # NetworkManager would read these two as byte lists
    "42",
    " leading",
    "trailing ",
    "  ",
    "key=value [group]",
    "#not a comment",
    "key: value",
    "- item",
    "{a: b}",
    "[1, 2]",
    "&anchor *alias !tag %d @",
    "yes",
    "null",
    "~",
    "back\\slash",
    "\\;",
    "\\s\\n",
    "robots 🤖",
    "\u00a0nbsp",
    "\ufeffbom",
    "-dash",
]

AWKWARD_PASSWORDS = [
    PASSWORD,
    " leading and trailing ",
    "$(reboot) `id` \\x27",
    "a\\b;c=d[e]#f",
    "it's \"quoted\"",
    "ab" * 32,
]


def wifi_settings(ssid="Robo Lab", password=PASSWORD, method="static"):
    data = {**BASE, "network_kind": "wifi", "network_method": method, "wifi_ssid": ssid,
            "wifi_password_secret": "lab", "wifi_password": HiddenValue(password)}
    return network_settings(typed(data))


# A reader of GKeyFile values as glib's g_key_file_get_string(_list) reads them, and of an
# SSID as NetworkManager's keyfile reader (get_bytes in libnm-core's nm-keyfile.c) reads it.

GKEYFILE_ESCAPES = {"s": " ", "n": "\n", "t": "\t", "r": "\r", "\\": "\\"}


def gkeyfile_unescape(raw: str, as_list: bool = False):
    items, current, i = [], [], 0
    while i < len(raw):
        char = raw[i]
        if char == "\\":
            i += 1
            if i == len(raw):
                raise ValueError("escape character at end of line")
            if raw[i] in GKEYFILE_ESCAPES:
                current.append(GKEYFILE_ESCAPES[raw[i]])
            elif as_list and raw[i] == ";":
                current.append(";")
            else:
                raise ValueError(f"invalid escape sequence \\{raw[i]}")
        elif as_list and char == ";":
            items.append("".join(current))
            current = []
        else:
            current.append(char)
        i += 1
    if not as_list:
        return "".join(current)
    if current:
        items.append("".join(current))
    return items


def gkeyfile(text: str) -> dict[str, dict[str, str]]:
    """Groups of raw values, split as GKeyFile splits lines (the value's leading spaces dropped)."""
    groups: dict[str, dict[str, str]] = {}
    group = None
    for line in text.split("\n"):
        line = line[:-1] if line.endswith("\r") else line
        stripped = line.lstrip(" \t\n\v\f\r")
        if not stripped or stripped.startswith("#"):
            continue
        if stripped.startswith("["):
            assert stripped.endswith("]"), line
            group = groups.setdefault(stripped[1:-1], {})
            continue
        key, _, value = stripped.partition("=")
        assert group is not None and key.rstrip() not in group, line
        group[key.rstrip()] = value.lstrip(" \t\n\v\f\r")
    return groups


def nm_ssid(raw: str) -> bytes:
    """The SSID bytes NetworkManager reads from a keyfile's raw `ssid=` value."""
    value = gkeyfile_unescape(raw)
    if value and all(c in "0123456789;" or c.isspace() for c in value):
        numbers = [part.strip() for part in value.split(";")]
        if len(numbers) > 1 and numbers[-1] == "" and all(n.isdigit() and len(n) <= 3 and int(n) <= 255 for n in numbers[:-1]):
            return bytes(int(n) for n in numbers[:-1])  # the old format: a list of byte values
    return value.replace("\\;", ";").encode()


def test_gkeyfile_reader_reads_what_the_escaping_means():
    # The test's reader against the escapes nm-settings-keyfile(5) and glib document.
    assert gkeyfile_unescape("\\sa b\\s\\\\n\\n") == " a b \\n\n"
    assert gkeyfile_unescape("a\\;b;c;", as_list=True) == ["a;b", "c"]
    with pytest.raises(ValueError):
        gkeyfile_unescape("a\\;b")  # only list values escape ';'
    assert nm_ssid("12;34;") == bytes([12, 34])
    assert nm_ssid("a\\\\;b") == b"a;b"


@pytest.mark.parametrize("ssid", AWKWARD_SSIDS)
def test_netplan_ssid_reads_back_exactly(ssid):
    text = render_netplan(wifi_settings(ssid=ssid), "networkd")
    wlan0 = yaml.safe_load(text)["network"]["wifis"]["wlan0"]
    assert list(wlan0["access-points"]) == [ssid]
    assert wlan0["access-points"][ssid] == {"password": PASSWORD}


@pytest.mark.parametrize("ssid", AWKWARD_SSIDS)
def test_keyfile_ssid_reads_back_exactly(ssid):
    groups = gkeyfile(render_keyfile(wifi_settings(ssid=ssid)))
    assert nm_ssid(groups["wifi"]["ssid"]) == ssid.encode()
    assert gkeyfile_unescape(groups["wifi-security"]["psk"]) == PASSWORD


@pytest.mark.parametrize("password", AWKWARD_PASSWORDS)
def test_password_reads_back_exactly_and_is_masked(password):
    netplan = render_netplan(wifi_settings(password=password), "networkd")
    access_point = yaml.safe_load(netplan)["network"]["wifis"]["wlan0"]["access-points"]["Robo Lab"]
    assert access_point == {"password": password}
    keyfile_text = render_keyfile(wifi_settings(password=password))
    assert gkeyfile_unescape(gkeyfile(keyfile_text)["wifi-security"]["psk"]) == password
    for text in (netplan, keyfile_text):
        masked = mask_secrets(text)
        assert password.strip() not in masked and masked.count("\n") == text.count("\n")


def test_every_keyfile_value_reads_back():
    settings = host_settings("ethernet", "static")
    groups = gkeyfile(render_keyfile(settings))
    values = {f"{group}.{key}": gkeyfile_unescape(raw, as_list=key == "dns")
              for group, keys in groups.items() for key, raw in keys.items()}
    assert values["connection.interface-name"] == "eth0"
    assert values["ipv4.address1"] == "192.168.50.11/24,192.168.50.1"
    assert values["ipv4.dns"] == ["192.168.50.1"] and values["ipv6.dns"] == ["fd00::53"]


def printed_names(template: str) -> set[str]:
    """The names a template prints ({{ name }}); anything but a bare name fails the test."""
    source = (TEMPLATES / template).read_text()
    assert source.startswith("# managed by roslab")
    names = set()
    for output in ENVIRONMENT.parse(source).find_all(jinja2.nodes.Output):
        for node in output.nodes:
            if not isinstance(node, jinja2.nodes.TemplateData):
                assert isinstance(node, jinja2.nodes.Name), f"{template}: prints an expression: {node}"
                names.add(node.name)
    return names


@pytest.mark.parametrize("kind", ["ethernet", "wifi"])
def test_templates_print_only_escaped_values(kind):
    # The templates do no quoting of their own: each value they print was escaped for its
    # format in netplan_values / keyfile_values; the choices are only for conditions.
    settings = host_settings(kind, "static")
    netplan = netplan_values(settings, "networkd")
    assert printed_names("netplan.yaml.j2") == {name for name in netplan if name not in (
        "kind", "method", "ipv6", "nameservers")} | {"server"}
    for name, value in netplan.items():
        if name in ("kind", "method", "ipv6") or value is None:
            continue
        for item in value if isinstance(value, list) else [value]:
            assert item.startswith('"') and isinstance(yaml.safe_load(item), str), (name, item)
    keyfile_names = printed_names("nm-connection.nmconnection.j2")
    assert keyfile_names == set(keyfile_values(settings)) - {"kind", "method"}


def yaml_reads(values: list[str]) -> list[str]:
    return yaml.safe_load("[" + ", ".join(yaml_string(value) for value in values) + "]")


def test_yaml_string_round_trips_every_character():
    # libyaml and PyYAML share YAML's rules: C0, DEL and C1 controls are not printable
    # (a reader error), NEL, U+2028 and U+2029 are line breaks (folded into a space).
    code_points = [*range(0, 0x3000), *range(0xD700, 0xD800), *range(0xE000, 0xE100),
                   *range(0xFEF0, 0x10100), *range(0x10FFF0, 0x110000)]
    characters = [chr(code) for code in code_points]
    assert yaml_reads(characters) == characters
    assert yaml_reads(AWKWARD_SSIDS + AWKWARD_PASSWORDS) == AWKWARD_SSIDS + AWKWARD_PASSWORDS


def test_yaml_string_is_not_json_where_yaml_differs():
    for character in ("\x7f", "\x85", "\x9b", "\u2028", "\u2029", "\ufeff"):
        assert character not in yaml_string(f"a{character}b")
    assert yaml_string('Lab "A" — Café #2') == '"Lab \\"A\\" — Café #2"'
    with pytest.raises(ValueError):
        yaml_string("\ud800")


def test_keyfile_string_round_trips_and_refuses_what_gkeyfile_cannot_hold():
    values = ["\tx\ny\r", " ", "a  b", "\\", "é;=[]#", *AWKWARD_SSIDS, *AWKWARD_PASSWORDS]
    for value in values:
        escaped = keyfile_string(value)
        assert "\n" not in escaped and "\r" not in escaped
        assert not escaped.startswith(" ") and not escaped.endswith(" ")
        assert gkeyfile_unescape(gkeyfile(f"[g]\nk={escaped}\n")["g"]["k"]) == value
    assert gkeyfile_unescape(keyfile_list(["a;b", " c "]), as_list=True) == ["a;b", " c "]
    for control in ("\x00", "\x01", "\x0b", "\x0c", "\x1b", "\x7f"):
        with pytest.raises(ValueError):
            keyfile_string(f"a{control}b")
    with pytest.raises(TypeError):
        keyfile_string(None)


def test_keyfile_ssid_is_never_a_byte_list():
    # NetworkManager's own writer escapes ';' in an SSID the same way (ssid_writer).
    assert keyfile_ssid("12;34;") == "12\\\\;34\\\\;"
    assert keyfile_ssid("42") == "42"
