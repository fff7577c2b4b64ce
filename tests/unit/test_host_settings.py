"""A host's typed settings (roslab.host_settings): what the deploys read instead of host.data."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest
from pyinfra.api import Inventory

from roslab import host_settings as typed
from roslab import settings
from roslab.profiles.resolve import ResolvedProfile
from roslab.roster import inventory_groups, load_roster

REPO = Path(__file__).resolve().parents[2]
ROSTERS = [REPO / "inventories" / "lab.yaml", Path(__file__).parent / "rosters" / "two_teams.yaml"]


def roster_inventory(path: Path) -> Inventory:
    groups = inventory_groups(load_roster(path))
    hosts = {name: data for entries in groups.values() for name, data in entries}
    return Inventory((list(hosts.items()), {}))


@pytest.mark.parametrize("path", ROSTERS, ids=lambda path: path.name)
def test_the_typed_settings_of_a_roster_host_are_its_data(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    inventory = roster_inventory(path)
    assert len(inventory) > 1
    for host in inventory:
        data = host.data.dict()
        built = typed.host_settings(host)
        for item in fields(built):
            if item.name == "roslab_profile":
                continue
            assert getattr(built, item.name) == data.get(item.name), (host.name, item.name)
        assert isinstance(built.roslab_profile, ResolvedProfile)
        assert built.roslab_profile.name == data["roslab_profile"]["name"]
        assert built.roslab_profile.packages == data["roslab_profile"]["packages"]
        assert built.roslab_role in ("main", "robot") and built.roslab_hostname == host.name


def test_a_deploy_setting_missing_from_a_hand_made_inventory_is_its_default():
    inventory = Inventory(([("pi", {"ssh_user": "lab"})], {}))
    built = typed.host_settings(inventory.get_host("pi"))
    assert built.apt_lock_timeout == settings.SETTINGS["apt_lock_timeout"].default
    assert built.apt_extra_suites == ["updates", "backports"]
    assert built.ssh_user == "lab"
    assert built.ssh_port is None  # a connection key: pyinfra's own default, not the schema's
    assert built.roslab_profile is None and built.roslab_team is None


@pytest.mark.parametrize("data, override, expected", [
    ({"apt_lock_timeout": "600"}, {}, "host pi: apt_lock_timeout must be an integer, not '600' (remove the quotes)"),
    ({}, {"ssh_port": "22"}, "host pi: ssh_port must be an integer, not '22'"),
    ({}, {"manage_hostname": "no"}, "host pi: manage_hostname must be true or false, not 'no'"),
    ({"apt_extra_suites": ["updates", 3]}, {}, "host pi: apt_extra_suites item 2: must be a string, not 3"),
    ({"ros_environment": {"LAB_NAME": 1}}, {}, "host pi: ros_environment 'LAB_NAME': must be a string, not 1"),
    ({"locale": None}, {}, "host pi: locale must not be null"),
    ({"roslab_team_hosts": "team1"}, {}, "host pi: roslab_team_hosts must be a list, not 'team1'"),
    ({"roslab_profile": {"name": "demo"}}, {}, "host pi: roslab_profile is not a resolved profile (KeyError"),
])
def test_a_wrong_type_from_a_hand_made_inventory_or_data_is_one_error_naming_host_and_key(data, override, expected):
    inventory = Inventory(([("pi", data)], {}), override_data=override)
    with pytest.raises(typed.HostSettingsError) as raised:
        typed.host_settings(inventory.get_host("pi"))
    message = str(raised.value)
    assert message.startswith(expected), message
    assert message.count("host pi") == 1 and "--data" in message


def test_two_wrong_values_are_named_in_one_error():
    inventory = Inventory(([("pi", {"apt_lock_timeout": True, "locale": 5})], {}))
    with pytest.raises(typed.HostSettingsError, match="apt_lock_timeout must be an integer.*; locale must be a string"):
        typed.host_settings(inventory.get_host("pi"))


def test_settings_are_built_once_per_host_per_run(monkeypatch):
    built = []
    original = typed.settings_of
    monkeypatch.setattr(typed, "settings_of", lambda name, data: built.append(name) or original(name, data))
    inventory = Inventory(([("pi1", {}), ("pi2", {"locale": "de_DE.UTF-8"})], {}))
    pi1, pi2 = inventory.get_host("pi1"), inventory.get_host("pi2")
    for _ in range(3):
        assert typed.host_settings(pi1).locale == "en_US.UTF-8"
        assert typed.host_settings(pi2).locale == "de_DE.UTF-8"
    assert built == ["pi1", "pi2"]
    assert typed.host_settings(pi1) is typed.host_settings(pi1)


def test_the_context_host_and_the_host_share_one_build():
    from pyinfra import host
    from pyinfra.context import ctx_host

    inventory = Inventory(([("pi", {})], {}))
    pi = inventory.get_host("pi")
    with ctx_host.use(pi):
        assert typed.host_settings(host) is typed.host_settings(pi)


def test_the_settings_are_frozen():
    built = typed.host_settings(Inventory(([("pi", {})], {})).get_host("pi"))
    with pytest.raises(AttributeError):
        built.locale = "C.UTF-8"


def test_another_hosts_wrong_data_is_none_for_its_peers_not_an_error():
    inventory = Inventory(([("pi1", {}), ("pi2", {"apt_cache_port": "3142"})], {}))
    assert typed.peer_settings(inventory.get_host("pi1")).apt_cache_port == 3142
    assert typed.peer_settings(inventory.get_host("pi2")) is None


@pytest.mark.parametrize("concern", ["locale", "apt_cache", "workspace"])
def test_the_settings_are_the_same_whichever_deploy_asks_first(concern):
    """pyinfra overlays a @deploy's data_defaults on host data while it runs; the typed
    settings have the schema's defaults under them anyway, so the first asker does not matter."""
    data = {"ssh_user": "lab", "locale": "de_DE.UTF-8"}
    outside = typed.host_settings(Inventory(([("pi", data)], {})).get_host("pi"))
    inside_host = Inventory(([("pi", data)], {})).get_host("pi")
    inside_host.current_deploy_data = settings.defaults(concern)
    inside = typed.host_settings(inside_host)
    assert inside == outside
    assert inside.locale == "de_DE.UTF-8" and inside.apt_cache_port == 3142


@pytest.mark.parametrize("rule", [
    'SUBSYSTEM=="tty", ATTR{dev}=="4:*", MODE="0666"',  # every virtual console
    'SUBSYSTEM=="input", KERNEL=="*e*", MODE="0666"',  # every keyboard
    'SUBSYSTEM=="tty", KERNEL=="ttyAMA0", ENV{ROSLAB_DEVICE}="uart", RUN+="/bin/sh -c id"',
    'SUBSYSTEM=="tty", ATTRS{idVendor}=="10c4", ATTRS{idProduct}=="ea60", ENV{ROSLAB_DEVICE}="x", GROUP="disk"',
])
def test_hand_made_profile_data_carries_only_rules_roslab_writes_from_devices(rule):
    """A hand-made inventory or --data may bring a resolved profile: its udev rules are read back
    as roslab writes them from a profile's devices, and rule text of its own is refused."""
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    profile, _ = resolve_host(builtin_profiles()["turtlebot3"], {"turtlebot3_model": "burger", "lds_model": "LDS-03"},
                              distro="jazzy", role="robot")
    good = Inventory(([("pi", {"roslab_profile": profile})], {}))
    assert "tb3_lidar" in typed.host_settings(good.get_host("pi")).roslab_profile.udev_rules
    inventory = Inventory(([("pi", {"roslab_profile": {**profile, "udev_rules": profile["udev_rules"] + rule + "\n"}})],
                           {}))
    with pytest.raises(typed.HostSettingsError, match="roslab_profile: line 9 of its udev rules is not one roslab "
                                                      "writes from a profile's devices"):
        typed.host_settings(inventory.get_host("pi"))


@pytest.mark.parametrize("key", ["wifi_password", "console_password"])
def test_a_password_given_as_plain_text_stays_out_of_the_settings_repr(key):
    """The roster loader gives the passwords as masked Secrets; a hand-made inventory or --data
    may give plain text, and a HostSettings shown in a traceback or a log must not carry it."""
    built = typed.settings_of("pi", {key: "correct horse battery"})
    assert getattr(built, key) == "correct horse battery"
    assert "correct horse" not in repr(built) and "ssh_user" in repr(built)
