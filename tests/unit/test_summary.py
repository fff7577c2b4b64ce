"""roslab.reporting.summary: the table a teacher reads at the end of a run, and the exit code line.

The handler is fed the events pyinfra gives it (callbacks, roslab's stop_host, pyinfra's
log lines) on a real pyinfra State; one test drives pyinfra's own run_ops so the order
the callbacks fire in (before an operation's result is complete) is the real one.
"""

from __future__ import annotations

import io
import logging
from unittest import mock

import gevent
import pytest
from fixtures.classroom import host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import fake_host
from fixtures.fake_ubuntu import FakeUbuntu
from pyinfra import logger
from pyinfra.api import Config, Inventory, State, operation
from pyinfra.api.host import Host
from pyinfra.api.operation import OperationMeta
from pyinfra.api.operations import run_ops
from pyinfra.api.state import StateOperationHostData, StateOperationMeta, StateStage
from pyinfra.connectors.util import CommandOutput, OutputLine
from pyinfra.context import ctx_host, ctx_state

from roslab.reporting import summary
from roslab.secrets import Secret

INSTALL = "ROS 2 is installed for the host's distro and role | Ensure ROS 2 jazzy is installed"
SUPPORTED = "The host runs an Ubuntu release that has packages for its ROS 2 distro"


def classroom(*names: str, data: dict | None = None) -> tuple[State, summary.RunSummary]:
    """A pyinfra State over `names` (all connected) with the run summary installed."""
    inventory = Inventory(([(name, dict((data or {}).get(name, {}))) for name in names], {}))
    state = State(inventory, Config())
    for host in inventory:
        state.activate_host(host)
    state.set_stage(StateStage.Prepare)
    return state, summary.install(state)


def operation_on(state: State, host_name: str, op_hash: str, name: str, *, changed: bool) -> OperationMeta:
    """An operation planned on one host, as pyinfra records it (not yet executed)."""
    host = state.inventory.get_host(host_name)
    op_meta = state.op_meta.setdefault(op_hash, StateOperationMeta((len(state.op_meta),)))
    op_meta.names.add(name)
    meta = OperationMeta(op_hash, is_change=changed)
    state.set_op_data_for_host(
        host, op_hash, StateOperationHostData(lambda: iter(()), {"_ignore_errors": False}, meta),
    )
    state.get_meta_for_host(host).ops += 1
    if changed:
        state.get_meta_for_host(host).ops_change += 1
    return meta


def executed(state: State, handler, host_name: str, op_hash: str, *, success: bool,
             commands: int = 1, output: list[tuple[str, str]] = ()) -> None:
    """pyinfra's order: the callback first, then the operation's result is completed."""
    host = state.inventory.get_host(host_name)
    if success:
        handler.operation_host_success(state, host, op_hash)
    else:
        handler.operation_host_error(state, host, op_hash)
    state.ops[host][op_hash].operation_meta.set_complete(
        success, ["command"] * commands, CommandOutput([OutputLine(buffer, line) for buffer, line in output]),
    )


def printed(state: State, handler) -> list[str]:
    out = io.StringIO()
    handler.write(state, out)
    return out.getvalue().splitlines()


def finished_run(state: State) -> None:
    state.set_stage(StateStage.Execute)
    state.is_executing = True
    state.set_stage(StateStage.Disconnect)


def test_three_hosts_ok_changed_failed_and_the_exit_code():
    state, handler = classroom("team1-main", "team1-robot", "team2-main")
    for name in ("team1-main", "team1-robot", "team2-main"):
        operation_on(state, name, "op-install", INSTALL, changed=name != "team1-main")
    finished_run(state)

    executed(state, handler, "team1-main", "op-install", success=True, commands=0)
    executed(state, handler, "team1-robot", "op-install", success=True)
    executed(state, handler, "team2-main", "op-install", success=False, commands=0, output=[
        ("stdout", "Reading package lists..."),
        ("stderr", "W: an unrelated warning"),
        ("stderr", "E: Unable to locate package roslab-no-such-package"),
        ("stderr", "E: a second error line"),
    ])
    state.fail_hosts({state.inventory.get_host("team2-main")})

    assert printed(state, handler) == [
        "",
        "--> roslab summary",
        "    team1-main   ok",
        "    team1-robot  changed",
        f'    team2-main   failed   in "{INSTALL}": E: Unable to locate package roslab-no-such-package',
        "    exit code 1: 1 failed, 1 changed, 1 ok (3 hosts)",
    ]
    assert handler.exit_code(state) == 1


def test_no_failure_exits_0():
    state, handler = classroom("team1-main", "team1-robot")
    operation_on(state, "team1-main", "op", INSTALL, changed=True)
    finished_run(state)
    executed(state, handler, "team1-main", "op", success=True)

    assert printed(state, handler)[-3:] == [
        "    team1-main   changed",
        "    team1-robot  ok",
        "    exit code 0: 0 failed, 1 changed, 1 ok (2 hosts)",
    ]


def test_a_host_roslab_stopped_shows_the_deploy_and_the_first_line_of_the_message():
    state, handler = classroom("team1-main", "team1-robot", "team2-main")
    robot = state.inventory.get_host("team1-robot")
    operation_on(state, "team1-main", "op", INSTALL, changed=True)
    with ctx_host.use(robot):
        robot.current_deploy_name = SUPPORTED  # stop_host runs inside the deploy
        summary.record_stop(
            robot,
            "host team1-robot (team team1): ubuntu_release is 22.04 (jammy) in the roster but the host "
            "runs Ubuntu noble; nothing was changed on it\nsecond line not shown",
        )
        robot.current_deploy_name = None
    state.fail_hosts({robot})
    for host in state.active_hosts:
        summary.mark_planned(host)

    # --dry: planning ended, nothing was executed.
    assert printed(state, handler)[1:] == [
        "--> roslab summary (nothing was executed: changed = would change)",
        "    team1-main   changed",
        f'    team1-robot  failed   in "{SUPPORTED}": ubuntu_release is 22.04 (jammy) in the roster '
        "but the host runs Ubuntu noble; nothing was changed on it",
        "    team2-main   ok",
        "    exit code 1: 1 failed, 1 changed, 1 ok (3 hosts)",
    ]


def test_a_host_failed_through_pyinfras_context_proxy_is_still_failed_after_the_run():
    """deploy.common.stop_host calls `state.fail_hosts({host})` with pyinfra's `host` proxy:
    once the run is over that proxy stands for no host, so `host in state.failed_hosts` is False."""
    from pyinfra import host as host_proxy

    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    with ctx_state.use(state), ctx_host.use(robot):
        robot.current_deploy_name = SUPPORTED
        summary.record_stop(host_proxy, "host team1-robot (team team1): it runs Debian, not Ubuntu")
        state.fail_hosts({host_proxy})
        robot.current_deploy_name = None
    summary.mark_planned(state.inventory.get_host("team1-main"))

    assert robot not in state.failed_hosts  # what the summary must not rely on
    assert printed(state, handler)[3:] == [
        f'    team1-robot  failed   in "{SUPPORTED}": it runs Debian, not Ubuntu',
        "    exit code 1: 1 failed, 0 changed, 1 ok (2 hosts)",
    ]


def test_the_step_is_the_failed_hosts_own_operation_name():
    """One operation, a name per host (pyinfra keeps them in one set): the host's own is shown."""
    state, handler = classroom("team1-main", "team2-main")
    jazzy, humble = "Ensure ROS 2 jazzy is installed", "Ensure ROS 2 humble is installed"
    for name, op in (("team1-main", jazzy), ("team2-main", humble)):
        operation_on(state, name, "op", f"ROS 2 is installed | {op}", changed=True)
        state.ops[state.inventory.get_host(name)]["op"].global_arguments["name"] = op
    finished_run(state)
    executed(state, handler, "team1-main", "op", success=True)
    executed(state, handler, "team2-main", "op", success=False, output=[("stderr", "E: Unable to locate package x")])
    state.fail_hosts({state.inventory.get_host("team2-main")})

    assert printed(state, handler)[3] == (
        f'    team2-main  failed   in "ROS 2 is installed | {humble}": E: Unable to locate package x'
    )


def test_a_stop_only_logged_by_stop_host_is_found_in_pyinfras_log():
    """Until deploy.common.stop_host calls record_stop, its log line is the record."""
    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    with ctx_state.use(state), ctx_host.use(robot):
        robot.current_deploy_name = SUPPORTED
        logger.error(f"{robot.print_prefix}roslab stops this host: host team1-robot (team team1): "
                     "it runs Debian GNU/Linux 12, not Ubuntu; nothing was changed on it")
        robot.current_deploy_name = None
    state.fail_hosts({robot})
    summary.mark_planned(state.inventory.get_host("team1-main"))

    assert printed(state, handler)[3] == (
        f'    team1-robot  failed   in "{SUPPORTED}": it runs Debian GNU/Linux 12, not Ubuntu; '
        "nothing was changed on it"
    )


def test_a_fact_that_failed_while_planning_names_its_stderr_not_pyinfras_error_line():
    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    with ctx_state.use(state), ctx_host.use(robot):
        robot.current_deploy_name = "apt is ready"
        logger.error(f"{robot.print_prefix}sudo: a password is required")
        logger.error(f"{robot.print_prefix}Error: could not load fact: server.Home user=student")
        robot.current_deploy_name = None
    state.fail_hosts({robot})
    summary.mark_planned(state.inventory.get_host("team1-main"))

    assert printed(state, handler)[3] == (
        '    team1-robot  failed   in "apt is ready": sudo asks for a password and the roster sets no '
        "sudo_password_secret for this host (sudo: a password is required)")


@operation()
def step_for_test(commands_by_host: dict):
    """Yields this host's commands: none (no change), or some that succeed or fail."""
    from pyinfra import host

    yield from commands_by_host.get(host.name, [])


def test_a_real_pyinfra_run_reports_the_failed_operations_stderr():
    """pyinfra's own run_ops: callbacks fire before the result is complete; the summary still
    shows the operation's stderr line, never pyinfra's "Error: executed 0 commands"."""
    state, handler = classroom("quiet", "busy", "broken")
    state.set_stage(StateStage.Execute)
    results = {"true": (True, []), "fail": (False, [
        OutputLine("stderr", "Reading package lists..."),
        OutputLine("stderr", "E: Unable to locate package roslab-no-such-package"),
    ])}

    def run_shell_command(self, command, **kwargs):
        status, lines = results[command.get_raw_value()]
        return status, CommandOutput(lines)

    from pyinfra.api.operation import add_op

    with mock.patch.object(Host, "run_shell_command", run_shell_command):
        add_op(state, step_for_test, name="Extra packages are installed",
               commands_by_host={"busy": ["true"], "broken": ["fail"]})
        run_ops(state)
    state.set_stage(StateStage.Disconnect)

    assert printed(state, handler)[2:] == [
        "    quiet   ok",
        "    busy    changed",
        '    broken  failed   in "Extra packages are installed": E: Unable to locate package roslab-no-such-package',
        "    exit code 1: 1 failed, 1 changed, 1 ok (3 hosts)",
    ]


def test_secrets_never_appear_in_the_summary():
    wifi = "correct-horse-battery"
    sudo = "s3cret-sudo"
    state, handler = classroom("team1-main", "team1-robot", data={
        "team1-main": {"wifi_password": Secret(wifi), "_sudo_password": sudo},
        "team1-robot": {},
    })
    operation_on(state, "team1-robot", "op", "Network is in effect", changed=True)
    finished_run(state)
    executed(state, handler, "team1-robot", "op", success=False, output=[
        ("stderr", f"netplan: invalid password {wifi} (sudo {sudo})"),
    ])
    state.fail_hosts({state.inventory.get_host("team1-robot")})

    text = "\n".join(printed(state, handler))
    assert wifi not in text and sudo not in text
    assert 'failed   in "Network is in effect": netplan: invalid password *** (sudo ***)' in text


def test_a_run_pyinfra_stopped_midway_is_exit_code_1_even_without_a_failed_host():
    state, handler = classroom("team1-main", "team1-robot")
    state.set_stage(StateStage.Execute)  # an exception ended run_ops: never reached Disconnect
    state.is_executing = True

    operation_on(state, "team1-main", "op-1", INSTALL, changed=False)
    operation_on(state, "team1-main", "op-2", "Workspace is built", changed=True)
    operation_on(state, "team1-robot", "op-1", INSTALL, changed=False)
    executed(state, handler, "team1-main", "op-1", success=True, commands=0)
    executed(state, handler, "team1-robot", "op-1", success=True, commands=0)

    assert printed(state, handler)[-3:] == [
        "    team1-main   not run",  # op-2 never ran
        "    team1-robot  ok",
        "    exit code 1: pyinfra stopped before the end of the run (its error is above); "
        "0 failed, 0 changed, 1 ok, 1 not run (2 hosts)",
    ]


def test_a_run_pyinfra_stopped_while_planning_runs_no_host():
    state, handler = classroom("team1-main", "team1-robot")
    summary.mark_planned(state.inventory.get_host("team1-main"))  # team1-robot raised while planning

    assert printed(state, handler)[-3:] == [
        "    team1-main   not run",
        "    team1-robot  not run",
        "    exit code 1: pyinfra stopped before the end of the run (its error is above); "
        "0 failed, 0 changed, 0 ok, 2 not run (2 hosts)",
    ]


def test_a_plan_that_did_not_reach_the_end_of_deploy_py_is_exit_code_1():
    state, handler = classroom("team1-main", "team1-robot")
    summary.mark_planned(state.inventory.get_host("team1-main"))  # team1-robot raised while planning

    assert handler.exit_code(state) == 1
    summary.mark_planned(state.inventory.get_host("team1-robot"))
    assert handler.exit_code(state) == 0


def test_install_registers_one_handler_per_run():
    state, handler = classroom("team1-main", "team1-robot")
    assert summary.install(state) is handler
    assert sum(isinstance(h, summary.RunSummary) for h in state.callback_handlers) == 1


def test_deploy_py_installs_the_summary_and_marks_the_host_planned(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    with fake_host(host.facts(), host_data(tmp_path)) as (state, pi):
        run_deploy_py()
        run_deploy_py()  # pyinfra runs deploy.py once per host
        handlers = [h for h in state.callback_handlers if isinstance(h, summary.RunSummary)]
        assert len(handlers) == 1
        assert handlers[0].planned == {pi.name}


def test_record_stop_without_a_summary_does_nothing():
    with fake_host({}) as (state, pi):
        summary.record_stop(pi, "host pi: anything")  # a unit test calling a deploy directly


@pytest.mark.parametrize(("lines", "expected"), [
    (["Error: executed 0 commands"], None),
    (["Reading package lists...", "E: Unable to locate package x", "E: second"], "E: Unable to locate package x"),
    (["roslab: apt-get update failed, the lists stay stale until one succeeds: E: Failed to fetch"],
     "roslab: apt-get update failed, the lists stay stale until one succeeds: E: Failed to fetch"),
    (["Traceback (most recent call last):", '  File "x.py", line 1', "ValueError: bad value"],
     "ValueError: bad value"),
    (["Starting >>> pkg", "Failed   <<< pkg [0.5s, exited with code 1]", "Summary: 0 packages finished"],
     "Failed <<< pkg [0.5s, exited with code 1]"),
    (["one", "two"], "two"),
    (["Error: could not load fact: server.Home"], "Error: could not load fact: server.Home"),
    (["\x1b[31mE: coloured\x1b[0m"], "E: coloured"),
    (["x" * 400], "x" * (summary.MAX_REASON - 3) + "..."),
])
def test_most_useful_line(lines, expected):
    assert summary.most_useful_line(lines) == expected


def test_log_capture_ignores_info_lines_and_lines_without_a_host():
    state, handler = classroom("team1-main", "team1-robot")
    with ctx_state.use(state):
        logger.info("[team1-robot] Success")
        logger.error("no host prefix here")
        logger.warning("[team1-robot] roslab: a warning")
    assert [(line.level, line.text) for line in handler.host("team1-robot").log] == [
        (logging.WARNING, "roslab: a warning"),
    ]


def test_a_wrong_sudo_password_names_the_roster_setting_not_just_sudos_words():
    state, handler = classroom("team1-main", "team1-robot", data={"team1-main": {
        "sudo_password_secret": "lab_sudo", "_sudo_password": Secret("wrong")}})
    main = state.inventory.get_host("team1-main")
    operation_on(state, "team1-main", "op-hostname", "Ensure the hostname is team1-main", changed=True)
    finished_run(state)
    executed(state, handler, "team1-main", "op-hostname", success=False, commands=0, output=[
        ("stderr", "Sorry, try again."), ("stderr", "Sorry, try again."),
        ("stderr", "sudo: 3 incorrect password attempts"),
    ])
    state.fail_hosts({main})

    assert printed(state, handler)[2] == (
        '    team1-main   failed   in "Ensure the hostname is team1-main": sudo refused the password from '
        "the roster's sudo_password_secret: the secret it names does not hold this host's sudo password "
        "(sudo: 3 incorrect password attempts)")
    assert "wrong" not in "\n".join(printed(state, handler))


def test_an_interrupted_run_names_each_unfinished_host_and_step_and_exits_130():
    state, handler = classroom("team1-main", "team1-robot", "team2-main")
    for name in ("team1-main", "team1-robot", "team2-main"):
        operation_on(state, name, "op-1", "Ensure the locale", changed=True)
        operation_on(state, name, "op-2", INSTALL, changed=True)
    state.set_stage(StateStage.Execute)
    state.is_executing = True
    for name in ("team1-main", "team1-robot", "team2-main"):
        executed(state, handler, name, "op-1", success=True)
    executed(state, handler, "team2-main", "op-2", success=True)  # finished before the signal
    handler.end(130, "stopped by SIGINT (Ctrl-C)", "SIGINT (Ctrl-C)")

    lines = printed(state, handler)
    assert lines[2] == (f'    team1-main   interrupted  in "{INSTALL}": the run was stopped by SIGINT (Ctrl-C) '
                        "before this step finished here")
    assert lines[3].startswith(f'    team1-robot  interrupted  in "{INSTALL}"')
    assert lines[4] == "    team2-main   changed"
    assert lines[5] == ("    exit code 130: stopped by SIGINT (Ctrl-C); 0 failed, 1 changed, 0 ok, "
                        "2 interrupted (3 hosts)")
    assert handler.exit_code(state) == 130
    assert {run.host: run.result for run in handler_runs(state, handler)} == {
        "team1-main": "interrupted", "team1-robot": "interrupted", "team2-main": "changed"}


def handler_runs(state, handler):
    return [summary.HostRun(row.host, row.status, row.step, row.reason) for row in handler.rows(state)]


def conditional(state, host_name, op_hash, name, condition):
    meta = operation_on(state, host_name, op_hash, name, changed=True)
    state.ops[state.inventory.get_host(host_name)][op_hash].global_arguments["_if"] = condition
    return meta


def test_dry_a_converged_host_is_ok_although_pyinfra_counts_its_conditional_restart():
    state, handler = classroom("team1-main", "team1-robot")
    unit = operation_on(state, "team1-main", "op-unit", "Ensure the unit", changed=False)
    conditional(state, "team1-main", "op-reload", "Reload systemd", unit.did_change)
    conditional(state, "team1-main", "op-restart", "Restart", lambda: unit.did_change())
    changed_unit = operation_on(state, "team1-robot", "op-unit", "Ensure the unit", changed=True)
    conditional(state, "team1-robot", "op-reload", "Reload systemd", [changed_unit.did_change])
    for host in state.active_hosts:
        summary.mark_planned(host)
    assert state.get_meta_for_host(state.inventory.get_host("team1-main")).ops_change == 2  # pyinfra's count

    assert printed(state, handler)[1:] == [
        "--> roslab summary (nothing was executed: changed = would change)",
        "    team1-main   ok",
        "    team1-robot  changed",
        "    exit code 0: 0 failed, 1 changed, 1 ok (2 hosts)",
    ]


def test_dry_a_condition_that_cannot_be_known_counts_as_a_change():
    state, handler = classroom("team1-main")

    def unknowable():
        raise RuntimeError("needs the host")

    conditional(state, "team1-main", "op", "Restart", unknowable)
    summary.mark_planned(state.inventory.get_host("team1-main"))
    assert printed(state, handler)[2] == "    team1-main  changed"


def test_compact_output_hides_steps_that_changed_nothing_and_shows_the_others_with_their_lines():
    shown: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            shown.append(record.getMessage())

    log = logging.getLogger("roslab-test-compact")
    log.propagate = False
    log.setLevel(logging.INFO)
    log.handlers = [Collect()]
    compact = summary.CompactOutput(log, long_step=None)
    log.addFilter(compact)
    try:
        for line in ["    [team1-main] Connected", "--> Starting operation: Ensure the locale",
                     "    [team1-main] No changes", "    [team1-robot] No changes",
                     "--> Starting operation: Ensure ROS 2 jazzy", "    [team1-main] No changes",
                     "    [team1-robot] Success",
                     "--> Starting operation: Ensure the unit", "    [team1-main] No changes"]:
            log.info(line)
        log.warning("    [team1-main] roslab: a warning in that step")
        log.info("--> Starting operation: Reload sshd")
        log.error("    [team1-robot] Error: executed 0 commands")
        log.info("--> Disconnecting from hosts...")
    finally:
        log.removeFilter(compact)

    assert shown == ["    [team1-main] Connected",
                     "--> Starting operation: Ensure ROS 2 jazzy", "    [team1-robot] Success",
                     "--> Starting operation: Ensure the unit", "    [team1-main] roslab: a warning in that step",
                     "--> Starting operation: Reload sshd", "    [team1-robot] Error: executed 0 commands",
                     "--> Disconnecting from hosts..."]
    assert compact.hidden_steps == 1


def test_compact_output_shows_a_long_step_before_any_host_is_done():
    import gevent

    shown: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            shown.append(record.getMessage())

    log = logging.getLogger("roslab-test-compact-long")
    log.propagate = False
    log.setLevel(logging.INFO)
    log.handlers = [Collect()]
    compact = summary.CompactOutput(log, long_step=0.05)
    log.addFilter(compact)
    try:
        log.info("--> Starting operation: Ensure ROS 2 jazzy is installed")
        assert shown == []
        gevent.sleep(0.2)
        assert shown == ["--> Starting operation: Ensure ROS 2 jazzy is installed"]
        log.info("    [team1-main] No changes")
        log.info("    [team1-robot] Success")
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Starting operation: Ensure ROS 2 jazzy is installed", "    [team1-robot] Success"]
    assert compact.hidden_steps == 0


def test_a_long_step_says_which_hosts_are_still_in_it():
    import gevent

    shown: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            shown.append(record.getMessage())

    log = logging.getLogger("roslab-test-compact-still")
    log.propagate = False
    log.setLevel(logging.INFO)
    log.handlers = [Collect()]
    compact = summary.CompactOutput(log, long_step=0.05, every=0.1,
                                    hosts=lambda: ["team1-main", "team1-robot", "team2-main"])
    log.addFilter(compact)
    try:
        log.info("--> Starting operation: Ensure ROS 2 is installed")
        log.info("    [team1-main] No changes")
        gevent.sleep(0.1)
        log.info("    [team2-main] Success")
        gevent.sleep(0.15)
        log.info("--> Starting operation: Ensure the locale")
        still = [line for line in shown if line.startswith("    still running on ")]
        gevent.sleep(0.3)  # the next step: its own lines, none about the last one
    finally:
        log.removeFilter(compact)
    assert shown[0] == "--> Starting operation: Ensure ROS 2 is installed"
    assert still and all(line.startswith("    still running on team1-robot (") for line in still), shown
    after = shown[shown.index("--> Starting operation: Ensure the locale") + 1:]
    assert after and all(line.startswith("    still running on team1-main, team1-robot, team2-main (")
                         for line in after), shown


class _ClosedTransport:
    def is_active(self) -> bool:
        return False


class _DroppedClient:
    """paramiko's SSHClient after the host went away: its transport is no longer active."""

    def get_transport(self):
        return _ClosedTransport()


def test_a_host_that_lost_power_during_a_step_is_named_as_lost_not_as_a_silent_failure():
    state, handler = classroom("team1-main", "team1-robot")
    for name in ("team1-main", "team1-robot"):
        operation_on(state, name, "op-install", INSTALL, changed=True)
    finished_run(state)
    robot = state.inventory.get_host("team1-robot")
    robot.connector.client = _DroppedClient()
    executed(state, handler, "team1-main", "op-install", success=True)
    executed(state, handler, "team1-robot", "op-install", success=False, commands=0)  # no output at all
    state.fail_hosts({robot})

    line = printed(state, handler)[3]
    assert line.startswith(f'    team1-robot  failed   in "{INSTALL}": lost the connection to the host during '
                           "this step"), line
    assert "without printing an error" not in line


def test_a_host_gone_while_roslab_read_it_is_named_as_lost_not_as_a_fact_with_85_commands():
    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    robot.connector.client = _DroppedClient()
    with ctx_state.use(state), ctx_host.use(robot):
        robot.current_deploy_name = SUPPORTED
        logger.error(f"{robot.print_prefix}Error: could not load fact: roslab.probe.HostProbe commands=<85 commands>")
        robot.current_deploy_name = None
    state.fail_hosts({robot})
    summary.mark_planned(state.inventory.get_host("team1-main"))

    line = printed(state, handler)[3]
    assert line.startswith(f'    team1-robot  failed   in "{SUPPORTED}": lost the connection to the host'), line
    assert "HostProbe" not in line


class _Transport:
    """paramiko's transport: active until it ends, keeping the error that ended it (an end of
    file when the host went away; none when the controller closed it)."""

    def __init__(self):
        self.active, self.saved_exception = True, None

    def is_active(self) -> bool:
        return self.active


class _Client:
    def __init__(self, transport):
        self.transport = transport

    def get_transport(self):
        return self.transport


@pytest.mark.parametrize("reading", [False, True], ids=["step", "reading"])
def test_a_host_whose_command_ended_a_moment_before_its_connection_is_named_as_lost(reading):
    # Its processes die one by one: sshd reports the command killed, then the connection ends.
    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    connection = _Transport()
    robot.connector.client = _Client(connection)
    if reading:
        with ctx_state.use(state), ctx_host.use(robot):
            robot.current_deploy_name = SUPPORTED
            logger.error(f"{robot.print_prefix}Error: could not load fact: roslab.probe.HostProbe commands=<31 "
                         "commands>, marker=3f085e9f")
            robot.current_deploy_name = None
        summary.mark_planned(state.inventory.get_host("team1-main"))
    else:
        for name in ("team1-main", "team1-robot"):
            operation_on(state, name, "op-install", INSTALL, changed=True)
        finished_run(state)
        executed(state, handler, "team1-main", "op-install", success=True)
        executed(state, handler, "team1-robot", "op-install", success=False)  # killed: no words of its own
    state.fail_hosts({robot})
    connection.active, connection.saved_exception = False, EOFError()  # then it ended: the host is gone

    [line] = [" ".join(line.split()) for line in printed(state, handler) if line.split()[:1] == ["team1-robot"]]
    step = SUPPORTED if reading else INSTALL
    assert line == f'team1-robot failed in "{step}": {summary.LOST_CONNECTION}', line


def test_a_step_that_failed_on_a_connection_the_run_closed_itself_is_not_called_lost():
    state, handler = classroom("team1-main", "team1-robot")
    main = state.inventory.get_host("team1-main")
    connection = _Transport()
    main.connector.client = _Client(connection)
    operation_on(state, "team1-main", "op-net", "Ensure the network", changed=True)
    finished_run(state)
    executed(state, handler, "team1-main", "op-net", success=False, output=[("stderr", "E: Unable to locate package")])
    state.fail_hosts({main})
    connection.active = False  # pyinfra disconnects every host at the end of the run: no error kept

    [line] = [" ".join(line.split()) for line in printed(state, handler) if line.split()[:1] == ["team1-main"]]
    assert line == 'team1-main failed in "Ensure the network": E: Unable to locate package', line


class _AskedTransport(_Transport):
    """Still open when the summary asks the host for an answer (a keepalive request)."""

    def __init__(self, answer):
        super().__init__()
        self.answer = answer

    def global_request(self, kind, data=None, wait=True):
        assert kind == "keepalive@openssh.com" and wait
        return self.answer(self)


def _ends(transport):  # the host was going away: the connection ends while the summary asks
    transport.active, transport.saved_exception = False, EOFError()


def _silent(transport):
    gevent.sleep(5)


@pytest.mark.parametrize("answer, lost", [(_ends, True), (_silent, True), (lambda transport: None, False)],
                         ids=["ends", "silent", "answers"])
def test_a_connection_still_open_at_the_summary_is_lost_only_if_the_host_does_not_answer(
        monkeypatch, answer, lost):
    monkeypatch.setattr(summary, "ANSWER_WITHIN", 0.2)
    state, handler = classroom("team1-main", "team1-robot")
    robot = state.inventory.get_host("team1-robot")
    robot.connector.client = _Client(_AskedTransport(answer))
    for name in ("team1-main", "team1-robot"):
        operation_on(state, name, "op-install", INSTALL, changed=True)
    finished_run(state)
    executed(state, handler, "team1-main", "op-install", success=True)
    executed(state, handler, "team1-robot", "op-install", success=False)
    state.fail_hosts({robot})

    [line] = [" ".join(line.split()) for line in printed(state, handler) if line.split()[:1] == ["team1-robot"]]
    reason = summary.LOST_CONNECTION if lost else summary.NO_ERROR_PRINTED
    assert line == f'team1-robot failed in "{INSTALL}": {reason}', line


def test_a_host_unreachable_after_a_killed_network_change_names_the_change_and_the_addresses(tmp_path):
    from roslab.network import state as network_state

    roster = tmp_path / "roster.yaml"
    roster.write_text("")
    network_state.record_pending(roster, "team1-robot", "10.0.0.200", "10.0.0.12", 90, "2026-11-26 18:02:00 UTC")
    state, handler = classroom("team1-main", "team1-robot", data={
        "team1-robot": {"roslab_roster_path": str(roster), "ssh_hostname": "10.0.0.200"}})
    robot = state.inventory.get_host("team1-robot")
    handler.host_connect_error(state, robot, Exception("Could not connect (timed out)"))
    state.activated_hosts.discard(robot)
    state.active_hosts.discard(robot)
    state.fail_hosts({robot})
    summary.mark_planned(state.inventory.get_host("team1-main"))

    line = " ".join(printed(state, handler)[3].split())
    assert line.startswith('team1-robot failed in "connect": tried 10.0.0.200: Could not connect (timed out); '
                           "a network change started 2026-11-26 18:02:00 UTC (from 10.0.0.200 to 10.0.0.12) "
                           "was not seen to end"), line
    assert "within 90 s" in line
    # once the change ends (confirmed here), nothing is pending any more
    network_state.record_address(roster, "team1-robot", "10.0.0.12")
    network_state.clear_pending(roster, "team1-robot")
    assert network_state.pending_changes(roster) == {}


def test_a_lost_host_keeps_the_steps_own_words_when_it_had_any():
    state, handler = classroom("team1-main", "team1-robot")
    operation_on(state, "team1-main", "op-net", "Ensure the network", changed=True)
    finished_run(state)
    main = state.inventory.get_host("team1-main")
    main.connector.client = _DroppedClient()
    executed(state, handler, "team1-main", "op-net", success=False, output=[
        ("stderr", "Network change not confirmed at 10.0.0.11, and the host does not answer at 10.0.0.200 either")])
    state.fail_hosts({main})

    line = " ".join(printed(state, handler)[2].split())
    assert "lost the connection to the host during this step" in line
    assert line.endswith("(Network change not confirmed at 10.0.0.11, and the host does not answer at 10.0.0.200 "
                         "either)"), line
# pyinfra's tables in the compact output ---------------------------------------------------

PLAN_TABLE = ["    Operation    Change    Conditional Change",
              "    Ensure the unit    -    -",
              "    Restart roslab-nodes    -    2 (team1-main, team1-robot)"]
RESULTS_TABLE = ["    Operation    Hosts    Success    Error    No Change",
                 "    Ensure the unit    2    -    -    2", "    Grand total    2    -    -    2"]


def compact_log(state, name):
    shown: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record):
            shown.append(record.getMessage())

    log = logging.getLogger(name)
    log.propagate = False
    log.setLevel(logging.INFO)
    log.handlers = [Collect()]
    compact = summary.CompactOutput(log, long_step=None)
    compact.state = state
    log.addFilter(compact)
    return log, compact, shown


def test_a_converged_plan_shows_no_conditional_restart_and_keeps_the_state_unexecuted():
    state, handler = classroom("team1-main", "team1-robot")
    restarts = []
    for name in ("team1-main", "team1-robot"):
        unit = operation_on(state, name, "op-unit", "Ensure the unit", changed=False)
        restarts.append(conditional(state, name, "op-restart", "Restart roslab-nodes", unit.did_change))
    log, compact, shown = compact_log(state, "roslab-test-plan")
    try:
        for line in ["--> Detected changes:", *PLAN_TABLE, "--> Disconnecting from hosts..."]:
            log.info(line)
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Detected changes:", "nothing would change on any host", "--> Disconnecting from hosts..."]
    # Nothing was executed by looking: pyinfra would still run every operation.
    assert not any(op.operation_meta.is_complete() for ops in state.ops.values() for op in ops.values())
    assert [meta.is_complete() for meta in restarts] == [False, False]


def test_a_plan_names_each_step_that_would_change_with_its_hosts():
    state, handler = classroom("team1-main", "team1-robot")
    for name in ("team1-main", "team1-robot"):
        unit = operation_on(state, name, "op-unit", "Ensure the unit", changed=name == "team1-robot")
        conditional(state, name, "op-restart", "Restart roslab-nodes", unit.did_change)
    log, compact, shown = compact_log(state, "roslab-test-plan-changes")
    try:
        for line in ["--> Detected changes:", *PLAN_TABLE]:
            log.info(line)
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Detected changes:", "Ensure the unit: team1-robot", "Restart roslab-nodes: team1-robot"]


def test_the_results_of_a_no_op_are_not_shown_and_a_change_names_its_hosts():
    state, handler = classroom("team1-main", "team1-robot")
    for name in ("team1-main", "team1-robot"):
        operation_on(state, name, "op-unit", "Ensure the unit", changed=False)
    state.set_stage(StateStage.Execute)
    state.is_executing = True
    for name in ("team1-main", "team1-robot"):
        executed(state, handler, name, "op-unit", success=True, commands=0)
    log, compact, shown = compact_log(state, "roslab-test-results")
    try:
        for line in ["--> Results:", *RESULTS_TABLE, "--> Disconnecting from hosts..."]:
            log.info(line)
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Disconnecting from hosts..."]

    state, handler = classroom("team1-main", "team1-robot")
    for name in ("team1-main", "team1-robot"):
        operation_on(state, name, "op-unit", "Ensure the unit", changed=True)
    state.set_stage(StateStage.Execute)
    state.is_executing = True
    executed(state, handler, "team1-main", "op-unit", success=True)
    executed(state, handler, "team1-robot", "op-unit", success=False)
    log, compact, shown = compact_log(state, "roslab-test-results-changed")
    try:
        for line in ["--> Results:", *RESULTS_TABLE]:
            log.info(line)
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Results:", "Ensure the unit: changed on team1-main; failed on team1-robot"]


def test_a_step_named_with_a_hosts_value_is_shown_with_each_hosts_own_name():
    # One operation, two names: "Ensure ROS 2 jazzy ..." on one host, "... humble ..." on the other.
    state, handler = classroom("team1-main", "team2-main")
    for name, distro in (("team1-main", "jazzy"), ("team2-main", "humble")):
        operation_on(state, name, "op-ros", f"Ensure ROS 2 {distro} is installed", changed=True)
        state.ops[state.inventory.get_host(name)]["op-ros"].global_arguments["name"] = \
            f"Ensure ROS 2 {distro} is installed"
    log, compact, shown = compact_log(state, "roslab-test-plan-names")
    try:
        log.info("--> Detected changes:")
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Detected changes:", "Ensure ROS 2 jazzy is installed: team1-main",
                     "Ensure ROS 2 humble is installed: team2-main"]


def test_the_hosts_ready_lines_are_not_shown_but_a_step_s_lines_are():
    state, handler = classroom("team1-main")
    log, compact, shown = compact_log(state, "roslab-test-ready")
    try:
        for line in ["--> Preparing operation files...", "    Loading: deploy.py", "    [team1-main] Ready: deploy.py",
                     "--> Starting operation: Ensure the unit", "    [team1-main] Success"]:
            log.info(line)
        log.warning("    [team1-main] a warning while planning")
    finally:
        log.removeFilter(compact)
    assert shown == ["--> Preparing operation files...", "    Loading: deploy.py",
                     "--> Starting operation: Ensure the unit", "    [team1-main] Success",
                     "    [team1-main] a warning while planning"]


def test_a_connect_error_before_any_host_connected_is_kept_for_the_summary(monkeypatch):
    """No host connects: deploy.py never runs, so the summary has no state yet when pyinfra logs
    "[host] Could not connect (...)"; the line must still be kept (it is the row's reason)."""
    run = summary.RunSummary()
    monkeypatch.setattr(summary, "_current", (run, None))
    capture = summary._LogCapture(level=logging.WARNING)
    record = logging.LogRecord("pyinfra", logging.ERROR, __file__, 1,
                               "[team1-main] \x1b[31mCould not connect\x1b[0m ([Errno None] Unable to connect to "
                               "port 2 on 10.0.0.11)", None, None)
    capture.emit(record)
    assert [line.text for line in run.host("team1-main").log] == [
        "Could not connect ([Errno None] Unable to connect to port 2 on 10.0.0.11)"]


@pytest.mark.parametrize("value, every, warned", [
    (None, 15.0, False), ("", 15.0, False), ("5", 5.0, False), ("3600", 3600.0, False),
    ("0", 15.0, True), ("3601", 15.0, True), ("2.5", 15.0, True), ("-1", 15.0, True), ("\u0665", 15.0, True),
    ("ten", 15.0, True),
])
def test_the_still_running_interval_is_the_environments_whole_seconds_or_fifteen(value, every, warned):
    environ = {} if value is None else {summary.STILL_RUNNING_VARIABLE: value}
    got, problem = summary.still_running_every(environ)
    assert got == every and (problem is not None) is warned, problem
    if warned:
        assert problem.startswith("ROSLAB_STILL_RUNNING_SECONDS=") and problem.endswith("every 15 s")
