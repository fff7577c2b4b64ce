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

"""Log temperature readings, warning above one threshold and erring above another."""

import signal

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from roslab_demo.logic import (
    check_thresholds, end_on_first_interrupt, log_at_level, temperature_level,
    temperature_line)
from roslab_demo.parameters import declare_parameters
from sensor_msgs.msg import Temperature


class TemperatureMonitor(Node):
    """Compare each reading with the thresholds and log it at the matching severity."""

    def __init__(self):
        super().__init__('temperature_monitor')
        params = declare_parameters(self, 'temperature_monitor')
        self.warn_above = params['warn_above_celsius']
        self.error_above = params['error_above_celsius']
        check_thresholds(self.warn_above, self.error_above)
        self.subscription = self.create_subscription(
            Temperature, params['topic'], self.on_reading, 10)

    def on_reading(self, msg):
        level = temperature_level(msg.temperature, self.warn_above, self.error_above)
        line = temperature_line(msg.temperature, level, self.warn_above, self.error_above)
        log_at_level(self.get_logger(), level, line)


def main(args=None):
    end_on_first_interrupt()
    rclpy.init(args=args)
    node = TemperatureMonitor()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or `ros2 launch` stopping us is a normal end, not an error
    finally:
        # Ctrl-C reaches every process of a launch, and ros2 launch then sends SIGINT
        # again: a second one must not cut the clean-up short with a traceback.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
