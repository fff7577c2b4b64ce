"""roslab.op_order gives pyinfra's own operation order, on real deploy call stacks."""

from __future__ import annotations

import runpy
import tomllib
from pathlib import Path

import pyinfra
import pytest
from fixtures.classroom import DEPLOY_PY, host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import fake_host, plan
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra.api import State
from pyinfra.api import util as pyinfra_util
from pyinfra.api.state import StateStage

from roslab import op_order

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


@pytest.fixture
def cli_mode(monkeypatch):
    """pyinfra as its CLI runs deploy files: operations ordered by their call stack."""
    monkeypatch.setattr(pyinfra, "is_cli", True)
    monkeypatch.setattr(State, "current_stage", StateStage.Prepare)


@pytest.fixture
def both_orders(monkeypatch, cli_mode):
    """Make pyinfra call a recorder that asks both functions from the same frame.

    deploy.py calls op_order.install(), which installs the recorder (it stands in for
    roslab's function); a deploy file without install() gets it directly.
    """
    monkeypatch.delenv(op_order.SWITCH, raising=False)
    ours = op_order.get_operation_order_from_stack
    pairs: list[tuple[list[int], list[int]]] = []

    def recorder(state):
        # Both on one line: this frame (not pyinfra's) is on both stacks, at the same line.
        pair = (op_order.pyinfra_get_operation_order_from_stack(state), ours(state))
        pairs.append((list(pair[0]), pair[1]))  # pyinfra appends to the list it gets
        return pair[0]

    monkeypatch.setattr(op_order, "get_operation_order_from_stack", recorder)
    monkeypatch.setattr(op_order.pyinfra_operation, "get_operation_order_from_stack", recorder)
    yield pairs
    op_order.install()  # not the recorder: undo with the real function in place
    monkeypatch.undo()
    op_order.pyinfra_operation.get_operation_order_from_stack = op_order.pyinfra_get_operation_order_from_stack


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
    for switch in ("", op_order.USE_PYINFRA):
        monkeypatch.setenv(op_order.SWITCH, switch)
        plans[switch] = plan(run_deploy_py, host.facts(), host_data(tmp_path))
        assert (op_order.pyinfra_operation.get_operation_order_from_stack
                is (op_order.get_operation_order_from_stack if not switch
                    else op_order.pyinfra_get_operation_order_from_stack))
    op_order.pyinfra_operation.get_operation_order_from_stack = op_order.pyinfra_get_operation_order_from_stack

    ours, theirs = plans[""], plans[op_order.USE_PYINFRA]
    assert [op.name for op in ours.operations] == [op.name for op in theirs.operations]
    assert ours.changing() == theirs.changing() == {}


def test_install_only_for_the_checked_pyinfra_and_without_the_switch(monkeypatch):
    monkeypatch.delenv(op_order.SWITCH, raising=False)
    try:
        assert op_order.install() is True
        assert op_order.pyinfra_operation.get_operation_order_from_stack is op_order.get_operation_order_from_stack
        assert op_order.install() is True  # idempotent

        monkeypatch.setenv(op_order.SWITCH, "pyinfra")
        assert op_order.install() is False
        assert op_order.pyinfra_operation.get_operation_order_from_stack is op_order.pyinfra_get_operation_order_from_stack

        monkeypatch.delenv(op_order.SWITCH)
        monkeypatch.setattr(op_order, "installed_pyinfra", lambda: "3.11.0")
        assert op_order.install() is False
        assert op_order.pyinfra_operation.get_operation_order_from_stack is op_order.pyinfra_get_operation_order_from_stack
    finally:
        op_order.pyinfra_operation.get_operation_order_from_stack = op_order.pyinfra_get_operation_order_from_stack


def test_the_checked_version_is_the_pinned_and_installed_pyinfra():
    """Moving the pin means checking pyinfra's new function against this module again."""
    dependencies = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    assert f"pyinfra=={op_order.CHECKED_PYINFRA}" in dependencies
    assert op_order.installed_pyinfra() == op_order.CHECKED_PYINFRA
    assert op_order.pyinfra_get_operation_order_from_stack is pyinfra_util.get_operation_order_from_stack


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
