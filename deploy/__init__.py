"""roslab's pyinfra deploys, one module per concern.

`ALL_DEFAULTS` merges every deploy's DEFAULTS: the complete set of settings a
roster may use (the roster validator rejects any other key).
"""

from __future__ import annotations

import importlib

# In the order deploy.py runs them.
DEPLOY_MODULES = (
    "common",  # shared settings (login_user) and the supported-host check
    "apt_ready",
    "locale",
    "ros_apt_source",
    "ros_install",
    "rosdep",
    "shell_env",
    "ssh_identity",
    "network",
    "workspace",
)


def _collect_defaults() -> dict:
    merged: dict = {}
    for name in DEPLOY_MODULES:
        module = importlib.import_module(f"deploy.{name}")
        for key, value in module.DEFAULTS.items():
            if key in merged:
                raise RuntimeError(f"setting {key!r} is defined by two deploys")
            merged[key] = value
    return merged


ALL_DEFAULTS = _collect_defaults()
