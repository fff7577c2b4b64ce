"""The ROS snapshot archives (snapshots.ros.org): the ROS apt archive as it was at one sync.

packages.ros.org keeps only the newest version of each package, so a sync moves every new
install; a snapshot keeps a sync's versions (ROS 2 documentation, "Installing from the
snapshot repository"). A snapshot is named by its sync's date (YYYY-MM-DD) or `final` (a
distro's last, after its end of life); its apt source is `<server>/<distro>/<snapshot>/ubuntu`,
suite the Ubuntu codename, component main; snapshots exist for LTS distros only, and they are
signed with a key of their own, not packages.ros.org's (its fingerprint: SNAPSHOTS_FINGERPRINT).

Used by the roster's checks (before any host) and by deploy/ros_apt_source.py (snapshot mode).
"""

from __future__ import annotations

from urllib.parse import urlsplit

from roslab import openpgp

SNAPSHOTS_HOST = "snapshots.ros.org"


def snapshot_url(server: str, distro: str, snapshot: str) -> str:
    """The apt source of a host in snapshot mode (ros_apt_snapshot_url, its distro,
    ros_apt_snapshot): <server>/<distro>/<snapshot>/ubuntu."""
    return f"{server.rstrip('/')}/{distro}/{snapshot}/ubuntu"


def key_problem(server: str, key: bytes) -> str | None:
    """Why `key` (binary) is not the signing key of the snapshot server `server`, or None.

    Only snapshots.ros.org's key is known (the ROS 2 documentation publishes its
    fingerprint); another server (a local mirror that signs its copy itself) is trusted with
    the key the roster names, as mirror mode's is."""
    if urlsplit(server).hostname != SNAPSHOTS_HOST:
        return None
    try:
        found = openpgp.fingerprint(key)
    except openpgp.UnreadableKey as error:
        return f"is not a readable OpenPGP public key: {error}"
    if found != openpgp.SNAPSHOTS_FINGERPRINT:
        return (f"holds the key {openpgp.spaced(found)}, not snapshots.ros.org's "
                f"({openpgp.spaced(openpgp.SNAPSHOTS_FINGERPRINT)})")
    return None
