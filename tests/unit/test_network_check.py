"""Network settings checks: every bad input is named by its field, and good input parses."""

from __future__ import annotations

from ipaddress import IPv4Address, IPv4Interface

import pytest
from pyinfra.api import HiddenValue

from deploy.network import DEFAULTS as NETWORK_DEFAULTS
from roslab.netcheck import (
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
    return {**BASE, **changes}


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
            ("team1", "team1-main", settings(address="10.0.0.5")),
            ("team1", "team1-robot", settings(address="10.0.0.6")),
        ]
    )
    assert [(p.team, p.host, p.field) for p in problems] == [("team1", "team1-robot", "network_address")]
    assert "also the network_address of team1-main" in problems[0].message


def test_classroom_address_taken_by_another_hosts_current_address():
    problems = check_classroom_network(
        [
            ("team1", "team1-main", settings(network_address="192.168.50.12/24", address="10.0.0.5")),
            ("team1", "team1-robot", settings(network_address="192.168.50.13/24", address="192.168.50.12")),
        ]
    )
    assert [(p.host, p.field) for p in problems] == [("team1-main", "network_address")]
    assert "team1-robot is reached at now" in problems[0].message


def test_classroom_reports_each_bad_host_and_passes_good_ones():
    problems = check_classroom_network(
        [
            ("t1", "a", settings(network_address="192.168.50.21/24")),
            ("t1", "b", settings(network_address="192.168.50.22/24", network_gateway="10.0.0.1")),
            ("t2", "c", wifi(network_address="192.168.50.23/24", wifi_password=None)),
            ("t2", "d", settings(network_address=None)),
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
