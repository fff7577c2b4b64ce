"""Network: each host at its fixed address from the roster, never locked out on the way.

The renderer in charge is read from the host (netplan with systemd-networkd on
Ubuntu Server, NetworkManager on Ubuntu Desktop: keyfiles on 22.04, netplan
files from 23.10 on) unless `network_backend` forces one. The change itself is
the operation `roslab.network.operation.network_in_effect`: staged, validated on the
host, applied detached from SSH, and rolled back by the host itself unless the
controller confirms it at the new address; the rest of the deploy then runs there.
"""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy

from deploy.common import should_run, stop_host, where
from roslab import probe
from roslab import settings as schema
from roslab.network.operation import network_in_effect, network_in_effect_reads
from roslab.network.settings import NetworkSettingError, network_settings
from roslab.host_settings import host_settings

DEFAULTS = schema.defaults("network")


def current_address() -> str:
    """Where pyinfra reaches the host now."""
    return str(host_settings(host).ssh_hostname or host.name)


@deploy("Each host has its fixed address from the roster and is reached there", data_defaults=DEFAULTS)
def network():
    """Write the host's network configuration and move the connection to its new address.

    Reads host_settings(host): network_enabled, network_backend, network_interface, network_kind,
    network_method, network_address, network_prefix, network_gateway, network_nameservers,
    network_ipv6, wifi_ssid, wifi_password_secret, wifi_password (the resolved secret),
    network_confirm_timeout, network_disable_cloud_init, network_backups_keep, ssh_hostname,
    roslab_roster_path.
    """
    typed = host_settings(host)
    if not should_run("network_enabled"):
        return
    try:
        settings = network_settings(typed)
    except NetworkSettingError as error:
        stop_host(f"{where()}: field {error.field!r}: {error.message}; the network was not changed")
        return
    if settings is None:
        host.noop("network left alone: the roster gives this host no network_address")
        return
    target = str(settings.address.ip) if settings.address else "its DHCP address"
    network_in_effect(
        name=f"Ensure the host's {settings.kind} network is configured and it answers at {target}",
        settings=settings,
        current_address=current_address(),
        roster_path=typed.roslab_roster_path,
    )


@probe.reader
def network_reads() -> list:
    """What the network step reads on a host whose network is in place (roslab.probe)."""
    if not should_run("network_enabled"):
        return []
    try:
        settings = network_settings(host_settings(host))
    except NetworkSettingError:
        return []  # the step stops this host, reading nothing
    return network_in_effect_reads(settings) if settings is not None else []
