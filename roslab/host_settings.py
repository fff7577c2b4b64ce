"""A host's settings as the deploys read them: typed (`HostSettings`, generated from the schema
into roslab/host_fields.py) and built once per host per run.

    from roslab.host_settings import host_settings
    settings = host_settings(host)
    settings.apt_lock_timeout       # int
    settings.roslab_profile         # ResolvedProfile | None (a frozen dataclass)

The roster loader has checked every value (type and format) and merged every default into
the host's data; a hand-made inventory or pyinfra's `--data` may give anything, so the types
are checked here once, and a wrong one is one error naming the host and the key. A deploy
setting a host's data lacks gets its schema default: what the deploy's `data_defaults`
(`settings.defaults(concern)`) would have given it, so the result does not depend on which
deploy asks first.
"""

from __future__ import annotations

import copy
import dataclasses
import weakref
from collections.abc import Mapping
from typing import Any

from pyinfra.context import ContextObject

from roslab import host_rules, settings
from roslab.host_fields import HostSettings
from roslab.profiles.devices import rules_text_problem
from roslab.profiles.resolve import ResolvedProfile

__all__ = ["HostSettings", "HostSettingsError", "host_settings", "peer_settings", "settings_of", "updated"]


class HostSettingsError(ValueError):
    """A host's data holds a value of the wrong type (a hand-made inventory, `--data`)."""


# One HostSettings per pyinfra Host: a no-op run is measured per host (issue 32), so the data
# layers are merged once, not once per deploy or per key. Keyed weakly: a run's hosts go with it.
_BUILT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def host_settings(host) -> HostSettings:
    """The typed settings of `host` (pyinfra's Host, or its `host` context proxy), built on the
    first call of the run from `host.data`. Raises HostSettingsError on a wrong-typed value."""
    real = host._get_module() if isinstance(host, ContextObject) else host
    built = _BUILT.get(real)
    if built is None:
        built = _BUILT[real] = settings_of(real.name, real.data.dict())
    return built


def peer_settings(other) -> HostSettings | None:
    """Another host's settings, for a deploy that looks at the run's other hosts (the apt cache,
    the underlay's builder); None when its data is wrong: that host stops itself on it
    (deploy.common.supported_host), it never stops this one."""
    try:
        return host_settings(other)
    except HostSettingsError:
        return None


def _problem(value, kind: type, item: type | None = None) -> str | None:
    problem = settings.type_problem(value, kind)
    if problem is None and kind is list and item is not None:
        problem = next((f"item {index + 1}: {inner}" for index, element in enumerate(value)
                        if (inner := settings.type_problem(element, item))), None)
    elif problem is None and kind is dict and item is not None:
        problem = next((f"{key!r}: {inner}" for key, element in value.items()
                        if (inner := settings.type_problem(key, str) or settings.type_problem(element, item))),
                       None)
    return problem


# What settings_of checks of each setting, worked out once: every host's settings are built in
# a roster's check (issue 41 measures it per host), so the common case (each value exactly of its
# type) is a few comprehensions; a value that fails them is judged again by _problem, which words it.
_CHECKS = {s.key: (s.kind, str if s.kind is dict else s.item, s.nullable or s.concern in settings.ROSTER_CONCERNS)
           for s in settings.HOST_SETTINGS}
# pyinfra's own defaults for the connection's keys: None here, as in settings.defaults()
_DEFAULTS = [(s.key, None if s.concern in settings.ROSTER_CONCERNS else s.default) for s in settings.HOST_SETTINGS]
_MUTABLE = frozenset(key for key, default in _DEFAULTS if isinstance(default, (list, dict)))  # copied per host
_SCALARS = [(kind, [key for key, (k, _, none) in _CHECKS.items() if k is kind and none is may_be_none], may_be_none)
            for kind in (str, int, bool) for may_be_none in (False, True)]
_CONTAINERS = [key for key, (kind, _, _) in _CHECKS.items() if kind in (list, dict)]
_EMPTY = {key: _CHECKS[key][0]() for key in _CONTAINERS}  # [] or {}: nothing to look into
_ORDER = {key: index for index, key in enumerate(_CHECKS)}
_HOST_KEYS = [(key.key, key.kind) for key in settings.HOST_KEYS]
_FIELDS = frozenset(field.name for field in dataclasses.fields(HostSettings))
assert _FIELDS == {*_CHECKS, *(key.key for key in settings.HOST_KEYS)}, "roslab/host_fields.py is stale"


def _plainly(value, kind: type, item: type | None) -> bool:
    """Whether a list or mapping is exactly of `kind`, its items exactly of `item`."""
    if kind is list:
        return type(value) is list and set(map(type, value)) <= {item}
    return type(value) is dict and set(map(type, value)) <= {str} and set(map(type, value.values())) <= {item}


def _suspects(values: dict[str, Any]) -> list[str]:
    """The settings whose values are not plainly of their type (what _problem then judges), in
    the schema's order."""
    found = [key for kind, keys, may_be_none in _SCALARS for key in keys
             if type(values[key]) is not kind and not (may_be_none and values[key] is None)]
    found += [key for key in _CONTAINERS if not (values[key] is None and _CHECKS[key][2])
              and not (values[key] == _EMPTY[key] or _plainly(values[key], *_CHECKS[key][:2]))]
    return sorted(found, key=_ORDER.__getitem__) if found else found


def settings_of(name: str, data: Mapping[str, Any]) -> HostSettings:
    """A host's typed settings from its data (a pyinfra host's `data.dict()` or a roster host's
    dict): the schema's defaults under it, every value's type checked."""
    values: dict[str, Any] = {key: data[key] if key in data else copy.deepcopy(default) if key in _MUTABLE else default
                              for key, default in _DEFAULTS}
    problems: list[str] = []
    for key in _suspects(values):
        kind, item, may_be_none = _CHECKS[key]
        problem = "must not be null" if values[key] is None else _problem(values[key], kind, item)
        if problem:
            problems.append(f"{key} {problem}")
    for key, kind in _HOST_KEYS:
        value = values[key] = data.get(key)
        problem = None if value is None or type(value) is kind else settings.type_problem(value, kind)
        if problem:
            problems.append(f"{key} {problem}")
    profile = values["roslab_profile"]
    if isinstance(profile, Mapping):
        try:
            values["roslab_profile"] = ResolvedProfile.from_data(profile)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            problems.append(f"roslab_profile is not a resolved profile ({type(error).__name__}: {error})")
        else:
            rules = values["roslab_profile"].udev_rules
            rules_problem = rules_text_problem(rules) if isinstance(rules, str) else "udev_rules is not text"
            if rules_problem:
                problems.append(f"roslab_profile: {rules_problem}")
    if "roslab_roster_path" not in data:  # a hand-made inventory: the rules a roster's values meet
        merged = {**settings.defaults(), **data}
        problems.extend(f"{key}: {problem}" for key, problem in host_rules.hand_made_problems(data, merged)
                        if not any(shown.startswith(f"{key} ") for shown in problems))
    if problems:
        raise HostSettingsError(f"host {name}: {'; '.join(problems)} (in its inventory data or pyinfra's --data)")
    return _built(values)


def updated(typed: HostSettings, values: Mapping[str, Any]) -> HostSettings:
    """`typed` with `values` in place of some fields' (what the roster loader derives after a
    host's settings were first read: its team's assigned domain, the classroom's host lists).
    The loader made them, so they are not checked again here."""
    unknown = set(values) - _FIELDS
    if unknown:
        raise TypeError(f"not fields of HostSettings: {', '.join(sorted(unknown))}")
    return _built({**vars(typed), **values})


def _built(values: dict[str, Any]) -> HostSettings:
    """HostSettings of `values` (one per field, _FIELDS): its fields set as dataclass's frozen
    __init__ would set them, without its 160 object.__setattr__ calls (a third of settings_of)."""
    typed = object.__new__(HostSettings)
    typed.__dict__.update(values)
    return typed
