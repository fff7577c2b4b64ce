"""The demo nodes' logic (nodes/roslab_demo/roslab_demo/logic.py), tested without ROS."""

import random
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "nodes" / "roslab_demo"))

from roslab_demo import logic  # noqa: E402  (importable only once the path is set)
from roslab_demo.logic import ERROR, OK, STALE, WARN  # noqa: E402


# --- rates and names -----------------------------------------------------------


def test_timer_period_is_the_inverse_of_the_rate():
    assert logic.timer_period(2.0) == 0.5


@pytest.mark.parametrize("rate", [0, 0.0, -1.0])
def test_timer_period_rejects_a_rate_that_never_ticks_naming_the_parameter(rate):
    with pytest.raises(ValueError, match=r"publish_rate_hz must be above 0, got"):
        logic.timer_period(rate)


def test_robot_name_defaults_to_the_host_name():
    assert logic.robot_name_or_host("", "team1-robot") == "team1-robot"
    assert logic.robot_name_or_host("rover", "team1-robot") == "rover"


def test_chatter_text_names_the_robot_and_counts():
    assert logic.chatter_text("team1-robot", 3) == "Hello from team1-robot #3"


@pytest.mark.parametrize(
    "robot_name",
    ["team1-robot", "r", "my robot", "rover #2", "Hello from x #1", "robôt-ü", "two\nlines"],
)
@pytest.mark.parametrize("count", [1, 7, 10**9])
def test_robot_name_reads_back_from_every_greeting(robot_name, count):
    text = logic.chatter_text(robot_name, count)
    assert logic.robot_name_from_chatter(text) == robot_name


def test_robot_name_from_the_greeting_documented_in_the_readme():
    # nodes/README.md shows this message; `roslab verify` relies on reading it so.
    assert logic.robot_name_from_chatter("Hello from team1-robot #7") == "team1-robot"


@pytest.mark.parametrize(
    "text",
    [
        "",
        "hello world",
        "Hello from team1-robot",  # no count
        "Hello from  #7",  # no name
        "Hello from team1-robot #",
        "Hello from team1-robot #7a",
        "Hello from team1-robot #-1",
        "Hello from team1-robot #7 ",
        " Hello from team1-robot #7",
        "hello from team1-robot #7",
        "Hello World: 7",  # the stock ROS 2 demo talker's message
        'I heard: "Hello from team1-robot #7"',  # the listener's log line, not the message
    ],
)
def test_robot_name_is_none_for_anything_but_a_greeting(text):
    assert logic.robot_name_from_chatter(text) is None


# --- robot status ----------------------------------------------------------------


def test_levels_are_numbered_as_in_diagnostic_msgs():
    # diagnostic_msgs/DiagnosticStatus: OK=0 WARN=1 ERROR=2 STALE=3
    assert (OK, WARN, ERROR, STALE) == (0, 1, 2, 3)


def test_robot_state_holds_for_publishes_per_state_then_moves_on_and_wraps():
    states = logic.ROBOT_STATES
    seen = [logic.robot_state_at(step, 2) for step in range(2 * len(states) + 2)]
    expected = [state for state in states for _ in range(2)] + [states[0], states[0]]
    assert seen == expected


def test_robot_states_show_every_severity_the_monitor_logs():
    assert {state.level for state in logic.ROBOT_STATES} == {OK, WARN, ERROR}


def test_robot_state_rejects_zero_publishes_per_state():
    with pytest.raises(ValueError, match="publishes_per_state must be above 0"):
        logic.robot_state_at(0, 0)


@pytest.mark.parametrize("raw", [bytes([1]), bytearray([1]), 1])
def test_level_code_reads_rclpy_byte_fields_and_ints(raw):
    assert logic.level_code(raw) == WARN


class CallSiteLogger:
    """Records which severity each logger call site used, as rclpy's logger tracks it."""

    def __init__(self):
        self.lines = []
        self.severity_by_call_site = {}

    def _log(self, severity, line):
        caller = sys._getframe(2)
        call_site = (caller.f_code.co_filename, caller.f_lineno)
        # rclpy raises "Logger severity cannot be changed between calls" here.
        assert self.severity_by_call_site.setdefault(call_site, severity) == severity
        self.lines.append((severity, line))

    def info(self, line):
        self._log("info", line)

    def warning(self, line):
        self._log("warning", line)

    def error(self, line):
        self._log("error", line)


@pytest.mark.parametrize(
    "level, severity",
    [(OK, "info"), (WARN, "warning"), (STALE, "warning"), (ERROR, "error"), (9, "error")],
)
def test_each_level_is_logged_at_its_severity(level, severity):
    logger = CallSiteLogger()
    logic.log_at_level(logger, level, "text")
    assert logger.lines == [(severity, "text")]


def test_one_logger_can_log_every_level_in_turn():
    # A monitor's logger sees OK, WARN, ERROR, then OK again as the robot's state cycles.
    logger = CallSiteLogger()
    for level in (OK, WARN, ERROR, STALE, OK, ERROR):
        logic.log_at_level(logger, level, f"level {level}")
    assert [severity for severity, _ in logger.lines] == [
        "info", "warning", "error", "warning", "info", "error"
    ]


def test_status_line_shows_robot_level_state_and_message():
    line = logic.status_line("team1-robot", WARN, "battery low", "returning to the dock")
    assert line == "[team1-robot] WARN battery low: returning to the dock"


def test_status_line_shows_an_unknown_level_by_number():
    assert logic.status_line("r", 7, "s", "m") == "[r] level 7 s: m"


# --- silence detection ---------------------------------------------------------------


def test_silence_is_reported_once_when_the_robot_stops_and_once_when_it_is_back():
    watch = logic.SilenceWatch(silent_after_s=10.0, now=100.0)
    assert watch.check(105.0) is None
    assert watch.check(110.0) is None  # exactly at the limit: not yet silent

    gone = watch.check(111.0)
    assert gone == "no robot status for 11 s: is the robot running?"
    assert watch.check(130.0) is None  # still silent: not repeated

    assert watch.heard(131.0) == "robot status heard again"
    assert watch.heard(132.0) is None
    assert watch.check(140.0) is None
    assert watch.check(142.5) is not None  # silent again after a new gap


def test_silence_watch_rejects_a_non_positive_limit():
    with pytest.raises(ValueError, match="silent_after_s must be above 0"):
        logic.SilenceWatch(silent_after_s=0, now=0.0)


# --- temperature ---------------------------------------------------------------


@pytest.mark.parametrize(
    "elapsed, expected", [(0.0, 50.0), (15.0, 75.0), (30.0, 50.0), (45.0, 25.0), (60.0, 50.0)]
)
def test_simulated_temperature_without_noise_is_a_sine_wave(elapsed, expected):
    reading = logic.simulated_temperature(elapsed, 50.0, 25.0, 60.0)
    assert reading == pytest.approx(expected)


def test_simulated_noise_is_repeatable_with_a_seeded_generator():
    first = logic.simulated_temperature(0.0, 50.0, 25.0, 60.0, 0.5, random.Random(7))
    again = logic.simulated_temperature(0.0, 50.0, 25.0, 60.0, 0.5, random.Random(7))
    assert first == again != 50.0
    assert abs(first - 50.0) < 5 * 0.5


def test_simulated_temperature_rejects_a_zero_period():
    with pytest.raises(ValueError, match="period_s must be above 0"):
        logic.simulated_temperature(1.0, 50.0, 25.0, 0.0)


def test_default_wave_crosses_both_default_thresholds():
    # With the shipped defaults a student sees OK, warning and error lines within a minute.
    publisher = {k: p.default for k, p in logic.PARAMETERS["temperature_publisher"].items()}
    monitor = {k: p.default for k, p in logic.PARAMETERS["temperature_monitor"].items()}
    readings = [
        logic.simulated_temperature(
            second,
            publisher["baseline_celsius"],
            publisher["swing_celsius"],
            publisher["period_s"],
        )
        for second in range(int(publisher["period_s"]))
    ]
    levels = {
        logic.temperature_level(r, monitor["warn_above_celsius"], monitor["error_above_celsius"])
        for r in readings
    }
    assert levels == {OK, WARN, ERROR}


@pytest.mark.parametrize(
    "celsius, level",
    [(20.0, OK), (60.0, OK), (60.1, WARN), (70.0, WARN), (70.1, ERROR), (300.0, ERROR)],
)
def test_temperature_level_is_strictly_above_each_threshold(celsius, level):
    assert logic.temperature_level(celsius, 60.0, 70.0) == level


@pytest.mark.parametrize("warn, error", [(70.0, 70.0), (80.0, 70.0)])
def test_thresholds_must_leave_room_for_a_warning(warn, error):
    with pytest.raises(ValueError, match=r"warn_above_celsius \(.*\) must be below"):
        logic.check_thresholds(warn, error)


def test_temperature_lines_name_the_threshold_crossed():
    assert logic.temperature_line(42.04, OK, 60.0, 70.0) == "42.0 °C"
    assert logic.temperature_line(65.0, WARN, 60.0, 70.0) == (
        "65.0 °C: above the warning threshold of 60.0 °C"
    )
    assert logic.temperature_line(71.26, ERROR, 60.0, 70.0) == (
        "71.3 °C: above the error threshold of 70.0 °C"
    )


def test_logic_module_does_not_need_ros():
    source = Path(logic.__file__).read_text()
    assert "rclpy" not in {
        line.split()[1].split(".")[0]
        for line in source.splitlines()
        if line.startswith(("import ", "from "))
    }


@pytest.mark.parametrize(
    ('node', 'name', 'value', 'expected'),
    [
        ('talker', 'publish_rate_hz', 2, 2.0),  # a teacher's `publish_rate_hz: 2`
        ('talker', 'publish_rate_hz', 0.5, 0.5),
        ('status_publisher', 'publishes_per_state', 3.0, 3),
        ('status_publisher', 'publishes_per_state', 4, 4),
        ('temperature_monitor', 'warn_above_celsius', 65, 65.0),
        ('talker', 'robot_name', 'r2', 'r2'),
    ],
)
def test_parameter_value_takes_a_number_in_either_form(node, name, value, expected):
    coerced = logic.parameter_value(node, name, value)
    assert coerced == expected and type(coerced) is type(expected)


@pytest.mark.parametrize(
    ('node', 'name', 'value', 'message'),
    [
        ('talker', 'publish_rate_hz', 'fast', "talker.publish_rate_hz must be a number, got 'fast' (str)"),
        ('talker', 'publish_rate_hz', True, 'talker.publish_rate_hz must be a number, got True (bool)'),
        ('status_publisher', 'publishes_per_state', 2.5,
         'status_publisher.publishes_per_state must be a whole number, got 2.5 (float)'),
        ('talker', 'robot_name', 7, 'talker.robot_name must be text, got 7 (int)'),
    ],
)
def test_parameter_value_refuses_the_wrong_kind_naming_node_and_parameter(node, name, value, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        logic.parameter_value(node, name, value)


def test_the_first_interrupt_ends_the_node_and_a_second_one_is_ignored():
    import os
    import signal

    before = signal.getsignal(signal.SIGINT)
    try:
        logic.end_on_first_interrupt()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGINT)  # ros2 launch's forwarded SIGINT: nothing happens
    finally:
        signal.signal(signal.SIGINT, before)
