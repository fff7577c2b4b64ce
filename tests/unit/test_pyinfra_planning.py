"""roslab.pyinfra_planning plans as pyinfra's own functions do: operation order, global arguments."""

from __future__ import annotations

import importlib
import importlib.metadata
import inspect
import runpy
import tomllib
from pathlib import Path

import pyinfra
import pytest
from fixtures.classroom import DEPLOY_PY, host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import fake_host, plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.api import State
from pyinfra.api import arguments as pyinfra_arguments
from pyinfra.api import connectors as pyinfra_connectors
from pyinfra.api import facts as pyinfra_facts
from pyinfra.api import host as pyinfra_host
from pyinfra.api import inventory as pyinfra_inventory
from pyinfra.api import util as pyinfra_util
from pyinfra.api.state import StateStage

from roslab import pyinfra_planning
from roslab.reporting import summary

REPO = Path(__file__).resolve().parents[2]

# A deploy file with what shapes pyinfra's order: nested @deploy, a loop, the same line
# twice, a helper function between the file and an operation, and a call spread over lines.
NESTED_DEPLOY = '''
from pyinfra.api import deploy
from pyinfra.operations import server


def helper(text):
    server.shell(name=f"helper {text}", commands=[f"echo {text}"])


@deploy("inner")
def inner(count):
    for index in range(count):
        server.shell(name=f"inner loop {index}", commands=["true"])
    helper("from inner")


@deploy("outer")
def outer():
    server.shell(name="outer first", commands=["true"])
    inner(2)
    inner(1)
    server.shell(
        name="outer spread",
        commands=[
            "true",
        ],
    )


outer()
for _ in range(2):
    server.shell(name="same line", commands=["true"])
helper("top")
helper("top")
outer()
'''


def restore_pyinfras_functions():
    pyinfra_planning.pyinfra_operation.get_operation_order_from_stack = (
        pyinfra_planning.pyinfra_get_operation_order_from_stack)
    pyinfra_planning.pyinfra_operation.signature = inspect.signature
    pyinfra_arguments.all_global_arguments = pyinfra_planning.pyinfra_all_global_arguments
    pyinfra_facts.all_global_arguments = pyinfra_planning.pyinfra_all_global_arguments
    for name in pyinfra_planning.POP_GLOBAL_ARGUMENTS_CALLERS:
        importlib.import_module(name).pop_global_arguments = pyinfra_planning.pyinfra_pop_global_arguments
    pyinfra_inventory.get_all_connectors = pyinfra_planning.pyinfra_get_all_connectors
    pyinfra_inventory.get_execution_connectors = pyinfra_planning.pyinfra_get_execution_connectors
    pyinfra_host.get_execution_connector = pyinfra_planning.pyinfra_get_execution_connector


@pytest.fixture
def cli_mode(monkeypatch):
    """pyinfra as its CLI runs deploy files: operations ordered by their call stack.

    Without the CLI's exit summary and signal handlers (roslab.reporting.summary), which are for a run.
    """
    monkeypatch.setattr(pyinfra, "is_cli", True)
    monkeypatch.setattr(summary, "deploying_files", lambda: False)
    monkeypatch.setattr(State, "current_stage", StateStage.Prepare)


@pytest.fixture
def both_orders(monkeypatch, cli_mode):
    """Make pyinfra call a recorder that asks both functions from the same frame.

    deploy.py calls pyinfra_planning.install(), which installs the recorder (it stands in for
    roslab's function); a deploy file without install() gets it directly.
    """
    monkeypatch.delenv(pyinfra_planning.SWITCH, raising=False)
    ours = pyinfra_planning.get_operation_order_from_stack
    pairs: list[tuple[list[int], list[int]]] = []

    def recorder(state):
        # Both on one line: this frame (not pyinfra's) is on both stacks, at the same line.
        pair = (pyinfra_planning.pyinfra_get_operation_order_from_stack(state), ours(state))
        pairs.append((list(pair[0]), pair[1]))  # pyinfra appends to the list it gets
        return pair[0]

    monkeypatch.setattr(pyinfra_planning, "get_operation_order_from_stack", recorder)
    monkeypatch.setattr(pyinfra_planning.pyinfra_operation, "get_operation_order_from_stack", recorder)
    yield pairs
    monkeypatch.undo()
    restore_pyinfras_functions()


def test_nested_deploys_loops_and_repeated_lines_get_pyinfras_order(tmp_path, both_orders):
    deploy_file = tmp_path / "nested_deploy.py"
    deploy_file.write_text(NESTED_DEPLOY)
    with fake_host({}) as (state, _host):
        state.current_deploy_filename = str(deploy_file)
        state.current_op_file_number = 3
        runpy.run_path(str(deploy_file))
        names = [sorted(state.op_meta[op_hash].names)[0] for op_hash in state.get_op_order()]

    assert len(both_orders) == 18
    assert [ours for _, ours in both_orders] == [theirs for theirs, _ in both_orders]
    orders = [theirs for theirs, _ in both_orders]
    assert all(order[0] == 3 for order in orders)  # the deploy file's position on the command line
    assert len({tuple(order) for order in orders}) < len(orders)  # loops and repeats: equal stacks
    # pyinfra's order is the order the file called them in, nesting and loops included
    assert names[:4] == ["outer | outer first", "outer | inner | inner loop 0",
                         "outer | inner | inner loop 1", "outer | inner | helper from inner"]
    assert names[-2:] == ["outer | inner | helper from inner", "outer | outer spread"]


def test_operations_outside_the_deploy_file_get_pyinfras_order(tmp_path, both_orders):
    """No frame in the deploy file (an operation called from elsewhere), and no deploy file."""
    deploy_file = tmp_path / "nested_deploy.py"
    deploy_file.write_text(NESTED_DEPLOY)
    with fake_host({}) as (state, _host):
        state.current_deploy_filename = str(tmp_path / "another_deploy.py")
        runpy.run_path(str(deploy_file))
        state.current_deploy_filename = None
        runpy.run_path(str(deploy_file))

    assert len(both_orders) == 36
    assert [ours for _, ours in both_orders] == [theirs for theirs, _ in both_orders]
    assert [theirs for theirs, _ in both_orders[:18]] == [[0]] * 18  # pyinfra's own answer then


def test_deploy_py_plans_in_the_same_order_with_either_function(tmp_path, both_orders):
    host = with_stand_in_deb(FakeUbuntu())
    with fake_host(host.facts(), host_data(tmp_path)) as (state, _host):
        state.current_deploy_filename = str(DEPLOY_PY)
        run_deploy_py()
        planned = len(state.get_op_order())

    assert planned > 20
    assert len(both_orders) >= planned
    assert [ours for _, ours in both_orders] == [theirs for theirs, _ in both_orders]


def test_a_converged_host_plans_the_same_operations_with_either_function(tmp_path, monkeypatch, cli_mode):
    """What a user sees: the same operations in the same order, the second run a no-op."""
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), host_data(tmp_path)))

    plans = {}
    for switch in ("", pyinfra_planning.USE_PYINFRA):
        monkeypatch.setenv(pyinfra_planning.SWITCH, switch)
        plans[switch] = plan(run_deploy_py, host.facts(), host_data(tmp_path))
        assert installed_functions() == (PYINFRAS if switch else OURS)
    restore_pyinfras_functions()

    ours, theirs = plans[""], plans[pyinfra_planning.USE_PYINFRA]
    assert [op.name for op in ours.operations] == [op.name for op in theirs.operations]
    assert ours.changing() == theirs.changing() == {}


def installed_functions():
    return (pyinfra_planning.pyinfra_operation.get_operation_order_from_stack,
            pyinfra_planning.pyinfra_operation.signature,
            pyinfra_arguments.all_global_arguments, pyinfra_facts.all_global_arguments,
            *(importlib.import_module(name).pop_global_arguments
              for name in pyinfra_planning.POP_GLOBAL_ARGUMENTS_CALLERS),
            pyinfra_inventory.get_all_connectors, pyinfra_inventory.get_execution_connectors,
            pyinfra_host.get_execution_connector)


OURS = (pyinfra_planning.get_operation_order_from_stack, pyinfra_planning.operation_signature,
        pyinfra_planning.all_global_arguments,
        pyinfra_planning.all_global_arguments, *[pyinfra_planning.pop_global_arguments] * 4,
        pyinfra_planning.all_connectors, pyinfra_planning.execution_connectors, pyinfra_planning.execution_connector)
PYINFRAS = (pyinfra_util.get_operation_order_from_stack, inspect.signature, pyinfra_arguments.all_global_arguments,
            pyinfra_facts.all_global_arguments, *[pyinfra_arguments.pop_global_arguments] * 4,
            pyinfra_connectors.get_all_connectors, pyinfra_connectors.get_execution_connectors,
            pyinfra_connectors.get_execution_connector)


def test_the_connectors_are_pyinfras_read_once_per_run(monkeypatch):
    """The same connectors by name, a dict of its own each call; the entry points read once."""
    pyinfra_planning._connectors.cache_clear()
    reads = []
    monkeypatch.setattr(pyinfra_connectors, "entry_points",
                        lambda **kwargs: reads.append(kwargs) or importlib.metadata.entry_points(**kwargs))
    monkeypatch.setattr(pyinfra_planning, "pyinfra_get_all_connectors", pyinfra_connectors.get_all_connectors)
    try:
        theirs = pyinfra_connectors.get_all_connectors()
        assert pyinfra_planning.all_connectors() == theirs and "ssh" in theirs
        assert pyinfra_planning.all_connectors() is not pyinfra_planning.all_connectors()
        assert pyinfra_planning.execution_connectors() == pyinfra_connectors.get_execution_connectors()
        assert pyinfra_planning.execution_connector("ssh") is pyinfra_connectors.get_execution_connector("ssh")
        for _ in range(3):
            pyinfra_planning.all_connectors()
            pyinfra_planning.execution_connector("local")
        assert len(reads) == 4  # pyinfra's own: one read per call; ours: one in all
    finally:
        pyinfra_planning._connectors.cache_clear()


def test_install_only_for_the_checked_pyinfra_and_without_the_switch(monkeypatch):
    monkeypatch.delenv(pyinfra_planning.SWITCH, raising=False)
    try:
        assert pyinfra_planning.install() is True
        assert installed_functions() == OURS
        assert pyinfra_planning.install() is True  # idempotent
        assert installed_functions() == OURS

        monkeypatch.setenv(pyinfra_planning.SWITCH, "pyinfra")
        assert pyinfra_planning.install() is False
        assert installed_functions() == PYINFRAS

        monkeypatch.delenv(pyinfra_planning.SWITCH)
        monkeypatch.setattr(pyinfra_planning, "installed_pyinfra", lambda: "3.11.0")
        assert pyinfra_planning.install() is False
        assert installed_functions() == PYINFRAS
    finally:
        restore_pyinfras_functions()


def test_the_checked_version_is_the_pinned_and_installed_pyinfra():
    """Moving the pin means checking pyinfra's new function against this module again."""
    dependencies = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert f"pyinfra=={pyinfra_planning.CHECKED_PYINFRA}" in dependencies
    assert pyinfra_planning.installed_pyinfra() == pyinfra_planning.CHECKED_PYINFRA
    assert pyinfra_planning.pyinfra_get_operation_order_from_stack is pyinfra_util.get_operation_order_from_stack


def test_a_frame_of_sourceless_bytecode_is_read_by_inspect(tmp_path, both_orders):
    """A co_filename ending in .pyc is the one case where inspect's filename differs from it."""
    deploy_file = tmp_path / "nested_deploy.py"
    deploy_file.write_text(NESTED_DEPLOY)
    code = compile(NESTED_DEPLOY.replace("\nouter()\nfor", "\nfor"), str(tmp_path / "compiled.pyc"), "exec")
    with fake_host({}) as (state, _host):
        state.current_deploy_filename = str(tmp_path / "compiled.py")
        (tmp_path / "compiled.py").write_text(NESTED_DEPLOY)
        exec(code, {"__name__": "compiled"})

    assert both_orders and [ours for _, ours in both_orders] == [theirs for theirs, _ in both_orders]
    assert all(len(theirs) > 1 for theirs, _ in both_orders)  # inspect named the frame compiled.py


def test_global_arguments_are_pyinfras_and_each_caller_gets_its_own_list():
    ours = pyinfra_planning.all_global_arguments()
    assert ours == pyinfra_planning.pyinfra_all_global_arguments()
    assert ("_sudo", bool) in ours and ("_serial", bool) in ours
    ours.clear()  # a caller changing its list changes nobody else's
    assert pyinfra_planning.all_global_arguments() == pyinfra_planning.pyinfra_all_global_arguments()


def test_operations_and_facts_get_pyinfras_global_arguments(tmp_path, monkeypatch, cli_mode):
    """The same arguments reach every operation (_sudo, _serial, ...) with either function."""
    monkeypatch.delenv(pyinfra_planning.SWITCH, raising=False)
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), host_data(tmp_path)))
    plans = {}
    for switch in ("", pyinfra_planning.USE_PYINFRA):
        monkeypatch.setenv(pyinfra_planning.SWITCH, switch)
        plans[switch] = plan(run_deploy_py, host.facts(), host_data(tmp_path, ssh_hardening_enabled=False))
    restore_pyinfras_functions()
    ours, theirs = plans[""], plans[pyinfra_planning.USE_PYINFRA]
    assert [(op.name, comparable(op.arguments)) for op in ours.operations] == [
        (op.name, comparable(op.arguments)) for op in theirs.operations]
    assert ours.facts_asked == theirs.facts_asked
    assert any(op.arguments.get("_sudo") for op in ours.operations)


def comparable(arguments: dict) -> dict:
    """Global arguments with functions (`_if`'s conditions, made anew by each plan) by name."""
    def named(value):
        if callable(value):
            return value.__qualname__
        if isinstance(value, (list, tuple)):
            return [named(item) for item in value]
        return value
    return {key: named(value) for key, value in arguments.items()}


def test_global_arguments_from_every_data_layer_are_popped_as_pyinfra_pops_them():
    """Override, host, group (merged in inventory order), inventory and @deploy data."""
    from pyinfra.api import Config, Inventory, State
    from pyinfra.api.deploy import deploy
    from pyinfra.context import ctx_host, ctx_state

    inventory = Inventory(
        ([("pi", {"_sudo_user": "student", "_env": {"A": "host"}}), ("other", {})], {}),
        first=(["pi"], {"_sudo": True, "_retries": 2}),
        second=([("pi", {})], {"_retries": 3, "_shell_executable": "bash"}),
    )
    state = State(inventory, Config(RETRY=1))
    host = inventory.get_host("pi")
    host.data._chdir = "/srv"  # an override, as a deploy may set one
    seen = []

    @deploy("with defaults", data_defaults={"_serial": True, "_sudo_user": "nobody"})
    def with_defaults():
        for kwargs in ({}, {"_sudo": False, "_env": {"B": "op"}, "name": "kept", "path": "/x"}):
            ours_kwargs, theirs_kwargs = dict(kwargs), dict(kwargs)
            ours = pyinfra_planning.pop_global_arguments(state, host, ours_kwargs)
            theirs = pyinfra_planning.pyinfra_pop_global_arguments(state, host, theirs_kwargs)
            seen.append((ours, theirs, ours_kwargs, theirs_kwargs))

    with ctx_state.use(state), ctx_host.use(host):
        with_defaults()
        for ours_kwargs, theirs_kwargs in (({"_doas": True}, {"_doas": True}),):
            seen.append((pyinfra_planning.pop_global_arguments(state, host, ours_kwargs),
                         pyinfra_planning.pyinfra_pop_global_arguments(state, host, theirs_kwargs),
                         ours_kwargs, theirs_kwargs))

    # getattr(host.data, key) reaches the layers only for names HostData does not have itself
    assert not [key for key, _ in pyinfra_arguments.all_global_arguments() if key in dir(host.data)]
    assert len(seen) == 3
    for ours, theirs, ours_kwargs, theirs_kwargs in seen:
        assert ours == theirs and ours_kwargs == theirs_kwargs
    arguments = seen[0][0][0]
    assert (arguments["_sudo"], arguments["_sudo_user"], arguments["_retries"], arguments["_chdir"],
            arguments["_shell_executable"], arguments["_env"]) == (True, "student", 3, "/srv", "bash", {"A": "host"})
    assert seen[1][2] == {"path": "/x"} and set(seen[1][0][1]) == {"_sudo", "_env", "name"}


def test_a_bad_global_argument_is_refused_as_pyinfra_refuses_it():
    from pyinfra.api import Config, Inventory, State
    from pyinfra.api.exceptions import ArgumentTypeError

    inventory = Inventory(([("pi", {})], {}))
    state = State(inventory, Config())
    host = inventory.get_host("pi")
    errors = []
    for pop in (pyinfra_planning.pop_global_arguments, pyinfra_planning.pyinfra_pop_global_arguments):
        with pytest.raises(ArgumentTypeError) as raised:
            pop(state, host, {"_sudo_user": 42})
        errors.append(str(raised.value))
    assert errors[0] == errors[1] and "_sudo_user" in errors[0]


def test_the_data_lookup_finds_what_host_data_finds_in_every_kind_of_layer():
    """Plain dicts are searched with get(); any other mapping as pyinfra does, with [] (a
    defaultdict answers every key there)."""
    from collections import defaultdict
    from types import SimpleNamespace

    from pyinfra.api.host import HostData

    data = HostData(None, {"set_to_none": None}, lambda: {"from_callable": [1], "set_to_none": "hidden"},
                    defaultdict(lambda: "made", {"in_default": 2}), {"last": 3})
    lookup = pyinfra_planning.host_data_lookup(SimpleNamespace(data=data))
    missing = object()
    for key in ("set_to_none", "from_callable", "in_default", "last", "anything"):
        assert lookup(key, missing) == getattr(data, key, missing), key
    assert lookup("anything", missing) == "made"
    served = lookup("from_callable", missing)
    served.append(2)  # a shallow copy, as HostData gives
    assert lookup("from_callable", missing) == [1]


def test_an_operations_signature_is_inspects_read_once():
    from pyinfra.operations import files

    function = files.put._inner
    assert pyinfra_planning.operation_signature(function) == inspect.signature(function)
    assert pyinfra_planning.operation_signature(function) is pyinfra_planning.operation_signature(function)
    with pytest.raises(TypeError):  # an argument the operation does not take is still refused
        pyinfra_planning.operation_signature(function).bind(src="a", dest="b", no_such_argument=1)


def test_the_data_lookup_of_plain_dict_layers_finds_the_first_layer_holding_a_global_argument():
    from types import SimpleNamespace

    from pyinfra.api.host import HostData

    data = HostData(None, {"_sudo_user": None}, lambda: {"_sudo_user": "student", "_env": {"A": "1"}},
                    {"_env": {"B": "2"}, "_retries": 2, "ssh_user": "ubuntu"})
    lookup = pyinfra_planning.host_data_lookup(SimpleNamespace(data=data))
    missing = object()
    for key in ("_sudo_user", "_env", "_retries", "_sudo", "ssh_user", "nothing"):
        assert lookup(key, missing) == getattr(data, key, missing), key
    assert lookup("_sudo_user", missing) is None and lookup("_sudo", missing) is missing
    lookup("_env", missing)["C"] = "3"  # a shallow copy, as HostData gives
    assert lookup("_env", missing) == {"A": "1"}
