"""The classroom's apt cache: each .deb downloaded once for the class, not once per Pi.

`apt_cache_server` installs apt-cacher-ng (Debian's and Ubuntu's, in universe) on the host
`apt_cache_host` names. `apt_cache_client` makes every host (the cache host too) ask it
first: apt's `Acquire::http::Proxy-Auto-Detect` runs a small managed script that prints
the cache's address when its port answers within a couple of seconds, else `DIRECT`, so
apt downloads from the source itself and a cache that is down never fails a run. Only
http:// sources go through it (packages.ros.org and Ubuntu's archives are http; an https
source is tunnelled at best and cached never, so apt's https settings are left alone).

deploy.py runs the server part before every other step: pyinfra runs each operation on
all hosts before the next, so the cache answers before any host's first `apt-get update`.
The cache host's own apt needs universe and fresh lists for apt-cacher-ng first; it gets
them here, the first time only.

With `offline: true` the cache serves only what it holds (apt-cacher-ng's Offlinemode)
and the script never says DIRECT: no host downloads from upstream.
"""

from __future__ import annotations

import shlex
import threading
from io import StringIO

from pyinfra import host, logger, state
from pyinfra.api import deploy
from pyinfra.facts.deb import DebPackages
from pyinfra.facts.files import File
from pyinfra.facts.server import Command
from pyinfra.operations import apt, files, systemd

from deploy.common import ubuntu_codename, should_run, stop_host, where
from roslab import probe, settings
from roslab.ros.distro import DistroError, codename_for
from roslab.ops.apt import (
    apt_install_options,
    apt_lists_updated,
    packages_downloaded,
    packages_downloaded_reads,
    ubuntu_apt_sources,
)
from roslab.quoting import shell_word
from roslab.templating import render
from roslab.host_settings import HostSettings, host_settings, peer_settings

DEFAULTS = settings.defaults("apt_cache")

PACKAGE = "apt-cacher-ng"
SERVICE = "apt-cacher-ng"
# apt-cacher-ng reads every *.conf in its directory, in order: this one sorts last.
SERVER_CONFIG = "/etc/apt-cacher-ng/zz-roslab.conf"
DETECT_SCRIPT = "/usr/local/lib/roslab/apt-proxy-detect"
PROXY_CONFIG = "/etc/apt/apt.conf.d/01-roslab-proxy"
# Seconds the script waits for the cache's port: apt runs it once per server it contacts.
DETECT_TIMEOUT = 2

_warned_lock = threading.Lock()
_warned: set[str] = set()


def cache_address(cache_host: str) -> str | None:
    """Where the hosts reach the cache host: its address in the roster (after a move, the new one)."""
    for entry in host_settings(host).roslab_classroom_hosts or []:
        if entry.get("name") == cache_host:
            return entry.get("address") or cache_host
    return None


def proxy_url(address: str, port: int) -> str:
    return f"http://[{address}]:{port}/" if ":" in address else f"http://{address}:{port}/"


def cache_in_this_run(cache_host: str) -> bool:
    """True when this run reaches the cache host: it is converged (and its cache started)
    before any host's apt needs it."""
    return any(((typed := peer_settings(other)) is not None and typed.roslab_hostname or other.name) == cache_host
               for other in state.active_hosts)


@deploy("The classroom's apt cache runs on apt_cache_host", data_defaults=DEFAULTS)
def apt_cache_server():
    """Install and run apt-cacher-ng on the host apt_cache_host names (no other host).

    Reads host_settings(host): apt_cache_enabled, apt_cache_host, apt_cache_port, apt_cache_upstream_ports,
    offline, apt_enable_universe, apt_extra_suites, apt_lock_timeout, roslab_hostname.
    """
    typed = host_settings(host)
    if not should_run("apt_cache_enabled") or not typed.apt_cache_host:
        return
    if typed.apt_cache_host != (typed.roslab_hostname or host.name):
        return
    lock_timeout = typed.apt_lock_timeout
    if PACKAGE not in (host.get_fact(DebPackages) or {}):
        # apt-cacher-ng is in universe: the cache host's apt gets it before apt_ready runs.
        if not typed.apt_enable_universe:
            stop_host(f"{where()}: apt_cache_host needs the universe component for {PACKAGE}, but "
                      "apt_enable_universe is false; nothing was changed on it")
            return
        ubuntu_apt_sources(
            name="Ensure the Ubuntu apt sources enable universe (the apt cache's package is there)",
            codename=ubuntu_codename(),
            components=["universe"],
            suites=list(typed.apt_extra_suites),
        )
        apt_lists_updated(
            name=f"Ensure the apt lists are fresh before {PACKAGE} is installed",
            lock_timeout=lock_timeout,
        )
    apt.packages(
        name=f"Ensure {PACKAGE} is installed",
        packages=[PACKAGE],
        extra_install_args=apt_install_options(lock_timeout),
    )
    config = files.put(
        name=f"Ensure {PACKAGE} listens on port {typed.apt_cache_port} and may fetch from "
             f"ports {', '.join(map(str, typed.apt_cache_upstream_ports))}",
        src=StringIO(render(
            "apt-cacher-ng-roslab.conf.j2",
            port=typed.apt_cache_port,
            upstream_ports=[int(port) for port in typed.apt_cache_upstream_ports],
            offline=typed.offline,
        )),
        dest=SERVER_CONFIG,
        mode="644",
    )
    systemd.service(
        name=f"Ensure {SERVICE} is running and enabled",
        service=SERVICE,
        running=True,
        enabled=True,
    )
    systemd.service(
        name=f"Ensure {SERVICE} runs with the changed configuration",
        service=SERVICE,
        restarted=True,
        _if=config.did_change,
    )


@deploy("apt downloads through the classroom's apt cache, or directly while it does not answer",
        data_defaults=DEFAULTS)
def apt_cache_client():
    """Make apt use the classroom's apt cache as its proxy, with a fallback to direct downloads.

    Reads host_settings(host): apt_cache_enabled, apt_cache_host, apt_cache_port, offline,
    roslab_classroom_hosts.
    """
    typed = host_settings(host)
    if not should_run("apt_cache_enabled"):
        return
    cache_host = typed.apt_cache_host
    if not cache_host:
        if host.get_fact(File, path=PROXY_CONFIG):  # left by a roster that had a cache
            files.file(
                name="Ensure apt uses no classroom apt cache (apt_cache_host is not set)",
                path=PROXY_CONFIG,
                present=False,
            )
        return
    address = cache_address(cache_host)
    if address is None:  # the roster check refuses this; a hand-made inventory may not
        stop_host(f"{where()}: apt_cache_host {cache_host!r} is not a host of this roster; "
                  "nothing was changed on it")
        return
    port = typed.apt_cache_port
    offline = typed.offline
    files.put(
        name="Ensure the apt proxy script finds the classroom's apt cache (or DIRECT when it is down)",
        src=StringIO(render(
            "apt-proxy-detect.sh.j2",
            cache_host=cache_host,
            address=shell_word(address),
            port=shell_word(str(port)),
            proxy=shell_word(proxy_url(address, port)),
            timeout=DETECT_TIMEOUT,
            offline=offline,
        )),
        dest=DETECT_SCRIPT,
        mode="755",
        create_remote_dir=True,
    )
    files.put(
        name=f"Ensure apt asks the classroom's apt cache on {cache_host} first",
        src=StringIO(render("apt-proxy.conf.j2", cache_host=cache_host, script=DETECT_SCRIPT,
                            offline=offline)),
        dest=PROXY_CONFIG,
        mode="644",
    )
    if not cache_in_this_run(cache_host):
        report_cache_down(cache_host, address, port, offline)


def report_cache_down(cache_host: str, address: str, port: int, offline: bool) -> None:
    """Say (once per run) that the cache does not answer and what apt does instead."""
    probe = (f"timeout {DETECT_TIMEOUT} bash -c 'exec 3<>\"/dev/tcp/$0/$1\"' "
             f"{shlex.quote(address)} {shlex.quote(str(port))} 2>/dev/null && echo up || echo down")
    if host.get_fact(Command, command=probe) == "up":
        return
    with _warned_lock:
        if cache_host in _warned:
            return
        _warned.add(cache_host)
    if offline:
        logger.warning(f"roslab: the apt cache on {cache_host} ({address}:{port}) does not answer and "
                       "offline is set: apt has nothing to download from until it is back")
    else:
        logger.warning(f"roslab: the apt cache on {cache_host} ({address}:{port}) does not answer: "
                       "hosts download from upstream directly this run")


def planned_packages(typed: HostSettings, codename: str, python_sdist: bool = False) -> list[str]:
    """The packages roslab's steps install on a host with these typed settings and Ubuntu
    codename (`python_sdist`: this run noted an sdist in its wheelhouse): what the class cache
    is filled with before anyone installs.

    Each step declares its packages once, beside itself (`@probe.installs`); this asks them
    all. Every deploy module is imported first, so the list does not depend on which of them
    the caller happened to import.
    """
    import importlib
    import pkgutil

    import deploy as deploy_package

    for module in pkgutil.iter_modules(deploy_package.__path__):
        importlib.import_module(f"deploy.{module.name}")
    return probe.declared_packages(typed, codename, python_sdist)


def _planned_for(some_host, codename: str) -> list[str]:
    """The packages a host of this run will install: from its typed settings (every deploy's
    default under what its data sets), and this run's note read now, not host_settings'
    snapshot (python_env notes `_roslab_python_sdist` on its data as it plans). A host whose
    data is wrong installs nothing: it stops itself (deploy.common.supported_host)."""
    typed = peer_settings(some_host)
    if typed is None:
        return []
    return planned_packages(typed, codename, bool(some_host.data.get("_roslab_python_sdist")))


def _codename_of(typed: HostSettings) -> str | None:
    try:
        return codename_for(typed.ubuntu_release)
    except DistroError:
        return None  # that host is stopped by supported_host before it installs anything


def release_peers() -> list:
    """The hosts in this run that install through the same cache as this host and run the
    same Ubuntu release as the roster says, in inventory order (this host included)."""
    cache_host, codename = host_settings(host).apt_cache_host, _codename_of(host_settings(host))
    return [
        other for other in state.inventory
        if other in state.active_hosts and (typed := peer_settings(other)) is not None
        and typed.apt_cache_enabled and typed.apt_cache_host == cache_host
        and _codename_of(typed) == codename
    ]


def updates_through_the_class_cache() -> bool:
    """True on a host whose apt asks the class cache in this run."""
    typed = host_settings(host)
    return bool(should_run("apt_cache_enabled") and typed.apt_cache_host
                and cache_in_this_run(typed.apt_cache_host))


def fills_the_class_cache() -> bool:
    """True on the one host per release that fills the class cache (the first in the roster)."""
    if not updates_through_the_class_cache():
        return False  # no cache, or the hosts download directly this run: there is nothing to fill
    peers = release_peers()
    return bool(peers) and peers[0].name == host.name  # `host` is pyinfra's context proxy


@deploy("The classroom's apt cache holds each release's packages before the class installs them",
        data_defaults=DEFAULTS)
def apt_cache_filled():
    """Download (not install) every package the class's hosts of this host's release will
    install, on the first such host in the roster only, one release after the other.

    apt-cacher-ng fetches a file that several clients miss in the same instant once per
    client: with 12 hosts installing together, 41 of 204 .debs went upstream 2 to 5 times.
    Filled first, by one host per release and one release at a time (`_serial`: the
    releases share arch-independent .debs), the cache answers every other host's install
    from what it holds, so each .deb is downloaded once for the class. The filling host
    installs its own packages from what it downloaded here.

    Reads host_settings(host): apt_cache_enabled, apt_cache_host, apt_lock_timeout, ubuntu_release;
    of every host in the run on the same cache and release: apt_cache_enabled,
    apt_cache_host, ubuntu_release, locale_enabled, ros_install_enabled, ros_distro,
    ros_variant, ros_variant_main, ros_variant_robot, ros_dev_tools, ros_extra_packages,
    roslab_role, ssh_identity_enabled.
    """
    if not fills_the_class_cache():
        return
    codename = ubuntu_codename()
    packages = sorted({name for peer in release_peers()
                       for name in _planned_for(peer, codename)})
    if not packages:
        return
    packages_downloaded(
        name=f"Ensure the classroom's apt cache holds the packages of every Ubuntu {codename} host "
             f"({len(packages)} packages and their dependencies, downloaded here once)",
        packages=packages,
        installed_here=_planned_for(host, codename),
        lock_timeout=host_settings(host).apt_lock_timeout,
        _serial=True,
    )


@probe.reader
def apt_cache_filled_reads() -> list:
    """What apt_cache_filled's operation reads on a host that needs no change (roslab.probe)."""
    return packages_downloaded_reads() if fills_the_class_cache() else []


@probe.reader
def apt_cache_reads() -> list:
    """What apt_cache_server's and apt_cache_client's operations read on a host that needs
    no change (roslab.probe)."""
    if not should_run("apt_cache_enabled"):
        return []
    cache_host = host_settings(host).apt_cache_host
    if not cache_host:
        return [probe.read(File, path=PROXY_CONFIG)]
    reads = [*probe.put_reads(DETECT_SCRIPT), *probe.put_reads(PROXY_CONFIG)]
    if cache_host == host.name:
        reads += [*probe.packages_reads(), *probe.put_reads(SERVER_CONFIG),
                  *probe.service_reads(f"{SERVICE}.service")]
    return reads
