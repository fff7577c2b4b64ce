# Copyright 2026 The roslab authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
What the demo nodes say and decide, as plain Python.

Nothing here imports rclpy, so all of it can be tested on any machine;
the node modules only wire these functions to topics and timers.
"""

import math
import random
import re
import signal
from typing import NamedTuple, Optional


class Parameter(NamedTuple):
    """A ROS parameter's default value and what it means."""

    default: object
    description: str


# Every node's ROS parameters. roslab_bringup/config/params.yaml repeats these
# defaults so students can see and edit them; a unit test keeps the two equal.
PARAMETERS = {
    'talker': {
        'topic': Parameter('chatter', 'Topic the greetings are published on.'),
        'publish_rate_hz': Parameter(1.0, 'Greetings per second.'),
        'robot_name': Parameter('', 'Name used in the greetings; empty means the host name.'),
    },
    'listener': {
        'topic': Parameter('chatter', 'Topic the greetings are heard on.'),
    },
    'status_publisher': {
        'topic': Parameter('robot_status', 'Topic the robot status is published on.'),
        'publish_rate_hz': Parameter(0.5, 'Status messages per second.'),
        'publishes_per_state': Parameter(
            3, 'Status messages sent in one state before the robot moves to the next.'),
        'robot_name': Parameter('', 'Name the status reports; empty means the host name.'),
    },
    'status_monitor': {
        'topic': Parameter('robot_status', 'Topic the robot status is heard on.'),
        'silent_after_s': Parameter(
            10.0, 'Seconds without a status before the monitor reports the robot silent.'),
    },
    'temperature_publisher': {
        'topic': Parameter('temperature', 'Topic the simulated temperature is published on.'),
        'publish_rate_hz': Parameter(1.0, 'Readings per second.'),
        'frame_id': Parameter('temperature_sensor', 'Frame named in each reading header.'),
        'baseline_celsius': Parameter(50.0, 'Middle of the simulated temperature wave.'),
        'swing_celsius': Parameter(25.0, 'How far the wave rises above and falls below it.'),
        'period_s': Parameter(60.0, 'Seconds for one full wave.'),
        'noise_celsius': Parameter(0.5, 'Standard deviation of the random noise per reading.'),
    },
    'temperature_monitor': {
        'topic': Parameter('temperature', 'Topic the temperature readings are heard on.'),
        'warn_above_celsius': Parameter(60.0, 'Readings above this log a warning.'),
        'error_above_celsius': Parameter(70.0, 'Readings above this log an error.'),
    },
}


# What a teacher may write for a parameter, by the type of its default: `publish_rate_hz: 2`
# means 2.0, and `publishes_per_state: 3.0` means 3. ROS itself would refuse both (a
# parameter's type is its default's), killing the node with InvalidParameterTypeException.
TYPE_NAMES = {bool: 'true or false', int: 'a whole number', float: 'a number', str: 'text'}


def parameter_value(node_name, name, value):
    """
    Return parameter `name` of `node_name` as its default's type, or raise ValueError.

    An integer stands for a float and a whole float for an integer; anything else of
    another type (text for a number, a number for text, true/false for a number) is an
    error naming the node, the parameter, what it wants and what it got.
    """
    wanted = type(PARAMETERS[node_name][name].default)
    is_bool = isinstance(value, bool)
    if wanted is bool and is_bool:
        return value
    if wanted is float and isinstance(value, (int, float)) and not is_bool:
        return float(value)
    if wanted is int and not is_bool:
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    if wanted is str and isinstance(value, str):
        return value
    raise ValueError(
        f'parameter {node_name}.{name} must be {TYPE_NAMES[wanted]}, '
        f'got {value!r} ({type(value).__name__})')


def end_on_first_interrupt():
    """
    Make the first SIGINT end the node (KeyboardInterrupt) and ignore any further one.

    Ctrl-C reaches every process of a launch, and ros2 launch then forwards its own
    SIGINT to each node: without this, the second one lands in the node's clean-up and
    ends it with a KeyboardInterrupt traceback. Call it before rclpy.init, whose own
    handler then passes the signal on to this one.
    """
    def interrupted(signum, frame):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupted)


def require_positive(parameter, value):
    """Raise ValueError naming the parameter unless its value is above 0."""
    if value <= 0:
        raise ValueError(f'parameter {parameter} must be above 0, got {value}')


def timer_period(rate_hz):
    """Return the timer period in seconds for a publish_rate_hz parameter."""
    require_positive('publish_rate_hz', rate_hz)
    return 1.0 / rate_hz


def robot_name_or_host(configured, hostname):
    """Return the configured robot name, or the host name when none is set."""
    return configured or hostname


# --- talker / listener -------------------------------------------------------

# The talker's message, in full: "Hello from team1-robot #7". `roslab verify` reads
# the robot's name back out of it, so nodes/README.md documents this format: change
# both together, and keep robot_name_from_chatter the inverse of chatter_text.
CHATTER_FORMAT = 'Hello from {robot_name} #{count}'
# Greedy: a name that itself holds ' #<digits>' still reads back whole.
CHATTER_PATTERN = re.compile(r'Hello from (?P<robot_name>.+) #(?P<count>[0-9]+)', re.DOTALL)


def chatter_text(robot_name, count):
    """Return the greeting number `count` of a robot."""
    return CHATTER_FORMAT.format(robot_name=robot_name, count=count)


def robot_name_from_chatter(text) -> Optional[str]:
    """
    Return the robot name in a chatter message, or None if it is not a greeting.

    `text` is the whole message (std_msgs/String data), as chatter_text made it:
    a log line that quotes a greeting is not one.
    """
    match = CHATTER_PATTERN.fullmatch(text)
    return match['robot_name'] if match else None


# --- robot status --------------------------------------------------------------

# Severity levels, numbered as in diagnostic_msgs/DiagnosticStatus.
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}


class RobotState(NamedTuple):
    """One state of the simulated robot: its name, severity and explanation."""

    name: str
    level: int
    message: str


# The simulated robot goes through these states in order, then starts over,
# so the status monitor shows every severity within a minute or two.
ROBOT_STATES = (
    RobotState('idle', OK, 'waiting for a command'),
    RobotState('driving', OK, 'driving the square course'),
    RobotState('battery low', WARN, 'battery below 20 %, returning to the dock'),
    RobotState('charging', OK, 'charging at the dock'),
    RobotState('bumper pressed', ERROR, 'bumper pressed, motors stopped'),
)


def robot_state_at(step, publishes_per_state):
    """Return the robot's state at status message number `step` (from 0)."""
    require_positive('publishes_per_state', publishes_per_state)
    return ROBOT_STATES[(step // publishes_per_state) % len(ROBOT_STATES)]


def level_code(raw_level):
    """
    Return a DiagnosticStatus level as an int.

    rclpy represents the message's `byte` field as a one-byte `bytes` value,
    so bytes([1]) and 1 both mean WARN.
    """
    if isinstance(raw_level, (bytes, bytearray)):
        return raw_level[0]
    return int(raw_level)


def log_at_level(logger, level, line):
    """
    Log `line` as info, warning or error, as the level says.

    Each severity has a logger call on a line of its own: rclpy remembers the
    severity of every call site and raises ValueError ("Logger severity cannot
    be changed between calls") when one site logs at a second severity.
    """
    if level == OK:
        logger.info(line)
    elif level in (WARN, STALE):
        logger.warning(line)
    else:  # ERROR, and levels this code does not know
        logger.error(line)


def status_line(hardware_id, level, state, message):
    """Return the log line for one robot status."""
    level_name = LEVEL_NAMES.get(level, f'level {level}')
    return f'[{hardware_id}] {level_name} {state}: {message}'


class SilenceWatch:
    """
    Notice when a robot stops sending status, and when it is back.

    Times are seconds on any monotonic clock. `check` and `heard` return a
    line to log only when the robot goes silent or comes back, not on every
    call, so a silent robot does not flood the log.
    """

    def __init__(self, silent_after_s, now):
        """Start watching at `now`, as if a status had just been heard."""
        require_positive('silent_after_s', silent_after_s)
        self.silent_after_s = silent_after_s
        self.last_heard = now
        self.silent = False

    def heard(self, now) -> Optional[str]:
        """Record a status heard at `now`; return a line if the robot was silent."""
        self.last_heard = now
        if self.silent:
            self.silent = False
            return 'robot status heard again'
        return None

    def check(self, now) -> Optional[str]:
        """Return a line if the robot has just gone silent at `now`."""
        quiet_for = now - self.last_heard
        if not self.silent and quiet_for > self.silent_after_s:
            self.silent = True
            return f'no robot status for {quiet_for:.0f} s: is the robot running?'
        return None


# --- temperature ---------------------------------------------------------------

def simulated_temperature(elapsed_s, baseline_celsius, swing_celsius, period_s,
                          noise_celsius=0.0, rng=random):
    """
    Return a simulated temperature in degrees Celsius at `elapsed_s`.

    A sine wave around the baseline, so the readings regularly cross the
    monitor's thresholds, plus Gaussian noise drawn from `rng` (the random module, or a
    seeded random.Random for repeatable readings).
    """
    require_positive('period_s', period_s)
    wave = swing_celsius * math.sin(2 * math.pi * elapsed_s / period_s)
    noise = rng.gauss(0.0, noise_celsius) if noise_celsius > 0 else 0.0
    return baseline_celsius + wave + noise


def check_thresholds(warn_above_celsius, error_above_celsius):
    """Raise ValueError unless the warning threshold is below the error threshold."""
    if warn_above_celsius >= error_above_celsius:
        raise ValueError(
            f'parameter warn_above_celsius ({warn_above_celsius}) must be below '
            f'error_above_celsius ({error_above_celsius})')


def temperature_level(celsius, warn_above_celsius, error_above_celsius):
    """Return OK, WARN or ERROR for a reading."""
    if celsius > error_above_celsius:
        return ERROR
    if celsius > warn_above_celsius:
        return WARN
    return OK


def temperature_line(celsius, level, warn_above_celsius, error_above_celsius):
    """Return the log line for one reading at the given level."""
    if level == ERROR:
        return f'{celsius:.1f} °C: above the error threshold of {error_above_celsius:.1f} °C'
    if level == WARN:
        return f'{celsius:.1f} °C: above the warning threshold of {warn_above_celsius:.1f} °C'
    return f'{celsius:.1f} °C'
