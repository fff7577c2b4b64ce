"""Network settings checks: every bad input is named by its field, and good input parses."""

from __future__ import annotations

import re
from dataclasses import replace
from ipaddress import IPv4Address, IPv4Interface

import pytest
from fixtures.classroom import typed
from pyinfra.api import HiddenValue

from deploy.network import DEFAULTS as NETWORK_DEFAULTS
from roslab.network.settings import (
    NetworkSettingError,
    check_classroom_network,
    manages_network,
    network_settings,
)

# The network deploy's own defaults, with a host's static address.
BASE = {
    **NETWORK_DEFAULTS,
    "network_address": "192.168.50.11/24",
    "network_gateway": "192.168.50.1",
    "network_nameservers": ["192.168.50.1", "9.9.9.9"],
}


def settings(**changes):
    """A host's typed settings with these values, set as they are (`replace` checks no type): a
    wrong-typed value reaches the parser as if HostSettings had let it through."""
    return replace(typed(BASE), **changes)


def wifi(**changes):
    wifi_defaults = {
        "network_kind": "wifi",
        "wifi_ssid": "robolab",
        "wifi_password_secret": "lab_wifi",
        "wifi_password": HiddenValue("correct horse"),
    }
    return settings(**{**wifi_defaults, **changes})


def test_static_ethernet_parses():
    parsed = network_settings(settings())
    assert parsed.address == IPv4Interface("192.168.50.11/24")
    assert parsed.gateway == IPv4Address("192.168.50.1")
    assert parsed.interface == "eth0"
    assert parsed.nameservers == ("192.168.50.1", "9.9.9.9")


def test_prefix_from_classroom_level():
    parsed = network_settings(settings(network_address="192.168.50.11", network_prefix=24))
    assert parsed.address == IPv4Interface("192.168.50.11/24")


def test_wifi_defaults_to_wlan0_and_keeps_password_hidden():
    parsed = network_settings(wifi())
    assert parsed.interface == "wlan0"
    assert parsed.password == "correct horse"
    assert "correct horse" not in repr(parsed)


def test_no_address_means_network_left_alone():
    assert network_settings(settings(network_address=None)) is None
    assert not manages_network(settings(network_address=None))


def test_disabled_means_network_left_alone():
    assert network_settings(settings(network_enabled=False)) is None


def test_dhcp_needs_no_address():
    parsed = network_settings(settings(network_method="dhcp", network_address=None, network_gateway=None))
    assert parsed.method == "dhcp" and parsed.address is None


@pytest.mark.parametrize(
    "changes, field, words",
    [
        ({"network_address": "192.168.50.300/24"}, "network_address", "not an IPv4 address"),
        ({"network_address": "192.168.50.11/33"}, "network_address", "not an IPv4 address"),
        ({"network_address": "192.168.50.11/4"}, "network_address", "too short"),
        ({"network_address": "192.168.50.11"}, "network_address", "no prefix length"),
        ({"network_address": "192.168.50.11", "network_prefix": 40}, "network_prefix", "not an IPv4"),
        ({"network_address": "192.168.50.11/24", "network_prefix": 16}, "network_address", "prefix /24"),
        ({"network_address": "192.168.50.0/24"}, "network_address", "network address"),
        ({"network_address": "192.168.50.255/24"}, "network_address", "broadcast address"),
        ({"network_gateway": "192.168.51.1"}, "network_gateway", "outside the subnet 192.168.50.0/24"),
        ({"network_gateway": "192.168.50.11"}, "network_gateway", "own address"),
        ({"network_gateway": "gateway"}, "network_gateway", "not an IPv4 address"),
        ({"network_nameservers": ["dns.example"]}, "network_nameservers", "not an IP address"),
        ({"network_kind": "lte"}, "network_kind", "not one of ethernet, wifi"),
        ({"network_method": "manual"}, "network_method", "not one of static, dhcp"),
        ({"network_backend": "dhcpcd"}, "network_backend", "not one of auto"),
        ({"network_ipv6": "yes"}, "network_ipv6", "not one of auto"),
        ({"network_interface": "eth0; reboot"}, "network_interface", "not an interface name"),
        ({"network_confirm_timeout": 2}, "network_confirm_timeout", "10 to 3600"),
        ({"network_confirm_timeout": "60"}, "network_confirm_timeout", "10 to 3600"),
    ],
)
def test_bad_setting_names_its_field(changes, field, words):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(settings(**changes))
    assert caught.value.field == field
    assert words in caught.value.message


@pytest.mark.parametrize(
    "changes, field, words",
    [
        ({"wifi_ssid": None}, "wifi_ssid", "needs wifi_ssid"),
        ({"wifi_ssid": "x" * 33}, "wifi_ssid", "not a valid SSID"),
        ({"wifi_ssid": "lab\nnet"}, "wifi_ssid", "not a valid SSID"),
        ({"wifi_password_secret": None}, "wifi_password_secret", "needs wifi_password_secret"),
        ({"wifi_password": None}, "wifi_password_secret", "'lab_wifi' was not found"),
        ({"wifi_password": HiddenValue("short")}, "wifi_password_secret", "not a WPA password"),
    ],
)
def test_bad_wifi_setting_names_its_field(changes, field, words):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(wifi(**changes))
    assert caught.value.field == field
    assert words in caught.value.message


def test_short_password_message_does_not_quote_it():
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(wifi(wifi_password=HiddenValue("abc123")))
    assert "abc123" not in str(caught.value)


def test_64_hex_digits_are_a_valid_key():
    assert network_settings(wifi(wifi_password=HiddenValue("ab" * 32))).password == "ab" * 32


def test_classroom_duplicate_address_is_reported_on_the_second_host():
    problems = check_classroom_network(
        [
            ("team1", "team1-main", "10.0.0.5", settings()),
            ("team1", "team1-robot", "10.0.0.6", settings()),
        ]
    )
    assert [(p.team, p.host, p.field) for p in problems] == [("team1", "team1-robot", "network_address")]
    assert "also the network_address of team1-main" in problems[0].message


def test_classroom_address_taken_by_another_hosts_current_address():
    problems = check_classroom_network(
        [
            ("team1", "team1-main", "10.0.0.5", settings(network_address="192.168.50.12/24")),
            ("team1", "team1-robot", "192.168.50.12", settings(network_address="192.168.50.13/24")),
        ]
    )
    assert [(p.host, p.field) for p in problems] == [("team1-main", "network_address")]
    assert "team1-robot is reached at now" in problems[0].message


def test_classroom_reports_each_bad_host_and_passes_good_ones():
    problems = check_classroom_network(
        [
            ("t1", "a", None, settings(network_address="192.168.50.21/24")),
            ("t1", "b", None, settings(network_address="192.168.50.22/24", network_gateway="10.0.0.1")),
            ("t2", "c", None, wifi(network_address="192.168.50.23/24", wifi_password=None)),
            ("t2", "d", None, settings(network_address=None)),
            ("t2", "e", None, None),  # the roster gives it no network
        ]
    )
    assert [(p.team, p.host, p.field) for p in problems] == [
        ("t1", "b", "network_gateway"),
        ("t2", "c", "wifi_password_secret"),
    ]


# Through the roster loader: problems name the file and line, team, host and field.


def load_roster_text(tmp_path, hosts_yaml, secrets_yaml='lab_wifi: "correct horse"\n'):
    import textwrap

    from roslab.roster import load_roster

    secrets = tmp_path / "secrets.yaml"
    secrets.write_text(secrets_yaml)
    secrets.chmod(0o600)
    roster = tmp_path / "lab.yaml"
    roster.write_text(textwrap.dedent(
        """\
        classroom:
          ssh_user: ubuntu
          network_gateway: 192.168.50.1
        teams:
          team1:
            ros_domain_id: 11
            hosts:
        """) + textwrap.indent(textwrap.dedent(hosts_yaml), " " * 6))
    return load_roster(roster)


def test_roster_with_gateway_outside_the_subnet_is_stopped(tmp_path):
    from roslab.roster import RosterError

    with pytest.raises(RosterError) as caught:
        load_roster_text(tmp_path, """\
            team1-main: {role: main, address: 10.0.0.5, network_address: 10.1.0.11/24}
            """)
    message = str(caught.value)
    assert "lab.yaml:3: team 'team1', host 'team1-main', field 'network_gateway'" in message
    assert "192.168.50.1 is outside the subnet 10.1.0.0/24" in message


def test_roster_wifi_host_without_password_secret_is_stopped(tmp_path):
    from roslab.roster import RosterError

    with pytest.raises(RosterError) as caught:
        load_roster_text(tmp_path, """\
            team1-main:
              role: main
              network_address: 192.168.50.11/24
              network_kind: wifi
              wifi_ssid: robolab
            """)
    assert "field 'wifi_password_secret': a wifi host needs wifi_password_secret" in str(caught.value)


def test_roster_wifi_host_with_its_secret_loads(tmp_path):
    classroom = load_roster_text(tmp_path, """\
        team1-main:
          role: main
          network_address: 192.168.50.11/24
          network_kind: wifi
          wifi_ssid: robolab
          wifi_password_secret: lab_wifi
        """)
    assert classroom.hosts[0].data["wifi_password"].unmask() == "correct horse"


# Hostile values: what the network files cannot hold is refused, naming the field.


@pytest.mark.parametrize(
    "ssid",
    ["lab\nnet", "lab\rnet", "lab\tnet", "lab\x00", "\x1b[31mred", "del\x7f", "nel\x85",
     "line\u2028sep", "para\u2029sep", "surrogate\ud800", "x" * 33, "é" * 17],
)
def test_ssid_that_no_file_can_hold_is_refused(ssid):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(wifi(wifi_ssid=ssid))
    assert caught.value.field == "wifi_ssid"
    assert "not a valid SSID" in caught.value.message
    assert "\n" not in caught.value.message and "\x1b" not in caught.value.message


@pytest.mark.parametrize("ssid", [1234, True, ["robolab"], {"a": 1}, 1.5])
def test_ssid_that_yaml_read_as_something_else_is_refused(ssid):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(wifi(wifi_ssid=ssid))
    assert caught.value.field == "wifi_ssid" and "quote it" in caught.value.message


@pytest.mark.parametrize(
    "ssid",
    ['Lab "A" — Café #2', "$(reboot)", "`id`", "it's", "a;b", "-dash", " spaced ", "x" * 32, "é" * 16],
)
def test_awkward_but_legal_ssid_is_kept_exactly(ssid):
    assert network_settings(wifi(wifi_ssid=ssid)).wifi_ssid == ssid


@pytest.mark.parametrize(
    "interface",
    ["eth0\n", "eth0\nrenderer: x", "-eth0", "--help", ".", "..", ".hidden", "eth0;reboot", "$(reboot)",
     "`id`", "eth'0", "eth\x27", 'eth"0', "eth 0", "eth/0", "eth:0", "eth\\0", "x" * 16, "", "é", 5,
     ["eth0"]],
)
def test_interface_that_is_not_a_plain_name_is_refused(interface):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(settings(network_interface=interface))
    assert caught.value.field == "network_interface"
    assert "not an interface name" in caught.value.message


@pytest.mark.parametrize("interface", ["eth0", "wlan0", "enp0s31f6", "br-lab", "eth0.100", "_x", "x" * 15])
def test_plain_interface_names_are_accepted(interface):
    assert network_settings(settings(network_interface=interface)).interface == interface


@pytest.mark.parametrize(
    "password",
    ["Zq9Kx7Wm\n", "Zq9K\nx7Wm", "Zq9K\tx7Wm", "Zq9Kx7Wmä", "Zq9K\x00x7Wm", "\x1b[2JZq9Kx7Wm",
     "Zq9K", "Zq9K" * 16, "ab" * 31 + "zz", 12345678],
)
def test_password_that_is_not_a_wpa_password_is_refused_without_quoting_it(password):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(wifi(wifi_password=HiddenValue(password)))
    assert caught.value.field == "wifi_password_secret"
    message = str(caught.value)
    assert "lab_wifi" in message
    for part in re.split(r"[\x00-\x1f]", str(password)):
        assert len(part) < 4 or part not in message


@pytest.mark.parametrize("password", ["$(reboot) `id`", " spaces at both ends ", "it's \"q\";#=", "Ab" * 32])
def test_awkward_but_legal_password_is_kept_exactly(password):
    assert network_settings(wifi(wifi_password=HiddenValue(password))).password == password


@pytest.mark.parametrize(
    "nameservers",
    [["fe80::1%eth0"], ["fe80::1%\n[connection]"], ["1.1.1.1\nx"], ["1.1.1.1;8.8.8.8"], [5], 5, {"a": 1}],
)
def test_nameserver_that_is_not_a_plain_address_is_refused(nameservers):
    with pytest.raises(NetworkSettingError) as caught:
        network_settings(settings(network_nameservers=nameservers))
    assert caught.value.field == "network_nameservers"


WEIRD_VALUES = [None, "", 0, 1, -1, True, False, 1.5, [], ["x"], [None], {}, {"a": 1}, "x\ny",
                "\ud800", "$(reboot)", HiddenValue("x")]


@pytest.mark.parametrize("key", sorted(set(NETWORK_DEFAULTS) | {"wifi_password", "wifi_ssid"}))
def test_any_value_of_any_key_is_a_setting_error_or_accepted_never_a_crash(key):
    for base in (settings(), wifi(), settings(network_method="dhcp", network_address=None)):
        for value in WEIRD_VALUES:
            try:
                network_settings(replace(base, **{key: value}))
            except NetworkSettingError:
                pass


class Report:
    def __init__(self):
        self.errors = []

    def error(self, message, **where):
        self.errors.append((message, where))


def test_validate_roster_reports_and_never_raises(monkeypatch):
    from types import SimpleNamespace

    from roslab.network import settings as network_settings_module

    hosts = [
        SimpleNamespace(team="t1", name="a", address="10.0.0.5", lines={"wifi_ssid": 7},
                        data=BASE, settings=wifi(wifi_ssid="bad\nssid")),
        SimpleNamespace(team="t1", name="b", address="10.0.0.6", lines={},
                        data=BASE, settings=settings(network_interface=["eth0"], network_address="192.168.50.12/24")),
        SimpleNamespace(team="t1", name="c", address="10.0.0.7", lines={},  # no network: its settings unread
                        data={**BASE, "network_address": None}, settings=None),
    ]
    report = Report()
    network_settings_module.validate_roster(SimpleNamespace(hosts=hosts), report)
    assert [(where["host"], where["field"], where["line"]) for _, where in report.errors] == [
        ("a", "wifi_ssid", 7), ("b", "network_interface", None)]

    def broken(data):
        raise RuntimeError("a bug")

    monkeypatch.setattr(network_settings_module, "network_settings", broken)
    report = Report()
    network_settings_module.validate_roster(SimpleNamespace(hosts=hosts), report)
    assert [where["host"] for _, where in report.errors] == ["a", "b"]
    assert all("a bug" in message for message, _ in report.errors)

    report = Report()
    network_settings_module.validate_roster(SimpleNamespace(hosts=None), report)  # not even a classroom
    assert len(report.errors) == 1 and "could not be checked" in report.errors[0][0]
