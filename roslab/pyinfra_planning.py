"""pyinfra's planning of an operation, without the costs that made each host cost like the first.

pyinfra runs deploy.py once per host, and for every operation, @deploy and fact on every
host it does work that costs far more CPU than its result needs: on a converged class's
no-op re-run that was most of the controller's CPU, and it grew with every host (issue 32).
Five of pyinfra 3.10's functions are replaced by exact equivalents:

1. `pyinfra.api.util.get_operation_order_from_stack`: in CLI mode pyinfra orders operations
   by the line numbers of the call stack from deploy.py inwards, leaving out pyinfra's own
   frames. It takes them from `inspect.stack()`, which also reads each frame's line of
   source (`findsource`, `linecache`) and, for frames whose file does not exist (gevent's,
   runpy's frozen code), scans every module in `sys.modules` (`getmodule`): about half of a
   no-op's CPU. `get_operation_order_from_stack` below walks `frame.f_back` and takes, for
   each frame, exactly what `inspect.getframeinfo` reports as its filename and line, with
   no source context:
   - filename: the code object's `co_filename`. `inspect.getsourcefile` differs from it
     only for a `co_filename` ending in a bytecode suffix (`.pyc`, a sourceless module);
     such a frame is handed to `inspect.getframeinfo` itself;
   - line: the start line of the frame's current instruction in `co_positions()` (as
     `inspect._get_code_position`), or `f_lineno` where the instruction has none.
2. `pyinfra.api.arguments.all_global_arguments`: `typing.get_type_hints` of the fixed
   `AllArguments` TypedDict, evaluated again for every operation, @deploy and fact on every
   host. `all_global_arguments` below evaluates it once and hands out a new list of the same
   pairs each time.
3. `pyinfra.api.operation.signature` (inspect's), read for every operation on every host only to
   bind its arguments: `operation_signature` below reads each function's once.
4. `pyinfra.api.arguments.pop_global_arguments`, called for every operation, @deploy and
   fact on every host: for each of its ~30 global arguments (`_sudo`, `_serial`, ...) it
   asks `host.data`, and each ask calls all five data layers again (override, host, the
   host's groups merged anew, the inventory's, the @deploy's defaults) and searches them.
   `pop_global_arguments` below is pyinfra's, line for line, except that it calls the five
   layers once per call and searches those, as `HostData.__getattr__` does (first layer
   holding the key, a shallow copy of its value). Nothing in the loop can change a layer:
   it runs only pyinfra's argument defaults and `generate_env`.
5. `pyinfra.api.connectors.get_all_connectors`, as `pyinfra.api.inventory` and `pyinfra.api.host`
   call it (also through `get_execution_connectors` and `get_execution_connector`): it reads
   every installed distribution's entry points again on each call (`importlib.metadata`,
   about 7 ms), four times before the first host is contacted. `all_connectors` below reads
   them once per run (what is installed does not change during a run) and hands out a new
   dict of the same connectors each time.

`install()` puts them in place of pyinfra's, in the modules that call them, only for the
pyinfra version they were checked against (`CHECKED_PYINFRA`, the pin in pyproject.toml;
tests/unit/test_pyinfra_planning.py compares them with pyinfra's own on real nested deploy
call stacks and fails when the pin moves). Any other pyinfra keeps its own functions.

Diagnostic switch: `ROSLAB_PYINFRA_PLANNING=pyinfra` in the environment keeps pyinfra's own
functions (the plan is the same; only the controller's CPU differs). bench/noop_rerun.py
measures both.
"""

from __future__ import annotations

import copy
import importlib
import importlib.machinery
import inspect
import itertools
import os
import sys
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from types import FrameType

import pyinfra
from pyinfra.api import arguments as pyinfra_arguments
from pyinfra.api import facts as pyinfra_facts
from pyinfra.api import connectors as pyinfra_connectors
from pyinfra.api import host as pyinfra_host
from pyinfra.api import inventory as pyinfra_inventory
from pyinfra.api import util as pyinfra_util
from pyinfra.api.host import extract_callable_datas
from pyinfra.context import ctx_config

# The module, not the `operation` decorator that pyinfra.api exports under the same name.
pyinfra_operation = importlib.import_module("pyinfra.api.operation")

# The pyinfra release whose functions this module reproduces.
CHECKED_PYINFRA = "3.10.0"
# The diagnostic switch: "pyinfra" keeps pyinfra's own functions.
SWITCH = "ROSLAB_PYINFRA_PLANNING"
USE_PYINFRA = "pyinfra"

# What inspect.getsourcefile maps to a source name: a co_filename ending in one of these.
BYTECODE_SUFFIXES = tuple(importlib.machinery.DEBUG_BYTECODE_SUFFIXES
                          + importlib.machinery.OPTIMIZED_BYTECODE_SUFFIXES)

# pyinfra's functions, kept before install() replaces them.
pyinfra_get_operation_order_from_stack = pyinfra_util.get_operation_order_from_stack
pyinfra_all_global_arguments = pyinfra_arguments.all_global_arguments
pyinfra_pop_global_arguments = pyinfra_arguments.pop_global_arguments
pyinfra_get_all_connectors = pyinfra_connectors.get_all_connectors
pyinfra_get_execution_connectors = pyinfra_connectors.get_execution_connectors
pyinfra_get_execution_connector = pyinfra_connectors.get_execution_connector
# The modules that call pop_global_arguments by the name they imported.
POP_GLOBAL_ARGUMENTS_CALLERS = ("pyinfra.api.arguments", "pyinfra.api.deploy", "pyinfra.api.operation",
                                "pyinfra.api.facts")
_NOT_IN_DATA = object()


def frame_location(frame) -> tuple[str, int]:
    """(filename, line number) of a frame, as inspect.getframeinfo(frame) reports them."""
    code = frame.f_code
    filename = code.co_filename
    if filename.endswith(BYTECODE_SUFFIXES):
        info = inspect.getframeinfo(frame, context=0)
        return info.filename, info.lineno
    lineno = None
    if frame.f_lasti >= 0:
        # The nth entry of co_positions() is the instruction at byte offset 2n (Python 3.10+).
        lineno = next(itertools.islice(code.co_positions(), frame.f_lasti // 2, None))[0]
    return filename, frame.f_lineno if lineno is None else lineno


def get_operation_order_from_stack(state) -> list[int]:
    """pyinfra 3.10's operation order for the operation being added: line numbers from deploy.py in.

    The same list as `pyinfra.api.util.get_operation_order_from_stack(state)` called from
    the same place (that function's own frame is one of pyinfra's, which it leaves out).
    """
    locations = []
    frame: FrameType | None = sys._getframe(1)
    while frame is not None:
        locations.append(frame_location(frame))
        frame = frame.f_back
    locations.reverse()  # outermost first, as pyinfra reverses inspect.stack()

    # From the outermost frame in the deploy file; without one, pyinfra's loop ends on its
    # own frame (innermost), which is then left out as one of pyinfra's: no line numbers.
    start = 0
    if state.current_deploy_filename:
        start = next((index for index, (filename, _) in enumerate(locations)
                      if filename == state.current_deploy_filename), len(locations))

    line_numbers = [state.current_op_file_number] if pyinfra.is_cli else []
    line_numbers.extend(lineno for filename, lineno in locations[start:]
                        if not filename.startswith(pyinfra_util.PYINFRA_INSTALL_DIR))
    return line_numbers


@cache
def _global_argument_types() -> tuple[tuple[str, type], ...]:
    return tuple(pyinfra_all_global_arguments())


def all_global_arguments() -> list[tuple[str, type]]:
    """pyinfra's global arguments and their types (`_sudo`, `_serial`, ...), evaluated once."""
    return list(_global_argument_types())


@cache
def _global_argument_names() -> frozenset[str]:
    return frozenset(name for name, _ in _global_argument_types())


def host_data_lookup(host):
    """`getattr(host.data, key, default)` for the global arguments' keys: the data layers
    called once, and each plain dict layer searched once for all of them (the ~30 names
    against its keys, in C), so a key costs one dict lookup, not one per layer."""
    layers = list(extract_callable_datas(host.data.datas))
    if all(type(layer) is dict for layer in layers):
        names = _global_argument_names()
        found: dict = {}
        for layer in layers:  # the first layer holding a key wins, as in HostData.__getattr__
            for key in names & layer.keys():
                if key not in found:
                    found[key] = layer[key]

        def lookup(key, default):
            if key not in names:
                return host_data_layers_lookup(layers, key, default)
            value = found.get(key, _NOT_IN_DATA)
            return default if value is _NOT_IN_DATA else copy.copy(value)
        return lookup
    return lambda key, default: host_data_layers_lookup(layers, key, default)


def host_data_layers_lookup(layers, key, default):
    """HostData.__getattr__'s search over layers already called: a shallow copy of the
    first layer's value for the key."""
    for layer in layers:
        try:
            return copy.copy(layer[key])
        except KeyError:
            pass
    return default


def pop_global_arguments(state, host, kwargs):
    """pyinfra 3.10's `pop_global_arguments`, with `host.data`'s layers called once."""
    config = state.config
    if ctx_config.isset():
        config = ctx_config.get()
        assert config is not None

    cdkwargs = host.current_deploy_kwargs
    meta_kwargs = cdkwargs or {}

    arguments = {}
    found_keys = []
    host_data = host_data_lookup(host)

    for key, type_ in pyinfra_arguments.all_global_arguments():
        argument_meta = pyinfra_arguments.all_argument_meta[key]
        handler = argument_meta.handler
        default = argument_meta.default(config)

        host_default = host_data(key, _NOT_IN_DATA)
        if host_default is not _NOT_IN_DATA:
            default = host_default

        if key in kwargs:
            found_keys.append(key)
            value = kwargs.pop(key)
        else:
            value = meta_kwargs.get(key, default)

        if handler:
            value = handler(config, value)

        if value != default:
            pyinfra_arguments.raise_if_bad_type(
                value, type_, pyinfra_arguments.ArgumentTypeError, f"Invalid argument `{key}`:")

        arguments[key] = value
    return arguments, found_keys


@cache
def operation_signature(function) -> inspect.Signature:
    """`inspect.signature` of an operation's function, read once per run. pyinfra 3.10 reads it
    again on every call of every operation on every host (`signature(func).bind(...)`, to refuse
    arguments the operation does not take before it runs); a Signature never changes."""
    return inspect.signature(function)


@cache
def _connectors() -> tuple[tuple[str, object], ...]:
    return tuple(pyinfra_get_all_connectors().items())


def all_connectors() -> dict:
    """pyinfra's connectors by name, as `get_all_connectors` returns them, read once per run."""
    return dict(_connectors())


def execution_connectors() -> dict:
    """pyinfra's `get_execution_connectors` over `all_connectors`."""
    return {name: module for name, module in _connectors() if module.handles_execution}  # type: ignore[attr-defined]  # a connector class


def execution_connector(name: str):
    """pyinfra's `get_execution_connector` over `all_connectors`."""
    return execution_connectors()[name]


@cache
def installed_pyinfra() -> str | None:
    try:
        return version("pyinfra")
    except PackageNotFoundError:
        return None


def install() -> bool:
    """Let pyinfra plan with the functions above; True when it does.

    Idempotent (deploy.py calls it once per host). Leaves pyinfra's own functions in place
    for another pyinfra version than CHECKED_PYINFRA, and when ROSLAB_PYINFRA_PLANNING=pyinfra
    asks for them.
    """
    ours = (installed_pyinfra() == CHECKED_PYINFRA
            and os.environ.get(SWITCH, "").strip() != USE_PYINFRA)
    pyinfra_operation.get_operation_order_from_stack = (  # type: ignore[attr-defined]  # pyinfra imports it privately; roslab patches it here
        get_operation_order_from_stack if ours else pyinfra_get_operation_order_from_stack)
    pyinfra_operation.signature = operation_signature if ours else inspect.signature  # type: ignore[attr-defined]  # pyinfra imports it privately; roslab patches it here
    for module in (pyinfra_arguments, pyinfra_facts):
        module.all_global_arguments = all_global_arguments if ours else pyinfra_all_global_arguments  # type: ignore[attr-defined]  # pyinfra imports it privately; roslab patches it here
    for name in POP_GLOBAL_ARGUMENTS_CALLERS:
        importlib.import_module(name).pop_global_arguments = (  # type: ignore[attr-defined]  # pyinfra imports it privately; roslab patches it here
            pop_global_arguments if ours else pyinfra_pop_global_arguments)
    # pyinfra's inventory and host modules import these by name: patched where they call them
    pyinfra_inventory.get_all_connectors = all_connectors if ours else pyinfra_get_all_connectors
    pyinfra_inventory.get_execution_connectors = execution_connectors if ours else pyinfra_get_execution_connectors
    pyinfra_host.get_execution_connector = execution_connector if ours else pyinfra_get_execution_connector
    return ours
