"""pyinfra's operation order, read from the call stack without reading any source file.

In CLI mode pyinfra 3.10 orders operations by where deploy.py called them: for every
operation on every host, `pyinfra.api.util.get_operation_order_from_stack` takes the line
numbers of the call stack from deploy.py inwards, leaving out pyinfra's own frames. It gets
them with `inspect.stack()`, which also reads each frame's line of source (`findsource`,
`linecache`, and `getmodule` scanning every module in `sys.modules` for frames whose file
does not exist, such as gevent's and pyinfra's `exec`'d code). On a no-op re-run that was
about half of the controller's CPU, once per operation per host (issue 32).

`get_operation_order_from_stack` below gives the same list by walking `frame.f_back` and
taking, for each frame, exactly what `inspect.getframeinfo` would report as its filename
and line number, with no source context:

- filename: the code object's `co_filename`. `inspect.getsourcefile` differs from it only
  for a `co_filename` ending in a bytecode suffix (`.pyc`, a sourceless module); such a
  frame is handed to `inspect.getframeinfo` itself.
- line: the start line of the frame's current instruction in `co_positions()` (as
  `inspect._get_code_position`), or `f_lineno` where the instruction has none.

`install()` puts it in place of pyinfra's in `pyinfra.api.operation` (the only caller),
only for the pyinfra version it was checked against (`CHECKED_PYINFRA`, the pin in
pyproject.toml; tests/unit/test_op_order.py compares both functions on real nested deploy
call stacks and fails when the pin moves). Any other pyinfra keeps its own function.

Diagnostic switch: `ROSLAB_PYINFRA_OP_ORDER=pyinfra` in the environment keeps pyinfra's own
function (the order is the same; only the controller's CPU differs). bench/noop_rerun.py
measures both.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import inspect
import itertools
import os
import sys
from importlib.metadata import PackageNotFoundError, version

import pyinfra
from pyinfra.api import util as pyinfra_util

# The module, not the `operation` decorator that pyinfra.api exports under the same name.
pyinfra_operation = importlib.import_module("pyinfra.api.operation")

# The pyinfra release whose get_operation_order_from_stack this module reproduces.
CHECKED_PYINFRA = "3.10.0"
# The diagnostic switch: "pyinfra" keeps pyinfra's own (inspect.stack) function.
SWITCH = "ROSLAB_PYINFRA_OP_ORDER"
USE_PYINFRA = "pyinfra"

# What inspect.getsourcefile maps to a source name: a co_filename ending in one of these.
BYTECODE_SUFFIXES = tuple(importlib.machinery.DEBUG_BYTECODE_SUFFIXES
                          + importlib.machinery.OPTIMIZED_BYTECODE_SUFFIXES)

# pyinfra's function, kept before install() replaces it.
pyinfra_get_operation_order_from_stack = pyinfra_util.get_operation_order_from_stack


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
    frame = sys._getframe(1)
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


def installed_pyinfra() -> str | None:
    try:
        return version("pyinfra")
    except PackageNotFoundError:
        return None


def install() -> bool:
    """Let pyinfra order operations with the function above; True when it does.

    Idempotent. Leaves pyinfra's own function in place for another pyinfra version than
    CHECKED_PYINFRA, and when ROSLAB_PYINFRA_OP_ORDER=pyinfra asks for it.
    """
    use_ours = (installed_pyinfra() == CHECKED_PYINFRA
                and os.environ.get(SWITCH, "").strip() != USE_PYINFRA)
    pyinfra_operation.get_operation_order_from_stack = (
        get_operation_order_from_stack if use_ours else pyinfra_get_operation_order_from_stack)
    return use_ours
